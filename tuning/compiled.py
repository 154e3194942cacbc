"""Simulators shared by later calls of the functions that compile one from a scene
(:func:`compiled`): called again on an equal scene with equal arguments, they run the
programs their first call compiled instead of compiling a new simulator's."""
from __future__ import annotations

import copy
import hashlib
import pickle

import jax

import diffpen as dp

from .record_batch import ProgramCache

__all__ = ["compiled", "scene_digest"]

_SIMS = ProgramCache()


def scene_digest(scene: dp.Scene) -> str | None:
    """A digest (hex) of everything ``scene`` holds; None where something in it cannot be
    pickled (a custom element holding a closure): such a scene is not shared."""
    try:
        data = pickle.dumps({k: v for k, v in vars(scene).items() if not k.startswith("_")},
                            protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:       # noqa: BLE001 - any object pickle refuses: not shared
        return None
    return hashlib.sha256(data).hexdigest()


def compiled(scene: dp.Scene, dt: float, **compile_kw) -> dp.Simulator:
    """``diffpen.compile(scene, dt, **compile_kw)``, or the simulator one of the last 8 calls
    built for an equal scene, ``dt`` and arguments (under the same float64 setting). The
    simulator holds a copy of the scene: changing ``scene`` afterwards changes its digest,
    not the simulator."""
    digest = scene_digest(scene)
    key = (digest, float(dt), bool(jax.config.jax_enable_x64),
           tuple(sorted(compile_kw.items())))
    try:
        hash(key)
    except TypeError:       # an unhashable argument (a list of terms): not shared
        digest = None
    if digest is None:
        return dp.compile(scene, dt, **compile_kw)
    return _SIMS.get(key, lambda: dp.compile(copy.deepcopy(scene), dt, **compile_kw))
