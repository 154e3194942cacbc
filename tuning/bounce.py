"""The bounce problem: fit contact k and c of a sphere bouncing on a plane to targets.

Targets (:data:`BOUNCE_METRICS`): apex heights, settling time, contact durations,
restitution, maximum penetration. :func:`check_bounce_targets` refuses targets no (k, c) can
reach before anything is compiled; :func:`bounce_metrics_fn` is the traceable metrics
function; :func:`first_guess_bounce` the closed-form start; :func:`fit_bounce` (behind
``diffpen fit``) puts them together and runs :func:`tuning.fit.fit`;
:func:`step_restitution_error` (from :mod:`tuning.step_error`) is the time step's own
restitution error at a (k, c), which the fit notes when it is large.
"""
from __future__ import annotations

import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .compiled import compiled
from .errors import FitError, positive_int
from .metrics import check_ball_model
from .fit import FitResult, check_method, fit
from .problem import FreeLeaves, normalise_targets
from .compiled import ProgramCache
from .stable import (contact_scales, law_c, law_k, law_units, rollout_unstable,
                     safe_contact_bounds)
from .bounce_start import apex_settle_search, event_search
from .step_error import step_error_note, step_restitution_error

__all__ = ["BOUNCE_METRICS", "EVENT_TARGETS", "check_bounce_targets", "bounce_metrics_fn",
           "first_guess_bounce", "fit_bounce", "step_restitution_error", "law_units"]


#: Metrics a bounce fit can target, with their default relative tolerances.
#: A settling-time fit's rollout lasts at least this many times the target (an unsettled
#: ball's settling time reads as the rollout's end, far outside the target's tolerance).
SETTLE_MARGIN = 1.1

#: Fewest steps :func:`fit_bounce` rolls out: a coarser dt cannot resolve the fall and the
#: bounces the targets describe.
MIN_STEPS = 100

#: Masses (kg) :func:`fit_bounce` fits a ball of: its stiffness and damping scale as 1e4 m
#: and 1e2 m, and their products (k m, c^2) must stay inside float64's range.
MASS_RANGE = (1e-100, 1e100)

#: Most steps one :func:`fit_bounce` rollout takes: a fit rolls out about a hundred times, so
#: dt = 1e-7 s (38 million steps on the default ball) ran for days without a word.
MAX_STEPS = 1_000_000

#: A decay-time fit's default rollout lasts at least this many times the target: the decay
#: time is reported only when the energy left at the end is at most
#: ``tuning.metrics.DECAY_TAIL`` of the start's (ln 1000 ~ 6.9 decay times for an
#: exponential decay; a bouncing ball's energy dies out sooner).
DECAY_MARGIN = 8.0

BOUNCE_METRICS = {"apex_heights": 1e-3, "settling_time": 5e-3, "contact_durations": 2e-3,
                  "restitution": 1e-3, "max_penetration": 2e-3, "decay_time": 2e-3}

#: Targets that name events of the rollout: a rebound (apex, restitution) or the end of a
#: contact. Where the model does not have them their metric is nan, with no gradient that
#: leads to them: :func:`fit_bounce` starts where they occur
#: (:func:`tuning.bounce_start.event_search`).
EVENT_TARGETS = ("apex_heights", "restitution", "contact_durations")


def _fall_time(h0: float, v0: float, g: float) -> float:
    """Time for the lowest point to reach the surface from height h0 (m), velocity v0 (m/s)."""
    return (v0 + math.sqrt(v0 * v0 + 2.0 * g * h0)) / g


def _check_settle_tol(settle_tol) -> float:
    """The settling band (m): a finite number > 0, else :class:`FitError` (a NaN band made
    every state "settled" at t = 0, a band <= 0 none ever)."""
    if isinstance(settle_tol, bool) or not isinstance(settle_tol, (int, float, np.floating,
                                                                  np.integer)) \
            or not (math.isfinite(settle_tol) and settle_tol > 0.0):
        raise FitError(f"settle_tol (the settling band, m) must be a finite number > 0, got "
                       f"{settle_tol!r}; e.g. 1e-3.")
    return float(settle_tol)


def check_bounce_targets(scene: dp.Scene, targets: dict, *, body: int = 0, plane: int = 0,
                         settle_tol: float = 1e-3) -> dict:
    """Validate bounce targets against the scene BEFORE anything is compiled.

    Raises :class:`FitError` saying what to change for targets no (k, c) can reach: an apex at
    or above the drop height, apexes that do not decrease, a settling time shorter than the
    fall to the ground (plus the flights the apex targets imply), non-positive values.
    Returns a dict of facts used by the fit (drop apex, fall time, gravity, mass, radius).
    """
    unknown = set(targets) - set(BOUNCE_METRICS)
    if unknown:
        raise FitError(f"unknown target(s) {sorted(unknown)}; bounce fits know "
                       f"{sorted(BOUNCE_METRICS)}.")
    if not scene.planes:
        raise FitError("a bounce fit needs a plane for the body to bounce on.")
    if not 0 <= body < scene.n_bodies:
        raise FitError(f"body {body} is not in the scene ({scene.n_bodies} bodies).")
    _check_plane(scene, plane)
    _check_ball(scene, body)
    _check_settle_tol(settle_tol)
    b = scene.bodies[body]
    pl = scene.planes[plane]
    n = np.asarray(pl.normal)
    g = float(-np.dot(scene.gravity, n))
    if g <= 0.0:
        raise FitError("bounce targets need gravity pointing into the plane.")
    h0 = float(np.dot(b.position, n) - pl.offset - b.radius)
    v0 = float(np.dot(b.velocity, n))
    if h0 <= 0.0:
        raise FitError(f"body {body} starts in contact (lowest point {h0:.4g} m above the "
                       "plane): start it above the surface.")
    drop = h0 + v0 ** 2 / (2.0 * g)   # energy height: the first impact speed, either sign
    t_fall = _fall_time(h0, v0, g)
    tg = normalise_targets(targets)
    for name, arr in tg.items():
        if np.any(arr <= 0.0):
            raise FitError(f"target {name!r} must be positive, got {arr.tolist()}.")
    apex = tg.get("apex_heights")
    if apex is not None:
        if apex[0] >= drop:
            raise FitError(
                f"infeasible target: first apex {apex[0]:.4g} m is not below the drop height "
                f"{drop:.4g} m (lowest point); a passive contact cannot add energy. Give an "
                f"apex below {drop:.4g} m or raise the drop height.")
        if np.any(np.diff(apex) >= 0.0):
            raise FitError(f"infeasible target: apex heights must decrease bounce by bounce, "
                           f"got {apex.tolist()}.")
    e = tg.get("restitution")
    if e is not None and np.any(e >= 1.0):
        raise FitError(f"infeasible target: restitution must be below 1, got {e.tolist()}.")
    ts = tg.get("settling_time")
    if ts is not None:
        need = t_fall
        if apex is not None:   # the flights of the targeted bounces that leave the band
            need += float(np.sum(2.0 * np.sqrt(2.0 * apex[apex > settle_tol] / g)))
        if ts[0] <= need:
            what = "the fall to the ground" if apex is None else (
                "the fall plus the flights of the targeted bounces")
            raise FitError(
                f"infeasible target: settling time {ts[0]:.4g} s is shorter than {what} "
                f"({need:.4g} s); the body cannot be within {settle_tol:g} m of rest before. "
                f"Give a settling time above {need:.4g} s.")
    return {"drop": drop, "t_fall": t_fall, "g": g, "mass": b.mass, "radius": b.radius,
            "h0": h0, "v0": v0, "material": pl.material}


def _check_ball(scene: dp.Scene, body: int) -> None:
    try:        # springs or drag on the body: not the ball the metrics model
        check_ball_model(scene, body)
    except ValueError as exc:
        raise FitError(str(exc)) from None


def _check_plane(scene: dp.Scene, plane) -> None:
    """``plane``: an index into ``scene.planes``, else :class:`FitError`."""
    if isinstance(plane, bool) or not isinstance(plane, (int, np.integer)) \
            or not 0 <= plane < len(scene.planes):
        raise FitError(f"plane {plane!r} is not in the scene: give an index 0..."
                       f"{len(scene.planes) - 1} of its {len(scene.planes)} plane(s).")


def bounce_metrics_fn(sim, steps: int, *, body: int = 0, plane: int = 0, n_apex: int = 3,
                      settle_tol: float = 1e-3, save_every: int = 1,
                      decay_cut: str = "nan") -> Callable:
    """``params -> {metric: value}`` for a sphere bouncing on a plane (traceable).

    Rolls out ``steps`` steps of ``sim`` and returns the fields of
    :class:`tuning.metrics.BallMetrics` as a dict. A settling time not reached within the
    rollout is reported as the rollout's end time (a lower bound) for the optimiser. A decay
    time cut short by the rollout's end (``decay_valid`` False) is nan, or with
    ``decay_cut="bound"`` (what :func:`fit_bounce` uses, never calling it reached) its
    integral over the rollout, a lower bound that still moves with k and c.
    ``"unstable"`` (bool) is true when the rollout went past its safe step
    (:func:`tuning.stable.rollout_unstable`): fits report such a point as not reached and
    sweeps return NaN for it.
    """
    # checked here, not when the function is first traced (an empty jnp.stack, an index
    # error)
    if isinstance(body, bool) or not isinstance(body, (int, np.integer)) \
            or not 0 <= body < sim.n_bodies:
        raise FitError(f"body {body!r} is not in the scene: give an index 0..."
                       f"{sim.n_bodies - 1} of its {sim.n_bodies} bodies.")
    if not sim.scene.planes:
        raise FitError("bounce metrics need a plane for the body to bounce on.")
    _check_plane(sim.scene, plane)
    _check_ball(sim.scene, body)
    positive_int("n_apex", n_apex, "how many bounces are reported")
    positive_int("steps", steps, "the rollout's length")
    _check_settle_tol(settle_tol)
    key = (sim, steps, body, plane, n_apex, float(settle_tol), save_every, decay_cut)
    return _METRICS_FNS.get(key, lambda: _bounce_metrics(sim, steps, *key[2:]))


#: the last 8 bounce metrics functions (equal arguments, the same function: fits share programs)
_METRICS_FNS = ProgramCache()


def _bounce_metrics(sim, steps, body, plane, n_apex, settle_tol, save_every, decay_cut):
    from .metrics import ball_metrics
    t_end = steps * sim.dt

    def metrics_fn(params):
        s0 = sim.init_state()
        traj = sim.rollout(params, steps, s0, save_every=save_every, check_finite=False)
        m = ball_metrics(sim, traj, params, body=body, plane=plane, n_apex=n_apex,
                         settle_tol=settle_tol, state0=s0, decay_cut=decay_cut)._asdict()
        m["settling_time"] = jnp.where(m["settled"], m["settling_time"], t_end)
        m["unstable"] = rollout_unstable(sim, traj, params)   # fits and sweeps refuse these
        return m
    return metrics_fn


def first_guess_bounce(info: dict, targets: dict, *, law="linear", k0: float = 1e4):
    """Closed-form start (k, c) from bounce targets (docs/physics-notes.md section 2).

    The first apex gives the restitution ``e = sqrt(A_1 / H_0)`` and so the damping ratio; a
    contact-duration target gives w0 and hence k; otherwise k stays ``k0`` (a settling-time
    target is then met by a 1-D search over k, see :func:`fit_bounce`).
    Returns (k N/m, c N s/m, zeta or None).
    """
    m = info["mass"]
    zeta = None
    # the law's closed forms, or the linear law's as a start for laws without any
    family = dp.laws.get(law).closed_form or "linear"
    if "apex_heights" in targets:
        e = math.sqrt(float(np.atleast_1d(targets["apex_heights"])[0]) / info["drop"])
        zeta = float(dp.physical.zeta_from_restitution(e, family))
    elif "restitution" in targets:
        e = float(np.atleast_1d(targets["restitution"])[0])
        zeta = float(dp.physical.zeta_from_restitution(e, family))
    if zeta is not None and "contact_durations" in targets:
        tc = float(np.atleast_1d(targets["contact_durations"])[0])
        k, c = dp.physical.kc_from_restitution(e, tc, m, family)
        return float(k), float(c), zeta
    z = 0.1 if zeta is None else zeta
    return k0, 2.0 * z * math.sqrt(k0 * m), zeta


def fit_bounce(scene: dp.Scene, targets: dict, *, dt: float = 1e-3, law: str = "linear",
               body: int = 0, plane: int = 0, settle_tol: float = 1e-3, k0: float | None = None,
               c0: float | None = None, free=None, method: str = "lm", optimizer=None,
               maxiter: int | None = None, rtol=None, weights: dict | None = None,
               duration: float | None = None, progress: bool | None = False,
               first_guess: bool = True, **compile_kw) -> FitResult:
    """Fit contact k and c of a sphere bouncing on a plane to apex/settling/contact targets.

    Checks the targets against the scene first (:func:`check_bounce_targets`), then compiles,
    starts from the closed-form first guess (:func:`first_guess_bounce`; with apex and
    settling-time targets, :func:`tuning.bounce_start.apex_settle_search` scans k with c
    solved for the apex and bisects the settling time along that curve), and runs
    :func:`fit`. Targets that name
    events (:data:`EVENT_TARGETS`: a rebound, the end of a contact) start where the model has
    them: at a start without them c is lowered (or k raised) step by step until they occur
    (the notes say so); an absent event counts as a residual of
    :data:`tuning.problem.ABSENT_ERROR`, so the point reported has them whenever one the fit
    visited did. Stiffness stays below the accuracy limit ``w0 dt <= 0.25`` of the explicit
    step; that does not bound the restitution error of a damped contact, so the time step's
    own restitution error at the fitted point is measured (:func:`step_restitution_error`)
    and noted when above :data:`tuning.step_error.STEP_ERROR_NOTE` (1%).

    Bounce heights alone fix only the damping ratio: with apex/restitution targets but no
    settling-time or contact-duration target, k is held at ``k0`` and only c is fitted (the
    result's ``notes`` say so).

    Args:
      scene: the scene (the body must start above the plane).
      targets: ``{"apex_heights": [m, ...], "settling_time": s, "contact_durations": [s],
        "restitution": [...], "max_penetration": m, "decay_time": s}``; apexes are of the
        lowest point above the surface.
      dt: time step, s.  law: contact law.  settle_tol: settling band, m.
      k0, c0: start values (N/m, N s/m); default from the first guess.
      free: leaf paths to fit (default: k and c of the plane's material).
      method: ``"lm"`` (default) or ``"optax"`` (with ``optimizer``).
      maxiter: default 40 (lm) or 400 (optax).
      rtol: per-metric relative tolerances (default :data:`BOUNCE_METRICS`).
      duration: rollout length, s (default: covers the targets with margin, for a
        decay-time target :data:`DECAY_MARGIN` x the target + 0.2 s, rounded up to one of 8
        step counts per octave). A later call on an equal scene with the same ``dt``, law
        and ``compile_kw`` reuses its simulator (:func:`tuning.compiled.compiled`), and with
        the same step count its compiled fit: another target set then compiles nothing.
      progress: False (default): print nothing; None or True: progress on stderr (a bar on a
        terminal, else a line every 5 s; what the ``diffpen`` command passes).
    Returns: :class:`FitResult` (``notes`` lists what was held fixed and why).
    """
    check_method(method)                    # before anything is compiled or run
    if maxiter is not None:
        positive_int("maxiter", maxiter, "the iteration limit")
    info = check_bounce_targets(scene, targets, body=body, plane=plane, settle_tol=settle_tol)
    tg = {k: np.atleast_1d(np.asarray(v, float)) for k, v in targets.items()}
    notes = []
    mat = info["material"]
    g, m = info["g"], info["mass"]
    if not MASS_RANGE[0] <= m <= MASS_RANGE[1]:
        # the start's k ~ 1e4 m and c ~ sqrt(k m): a 1e-300 kg ball's damping underflowed to
        # 0 and the fit stopped on "math domain error"
        raise FitError(f"the ball's mass {m:g} kg is outside {MASS_RANGE[0]:g}.."
                       f"{MASS_RANGE[1]:g} kg, where the fit's stiffness and damping (k about "
                       "1e4 m N/m, c about sqrt(k m) N s/m) stay well inside the float range: "
                       "give the mass in kg (or rescale the units).")
    n_apex = max([tg[k].size for k in ("apex_heights", "restitution", "contact_durations")
                  if k in tg] + [1])
    given = duration is not None
    if duration is None:
        if "settling_time" in tg:
            duration = 1.4 * float(tg["settling_time"][0]) + 0.2
        else:
            a = tg.get("apex_heights", np.array([0.5 * info["drop"]]))
            flights = np.sum(2.0 * np.sqrt(2.0 * np.maximum(a, 1e-6) / g))
            duration = 1.3 * (info["t_fall"] + flights) + 0.3
        if "decay_time" in tg:
            # the decay must have died out by the end, or the metric is nan (cut short)
            duration = max(duration, DECAY_MARGIN * float(tg["decay_time"][0]) + 0.2)
    elif "decay_time" in tg and duration <= float(tg["decay_time"][0]):
        # int E dt / E(0) < duration: never reached; a rollout that ends before the energy
        # has died out gives nan (tuning.metrics.DECAY_TAIL), so longer is needed anyway
        raise FitError(f"duration {duration:g} s is too short for the decay-time target "
                       f"{float(tg['decay_time'][0]):g} s: the decay time is only measured "
                       "when the energy has died out by the end of the rollout. Give a "
                       f"duration of several times the target, or leave it out (default "
                       f"{DECAY_MARGIN:g} x the target + 0.2 s).")
    elif "settling_time" in tg and duration < SETTLE_MARGIN * float(tg["settling_time"][0]):
        # an unsettled ball's settling time is the rollout's end (bounce_metrics_fn): within
        # a tolerance of the target it would count as reached
        raise FitError(f"duration {duration:g} s is too short for the settling-time target "
                       f"{float(tg['settling_time'][0]):g} s: a ball still moving at the end "
                       "could not be told from one that settled on time. Give a duration of "
                       f"at least {SETTLE_MARGIN:g} x the target, or leave it out (default "
                       "1.4 x the target + 0.2 s).")
    if given and duration <= info["t_fall"]:
        # no contact in the rollout: every metric is missing, the fit only wanders
        raise FitError(f"duration {duration:g} s ends before the ball first lands (it falls "
                       f"for {info['t_fall']:.3g} s): give a longer duration (diffpen fit "
                       "--duration), or leave it out (default: covers the targets with "
                       "margin).")
    if not (isinstance(dt, (int, float, np.floating, np.integer)) and not isinstance(dt, bool)
            and math.isfinite(dt) and dt > 0.0):
        raise FitError(f"time step dt must be a finite number of seconds > 0, got {dt!r} "
                       "(default 1e-3 s).")
    ratio = duration / dt
    if not ratio <= MAX_STEPS:
        raise FitError(f"time step dt = {dt:g} s needs about {ratio:.3g} steps for the "
                       f"{duration:.3g} s rollout "
                       + ("(duration)" if given else "the targets need") +
                       f", and a fit rolls it out about a hundred times: at most {MAX_STEPS} "
                       f"steps a rollout. Give dt >= {duration / MAX_STEPS:.3g} s (default "
                       "1e-3 s).")
    steps = int(math.ceil(ratio))
    if steps < MIN_STEPS:
        raise FitError(f"time step dt = {dt:g} s leaves {steps} step(s) in the "
                       f"{duration:.3g} s rollout "
                       + ("(duration)" if given else "the targets need") +
                       f": at least {MIN_STEPS} are needed to resolve the fall and the "
                       f"bounces. Give dt <= {duration / MIN_STEPS:.3g} s (default 1e-3 s).")
    if not given:           # one of 8 lengths per octave (at most 12.5% longer): fits of
        unit = 1 << max(steps.bit_length() - 4, 0)     # nearby targets share their programs
        steps = min(-(-steps // unit) * unit, max(steps, MAX_STEPS))    # never past the cap
        duration = steps * dt
    sim = compiled(scene, dt, law=law, **compile_kw)    # an equal earlier call's simulator
    mfn = bounce_metrics_fn(sim, steps, body=body, plane=plane, n_apex=n_apex,
                            settle_tol=settle_tol, decay_cut="bound")
    # Accuracy limit of the explicit step: w0 dt <= 0.25 (docs/physics-notes.md section 4);
    # beyond it a fit would tune the integrator's error instead of the contact. It does not
    # keep the restitution error small once the contact is damped: the error grows with
    # c dt / m = 2 zeta w0 dt. Measured (a gravity-free impact against the closed form
    # exp(-zeta pi / sqrt(1 - zeta^2)), semi-implicit Euler, the default law): at
    # w0 dt = 0.05, -0.07% at zeta 0.1, -0.78% at 0.3, -2.98% at 0.5; at w0 dt = 0.25, -3.2%
    # at zeta 0.3 and -13.3% at 0.5 (laws.linear(centred=True): within 0.01-0.9% in the same
    # cases). So the error at the fitted point is measured after the fit and noted above
    # step_error.STEP_ERROR_NOTE. A start above the limit is lowered BEFORE the first guess.
    # A law whose stiffness grows with depth (Hunt-Crossley: k N/m^n, c N s/m^(n+1)) takes
    # these limits and the linear closed forms at its stiffness and damping at the depth the
    # drop's energy allows (tuning.stable.law_k / law_c, as the safe step counts them).
    start = sim.init_state()
    ku = law_units(sim.contact_law)[0]

    def linear_k(k):                # the law's k -> its stiffness there, N/m
        return k * contact_scales(sim, k, state=start)[0]
    kmax = law_k(sim, (0.25 / dt) ** 2 * m, state=start)
    k_first = law_k(sim, 1e4 * m, state=start) if k0 is None else float(k0)
    if k_first > kmax:
        notes.append(f"start k {k_first:.4g} {ku} lowered to {kmax:.4g} {ku}, the accuracy "
                     f"limit w0 dt <= 0.25 at dt = {dt:g} s (use a smaller dt for stiffer "
                     "contact)")
        k_first = kmax
        k0 = kmax if k0 is not None else None
    if dp.laws.get(law).closed_form is not None:     # the law's own closed forms: its units
        kk, cc, zeta = first_guess_bounce(info, tg, law=law, k0=k_first)
    else:                                            # the linear ones: N/m, N s/m
        k_lin = linear_k(k_first)
        kk_lin, cc_lin, zeta = first_guess_bounce(info, tg, law=law, k0=k_lin)
        # (without a contact-duration target the guess keeps k0 as given)
        kk = k_first if kk_lin == k_lin else law_k(sim, kk_lin, state=start)
        cc = law_c(sim, cc_lin, kk, state=start)
    heights_only = (("apex_heights" in tg or "restitution" in tg)
                    and not ({"settling_time", "contact_durations", "max_penetration",
                              "decay_time"} & set(tg)))
    kpath, cpath = f"contact.{mat}.k", f"contact.{mat}.c"
    if free is None:
        free = [kpath, cpath]
        if heights_only:
            free = [cpath]
            notes.append(f"bounce heights alone fix only the damping ratio (zeta ~ "
                         f"{zeta:.3g}); k is held at {kk:.4g} {ku} and only c is fitted. Give "
                         "a settling-time, decay-time or contact-duration target to fit k as "
                         "well.")
    starts = None
    if (first_guess and k0 is None and zeta is not None and "settling_time" in tg
            and "contact_durations" not in tg and kpath in free):
        # k is set by the settling time: start LM from the best points of a 1-D scan over k
        # at the damping ratio the apex implies (ranked with the fit's own compiled function).
        ks = np.geomspace(1e-3 * kmax, kmax, 32)
        starts = [{kpath: float(k), cpath: law_c(sim, 2.0 * zeta * math.sqrt(linear_k(k) * m),
                                                  float(k), state=start)}
                  for k in ks if cpath in free]
        notes.append(f"start: damping ratio {zeta:.4g} from the first apex; k from the best "
                     f"of a 32-point scan over {ks[0]:.3g}..{ks[-1]:.3g} {ku} (w0 dt <= 0.25)")
    if c0 is not None:
        cc = c0
    if k0 is not None:
        kk = k0
    if kk > kmax:
        notes.append(f"start k {kk:.4g} {ku} lowered to {kmax:.4g} {ku}, the accuracy limit "
                     f"w0 dt <= 0.25 at dt = {dt:g} s (use a smaller dt for stiffer contact)")
        kk = kmax
    params0 = sim.params(contact={mat: (kk, cc)})
    k_low = min(1e-3 * kmax, kk)
    # c dt / m < 1: inside the safe step (its damping at the depth of the softest k allowed)
    c_safe = safe_contact_bounds(sim, m, state=start, k_min=k_low)[1]
    bounds = {kpath: (k_low, kmax), cpath: (min(1e-6, 1e-3 * c_safe), c_safe)}
    tol = dict(BOUNCE_METRICS)
    if rtol is not None:
        tol.update(rtol if isinstance(rtol, dict) else {k: rtol for k in tol})
    # the targets' tolerances (a name given in rtol that is not a target is refused by fit)
    tol = {k: v for k, v in tol.items()
           if k in targets or (isinstance(rtol, dict) and k in rtol)}
    search = None
    if starts is not None and method == "lm" and free == [kpath, cpath]:
        search = apex_settle_search([math.log(s[kpath]) for s in starts],
                                     [math.log(s[cpath]) for s in starts])
        notes[-1] += ("; along the curve where the first apex is met (Newton on c), the "
                      "settling time is matched by bisection on k")
        starts = None
    n_starts = 3
    need = {n: int(tg[n].size) for n in EVENT_TARGETS if n in tg}
    if need and search is None and set(free) <= {kpath, cpath}:
        # a start without the targeted events (no rebound; a contact that does not end) has
        # no gradient towards them: start where they occur (c lowered step by step)
        look = event_search(free, {kpath: kk, cpath: cc}, need, tg, notes, kpath=kpath,
                             cpath=cpath)
        if method == "lm":      # with the fit's own compiled function
            search, n_starts = look, (1 if starts is None else n_starts)
        else:                   # optax: a forward rollout per step, then start there
            leaves = FreeLeaves.build(params0, free, {p: bounds[p] for p in free})
            fwd = jax.jit(lambda th: mfn(leaves.params_of(th)))
            found = look(lambda th: (None, None, jax.device_get(fwd(jnp.asarray(th)))), None,
                         leaves.log_lo, leaves.log_hi)
            if found:
                val = dict(zip(free, np.exp(found[0])))
                kk, cc = float(val.get(kpath, kk)), float(val.get(cpath, cc))
                params0 = sim.params(contact={mat: (kk, cc)})
    res = fit(mfn, params0, dict(targets), free=free,
              bounds={p: bounds[p] for p in free if p in bounds},
              weights=weights, rtol=tol, method=method, optimizer=optimizer, progress=progress,
              maxiter=(40 if method == "lm" else 400) if maxiter is None else maxiter,
              label="diffpen fit", starts=starts, search=search, n_starts=n_starts)
    res.notes = notes + res.notes
    # the law record the fit's simulator resolved (a name takes centred damping on a scene
    # of one contact: diffpen.checks.one_contact_per_body), so the impact is the same model
    note = step_error_note(res.params.contact[mat], dt=dt, law=sim.contact_law, mass=m,
                            radius=info["radius"], speed=math.sqrt(2.0 * g * info["drop"]),
                            compile_kw=compile_kw)
    if note:
        res.notes.append(note)
    if "decay_time" in tg:
        # the optimiser saw a cut-short decay as its lower bound: never a reached target
        # the fit's own evaluation at the fitted point (no second rollout program)
        if not bool(np.all(res.metrics["decay_valid"])):
            res.reached = False
            res.message = "decay time cut short by the rollout (targets not reached)"
            res.notes.append(f"the decay time at the fitted values is cut short by the "
                             f"{duration:g} s rollout (energy left at its end): give a "
                             f"longer duration")
    return res
