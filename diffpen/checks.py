"""Checks of what users give the simulator, run before anything is traced or compiled, and
of what a rollout returns:

* :func:`compile_arguments`: ``diffpen.compile``'s dt, integrator, law, smoothing, unroll and
  substeps; :func:`check_pairs`: the pair count without a broad phase;
* :func:`check_rollout` / :func:`check_rollout_options`: the params pytree, ``steps`` and
  ``save_every`` (with a size and time estimate for runs too large to hold), a given start
  state (type, shapes, dtypes, finite values), substeps and checkpoint; :func:`check_step`:
  ``sim.step``'s params and state, the same way;
* :func:`check_finite_trajectory`: a concrete trajectory that became NaN/inf, with the first
  step and body.

Each failure raises :class:`diffpen.SceneError` (or :class:`diffpen.NonFiniteError`) saying
what to change.
"""
from __future__ import annotations

import os
import warnings
import weakref

import math

import jax
import jax.numpy as jnp
import numpy as np

from .errors import (ContactWarning, NonFiniteError, PerformanceWarning, SceneError,
                     StabilityError)
from .state import Params, State

__all__ = ["compile_arguments", "check_rollout", "check_rollout_options",
           "check_finite_trajectory", "check_pairs", "check_step", "estimate", "memory_bytes",
           "human_bytes", "human_time", "STEP_RATE", "MAX_STEPS", "MAX_PAIRS"]

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


def estimate(sim, steps: int, save_every: int = 1, observe=None) -> tuple[float, float]:
    """(bytes one rollout's saved trajectory needs at its peak, seconds at STEP_RATE): the
    saved states, or with ``observe`` the saved ``observe(state)`` outputs and times. A
    rollout in the columns layout turns its saved positions and velocities into rows once,
    after the loop (diffpen.rollout): both copies exist for a moment. One rollout: a batch
    under ``jax.vmap`` is not counted."""
    n = int(sim.n_bodies)
    itemsize = np.dtype(sim.dtype).itemsize
    saved = steps // save_every
    seconds = float(steps) * max(n, 1) / STEP_RATE
    if observe is not None:
        return float(saved) * (observed_bytes(sim, observe) + itemsize), seconds
    per_body = 6 + (7 if getattr(sim.scene, "has_rotation", False) else 0)
    if getattr(sim, "columns", False):
        per_body += 6
    return float(saved) * n * per_body * itemsize, seconds


_OBSERVED: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def observed_bytes(sim, observe) -> float:
    """Bytes of one ``observe(state)`` output on this simulator's state (``jax.eval_shape``:
    nothing is computed; remembered per simulator and function), 0 when ``observe`` cannot
    be evaluated so (the rollout then reports its error)."""
    try:
        memo = _OBSERVED.setdefault(sim, weakref.WeakKeyDictionary())
        return memo[observe]
    except (KeyError, TypeError):
        pass
    try:
        out = jax.eval_shape(observe, _spec(sim))
        size = float(sum(math.prod(leaf.shape) * np.dtype(leaf.dtype).itemsize
                         for leaf in jax.tree_util.tree_leaves(out)))
    except Exception:  # noqa: BLE001 - the rollout itself reports a failing observe
        return 0.0
    try:
        _OBSERVED[sim][observe] = size
    except (KeyError, TypeError):
        pass
    return size


def compile_arguments(scene, dt, integrator, law, exponent, smoothing, unroll, substeps):
    """``diffpen.compile``'s arguments checked and normalised: ``(dt s, the Integrator record,
    the ContactLaw record, smoothing width m)``. ``smoothing="auto"`` is 0, the exact ramp:
    the integrators apply each contact's force averaged over the step (``diffpen.laws``),
    continuous through contact start and end, so no band is needed. Raises SceneError."""
    from . import laws
    from .integrators import resolve
    try:
        if isinstance(dt, (str, bytes, bool, np.bool_)):
            raise TypeError
        dt = float(dt)
    except (TypeError, ValueError):
        raise SceneError(f"dt must be a number of seconds, got {dt!r}.") from None
    if not math.isfinite(dt) or dt <= 0.0:
        raise SceneError(f"dt must be a positive, finite number of seconds, got {dt!r}; "
                         "try dt=1e-3.")
    method = resolve(integrator)
    try:
        contact_law = laws.get(law, exponent)
    except ValueError as e:
        raise SceneError(str(e)) from None
    if smoothing == "auto":
        width = 0.0
    else:
        try:
            width = float(smoothing)
        except (TypeError, ValueError):
            raise SceneError(f"smoothing must be 'auto' or a width in metres >= 0, got "
                             f"{smoothing!r}.") from None
        if not math.isfinite(width) or width < 0.0:
            raise SceneError(f"smoothing width must be >= 0 metres (0 = exact max(d, 0)), "
                             f"got {smoothing!r}.")
    if (not isinstance(unroll, (int, np.integer)) or isinstance(unroll, bool)
            or unroll < 1):
        raise SceneError(f"unroll must be a positive integer, got {unroll!r}.")
    if substeps != "auto" and (not isinstance(substeps, (int, np.integer))
                               or isinstance(substeps, bool) or substeps < 1):
        raise SceneError(f"substeps must be a positive int or 'auto', got {substeps!r}.")
    return dt, method, contact_law, width


def check_rollout_options(steps, save_every, substeps, checkpoint) -> None:
    """``steps``, ``save_every``, ``substeps`` and ``checkpoint`` of ``Simulator.rollout``
    (see its docstring). Raises SceneError."""
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps <= 0:
        raise SceneError(f"steps must be a positive int, got {steps!r}.")
    if (not isinstance(save_every, (int, np.integer)) or save_every <= 0
            or steps % save_every):
        raise SceneError(f"save_every must be a positive int dividing steps={steps}, got "
                         f"{save_every!r}.")
    if substeps is not None and (not isinstance(substeps, (int, np.integer))
                                 or isinstance(substeps, bool) or substeps < 1):
        raise SceneError(f"substeps must be a positive int or None, got {substeps!r}.")
    if checkpoint is not None and (
            not isinstance(checkpoint, (int, np.integer)) or checkpoint <= 0
            or steps % checkpoint or (checkpoint % save_every and save_every % checkpoint)):
        raise SceneError(f"checkpoint must be a positive int that divides steps={steps} and "
                         f"is a multiple or a divisor of save_every={save_every}, got "
                         f"{checkpoint!r}.")


@jax.jit
def _last_state_finite(fields):
    return jnp.all(jnp.stack([jnp.isfinite(f[-1]).all() for f in fields]))


#: Largest start spin that semi-implicit Euler is allowed to step, as ``kappa |w| h`` (rad per
#: inner step ``h``, scaled by the body's inertia anisotropy ``kappa = max |I_j - I_k| / I_i``,
#: 0 for a sphere or a cube, 1 for moments 1:2:3). It integrates Euler's equations
#: explicitly, which grows a spinning body's energy by about ``0.16 (kappa |w| h)^2`` per
#: step (over 5000 steps, worst of three spin axes: +2% at 0.005, +8% at 0.01, +42% at 0.02,
#: x2.5 at 0.03, NaN from 0.05 to 0.1); verlet and rk4 stay within 0.4% at |w| h = 0.3.
SPIN_LIMIT = 0.05


def anisotropy(inertia) -> float:
    """``kappa = max_i |I_j - I_k| / I_i`` of principal moments ``inertia`` (3,): how fast the
    gyroscopic term ``w x I w`` turns a spin, per unit ``|w|`` (0 for equal moments)."""
    i = np.asarray(inertia, dtype=float)
    return float(max(abs(i[1] - i[2]) / i[0], abs(i[0] - i[2]) / i[1],
                     abs(i[0] - i[1]) / i[2]))


def spin_anisotropy(scene) -> np.ndarray:
    """(n,) :func:`anisotropy` of each free rigid body's principal moments (0 for other
    bodies), computed once per simulator."""
    from .rigid import inertia_diagonal
    return np.array([anisotropy(inertia_diagonal(b)) if b.rigid and not b.pinned else 0.0
                     for b in scene.bodies])


def _kick_drift(sim) -> bool:
    """The simulator steps as semi-implicit Euler (by its record's step, not its name)."""
    from .integrators import kick_then_drift
    rec = getattr(getattr(sim, "analysis", None), "integrator", None)
    return kick_then_drift(rec if rec is not None else sim.integrator)


def check_spin(sim, state, substeps: int, *, auto: bool = False) -> int:
    """The inner steps a concrete start state needs so that no rigid body spins faster than
    :data:`SPIN_LIMIT` (``kappa |w| h``) under semi-implicit Euler: ``substeps`` when it is
    enough; else, with ``auto``, the count that is, and otherwise :class:`StabilityError`
    saying which dt, substeps or integrator would step it."""
    from .params import _is_concrete
    w = getattr(state, "angular_velocity", None)
    kappa = getattr(sim, "_spin_kappa", None)
    if (w is None or kappa is None or not kappa.any() or not _kick_drift(sim)
            or not _is_concrete(w) or _batched(state)):
        return substeps
    h = sim.dt / substeps
    speed = np.linalg.norm(np.asarray(w, dtype=float).reshape(-1, 3), axis=-1)
    rate = kappa * speed * h
    if not rate.size or not np.isfinite(rate).all() or rate.max() <= SPIN_LIMIT:
        return substeps
    b = int(np.argmax(rate))
    need = int(np.ceil(rate[b] / SPIN_LIMIT)) * substeps
    if auto:
        return need
    raise StabilityError(
        f"body {b} spins at |w| = {speed[b]:.4g} rad/s with inertia anisotropy kappa = "
        f"{kappa[b]:.3g}: kappa |w| h = {rate[b]:.3g} per step of {h:.3g} s. Semi-implicit "
        "Euler steps the gyroscopic term explicitly and grows such a spin's energy until it "
        f"turns NaN (above {SPIN_LIMIT}). Use dt <= {SPIN_LIMIT / (kappa[b] * speed[b]):.3g} s, "
        f"substeps={need} (or substeps='auto'), or integrator='verlet' or 'rk4' (stable to "
        "about |w| h = 0.3).",
        stable_dt=SPIN_LIMIT / (kappa[b] * speed[b]), substeps=need)


def tunnelling_table(scene):
    """The static part of :func:`check_tunnelling`, once per simulator: the colliding
    spheres ``(index (n,), radius (n,), mass (n,) with inf for pinned, material (n,))``, the
    free colliding spheres and particles the fixed spheres act on ``(index (p,), radius (p,),
    mass (p,), material (p,))`` and the fixed spheres ``(centre (f, 3), radius (f,),
    material (f,))``, or None when nothing can pass through anything."""
    bodies = scene.bodies
    idx = [i for i, b in enumerate(bodies)
           if b.kind == "sphere" and b.collide and b.radius > 0.0]
    fixed = scene.fixed_spheres
    fidx = [i for i, b in enumerate(bodies)
            if fixed and b.kind in ("sphere", "particle") and b.collide and not b.pinned]
    if len(idx) < 2 and not fidx:
        return None

    def rows(ids):
        return (np.array(ids, dtype=int), np.array([bodies[i].radius for i in ids]),
                np.array([np.inf if bodies[i].pinned else bodies[i].mass for i in ids]),
                [bodies[i].material for i in ids])
    return (rows(idx if len(idx) >= 2 else []), rows(fidx),
            (np.array([f.center for f in fixed], dtype=float).reshape(-1, 3),
             np.array([f.radius for f in fixed]), [f.material for f in fixed]))


def _impact(rel, vrel, reach):
    """Normal speed (m/s) at which bodies at relative position ``rel`` (k, 3) with relative
    velocity ``vrel`` (k, 3) (both b - a) would touch at centre distance ``reach`` (k,), moving
    in straight lines: ``|u| sqrt(1 - b^2 / reach^2)`` with ``b`` the distance between their
    paths; 0 when they move apart or their paths pass further apart than ``reach``."""
    u2 = np.einsum("ij,ij->i", vrel, vrel)
    along = -np.einsum("ij,ij->i", rel, vrel)                   # > 0: approaching
    b2 = np.einsum("ij,ij->i", rel, rel) - np.where(u2 > 0.0, along ** 2 / np.where(
        u2 > 0.0, u2, 1.0), 0.0)
    frac = np.clip(1.0 - np.maximum(b2, 0.0) / reach ** 2, 0.0, 1.0)
    return np.where(along > 0.0, np.sqrt(u2 * frac), 0.0)


def check_tunnelling(sim, params, state) -> None:
    """Warn (:class:`ContactWarning`) when, in a concrete start state, two colliding spheres
    (or a sphere or particle and a fixed sphere) would reach each other faster than their
    contact can stop before their centres meet: the kinetic energy of the normal speed they
    would touch at (straight paths from the start state: none if the paths pass further apart
    than the contact reaches), ``mu v_n^2 / 2`` (``mu`` the reduced mass), above the law's
    stored energy at the depth ``r_a + r_b`` (``ContactLaw.energy``; damping, which only
    helps, left out). Such bodies pass through each other if they meet. Start speeds only:
    what gravity or springs add on the way is not counted. A screen with the fastest speed
    and heaviest mass against the softest contact skips the pairwise check in ordinary
    scenes; more than 4000 spheres are not checked pairwise."""
    table = getattr(sim, "_tunnel_table", None)
    if table is None:
        return
    (idx, rad, mass, mats), (fidx, frad, fmass, fmats_b), (fc, fr, fmats) = table
    vel = np.asarray(state.velocity, dtype=float)
    both = np.concatenate([idx, fidx]).astype(int)
    vmax = float(np.linalg.norm(vel[both], axis=-1).max(initial=0.0)) if both.size else 0.0
    if not vmax > 0.0 or not np.isfinite(vmax):
        return
    law = sim.contact_law

    def k_of(m):
        return float(np.asarray(params.contact[m].k))
    allm = np.concatenate([mass, fmass])
    finite = allm[np.isfinite(allm)]
    m_max = float(finite.max(initial=0.0))
    k_min = min([k_of(m) for m in set(mats) | set(fmats) | {"default"} if m in params.contact]
                or [np.inf])
    r_min = min(2.0 * float(rad.min(initial=np.inf)),
                float(frad.min(initial=np.inf)) + float(fr.min(initial=np.inf)))
    if m_max * vmax ** 2 <= float(law.energy(r_min, k_min)) or len(idx) > 4000:
        return                                   # no pair can bring that much
    pos = np.asarray(state.position, dtype=float)
    from .terms.base import _pair_material
    worst = None

    def consider(ke, vn, mat, reach, a, other):
        nonlocal worst
        if mat not in params.contact:
            return
        k = k_of(mat)
        cap = float(law.energy(reach, k))
        if ke > cap and (worst is None or ke / cap > worst[0]):
            worst = (ke / cap, a, other, vn, mat, k, cap, ke)

    def reduced(ma, mb):
        inv = (1.0 / ma if np.isfinite(ma) else 0.0) + np.where(
            np.isfinite(mb), 1.0 / np.where(np.isfinite(mb), mb, 1.0), 0.0)
        return np.where(inv > 0.0, 1.0 / np.where(inv > 0.0, inv, 1.0), 0.0)
    for a in range(len(idx)):                     # sphere pairs, b > a
        reach = rad[a] + rad[a + 1:]
        vn = _impact(pos[idx[a + 1:]] - pos[idx[a]], vel[idx[a + 1:]] - vel[idx[a]], reach)
        ke = 0.5 * reduced(mass[a], mass[a + 1:]) * vn ** 2
        for c in np.nonzero(ke > 0.0)[0]:
            consider(ke[c], vn[c], _pair_material(sim.scene, mats[a], mats[a + 1 + c]),
                     reach[c], int(idx[a]), f"sphere {int(idx[a + 1 + c])}")
    for a in range(len(fidx)):                    # bodies against the fixed spheres
        reach = frad[a] + fr
        vn = _impact(fc - pos[fidx[a]], -np.broadcast_to(vel[fidx[a]], fc.shape), reach)
        ke = 0.5 * fmass[a] * vn ** 2
        for c in np.nonzero(ke > 0.0)[0]:
            consider(ke[c], vn[c], fmats[c], reach[c], int(fidx[a]), f"fixed sphere {c}")
    if worst is not None:
        ratio, i, other, vn, mat, k, cap, ke = worst
        kind = sim.scene.bodies[i].kind
        warnings.warn(
            f"{kind} {i} and {other} would meet at {vn:.3g} m/s: their contact (material "
            f"{mat!r}, k = {k:.3g}) stores at most {cap:.3g} J before their centres meet, and "
            f"they bring {ke:.3g} J: if they meet they pass through each other (a penalty "
            f"contact cannot stop them). Raise k above {k * ratio:.3g}, or slow them down.",
            ContactWarning, stacklevel=3)


def spin_unsafe(sim, state, h: float):
    """Traced counterpart of :func:`check_spin`: a bool scalar, True when a rigid body of the
    (possibly traced, e.g. vmapped) start ``state`` spins past :data:`SPIN_LIMIT`
    (``kappa |w| h``) under semi-implicit Euler, ``h`` the inner step in s. It joins the
    rollout's ``State.aux["unstable"]`` flag, so a sweep over start spins marks the rows a
    concrete rollout would refuse (they end NaN)."""
    w = getattr(state, "angular_velocity", None)
    kappa = getattr(sim, "_spin_kappa", None)
    if w is None or kappa is None or not kappa.any() or not _kick_drift(sim):
        return jnp.zeros((), bool)
    w = jnp.asarray(w)
    speed = jnp.sqrt(jnp.sum(w * w, axis=-1))
    rate = jnp.asarray(kappa, speed.dtype) * speed * h
    return jnp.any(rate > SPIN_LIMIT) | jnp.any(~jnp.isfinite(rate))


def check_finite_trajectory(traj, save_every: int, dt: float) -> None:
    """Raise NonFiniteError when a concrete trajectory became NaN/inf (traced ones pass):
    with whole states, naming the first step and body; with ``observe`` output only, saying
    so. NaN/inf positions persist (``x += h v``), so a finite last state means a finite run;
    the full scan for the first bad step runs only on failure."""
    from .params import _is_concrete
    if traj.position is None:
        leaves = jax.tree_util.tree_leaves(traj.observed)
        if leaves and all(map(_is_concrete, leaves)) and not all(
                bool(jnp.isfinite(a[-1]).all()) for a in leaves
                if jnp.issubdtype(a.dtype, jnp.inexact)):
            raise NonFiniteError(
                "the observed state became NaN/inf: the time step is probably past the "
                "stability limit for these k and c. Use a smaller dt, more substeps, or "
                "a stiffer-stable integrator (roll out without observe= to locate the "
                "step and body).")
        return
    # orientations and angular velocities too: a fast spin turns them NaN first
    fields = [f for f in (traj.position, traj.velocity, traj.orientation,
                          traj.angular_velocity) if f is not None]
    # every field concrete: under vmap over a start spin alone, a box's positions (which do not
    # depend on it) come back concrete while its angular velocities are tracers
    if not all(map(_is_concrete, fields)) or bool(_last_state_finite(fields)):
        return
    bad = np.zeros(np.shape(traj.position)[:-1], dtype=bool)
    for f in fields:
        bad |= ~np.isfinite(np.asarray(f)).all(axis=-1)
    if bad.any():
        s, b = (int(v) for v in np.argwhere(bad)[0])
        step = (s + 1) * save_every
        raise NonFiniteError(
            f"the state became NaN/inf by step {step} (t = {step * dt:.6g} s) at body "
            f"{b}: the time step is probably past the stability limit for these k and c, "
            "or for the body's spin. Use a smaller dt, more substeps, or a stiffer-stable "
            "integrator.",
            step=step, body=b)


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


def _check_params(sim, params, what: str) -> None:
    if not isinstance(params, Params):
        raise SceneError(f"{what} needs the params pytree from sim.params(k=..., c=...), got "
                         f"{type(params).__name__}"
                         + (" (None)" if params is None else "") + ".")
    from .params import validate
    validate(sim, params)


def check_step(sim, params, state) -> None:
    """Check ``sim.step``'s arguments as :func:`check_rollout` checks a rollout's: the params
    pytree and its values, the state's type, shapes, dtypes and finite values. Raises
    :class:`SceneError` saying what to change."""
    _check_params(sim, params, "step")
    _check_state(sim, state)


def check_rollout(sim, params, steps, state, save_every, observe=None) -> None:
    """Check ``sim.rollout``'s arguments; raise :class:`SceneError` saying what to change."""
    _check_params(sim, params, "rollout")
    steps = _int("steps", steps)
    save_every = _int("save_every", save_every)
    stored, seconds = estimate(sim, steps, save_every, observe)
    if steps > MAX_STEPS:
        raise SceneError(
            f"steps={steps} is more than a rollout can count ({MAX_STEPS}, int32)"
            + (f"; saving every {save_every} step(s) would store {human_bytes(stored)}"
               if stored else "")
            + f" and it would take about {human_time(seconds)} at ~{STEP_RATE:.0e} "
            "body-steps/s. Roll out in pieces (pass the last state as state=) or use a "
            "larger dt.")
    mem = memory_bytes()
    if stored > 0.5 * mem and observe is not None:
        raise SceneError(
            f"steps={steps} with save_every={save_every} and observe= would store "
            f"{steps // save_every} observed outputs of "
            f"{human_bytes(stored / (steps // save_every))} each (with their times): "
            f"{human_bytes(stored)}, more than half of this machine's {human_bytes(mem)} "
            f"(about {human_time(seconds)} of compute). Save less often (save_every=), "
            "observe less, or roll out in pieces.")
    if stored > 0.5 * mem:
        raise SceneError(
            f"steps={steps} with save_every={save_every} would store "
            f"{steps // save_every} states of {sim.n_bodies} bodies: {human_bytes(stored)}, "
            f"more than half of this machine's {human_bytes(mem)} (about "
            f"{human_time(seconds)} of compute). Save less often (save_every=), keep only what "
            "you need (observe=), or roll out in pieces.")
    if state is not None:
        _check_state(sim, state)


#: From how many steps a batched rollout that records every state is worth a warning.
RECORDING_WARN_STEPS = 64


def _batched(tree) -> bool:
    """True when a leaf of ``tree`` is being batched by ``jax.vmap`` (a batching tracer; JAX
    has no public test for it, so the tracer's class name is read:
    ``tests/test_performance_warning.py`` fails if a JAX release renames it)."""
    return any(type(leaf).__name__ == "BatchTracer" for leaf in jax.tree_util.tree_leaves(tree))


def warn_batched_recording(params, state, steps: int, save_every, observe) -> None:
    """Warn (:class:`PerformanceWarning`) when a rollout under ``jax.vmap`` records every
    state of every rollout because neither ``save_every`` nor ``observe`` was given.

    That form, ``jax.vmap(lambda k: sim.rollout(sim.params(k=k), steps).position[-1])``, is
    what one writes first, and it writes ``steps x batch x bodies`` positions, velocities and
    orientations through memory at every step to keep a few numbers: 15-34x the stepping
    floor at batch 1024-65536 against 1.3-5x for ``save_every=steps`` or ``observe=``
    (README, "Performance and scale"). An explicit ``save_every`` (1 included) says the
    whole trajectory is wanted and silences it, as does ``warnings.simplefilter("ignore",
    diffpen.PerformanceWarning)``. Only a rollout called inside ``vmap`` is seen; under
    ``vmap(jit(f))`` ``f`` is traced unbatched and nothing is said."""
    if save_every is not None or observe is not None or steps < RECORDING_WARN_STEPS:
        return
    if not (_batched(params) or _batched(state)):
        return
    warnings.warn(
        f"rollout(steps={steps}) under jax.vmap records every state of every rollout "
        "(no save_every= or observe= given); keeping only the final state or a few numbers "
        "this way is several times slower than stepping. Pass save_every=steps for the "
        "final state, observe=lambda s: ... for what you need at each step, or "
        "save_every=1 to say you want the whole trajectory (and silence this).",
        PerformanceWarning, stacklevel=3)


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
        if field == "orientation" and a.ndim == 2:
            norm = np.linalg.norm(a, axis=-1)
            off = np.abs(norm - 1.0) > 1e-3
            if off.any():
                body = int(np.argmax(off))
                raise SceneError(f"state.orientation of body {body} has norm {norm[body]:.6g}: "
                                 "orientations are unit quaternions (w, x, y, z). Normalise "
                                 "it (q / |q|), or set it with sim.state_from(body=..., "
                                 "orientation=...).")
        if field in ("velocity", "angular_velocity") and a.ndim == 2:
            moving = np.asarray(sim.pinned) & np.any(a != 0.0, axis=-1)
            if moving.any():
                body = int(np.argmax(moving))
                raise SceneError(f"state.{field} of body {body} is {a[body].tolist()}, but that "
                                 "body is pinned (fixed in space, it never moves): give it zero "
                                 f"{field.replace('_', ' ')}, or unpin it in the scene.")
    t = getattr(state, "time", None)
    if t is not None and not isinstance(t, jax.core.Tracer) and not np.all(
            np.isfinite(np.asarray(t))):
        raise SceneError(f"the start state's time is {np.asarray(t).tolist()}: give a finite "
                         "time in s (sim.init_state() starts at 0).")


#: how much coarser than at the scene's own scale (1 m or its largest body) the dtype's
#: resolution at the scene's farthest coordinate may be before it counts as far out
FAR_COARSER = 16.0


def check_coordinates(scene, dtype) -> None:
    """Refuse a scene placed so far from the origin that ``dtype`` cannot resolve its motion
    there: the spacing of representable numbers at its farthest coordinate (body positions,
    plane offsets, fixed spheres) above 1e-4 of its smallest body or 1% of the static
    deflection ``m g / k`` of its declared contact materials, where that is more than
    :data:`FAR_COARSER` times the spacing at the scene's own scale. There a step's
    displacement ``|v| dt`` rounds away (float32: a box sliding at x = 1e4 m never moved while
    friction stopped its velocity; a ball resting on a plane at z = 1e4 m froze, reading
    -0.3 m/s). Raises SceneError: move the scene near the origin, or use float64."""
    bodies = scene.bodies
    if not bodies:
        return
    pos = np.abs(np.array([b.position for b in bodies], dtype=float))
    far = float(pos.max())
    for pl in scene.planes:
        far = max(far, abs(float(pl.offset)))
    for fs in scene.fixed_spheres:
        far = max(far, float(np.max(np.abs(fs.center))) + float(fs.radius))
    sizes = [min(b.half_extents) if b.half_extents else b.radius for b in bodies]
    sizes = [s for s in sizes if s > 0.0]
    scale = max([1.0] + sizes)
    dt = np.dtype(dtype).type
    res_far = float(np.spacing(dt(far)))
    if not np.isfinite(far) or res_far <= FAR_COARSER * float(np.spacing(dt(scale))):
        return
    limits = []
    if sizes:
        limits.append((1e-4 * min(sizes), f"1e-4 of its smallest body ({min(sizes):.3g} m)"))
    g = float(np.linalg.norm(scene.gravity))
    ks = [m.k for m in scene.materials.values() if m.k]
    free = [b.mass for b in bodies if not b.pinned]
    if g > 0.0 and ks and free:
        depth = min(free) * g / max(ks)
        limits.append((0.01 * depth, f"1% of a body's resting depth m g / k ({depth:.3g} m)"))
    if not limits:
        return
    limit, what = min(limits)
    if res_far > limit:
        raise SceneError(
            f"the scene reaches {far:.4g} m from the origin, where {np.dtype(dtype).name} "
            f"resolves positions only to {res_far:.2g} m, more than {what}: a step's "
            "displacement |v| dt would round away there (bodies freeze while their velocity "
            "changes). Move the scene near the origin (only positions relative to each other "
            "and to the planes matter), or compile with dtype=float64.")
