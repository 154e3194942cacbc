"""Argument checks of :meth:`diffpen.Simulator.rollout`, run before anything is traced or
compiled: the params pytree, ``steps`` and ``save_every`` (with a size and time estimate for
runs too large to hold), and a given start state (type, shapes, dtypes, finite values).
Each failure raises :class:`diffpen.SceneError` saying what to change.
"""
from __future__ import annotations

import os
import weakref

import jax
import numpy as np

from .errors import SceneError
from .state import Params, State

__all__ = ["check_rollout", "check_pairs", "memory_bytes", "human_bytes", "human_time", "STEP_RATE", "MAX_STEPS",
           "MAX_PAIRS"]

#: most sphere-sphere pairs compiled without a broad phase (the pair list is built and
#: evaluated every step: 5e6 pairs already take seconds per step)
MAX_PAIRS = 5_000_000

#: body-steps per second assumed for time estimates (a single ball reaches ~1.5e7 steps/s
#: on a 2-core CPU; scenes with springs or many contacts are slower)
STEP_RATE = 1e7
#: lax.scan counts steps in int32
MAX_STEPS = 2 ** 31 - 1


def memory_bytes() -> float:
    """Physical memory of this machine, bytes (8 GiB when unknown)."""
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8.0 * 2 ** 30


def human_bytes(b: float) -> str:
    """``b`` bytes as text in TiB, GiB, MiB or B (for size estimates in messages)."""
    for unit, f in (("TiB", 2 ** 40), ("GiB", 2 ** 30), ("MiB", 2 ** 20)):
        if b >= f:
            return f"{b / f:.3g} {unit}"
    return f"{b:.0f} B"


def human_time(s: float) -> str:
    """``s`` seconds as text in s, min, h, days or years (for time estimates in messages)."""
    if s < 120:
        return f"{s:.3g} s"
    if s < 7200:
        return f"{s / 60:.3g} min"
    if s < 2 * 86400:
        return f"{s / 3600:.3g} h"
    if s < 730 * 86400:
        return f"{s / 86400:.3g} days"
    return f"{s / (365 * 86400):.3g} years"


def _int(name: str, v) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        hint = ""
        if isinstance(v, float) and v.is_integer() and v > 0:
            hint = f" (use {name}={int(v)})"
        raise SceneError(f"{name} must be a positive int, got {v!r}{hint}.")
    if v <= 0:
        raise SceneError(f"{name} must be a positive int, got {v!r}.")
    return int(v)


def _estimate(sim, steps: int, save_every: int, observe) -> tuple[float, float]:
    """(bytes of the saved trajectory, seconds at STEP_RATE)."""
    n = int(sim.n_bodies)
    per_body = 6 + (7 if getattr(sim.scene, "has_rotation", False) else 0)
    itemsize = np.dtype(sim.dtype).itemsize
    saved = steps // save_every
    stored = 0.0 if observe is not None else float(saved) * n * per_body * itemsize
    return stored, float(steps) * max(n, 1) / STEP_RATE


def check_pairs(scene, broadphase) -> None:
    """Refuse, before anything is built, an all-pairs sphere contact list too large to
    compile (the pair count grows as n^2 without a broad phase)."""
    if broadphase is not None:
        return
    s = sum(1 for b in scene.bodies if b.collide and b.kind == "sphere" and b.radius > 0.0)
    pairs = s * (s - 1) // 2
    if pairs > MAX_PAIRS:
        per_step = pairs * 1e-8 * 20          # ~20 flops per pair at ~1e8 pair-terms/s
        raise SceneError(
            f"{s} colliding spheres make {pairs:.3g} sphere-sphere pairs without a broad "
            f"phase (more than {MAX_PAIRS:.0e}): about {human_bytes(pairs * 16.0)} of pair "
            f"indices and ~{human_time(per_step)} per step. Compile with "
            "broadphase=diffpen.broadphase.Grid() (near-linear cost) or "
            "diffpen.broadphase.AABB(max_pairs).")


def check_rollout(sim, params, steps, state, save_every, observe=None) -> None:
    """Check ``sim.rollout``'s arguments; raise :class:`SceneError` saying what to change."""
    if not isinstance(params, Params):
        raise SceneError(f"rollout needs the params pytree from sim.params(k=..., c=...), got "
                         f"{type(params).__name__}"
                         + (" (None)" if params is None else "") + ".")
    steps = _int("steps", steps)
    save_every = _int("save_every", save_every)
    stored, seconds = _estimate(sim, steps, save_every, observe)
    if steps > MAX_STEPS:
        raise SceneError(
            f"steps={steps} is more than a rollout can count ({MAX_STEPS}, int32)"
            + (f"; saving every {save_every} step(s) would store {human_bytes(stored)}"
               if stored else "")
            + f" and it would take about {human_time(seconds)} at ~{STEP_RATE:.0e} "
            "body-steps/s. Roll out in pieces (pass the last state as state=) or use a "
            "larger dt.")
    mem = memory_bytes()
    if stored > 0.5 * mem:
        raise SceneError(
            f"steps={steps} with save_every={save_every} would store "
            f"{steps // save_every} states of {sim.n_bodies} bodies: {human_bytes(stored)}, "
            f"more than half of this machine's {human_bytes(mem)} (about "
            f"{human_time(seconds)} of compute). Save less often (save_every=), keep only what "
            "you need (observe=), or roll out in pieces.")
    if state is not None:
        _check_state(sim, state)


_SPECS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _spec(sim):
    """Shapes and dtypes of ``sim.init_state()`` (cached per simulator, which is frozen)."""
    try:
        return _SPECS[sim]
    except (KeyError, TypeError):
        spec = jax.eval_shape(sim.init_state)
        try:
            _SPECS[sim] = spec
        except TypeError:
            pass
        return spec


def _check_state(sim, state) -> None:
    if not isinstance(state, State):
        raise SceneError(f"state must be a diffpen.State (from sim.init_state(), or a saved "
                         f"state), got {type(state).__name__}.")
    spec = _spec(sim)
    for field in State._fields:
        want, got = getattr(spec, field), getattr(state, field)
        if field == "aux":
            if set(want) != set(got or {}):
                raise SceneError(f"state.aux has keys {sorted(got or {})}, this simulator's "
                                 f"state has {sorted(want)}: start from sim.init_state().")
            pairs = [(f"aux[{k!r}]", want[k], got[k]) for k in want]
        else:
            pairs = [(field, want, got)]
        for name, w, g in pairs:
            if w is None or g is None:
                if (w is None) != (g is None):
                    raise SceneError(f"state.{name} is {'missing' if g is None else 'given'} "
                                     f"but this simulator's state "
                                     f"{'has one' if w is not None else 'has none'}: start "
                                     "from sim.init_state().")
                continue
            shape = getattr(g, "shape", None)
            if shape is None:
                try:
                    shape = np.shape(g)
                except Exception:  # noqa: BLE001
                    shape = None
            if tuple(shape or ()) != tuple(w.shape):
                raise SceneError(f"state.{name} has shape {tuple(shape or ())}, this simulator "
                                 f"needs {tuple(w.shape)} ({sim.n_bodies} bodies): start from "
                                 "sim.init_state() and replace values with ._replace().")
            dt = getattr(g, "dtype", None)
            if dt is None or np.dtype(dt) != np.dtype(w.dtype):
                raise SceneError(f"state.{name} has dtype {dt}, this simulator runs in "
                                 f"{np.dtype(w.dtype).name}: cast it (jnp.asarray(x, "
                                 f"{np.dtype(w.dtype).name})) or start from sim.init_state().")
    for field in ("position", "velocity", "orientation", "angular_velocity"):
        v = getattr(state, field)
        if v is None or isinstance(v, jax.core.Tracer):
            continue
        a = np.asarray(v)
        bad = ~np.isfinite(a)
        if bad.any():
            body = int(np.argwhere(bad)[0][0]) if a.ndim else 0
            raise SceneError(f"the start state is not finite: state.{field} of body {body} is "
                             f"{a[body].tolist() if a.ndim else a.tolist()}. Fix the initial "
                             "state (NaN/inf in, NaN out; the time step is not the cause).")
