"""Fit contact k and c to a measured trajectory of a bouncing ball (system identification).

Input: a record of the ball centre's height ``z`` (m) at times ``t`` (s), e.g. a CSV with
columns ``t,z``. Pipeline (each step is a public function):

1. :func:`load_csv` reads and validates the record.
2. :func:`record_events` finds the free flights, fits each with the gravity parabola (linear
   least squares with g known) and derives apex heights, landing/take-off times, per-bounce
   restitution ``sqrt(H_n / H_{n-1})`` and contact durations, plus the noise level (from the
   second differences) and the initial state; a bounce between two samples (a contact
   shorter than a frame) splits the flights too. Each contact duration comes with its
   standard error (the parabolas' timing at the record's noise).
3. :func:`first_guess` turns the median restitution and contact time into (k, c) with the
   closed forms of :mod:`diffpen.physical` (a few percent off: gravity acts during contact).
   A record that does not resolve the contact time (durations not above 3 standard errors)
   gives k at that resolution, a lower bound, which :func:`fit_trajectory` holds (fitting c).
4. :func:`choose_dt` picks the time step from the data: the simulated trajectory at dt and
   at dt/2 must agree far below the noise (the model's own discretisation error otherwise
   dominates the misfit); it warns when it cannot.
5. :func:`fit_trajectory` runs Levenberg-Marquardt on the residuals ``z_sim(t_i) - z_i``
   (simulation resampled onto the record's times by linear interpolation) over a horizon
   grown bounce by bounce -- the least-squares landscape over many bounces is rugged, so the
   fit follows the record one bounce at a time -- and reports standard errors from the
   Gauss-Newton covariance ``s^2 (J^T J)^-1`` (forward-mode Jacobian), plus in quadrature
   the parameters' shift towards the continuous-time model (Richardson: twice the change on
   halving dt). On long records these errors are a lower bound (the model at a finite dt is
   rough at the 0.1% scale over many bounces).

The horizon is a weight mask passed to one compiled residual/Jacobian function, so growing
it never recompiles; the record is an argument too (a later record of the same layout and law
compiles nothing).
"""
from __future__ import annotations

import csv
import dataclasses
import math
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .errors import FitError
from .progress import Progress
from .compiled import ProgramCache, compiled
from .lm import levenberg_marquardt, residuals_and_jacobian, warn_record_precision
from .stable import contact_scales, law_c, law_k, law_units, safe_contact_bounds

__all__ = ["load_csv", "save_csv", "record_events", "first_guess", "choose_dt",
           "fit_trajectory", "TrajectoryFit", "synthetic_record", "RecordEvents"]


# --------------------------------------------------------------------------- input
def load_csv(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a record with columns ``t`` (s) and ``z`` (m, ball centre height).

    The first row must be a header naming ``t`` and ``z`` (other columns are ignored).
    Raises :class:`tuning.records.RecordError` (a :class:`FitError`) saying what to fix, with
    the file, line and column: missing file or columns, non-numeric or non-finite values,
    times not strictly increasing, too few rows, times in ms or heights in mm, binary files,
    files too large (see :func:`tuning.records.read_height_record`).
    Returns: ``(t (N,), z (N,))`` float64 arrays.
    """
    from .records import read_height_record
    return read_height_record(path)


def save_csv(path, t, z) -> None:
    """Write a ``t,z`` record (the format :func:`load_csv` reads)."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "z"])
        for a, b in zip(np.asarray(t), np.asarray(z)):
            w.writerow([repr(float(a)), repr(float(b))])


# --------------------------------------------------------------------------- events
@dataclasses.dataclass
class RecordEvents:
    """Events of a bouncing-ball record (heights of the lowest point, i.e. z - radius).

    noise: estimated noise std, m.  apex: (F,) apex heights of the flights, m.
    apex_time: (F,) s.  landing: (F,) time each flight reaches the surface, s.
    takeoff: (F,) time each flight left the surface, s (nan for the first flight).
    restitution: (F-1,) ``sqrt(H_n / H_{n-1})``.  contact: (F-1,) contact durations, s.
    z0, v0: centre height (m) and vertical velocity (m/s) at ``t[0]`` from the first flight.
    contact_resolution: (F-1,) standard errors of the contact durations, s (the parabolas'
    landing and take-off times, uncertain by the error of their heights there over the speed).
    """
    noise: float
    apex: np.ndarray
    apex_time: np.ndarray
    landing: np.ndarray
    takeoff: np.ndarray
    restitution: np.ndarray
    contact: np.ndarray
    z0: float
    v0: float
    contact_resolution: np.ndarray | None = None


def _noise(z) -> float:
    d2 = np.diff(z, 2)
    mad = np.median(np.abs(d2 - np.median(d2)))
    return float(1.4826 * mad / math.sqrt(6.0))


def record_events(t, z, *, radius: float, g: float = 9.81, min_samples: int = 6) -> RecordEvents:
    """Locate the flights of a record and measure them with gravity-parabola fits.

    A sample is in flight when its lowest point is above ``max(5 noise, 1 mm)`` and it is not
    beside a bounce between two samples (a contact shorter than a frame: the velocity
    reverses between two samples that lie within a frame's travel of the surface); each run
    of at least ``min_samples`` such samples is fitted with ``z = a + b s - g s^2 / 2`` (least
    squares, ``s = t - mean t``), whose covariance at the noise gives the standard errors of
    the contact durations. Raises :class:`FitError` if the record does not start in free
    flight or has no complete bounce.
    """
    t, z = np.asarray(t, float), np.asarray(z, float)
    sigma = _noise(z)
    h = z - radius
    margin = max(5.0 * sigma, 1e-3)
    fly = h > margin
    # A bounce between two samples (a contact shorter than a frame) can leave no sample near
    # the surface. The flight's velocity then reverses between samples i and i+1: the step
    # after them exceeds the step before them by twice the margin or more (a free flight's
    # steps decrease by g dt^2), and the lower of the two lies below that jump (within about
    # a frame's travel of the surface, so noise near an apex never counts). Both samples are
    # taken out of the flights, which splits them at the bounce.
    jump = np.full(h.shape, -np.inf)
    jump[1:-2] = (h[3:] - h[2:-1]) - (h[1:-2] - h[:-3])
    pair = ((jump > 2.0 * margin) & (np.minimum(h, np.roll(h, -1)) < jump)
            & fly & np.roll(fly, 1) & np.roll(fly, -1) & np.roll(fly, -2))
    fly &= ~(pair | np.roll(pair, 1))
    if not fly[0]:
        raise FitError("the record must start with the ball in free flight (its first "
                       f"height {z[0]:.4g} m is within {margin:.2g} m of contact at radius "
                       f"{radius} m); check --radius or trim the record.")
    edges = np.flatnonzero(np.diff(fly.astype(int)))
    starts = [0] + [int(e) + 1 for e in edges if fly[e + 1]]
    ends = [int(e) + 1 for e in edges if not fly[e + 1]] + ([len(z)] if fly[-1] else [])
    arcs = [(a, b) for a, b in zip(starts, ends) if b - a >= min_samples]
    apex, apex_t, land, take, land_err, take_err = [], [], [], [], [], []
    z0 = v0 = None
    for j, (a, b) in enumerate(arcs):
        ts, hs = t[a:b], h[a:b]
        tm = ts.mean()
        s = ts - tm
        A = np.stack([np.ones_like(s), s], axis=1)
        coef, *_ = np.linalg.lstsq(A, hs + 0.5 * g * s * s, rcond=None)
        aa, bb = coef
        ta = tm + bb / g
        H = aa + bb * bb / (2.0 * g)
        disc = math.sqrt(max(2.0 * H / g, 0.0))
        apex.append(H)
        apex_t.append(ta)
        land.append(ta + disc if b < len(z) else np.nan)
        take.append(ta - disc if j > 0 else np.nan)
        # standard error of the times the parabola crosses the surface: the error of its
        # height there (covariance of the fit at the record's noise) over the speed there
        cov = sigma ** 2 * np.linalg.pinv(A.T @ A)
        speed = math.sqrt(2.0 * g * max(H, 0.0))
        for sc, out in ((ta + disc - tm, land_err), (ta - disc - tm, take_err)):
            u = np.array([1.0, sc])
            out.append(math.sqrt(max(float(u @ cov @ u), 0.0)) / speed if speed > 0 else np.inf)
        if j == 0:
            s0 = t[0] - tm
            z0 = aa + bb * s0 - 0.5 * g * s0 * s0 + radius
            v0 = bb - g * s0
    if len(arcs) < 2:
        runs = [b - a for a, b in zip(starts, ends)]
        if len(runs) >= 2:
            step = float(np.median(np.diff(t)))
            short = max(n for n in runs if n < min_samples)
            raise FitError(f"the record holds fewer than two flights of at least {min_samples} "
                           f"samples (a flight's parabola needs them): {len(arcs)} of its "
                           f"{len(runs)} flights have that many, the longest of the others has "
                           f"{short}, at {step:.3g} s between samples ({1.0 / step:.3g} Hz). "
                           "Record faster: a trajectory fit needs at least one complete bounce "
                           "(landing and rebound) with that many samples in each flight.")
        raise FitError("the record holds fewer than two flights: a trajectory fit needs at "
                       "least one complete bounce (landing and rebound).")
    apex, land, take = np.array(apex), np.array(land), np.array(take)
    e = np.sqrt(np.maximum(apex[1:], 0.0) / apex[:-1])
    contact = take[1:] - land[:-1]
    resolution = np.hypot(np.array(take_err[1:]), np.array(land_err[:-1]))
    return RecordEvents(sigma, apex, np.array(apex_t), land, take, e, contact, float(z0),
                        float(v0), resolution)


#: A contact duration is resolved by the record when it exceeds this many of its standard
#: errors (``RecordEvents.contact_resolution``).
RESOLVED = 3.0
#: A held k (a record that does not resolve the contact time) is capped so that the model
#: covers the record in about this many steps at ``w0 dt = 0.25``.
HELD_STEPS = 5e5


def _contact_time(events: RecordEvents, n_bounces: int = 3) -> tuple[float, float, bool]:
    """(restitution, contact duration s, whether the record resolves the duration) over the
    first ``n_bounces`` usable bounces (medians). An unresolved duration is given at the
    record's resolution, ``RESOLVED`` standard errors: the longest contact the record cannot
    tell from an instantaneous bounce."""
    e = events.restitution[:n_bounces]
    tc = events.contact[:n_bounces]
    resolution = getattr(events, "contact_resolution", None)   # None: events made by hand
    res = np.zeros_like(tc) if resolution is None else resolution[:n_bounces]
    usable = np.isfinite(e) & np.isfinite(tc) & (e > 0.0) & (e < 1.0)
    if not usable.any():
        raise FitError("no usable bounce in the record (need 0 < restitution < 1).")
    bound = RESOLVED * float(np.median(res[usable]))
    ok = usable & (tc > 0.0)
    if ok.any() and float(np.median(tc[usable])) > bound:
        return float(np.median(e[ok])), float(np.median(tc[ok])), True
    if not (0.0 < bound < math.inf):
        raise FitError("no usable bounce in the record (need 0 < restitution < 1 and a "
                       "positive contact duration).")
    return float(np.median(e[usable])), bound, False


def first_guess(events: RecordEvents, mass: float, *, law: str = "linear",
                n_bounces: int = 3) -> tuple[float, float]:
    """(k N/m, c N s/m) from the record's events, in closed form.

    Restitution and contact time are the medians over the first ``n_bounces`` bounces (the
    largest, best resolved ones); :func:`diffpen.physical.kc_from_restitution` converts them.
    A contact time the record does not resolve (not above ``RESOLVED`` standard errors of the
    measured durations, e.g. a hard contact shorter than the timing the noise allows) is taken
    at that resolution: k is then the smallest stiffness consistent with the record, a lower
    bound.
    """
    e, tc, _ = _contact_time(events, n_bounces)
    # the law's closed forms, or the linear law's as a start for laws without any
    law_cf = dp.laws.get(law).closed_form or "linear"
    k, c = dp.physical.kc_from_restitution(e, tc, mass, law_cf)
    return float(k), float(c)


# --------------------------------------------------------------------------- model
#: the fit's residual programs by (simulator, steps, every, k held), the last 8: shared by
#: later records' fits (the start height and velocity are the rollouts' state)
_FIT_PROGRAMS = ProgramCache()


def _ball_sim(radius, mass, g, dt, law):
    """The ball's simulator, shared by choose_dt, the fit and later records' fits
    (:func:`tuning.compiled.compiled`: the start is each rollout's own state)."""
    from .scenes import ball_scene
    return compiled(ball_scene(radius=radius, mass=mass, gravity=g), dt, law=law)


def _start(sim, z0, v0):
    """The ball's state at centre height ``z0`` (m), rising at ``v0`` (m/s)."""
    s0 = sim.init_state()
    return s0._replace(position=s0.position.at[0, 2].set(z0),
                       velocity=s0.velocity.at[0, 2].set(v0))


def _model_heights(sim, params, t_data, t0, steps: int, z0, v0, every: int = 0):
    """Simulated centre height at the record's times, m, from centre height ``z0`` (m) and
    vertical velocity ``v0`` (m/s) at ``t0`` (s). ``every > 0``: the record is uniform with
    interval ``every * dt`` from ``t0``, so saved samples fall on its times (``steps //
    every`` saves); otherwise every step is saved and interpolated onto ``t_data``."""
    s0 = _start(sim, z0, v0)
    if every:
        traj = sim.rollout(params, steps, s0, save_every=every, check_finite=False)
        return jnp.concatenate([s0.position[None, 0, 2], traj.position[:, 0, 2]])
    traj = sim.rollout(params, steps, s0, check_finite=False)
    ts = jnp.concatenate([jnp.zeros((1,), traj.time.dtype), traj.time]) + t0
    zs = jnp.concatenate([s0.position[None, 0, 2], traj.position[:, 0, 2]])
    return jnp.interp(t_data, ts, zs)


def _fit_program(sim, steps: int, every: int, held: bool):
    """The fit's weighted residuals (m) and their Jacobian, ``rj(theta, w, td, zd, t0,
    log_k)``, theta = (log k, log c, z0, v0) (without log k where ``held``: ``log_k``): one
    program per simulator, layout and held k, the record its arguments."""
    def residuals(theta, w, td, zd, t0, log_k):
        theta = jnp.concatenate([log_k[None], theta]) if held else theta
        p = sim.params(k=jnp.exp(theta[0]), c=jnp.exp(theta[1]))
        return w * (_model_heights(sim, p, td, t0, steps, theta[2], theta[3], every) - zd)

    def rj(theta, *record):
        return residuals_and_jacobian(lambda th: (residuals(th, *record), None), theta)[:2]
    return _FIT_PROGRAMS.get((sim, steps, every, held), lambda: jax.jit(rj))


def _uniform_step(t) -> float | None:
    """The record's sample interval if uniform (to 1e-6 relative), else None."""
    d = np.diff(t)
    step = float(np.median(d))
    return step if np.all(np.abs(d - step) <= 1e-6 * step) else None


def _layout(t, dt: float):
    """(steps, every) of a rollout covering the record at step ``dt``."""
    step = _uniform_step(t)
    span = float(t[-1] - t[0])
    if step is not None:
        n = step / dt
        if abs(n - round(n)) < 1e-6:
            every = int(round(n))
            return every * (len(t) - 1), every
    return int(math.ceil(span / dt)) + 1, 0


def choose_dt(t, *, radius, mass, z0, v0, k, c, g=9.81, law="linear", noise=1e-3,
              dt=None, w0dt: float = 0.02, max_halvings: int = 3, match_c: bool = False):
    """Time step for fitting the record, from the data: from the record's sample interval
    divided so that ``w0 dt <= w0dt`` (w0 of the first guess), halved until the simulated
    heights at ``dt`` and ``dt / 2`` differ by less than a sixth of the noise (rms over the
    record). A ``dt`` given by the user is only checked. ``match_c``: compare the two after
    matching their restitution (the difference less its least-squares multiple of the
    heights' change with ``c``), for a fit in which k is held and c absorbs the step's own
    restitution error (most of the difference for a contact of a few steps). Returns
    ``(dt, discretisation_rms, warning or None)``."""
    t = np.asarray(t, float)
    # w0 of the law's stiffness at the depth the start's energy allows (k itself if linear)
    pre = _ball_sim(radius, mass, g, 1e-3, law)
    w0 = math.sqrt(k * contact_scales(pre, k, state=_start(pre, z0, v0))[0] / mass)
    tries = max_halvings if dt is None else 0
    if dt is None:
        step = float(np.median(np.diff(t)))
        dt = step / max(1, math.ceil(step * w0 / w0dt))
    td = jnp.asarray(t)
    for i in range(tries + 1):
        sims = [_ball_sim(radius, mass, g, h, law) for h in (dt, dt / 2)]
        zz = []
        for s in sims:
            st, every = _layout(t, s.dt)
            zz.append(np.asarray(_model_heights(s, s.params(k=k, c=c), td, t[0], st, z0, v0,
                                                every)))
        diff = zz[0] - zz[1]
        if match_c:
            st, every = _layout(t, sims[1].dt)
            dc = np.asarray(_model_heights(sims[1], sims[1].params(k=k, c=c * 1.001), td,
                                           t[0], st, z0, v0, every)) - zz[1]
            diff = diff - dc * float(diff @ dc) / max(float(dc @ dc), 1e-300)
        err = float(np.sqrt(np.mean(diff ** 2)))
        if err <= noise / 6.0:
            return dt, err, None
        if i < tries:
            dt /= 2.0
    msg = (f"at dt = {dt:.3g} s the model's own discretisation error ({err * 1e3:.3g} mm rms "
           f"between dt and dt/2) is not small against the record's noise "
           f"({noise * 1e3:.3g} mm): the fitted k and c absorb it. Use a smaller --dt.")
    return dt, err, msg


# --------------------------------------------------------------------------- fit
@dataclasses.dataclass
class TrajectoryFit:
    """Outcome of :func:`fit_trajectory` (SI units).

    k, c: fitted N/m, N s/m.  k_stderr, c_stderr: standard errors (Gauss-Newton).
    first_guess: (k, c) from the record's events.  rms: residual rms, m.  noise: the
    record's estimated noise, m.  dt: time step used, s.  dt_error: rms difference of the
    model at dt and dt/2, m.  iterations: LM iterations over all horizons.  seconds: wall
    time.  horizons: (H,) end times of the grown horizons, s.  history: cost after each
    accepted step.  z_fit: (N,) model heights at the record's times.  events: the
    :class:`RecordEvents`.  notes: warnings and choices, in words.  k_lower_bound: None
    when the record resolves the contact time; otherwise the smallest k consistent with the
    record, N/m (the contact time at its timing resolution): k was then held, not fitted (at
    this bound unless ``k0`` was given or :data:`HELD_STEPS` capped it), only c and the start
    state were fitted, and ``k_stderr`` is inf (undetermined).
    """
    k: float
    c: float
    k_stderr: float
    c_stderr: float
    first_guess: tuple
    rms: float
    noise: float
    dt: float
    dt_error: float
    iterations: int
    seconds: float
    horizons: list
    history: list
    z_fit: np.ndarray
    events: RecordEvents
    converged: bool
    message: str
    notes: list
    k_lower_bound: float | None = None


def fit_trajectory(t, z, *, radius: float, mass: float, g: float = 9.81,
                   law: str = "linear", dt: float | None = None, k0: float | None = None,
                   c0: float | None = None, maxiter: int = 15, grow: bool = True,
                   progress: bool | None = False) -> TrajectoryFit:
    """Fit (k, c) of a ball bouncing on the plane z = 0 to a record of its centre height.

    Args:
      t: (N,) sample times, s, strictly increasing.  z: (N,) centre heights, m.
      radius: m.  mass: kg.  g: gravity, m/s^2.  law: contact law (a name or a
        :class:`diffpen.laws.ContactLaw`).
      dt: time step, s (default chosen from the data by :func:`choose_dt`).
      k0, c0: start values (default: :func:`first_guess` from the record's events). When
        the record does not resolve the contact time, k is held (at ``k0`` if given, else at
        the record's lower bound, capped so the model takes about :data:`HELD_STEPS` steps)
        and only c and the start state are fitted, with a time step checked at matched
        restitution (``choose_dt(..., w0dt=0.25, match_c=True)``).
      maxiter: LM iterations per horizon (the last, full horizon gets twice as many).
      grow: grow the horizon bounce by bounce (otherwise fit the whole record at once).
      progress: False (default): print nothing; None or True: progress on stderr (a bar on a
        terminal, else a line every 5 s; what the ``diffpen`` command passes).
    Returns:
      :class:`TrajectoryFit` with standard errors from the Gauss-Newton covariance
      (``k_stderr`` inf and ``k_lower_bound`` set when k is held).
    """
    t0_wall = time.perf_counter()
    t, z = np.asarray(t, float), np.asarray(z, float)
    if t.shape != z.shape or t.ndim != 1:
        raise FitError(f"t and z must be 1-D arrays of one length, got {t.shape}, {z.shape}.")
    notes = []
    ev = record_events(t, z, radius=radius, g=g)
    if not ev.z0 > 0.5 * radius or not np.all(ev.apex > 0.0):
        raise FitError(f"the record's first flight is not a fall under gravity g = {g} m/s^2 "
                       f"from above the ground (its parabola starts at {ev.z0:.4g} m): check "
                       "the units (t in seconds, z in metres) and --radius.")
    kg_lin, cg_lin = first_guess(ev, mass, law=law)
    # a law whose stiffness grows with depth (Hunt-Crossley: k N/m^n, c N s/m^(n+1)) takes
    # the closed forms' N/m and N s/m at the depth the record's start energy allows, as
    # its safe step counts it (tuning.stable.law_k, law_c); the linear laws keep them
    pre = _ball_sim(radius, mass, g, 1e-3, law)
    start = _start(pre, ev.z0, ev.v0)
    ku, cu = law_units(pre.contact_law)
    kg, cg = kg_lin, cg_lin
    convert = dp.laws.get(law).closed_form is None     # the linear closed forms: N/m, N s/m
    if convert:
        kg = law_k(pre, kg_lin, state=start)
        cg = law_c(pre, cg_lin, kg, state=start)
    e_ev, tc_ev, resolved = _contact_time(ev)
    k_start = kg if k0 is None else float(k0)
    c_start = cg if c0 is None else float(c0)
    if resolved:
        notes.append(f"first guess from {len(ev.restitution)} bounces: restitution "
                     f"{np.median(ev.restitution[:3]):.4g}, contact time "
                     f"{np.median(ev.contact[:3]) * 1e3:.4g} ms -> k={kg:.5g} {ku}, "
                     f"c={cg:.5g} {cu}")
    else:
        notes.append(f"first guess from {len(ev.restitution)} bounces: restitution "
                     f"{e_ev:.4g}, contact time not resolved (measured "
                     f"{np.median(ev.contact[:3]) * 1e3:.3g} ms, not above {tc_ev * 1e3:.3g} "
                     f"ms = {RESOLVED:g} standard errors of the flights' timing) -> "
                     f"k={kg:.5g} {ku}, c={cg:.5g} {cu} at a {tc_ev * 1e3:.3g} ms contact")
        # the stiffest contact simulated within about HELD_STEPS steps over the record
        k_cap_lin = mass * (0.25 * HELD_STEPS / max(float(t[-1] - t[0]), 1e-9)) ** 2
        k_cap = law_k(pre, k_cap_lin, state=start) if convert else k_cap_lin
        if k0 is None and kg > k_cap:
            k_start = k_cap
            if c0 is None:
                c_start = cg_lin * math.sqrt(k_cap_lin / kg_lin)
                if convert:
                    c_start = law_c(pre, c_start, k_cap, state=start)
            notes.append(f"k is held at {k_cap:.5g} {ku}, below the record's bound {kg:.5g} "
                         f"{ku}, to keep the model within about {HELD_STEPS:.0e} steps: its "
                         f"contacts last {tc_ev * math.sqrt(kg_lin / k_cap_lin) * 1e3:.3g} ms, "
                         f"longer than the record allows (pass --k0 {kg:.3g} to hold the "
                         "bound; slower)")
    noise = max(ev.noise, 1e-6)
    dt, dt_err, warn = choose_dt(t, radius=radius, mass=mass, z0=ev.z0, v0=ev.v0, k=k_start,
                                 c=c_start, g=g, law=law, noise=noise, dt=dt,
                                 **({} if resolved else {"w0dt": 0.25, "match_c": True}))
    if warn:
        warnings.warn(warn, stacklevel=2)
        notes.append("WARNING: " + warn)
    notes.append(f"dt = {dt:.4g} s (model discretisation {dt_err * 1e3:.3g} mm rms vs noise "
                 f"{noise * 1e3:.3g} mm)")
    sim = _ball_sim(radius, mass, g, dt, law)
    warn_record_precision(sim.dtype)
    steps, every = _layout(t, dt)
    td = jnp.asarray(t)
    zd = jnp.asarray(z)

    # theta = (log k, log c, z0, v0): the start state is fitted too (nuisance parameters),
    # so its uncertainty enters the standard errors of k and c. A record that does not
    # resolve the contact time does not determine k: it is held, theta = (log c, z0, v0).
    f0 = 0 if resolved else 1

    def full(theta):        # log_k: the held k, set with the bounds below
        return theta if f0 == 0 else jnp.concatenate([jnp.full((1,), log_k), theta])

    program = _fit_program(sim, steps, every, bool(f0))

    def rj(theta, w):
        return program(theta, w, td, zd, *jnp.asarray([t[0], log_k], td.dtype))

    # Horizons: through the end of each flight (the next landing), then the whole record.
    ends = [x for x in ev.landing[1:] if np.isfinite(x)] if grow else []
    horizons = [float(x) + 0.5 * float(np.median(ev.contact[:3])) for x in ends] + [
        float(t[-1])]
    horizons = sorted(set(h for h in horizons if h <= t[-1]))
    lo = np.array([math.log(k_start * 1e-3), math.log(c_start * 1e-3), ev.z0 - 0.05,
                   ev.v0 - 1.0])
    k_safe, c_safe = safe_contact_bounds(sim, mass)     # inside the explicit safe step
    hi = np.array([math.log(min(k_start * 1e3, k_safe)),
                   math.log(min(c_start * 1e3, c_safe)), ev.z0 + 0.05, ev.v0 + 1.0])
    lo = np.minimum(lo, hi - 1e-9)
    x = np.clip(np.array([math.log(k_start), math.log(c_start), ev.z0, ev.v0]), lo, hi)
    log_k = float(x[0])
    if f0:
        notes.append(f"k is a LOWER BOUND, not determined by the record: any contact of "
                     f"k >= {kg:.5g} {ku} (the contact time at the record's timing "
                     f"resolution) explains it as well. k is held at {math.exp(log_k):.5g} "
                     f"{ku} (its standard error is undetermined: inf); c and the start state "
                     "are fitted (c sets the restitution at that k)")
    x, lo, hi = x[f0:], lo[f0:], hi[f0:]
    hist, its, converged, message = [], 0, False, ""
    bar = Progress(len(horizons) * maxiter, "diffpen fit --data", progress)
    for j, hz in enumerate(horizons):
        w = jnp.asarray((t <= hz).astype(float))
        last = j == len(horizons) - 1
        out = levenberg_marquardt(lambda th: rj(th, w), x, lo, hi,
                                  maxiter=2 * maxiter if last else maxiter, xtol=1e-6,
                                  ftol=1e-9 if last else 1e-6, progress=bar, offset=its)
        x = out.x
        its += out.iterations
        hist += out.cost_history
        converged, message = out.converged, out.message
    bar.close()
    r, J = (np.asarray(a) for a in rj(jnp.asarray(x), jnp.ones_like(td)))
    n, p = r.size, x.size
    s2 = float(r @ r) / max(n - p, 1)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
        se_log = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        se_log = np.full(p, np.inf)
        notes.append("J^T J is singular at the solution: standard errors are undefined.")
    # Discretisation term: the parameter shift between the model at dt and the continuous-time
    # model, by one Gauss-Newton step on the model's error. The contact events make the step
    # first order, so the error is estimated (Richardson) as twice the change on halving dt:
    # 2 (z_dt/2 - z_dt). It is added to the statistical error in quadrature, so the standard
    # errors cover the model's dependence on dt as well as the noise.
    x = np.asarray(full(jnp.asarray(x)))
    sim2 = _ball_sim(radius, mass, g, dt / 2, law)
    steps2, every2 = _layout(t, dt / 2)
    p_fit = sim.params(k=float(np.exp(x[0])), c=float(np.exp(x[1])))
    z_half = _model_heights(sim2, sim2.params(k=float(np.exp(x[0])), c=float(np.exp(x[1]))),
                            td, t[0], steps2, float(x[2]), float(x[3]), every2)
    z_full = _model_heights(sim, p_fit, td, t[0], steps, float(x[2]), float(x[3]), every)
    dz = np.asarray(z_half) - np.asarray(z_full)
    try:
        shift = np.linalg.lstsq(J, 2.0 * dz, rcond=None)[0]
    except np.linalg.LinAlgError:
        shift = np.zeros(p)
    if f0:      # k held: no statistical or dt part (reported as undetermined below)
        se_log = np.concatenate([[np.inf], se_log])
        shift = np.concatenate([[0.0], shift])
    se_stat = se_log.copy()
    se_log = np.sqrt(se_log ** 2 + shift ** 2)
    k, c = (float(v) for v in np.exp(x[:2]))
    if np.any(np.abs(shift[:2]) > 2.0 * se_stat[:2]):
        notes.append(f"the time step dominates the standard errors (and on long records "
                     f"may bias k and c beyond them): refit with --dt {dt / 2:.3g} for "
                     "tighter, more reliable errors")
    if f0:
        notes.append(f"standard errors: k undetermined (held); c: noise part "
                     f"{c * se_stat[1]:.3g} {cu}, dt part (shift to dt -> 0, Richardson) "
                     f"{c * abs(shift[1]):.3g} {cu}")
    else:
        notes.append(f"standard errors: noise part k {k * se_stat[0]:.3g} {ku}, c "
                     f"{c * se_stat[1]:.3g} {cu}; dt part (shift to dt -> 0, Richardson) k "
                     f"{k * abs(shift[0]):.3g} {ku}, c {c * abs(shift[1]):.3g} {cu}")
    return TrajectoryFit(
        k=k, c=c, k_stderr=k * float(se_log[0]), c_stderr=c * float(se_log[1]),
        first_guess=(kg, cg), rms=float(np.sqrt(np.mean(r * r))), noise=noise, dt=dt,
        dt_error=dt_err, iterations=its, seconds=time.perf_counter() - t0_wall,
        horizons=horizons, history=hist, z_fit=np.asarray(r) + z, events=ev,
        converged=converged, message=message, notes=notes,
        k_lower_bound=None if resolved else kg)


# --------------------------------------------------------------------------- synthetic data
def synthetic_record(k: float, c: float, *, radius: float = 0.1, mass: float = 1.0,
                     drop: float = 1.0, duration: float = 5.0, rate: float = 500.0,
                     noise: float = 1e-3, dt: float = 2e-5, g: float = 9.81,
                     law: str = "linear", seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A record of a ball dropped from rest at centre height ``drop`` (m): centre heights at
    ``rate`` Hz for ``duration`` s, simulated with a fine step ``dt`` (s) and Gaussian noise
    of std ``noise`` (m). Returns ``(t (N,), z (N,))``."""
    sim = _ball_sim(radius, mass, g, dt, law)
    every = int(round(1.0 / (rate * dt)))
    if abs(every * dt * rate - 1.0) > 1e-9:
        raise ValueError(f"1/rate = {1 / rate} s must be a multiple of dt = {dt} s.")
    n = int(round(duration * rate))
    traj = sim.rollout(sim.params(k=k, c=c), n * every, _start(sim, drop, 0.0),
                       save_every=every)
    t = np.concatenate([[0.0], np.asarray(traj.time)])[:n]
    zc = np.concatenate([[drop], np.asarray(traj.position)[:, 0, 2]])[:n]
    rng = np.random.default_rng(seed)
    return t, zc + noise * rng.standard_normal(zc.shape)
