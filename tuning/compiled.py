"""Compiled things kept for later calls: bounded caches of programs by key
(:class:`ProgramCache`), and simulators shared by later calls of the functions that compile
one from a scene (:func:`compiled`): called again on an equal scene with equal arguments, they
run the programs their first call compiled instead of compiling a new simulator's."""
from __future__ import annotations

import collections
import hashlib
import pickle

import jax
import numpy as np

import diffpen as dp

__all__ = ["ProgramCache", "compiled", "scene_digest", "frozen_key"]


class ProgramCache:
    """The last ``keep`` compiled programs (or simulators, metrics functions), by key (a key
    that holds a simulator keeps it alive only while it is one of the last ``keep``):
    :meth:`get` returns the cached one or builds it."""

    def __init__(self, keep: int = 8):
        self.keep = int(keep)
        self._programs: collections.OrderedDict = collections.OrderedDict()

    def get(self, key, build):
        if key in self._programs:
            self._programs.move_to_end(key)
            return self._programs[key]
        program = self._programs[key] = build()
        while len(self._programs) > self.keep:
            self._programs.popitem(last=False)
        return program


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
    # dp.compile keeps its own snapshot of the scene (Scene.snapshot): no deep copy (9.4 s
    # for a 90k-node cloth)
    return _SIMS.get(key, lambda: dp.compile(scene, dt, **compile_kw))


def frozen_key(*parts):
    """A hashable key of ``parts`` by value: dicts (sorted), lists and tuples taken apart,
    NumPy and JAX arrays and Params leaves by dtype, shape and bytes, Python numbers by type
    and bits (equal values, equal key; -0.0 and 0.0, 1 and 1.0 differ), pytrees
    (``diffpen.Params``) by structure and leaves, anything else as itself (functions and
    simulators by identity). None where a part is traced or unhashable: the caller then
    builds afresh."""
    def freeze(x):
        if isinstance(x, dict):
            return ("dict",) + tuple((k, freeze(v)) for k, v in sorted(x.items(), key=repr))
        if isinstance(x, (list, tuple)) and not hasattr(x, "_fields"):
            return (type(x).__name__,) + tuple(freeze(v) for v in x)
        if isinstance(x, (np.ndarray, np.generic, jax.Array)):
            a = np.asarray(x)           # a tracer raises here (TracerArrayConversionError)
            return ("array", a.dtype.str, a.shape, a.tobytes())
        if hasattr(x, "_fields"):       # a NamedTuple pytree (Params, ContactParams, ...)
            leaves, tree = jax.tree_util.tree_flatten(x)
            return ("tree", tree) + tuple(freeze(v) for v in leaves)
        if isinstance(x, float):            # -0.0 == 0.0 and nan != nan: by bits
            return ("float", x.hex())
        if isinstance(x, (bool, int, complex)):
            return (type(x).__name__, repr(x))  # 1 == 1.0 == True, not as leaves' dtypes
        hash(x)
        return x
    try:
        key = tuple(freeze(p) for p in parts)
        hash(key)
    except (TypeError, jax.errors.TracerArrayConversionError):
        return None
    return key
