"""Checks of what users give the simulator, run before anything is traced or compiled, and
of what a rollout returns:

* :func:`compile_arguments`: ``diffpen.compile``'s dt, integrator, law, smoothing, unroll and
  substeps; :func:`check_pairs`: the pair count without a broad phase;
* :func:`check_rollout` / :func:`check_rollout_options`: the params pytree, ``steps`` and
  ``save_every`` (with a size and time estimate for runs too large to hold), a given start
  state (type, shapes, dtypes, finite values), substeps and checkpoint; :func:`check_step`:
  ``sim.step``'s params and state, the same way;
* :func:`check_finite_trajectory`: a concrete trajectory that became NaN/inf, with the first
  step and body (from :func:`last_state_finite`, which the rollout's program computes).

What the dtype can hold and resolve (numbers past its range, a scene far from the origin)
is :mod:`diffpen.precision`.

Each failure raises :class:`diffpen.SceneError` (or :class:`diffpen.NonFiniteError`) saying
what to change.
"""
from __future__ import annotations

import os
import weakref

import math

import jax
import jax.numpy as jnp
import numpy as np

from .errors import NonFiniteError, PerformanceWarning, SceneError, warn
from .state import Params, State

__all__ = ["compile_arguments", "check_rollout", "check_rollout_options",
           "check_finite_trajectory", "last_state_finite", "check_pairs", "check_params",
           "check_step", "check_state_values", "state_values_ok",
           "estimate", "memory_bytes", "human_bytes", "human_time", "STEP_RATE", "MAX_STEPS",
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
        elif hasattr(v, "shape"):           # a JAX or NumPy array: static, so a Python int
            hint = f" ({name} is static, the compiled loop's length: pass a Python int, e.g. " \
                   f"int({name}))"
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


def _check_observe(sim, observe) -> None:
    """``observe`` must be a function of the state returning arrays: a string failed with
    "'str' object is not callable" from inside the rollout, and a function returning text
    with a raw error of JAX's scan. Raises SceneError (errors raised by ``observe`` itself
    are left to the rollout, which reports them)."""
    if not callable(observe):
        raise SceneError(f"observe must be a function of the state returning arrays (e.g. "
                         f"lambda s: s.position[:, 2]), got {observe!r}.")
    try:
        if observe in _OBSERVED[sim]:
            return                      # checked and measured by an earlier rollout
    except (KeyError, TypeError):
        pass
    try:
        out = jax.eval_shape(observe, _spec(sim))
    except TypeError as exc:
        if "valid JAX type" not in str(exc):
            return                      # the rollout itself reports a failing observe
        bad = [str(exc).split("of type ", 1)[-1].split(" at ", 1)[0]]
    except Exception:  # noqa: BLE001 - the rollout itself reports a failing observe
        return
    else:
        bad = [type(leaf).__name__ for leaf in jax.tree_util.tree_leaves(out)
               if not isinstance(leaf, jax.ShapeDtypeStruct)]
    if bad:
        raise SceneError(f"observe(state) must return arrays or a pytree of them, got "
                         f"{', '.join(sorted(set(bad)))} in its output.")


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


def one_contact_per_body(scene, builtin_terms: bool = True) -> bool:
    """Whether no body of ``scene`` can ever feel more than one force besides gravity: its
    colliding bodies are spheres or particles (no box corners), at most one pair of them
    can touch (one colliding body and one plane or fixed sphere, or two colliding bodies
    and no plane or fixed sphere), and nothing else pushes or pulls a body (no springs of
    any kind, no drag, no term from outside ``diffpen.terms.BUILTIN``; a rough material's
    friction is tangential to the contact and leaves its normal motion alone). There a law named
    by a string takes its damping at the step window's centre speed (``diffpen.laws``,
    ``centred``): semi-implicit Euler's velocity lags the position by half a step, and the
    centre speed is rebuilt from the contact's own force and gravity, which is exact for a
    body on one contact (apex heights +0.03/+0.07/+0.12% instead of 0.3-0.9% low at dt 1e-3 on the
    quick-start ball). Elsewhere it keeps the plain step average: a body on several
    contacts rests exactly with it, and would not with the centred form."""
    if not builtin_terms:
        return False
    colliding = [b for b in scene.bodies if b.collide]
    if any(b.kind == "box" for b in colliding):
        return False
    if scene.springs or scene.anchored_springs or scene.drags or scene.plastic_springs:
        return False
    statics = len(scene.planes) + len(scene.fixed_spheres)
    return (len(colliding) == 1 and statics <= 1) or (len(colliding) == 2 and statics == 0)


def compile_arguments(scene, dt, integrator, law, exponent, smoothing, unroll, substeps, *,
                      builtin_terms: bool = True):
    """``diffpen.compile``'s arguments checked and normalised: ``(dt s, the Integrator record,
    the ContactLaw record, smoothing width m)``. A law named by a string resolves to its
    centred record where :func:`one_contact_per_body` holds (``builtin_terms``: the scene
    is compiled with ``diffpen.terms.BUILTIN``'s builders only), else to its plain record.
    ``smoothing="auto"`` is 0, the exact ramp: the integrators apply each contact's force
    averaged over the step (``diffpen.laws``), continuous through contact start and end, so
    no band is needed. Raises SceneError."""
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
        contact_law = laws.get(law, exponent, centred=isinstance(law, str)
                               and one_contact_per_body(scene, builtin_terms))
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
    _check_one_contact_record(scene, method, contact_law, width, builtin_terms)
    if (not isinstance(unroll, (int, np.integer)) or isinstance(unroll, bool)
            or unroll < 1):
        raise SceneError(f"unroll must be a positive integer, got {unroll!r}.")
    if substeps != "auto" and (not isinstance(substeps, (int, np.integer))
                               or isinstance(substeps, bool) or substeps < 1):
        raise SceneError(f"substeps must be a positive int or 'auto', got {substeps!r}.")
    return dt, method, contact_law, width


def _check_one_contact_record(scene, method, contact_law, width, builtin_terms) -> None:
    """A one-contact record (``ContactLaw.one_contact``: ``linear(exact=True)``,
    ``events=True``) is a step of semi-implicit Euler for a body on one contact with the
    exact ramp; anywhere else the integrators would take the plain step average in its
    place, which is not what was asked for. Raises SceneError saying what to change."""
    need = getattr(contact_law, "one_contact", None)
    if need is None:
        return
    from .integrators import kick_then_drift
    what = f"diffpen.laws.{contact_law.name}({need}=True)"
    if not kick_then_drift(method):
        raise SceneError(f"{what} is a step of semi-implicit Euler (its velocity lags the "
                         f"position by h / 2), not of {method.name!r}; compile with "
                         f"integrator='semi_implicit_euler', or give law={contact_law.name!r}.")
    if width != 0.0:
        raise SceneError(f"{what} steps the exact contact (smoothing 0), not a smoothed band "
                         f"of {width:g} m; leave smoothing='auto' (or 0), or give "
                         f"law={contact_law.name!r}.")
    if not one_contact_per_body(scene, builtin_terms):
        raise SceneError(f"{what} rebuilds each contact's motion from that contact and "
                         "gravity alone, so it needs a scene where no body can feel more than "
                         "one force besides gravity (spheres or particles, one pair that can "
                         "touch, no box, spring, drag or custom term); this scene has more. "
                         f"Give law={contact_law.name!r} (its records fit any scene).")


def check_rollout_options(steps, save_every, substeps, checkpoint, **flags) -> None:
    """``steps``, ``save_every``, ``substeps`` and ``checkpoint`` of ``Simulator.rollout``
    (see its docstring), and its switches ``flags`` (``check_stability``, ``check_finite``:
    True or False; None switched the stability check off, "no" left it on). Raises
    SceneError."""
    for name, value in flags.items():
        if not isinstance(value, (bool, np.bool_)):
            raise SceneError(f"{name} must be True or False, got {value!r}.")
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps <= 0:
        raise SceneError(f"steps must be a positive int, got {steps!r}.")
    if (not isinstance(save_every, (int, np.integer)) or save_every <= 0
            or steps % save_every):
        raise SceneError(f"save_every must be a positive int dividing steps={steps}, got "
                         f"{save_every!r}.")
    if isinstance(substeps, str) and substeps == "auto":
        raise SceneError(
            "rollout(substeps=...) takes a positive int or None (the compiled count); "
            "'auto' is an option of compile: dp.compile(scene, dt, substeps=\"auto\") picks "
            "the smallest sufficient count from each rollout's concrete k and c. Under jit "
            "give the count: sim.rollout(params, steps, substeps=n).")
    if substeps is not None and (not isinstance(substeps, (int, np.integer))
                                 or isinstance(substeps, bool) or substeps < 1):
        raise SceneError(f"substeps must be a positive int or None, got {substeps!r}.")
    if checkpoint is not None and (
            not isinstance(checkpoint, (int, np.integer)) or checkpoint <= 0
            or steps % checkpoint or (checkpoint % save_every and save_every % checkpoint)):
        raise SceneError(f"checkpoint must be a positive int that divides steps={steps} and "
                         f"is a multiple or a divisor of save_every={save_every}, got "
                         f"{checkpoint!r}.")


def _checked_fields(traj) -> list:
    """The arrays :func:`check_finite_trajectory` checks: the saved states' positions,
    velocities, orientations and angular velocities (a fast spin turns the last two NaN
    first), or, for an ``observe`` rollout, the observed pytree's float leaves."""
    if traj.position is None:
        return [a for a in jax.tree_util.tree_leaves(traj.observed)
                if jnp.issubdtype(a.dtype, jnp.inexact)]
    return [f for f in (traj.position, traj.velocity, traj.orientation,
                        traj.angular_velocity) if f is not None]


def last_state_finite(traj) -> jax.Array:
    """() bool: every checked field of the last saved state is finite. Traceable: the
    rollout computes it inside its own program (one reduction after the loop), so checking
    a trajectory compiles nothing and moves nothing to the host. NaN/inf positions persist
    (``x += h v``), so a finite last state means a finite run."""
    fields = _checked_fields(traj)
    if not fields:
        return jnp.asarray(True)
    return jnp.all(jnp.stack([jnp.isfinite(f[-1]).all() for f in fields]))


def check_finite_trajectory(traj, save_every: int, dt: float, finite=None) -> None:
    """Raise NonFiniteError when a concrete trajectory became NaN/inf (traced ones pass):
    with whole states, naming the first step and body; with ``observe`` output only, saying
    so. ``finite``: :func:`last_state_finite` of ``traj`` as the rollout's program computed
    it (None: computed here, on the host); the full scan for the first bad step runs only
    on failure."""
    from .params import _is_concrete
    fields = _checked_fields(traj)
    # every field concrete: under vmap over a start spin alone, a box's positions (which do not
    # depend on it) come back concrete while its angular velocities are tracers
    if not fields or not all(map(_is_concrete, fields)):
        return
    if finite is not None and _is_concrete(finite):
        ok = bool(finite)
    else:
        ok = all(bool(np.isfinite(np.asarray(f[-1])).all()) for f in fields)
    if ok:
        return
    if traj.position is None:
        raise NonFiniteError(
            "the observed state became NaN/inf: the time step is probably past the "
            "stability limit for these k and c. Use a smaller dt, more substeps, or "
            "a stiffer-stable integrator (roll out without observe= to locate the "
            "step and body).")
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


def check_params(sim, params, what: str) -> None:
    """``params`` must be the pytree of ``sim.params``, its concrete values valid; ``what``
    names the caller in the error (``"rollout"``, ``"sim.forces"``...). Raises SceneError."""
    if not isinstance(params, Params):
        raise SceneError(f"{what} needs the params pytree from sim.params(k=..., c=...), got "
                         f"{type(params).__name__}"
                         + (" (None)" if params is None else "") + ".")
    from .params import validate
    validate(sim, params)


def check_step(sim, params, state) -> None:
    """Check ``sim.step``'s arguments as :func:`check_rollout` checks a rollout's: the params
    pytree and its values, the state's type, shapes and dtypes (a signature seen before is
    not checked again). The state's values (finite, unit quaternions, pins at rest) are
    checked by the step's own program instead (:func:`state_values_ok`, read as one bool
    after the step: a per-step conversion of the state to NumPy cost a third of a small
    step's time); :func:`check_state_values` then names what is wrong. Raises
    :class:`SceneError` saying what to change."""
    check_params(sim, params, "step")
    leaves, tree = jax.tree_util.tree_flatten(state)
    sig = (tree, tuple((np.shape(v), getattr(v, "dtype", None)) for v in leaves))
    seen = _SEEN.setdefault(sim, set())
    if sig not in seen:
        _check_structure(sim, state)
        if len(seen) < 64:
            seen.add(sig)


def state_values_ok(sim, state):
    """Traceable bool scalar: ``state``'s values pass :func:`check_state_values` (finite time,
    positions and velocities, unit quaternions within 1e-3, pinned bodies at rest)."""
    ok = jnp.all(jnp.isfinite(jnp.asarray(state.time)))
    pinned = np.asarray(sim.pinned, bool)
    for field in ("position", "velocity", "orientation", "angular_velocity"):
        v = getattr(state, field)
        if v is None:
            continue
        ok &= jnp.all(jnp.isfinite(v))
        if field == "orientation":
            ok &= jnp.all(jnp.abs(jnp.linalg.norm(v, axis=-1) - 1.0) <= 1e-3)
        elif field != "position" and pinned.any():
            ok &= ~jnp.any(pinned & jnp.any(v != 0.0, axis=-1))
    return ok


def check_rollout(sim, params, steps, state, save_every, observe=None) -> None:
    """Check ``sim.rollout``'s arguments; raise :class:`SceneError` saying what to change."""
    check_params(sim, params, "rollout")
    if observe is not None:
        _check_observe(sim, observe)
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
    warn(
        f"rollout(steps={steps}) under jax.vmap records every state of every rollout "
        "(no save_every= or observe= given); keeping only the final state or a few numbers "
        "this way is several times slower than stepping. Pass save_every=steps for the "
        "final state, observe=lambda s: ... for what you need at each step, or "
        "save_every=1 to say you want the whole trajectory (and silence this).",
        PerformanceWarning)


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


#: state signatures (tree and leaf shapes and dtypes) that passed :func:`_check_structure`,
#: per simulator (at most 64 each)
_SEEN: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _check_state(sim, state) -> None:
    _check_structure(sim, state)
    check_state_values(sim, state)


def _check_structure(sim, state) -> None:
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
                got = f"dtype {dt}" if dt is not None else f"no dtype ({type(g).__name__})"
                raise SceneError(f"state.{name} has {got}, this simulator runs in "
                                 f"{np.dtype(w.dtype).name}: cast it (jnp.asarray(x, "
                                 f"{np.dtype(w.dtype).name})) or start from sim.init_state().")


def check_state_values(sim, state) -> None:
    """Raise :class:`SceneError` naming the first value of a concrete ``state`` that is not
    finite, a quaternion off unit norm, or a pinned body moving (fields that are jit tracers
    are left out)."""
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
