"""The rollout gate: the up-front check (:func:`gate`, :class:`GateCache`), the
:class:`StabilityReport` of a compiled scene and the errors that name the safe step and the
substeps that reach it. See :mod:`diffpen.stability` for the overview.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .. import precision as _precision
from ..precision import PrecisionWarning
from ..errors import SceneError, StabilityError, warn
from .bounds import IMPLICIT_PRECISION, RESTING_RESOLUTION, Analysis, rates
from .modes import SAFE_CH, SAFE_STABLE, SAFE_TIE, safe_dt, stable_dt

__all__ = ["StabilityReport", "report", "gate", "step_gate", "GateCache", "MAX_AUTO_SUBSTEPS"]

#: ``substeps="auto"`` refuses to pick more inner steps than this (the run would be too slow).
MAX_AUTO_SUBSTEPS = 100_000


class StabilityReport(NamedTuple):
    """Stability of a compiled scene for given parameters.

    integrator: name.  dt: saved step, s.  substeps: inner steps per saved step (int).
    inner_dt: dt / substeps, s.
    stable_dt: largest linearly stable inner step, s (inf: no limit).
    margin: stable_dt / inner_dt (> 1 stable; < 1 unstable).
    stable: margin > 1.
    safe_dt: largest inner step the rollout accepts, s: ``min(SAFE_STABLE x stable_dt,
      SAFE_STABLE x the undamped limit at w_max, contact_wh / w_max_contact, SAFE_CH /
      C_contact)`` for
      explicit integrators (inf for implicit ones); see ``SAFE_WH`` (``contact_wh``: it, or
      the contact law's own, :class:`diffpen.stability.bounds.Analysis`).
    safe_margin: safe_dt / inner_dt; rollout raises StabilityError when it is < 1.
    safe: safe_margin >= 1 (a step equal to the safe step is accepted).
    substeps_needed: smallest substep count whose inner step is within safe_dt.
    omega_max: bound on the highest angular frequency sqrt(K), rad/s.
    damping_rate: bound on the largest C, 1/s.
    limiting_body: body index of the largest K row, or of the largest C row where the
      damping alone limits the step more than the stiffness (None when no springs or
      contacts).
    limiting: what sets the limit, in words.
    packed_dt: stable step if a sphere touches all its candidate sphere neighbours at once.
    """
    integrator: str
    dt: float
    substeps: int
    inner_dt: float
    stable_dt: float
    margin: float
    stable: bool
    safe_dt: float
    safe_margin: float
    safe: bool
    substeps_needed: int
    omega_max: float
    damping_rate: float
    limiting_body: int | None
    limiting: str
    packed_dt: float

    def __str__(self) -> str:
        def fmt(x):
            return "no limit" if math.isinf(x) else f"{x:.4g} s"
        verdict = ("ok" if self.safe else "UNSTABLE" if not self.stable
                   else "stable but past the safe step")
        spin = self.limiting.startswith("body ") and "'s spin" in self.limiting
        return (f"{self.integrator}: inner step {self.inner_dt:.4g} s; stable step "
                f"{fmt(self.stable_dt)} (margin {self.margin:.3g}); safe step "
                f"{fmt(self.safe_dt)} (margin {self.safe_margin:.3g}): {verdict}, needs "
                f"{self.substeps_needed} substep(s); "
                + (f"set by {self.limiting}" if spin else
                   f"w_max <= {self.omega_max:.4g} rad/s"
                   + (f", set by {self.limiting}" if self.limiting else "")))


def _down(x: float, digits: int) -> float:
    """``x`` rounded down to ``digits`` significant digits: a step the advice names must
    pass the check (rounded up, "use dt <= 0.006647 s" was refused at 0.00664694 s)."""
    if not (math.isfinite(x) and x > 0.0):
        return x
    q = 10.0 ** (math.floor(math.log10(x)) - digits + 1)
    return math.floor(x / q * (1.0 + 1e-15)) * q


def _count(n: int) -> str:
    """A substep count in words: exact up to a million, else three digits."""
    return str(n) if n <= 1_000_000 else f"about {float(n):.3g}"


def _needed(dt: float, sdt: float) -> int:
    """Smallest substep count ``n`` with ``dt / n`` within the safe step ``sdt`` (s)."""
    if math.isinf(sdt):
        return 1
    if sdt <= 0.0:
        return MAX_AUTO_SUBSTEPS + 1
    ratio = dt / sdt
    if not ratio < 2.0 ** 50:
        # past 2^53 dt / n and dt / (n - 1) are one float: the search below never ended
        # (k = 1e300 N/m or a 1e-300 kg body hung the rollout); a count that large is
        # refused anyway
        return int(min(ratio, 1e300)) + 1
    n = max(1, math.ceil(ratio))
    while dt / n > sdt * (1.0 + SAFE_TIE):  # a step equal to the safe step is accepted
        n += 1
    while n > 1 and dt / (n - 1) <= sdt * (1.0 + SAFE_TIE):
        n -= 1
    return n


def _analysis(sim) -> Analysis:
    return sim if isinstance(sim, Analysis) else sim.analysis


def report(sim, params, *, substeps: int | None = None,
           packed: bool = True, energy: float | None = None) -> StabilityReport | None:
    """Stability report of ``sim`` (a Simulator or its :class:`Analysis`) for ``params``
    (None when params are abstract tracers).

    ``substeps`` defaults to the simulator's (1 for ``"auto"``). ``packed=False`` skips the
    packed-spheres bound (``packed_dt`` is then ``stable_dt``). ``energy``: a start state's
    energy bounding the contacts' reference depth (:mod:`diffpen.stability.depth`), or None.
    """
    an = _analysis(sim)
    with np.errstate(invalid="ignore"):      # NaN values are refused just below
        r = rates(an, params, energy=energy)
    if r is None:
        return None
    K_row, C_row, source, Kc, Cc = r.K_row, r.C_row, r.source, r.Kc, r.Cc
    for rows in (K_row, C_row, Kc, Cc):
        rows = np.asarray(rows, dtype=float)
        if rows.size and not (np.all(np.isfinite(rows)) and np.all(rows >= 0.0)):
            raise SceneError("the stability analysis got a stiffness, damping or friction "
                             "value that is NaN, infinite or negative: every contact and "
                             "spring k and c and every friction mu must be finite and >= 0 "
                             "(build the params with sim.params(...), which checks them).")
    rec = an.integrator
    K, C = float(np.max(K_row, initial=0.0)), float(np.max(C_row, initial=0.0))
    sdt = stable_dt(rec, K, C)
    pdt = sdt
    if packed and any(b.packed is not None for b in an.bounds):
        pk = rates(an, params, packed=True, energy=energy)
        pdt = stable_dt(rec, float(np.max(pk.K_row, initial=0.0)),
                        float(np.max(pk.C_row, initial=0.0)))
    if substeps is None:
        substeps = an.substeps if isinstance(an.substeps, int) else 1
    h = an.dt / substeps
    margin = math.inf if math.isinf(sdt) else sdt / h
    safe = safe_dt(rec, float(np.max(Kc, initial=0.0)), float(np.max(Cc, initial=0.0)), sdt,
                   K, an.contact_wh)
    safe_margin = math.inf if math.isinf(safe) else safe / h
    body = int(np.argmax(K_row)) if K > 0.0 else None
    limiting = f"{source(body)} on body {body}" if body is not None else ""
    if C > 0.0 and r.damper is not None and stable_dt(rec, 0.0, C) < stable_dt(rec, K, 0.0):
        # the damping alone limits the step more than the stiffness: name the damper (a
        # stiff contact named instead sent users to lower a k that was not the cause)
        body = int(np.argmax(C_row))
        limiting = f"{r.damper(body)} on body {body}"
    return StabilityReport(rec.name, an.dt, substeps, h, sdt, margin, margin > 1.0,
                           safe, safe_margin, safe_margin >= 1.0 - SAFE_TIE,
                           _needed(an.dt, safe), math.sqrt(K), C, body, limiting, pdt)


class GateCache:
    """Verdicts of the up-front check (:func:`gate`) per set of scalar parameter values, so
    a repeated rollout pays a dictionary look-up, not the analysis. An explicit object held
    by the simulator (``sim.gate_cache``); a traced rollout never reads it (abstract values
    have no key), so a traced program never depends on earlier calls.
    """

    def __init__(self, size: int = 1024):
        self.size = size
        self._verdicts: dict = {}
        self._steps: dict = {}      # step_gate's verdicts: params key -> (energy, substeps)
        self.rest_warned = False    # the float32 resting-deflection warning was given

    def get(self, key, step: bool = False):
        """The verdict for ``key`` (``step``: :func:`step_gate`'s), or None."""
        return None if key is None else (self._steps if step else self._verdicts).get(key)

    def put(self, key, value, step: bool = False) -> None:
        if key is None:
            return
        table = self._steps if step else self._verdicts
        if len(table) >= self.size:
            table.clear()
        table[key] = value

    def __len__(self) -> int:
        return len(self._verdicts)


def gate(sim, params, *, check: bool = True, substeps: int | None = None,
         cache: GateCache | None = None, energy: float | None = None) -> int:
    """The up-front check ``Simulator.rollout`` runs before tracing. Returns the substep
    count to use: ``substeps`` when given, the pick of ``substeps="auto"``, else the
    simulator's own count.

    Raises StabilityError when an explicit integrator would run past its safe step (fixed
    substeps), or when ``"auto"`` would need more than MAX_AUTO_SUBSTEPS. With abstract
    (jit-traced) parameters nothing is checked here (the traced flag :func:`unsafe` records
    it in the rollout instead) and ``"auto"`` raises a SceneError: under tracing the count
    must be given (``rollout(..., substeps=N)``). ``cache`` memoises verdicts per set of
    concrete scalar values. ``energy``: as :func:`report` takes it.
    """
    an = _analysis(sim)
    n = _gate_count(an, params, check, substeps, cache, energy)
    warn_precision(an, an.dt / n)
    return n


def warn_precision(an, h: float) -> None:
    """The dtype's warnings for the inner step ``h`` (s): too short to resolve the motion
    (:func:`diffpen.precision.warn_step`) or, for an event-exact record, its rebuilt force
    (:func:`diffpen.precision.warn_events`)."""
    _precision.warn_step(an.min_step, h, an.dtype)
    if an.events_step:
        _precision.warn_events(an.events_step, h, an.dtype)


def _gate_count(an, params, check, substeps, cache, energy) -> int:
    """:func:`gate`'s substep count (and its refusals)."""
    auto = an.substeps == "auto" and substeps is None
    fixed = substeps if substeps is not None else (an.substeps if not auto else None)
    if not an.integrator.explicit:
        if check and np.dtype(an.dtype).itemsize < 8:
            _implicit_precision(an, params, fixed or 1)
        return fixed or 1
    if not (check or auto):
        return fixed
    key = _scalar_key(params)
    key = None if key is None else (fixed, energy, key)
    if cache is not None:
        hit = cache.get(key)
        if hit is not None:
            return hit
    n = _gate(an, params, auto, fixed, energy, cache)
    if cache is not None:
        cache.put(key, n)
    return n


def _implicit_precision(an: Analysis, params, substeps: int) -> None:
    """Raise StabilityError when implicit_euler's linear system cannot be resolved in the
    simulator's dtype (float32 with a very stiff, light body and a large step), or a body's
    static deflection under gravity is below the dtype's resolution of its positions (see
    :data:`RESTING_RESOLUTION`). The traced form of this check, for rollouts under jit, vmap
    and grad, is :func:`diffpen.stability.bounds.precision_unsafe` (it sets the rollout's
    ``State.aux["unstable"]`` flag)."""
    r = rates(an, params)
    if r is None:
        return
    K = float(np.max(r.K_row, initial=0.0))
    eps = float(np.finfo(np.dtype(an.dtype)).eps)
    unresolved = _unresolved_rest(an, r)
    if unresolved:
        raise StabilityError(
            f"{an.integrator.name} cannot resolve this system in {np.dtype(an.dtype).name}: "
            f"{unresolved}, and the step's linearisation, which differentiates the forces, "
            "gives wrong or NaN gradients there. Use dtype=float64, or a softer k or a "
            "heavier body.")
    h = an.dt / substeps
    if K * h * h * eps <= IMPLICIT_PRECISION:
        return
    h_ok = math.sqrt(IMPLICIT_PRECISION / (eps * K))
    n = _needed(an.dt, h_ok)
    raise StabilityError(
        f"{an.integrator.name} cannot resolve this system in {np.dtype(an.dtype).name}: "
        f"(w h)^2 = {K * h * h:.3g} swamps the identity at machine epsilon {eps:.2g} (the "
        f"matrix is singular in rounding). Use dtype=float64, or a step <= {h_ok:.3g} s "
        f"(substeps={n}).", stable_dt=h_ok, substeps=n)


def _unresolved_rest(an: Analysis, r) -> str | None:
    """Where a body's static deflection under gravity, ``g / K_i`` (m, ``K_i`` its stiffness
    over mass, from :func:`rates` ``r``), is below :data:`RESTING_RESOLUTION` of the dtype's
    resolution of its positions (machine epsilon x its size), the words that say so; else
    None."""
    eps = float(np.finfo(np.dtype(an.dtype)).eps)
    K_i = np.asarray(r.K_row, float)
    stiff = (K_i > 0.0) & ~np.asarray(an.pinned, bool)
    if not an.gravity > 0.0 or not stiff.any():
        return None
    depth = an.gravity / K_i[stiff]
    res = eps * np.asarray(an.d_ref, float)[stiff]
    j = int(np.argmin(depth / res))
    if depth[j] >= RESTING_RESOLUTION * res[j]:
        return None
    return (f"a body's static deflection under gravity, {depth[j]:.2g} m (g / (k / m)), is "
            f"below {RESTING_RESOLUTION:g} of the resolution of its positions ({res[j]:.2g} "
            "m: machine epsilon x its size)")


def _warn_unresolved_rest(an: Analysis, params) -> bool:
    """An explicit integrator's counterpart of :func:`_implicit_precision`'s refusal: warn
    (:class:`diffpen.PrecisionWarning`) when a body would rest with a deflection below its
    dtype's resolution (:func:`_unresolved_rest`; from the parameters: the gate warns once
    per simulator). Its motion is right to a rounding, but the derivatives w.r.t. that
    stiffness are lost to rounding (float32, a 1 g ball at rest on k 1e7 N/m: d z / dk
    5.6e-18 against m g / k^2 = 9.8e-17; k 1e9 on 1 kg: 52% off). Whether it warned."""
    if np.dtype(an.dtype).itemsize >= 8:
        return False
    r = rates(an, params)
    unresolved = None if r is None else _unresolved_rest(an, r)
    if unresolved:
        warn(f"{unresolved}: where it rests the motion is right to that rounding, but "
             "derivatives w.r.t. the stiffness holding it (and its resting height) are lost "
             "to it (a 1 g ball at rest on k 1e7 N/m in float32: d z / dk 17x too small). "
             "Use dtype=float64 to differentiate w.r.t. such a stiffness (warned once per "
             "simulator).", PrecisionWarning)
    return bool(unresolved)


def step_gate(sim, params, state, check: bool = True) -> int | None:
    """The gate of ``Simulator.step``: :func:`gate` for concrete ``params`` (None for traced
    ones, which the step cannot refuse, and without ``check``: then only the dtype's
    warnings at the simulator's own inner step, :func:`warn_precision`), returning the
    substep count to step with ("auto": its pick). Once per set of parameter values: a loop
    of steps pays a look-up. A law that
    stiffens with depth counts the energy of the state it is given
    (``Simulator.start_energy``); a later state keeps the verdict when it has no more energy,
    or none it can count (a body in contact: in a loop of steps that is the energy of the
    flight before, which the contacts only dissipate; a rollout from the same start counts
    the same, and a step loop was refused mid-bounce at the radius's bound)."""
    import jax
    if not check or any(isinstance(v, jax.core.Tracer)
                        for v in jax.tree_util.tree_leaves(params)):
        warn_precision(sim.analysis, sim.analysis.inner_dt)
        return None
    an, cache = sim.analysis, sim.gate_cache
    energy = sim.start_energy(state, params) if an.depth_exponent is not None else None
    key = _scalar_key(params)
    seen = cache.get(key, step=True)
    if seen is not None and (seen[0] is None or energy is None or energy <= seen[0]):
        return seen[1]
    n = gate(an, params, cache=cache, energy=energy)
    cache.put(key, (energy, n), step=True)
    return n


def _scalar_key(params):
    """Tuple of the float values of every parameter (contact, springs, extra), or None
    (arrays, abstract tracers)."""
    import jax
    try:
        return tuple(float(v) for v in jax.tree_util.tree_leaves(params))
    except Exception:  # noqa: BLE001 - non-scalar or abstract: take the slow path
        return None


def _gate(an: Analysis, params, auto: bool, fixed: int | None, energy=None,
          cache=None) -> int:
    if cache is None or not cache.rest_warned:
        if _warn_unresolved_rest(an, params) and cache is not None:
            cache.rest_warned = True                # once per simulator
    rep = report(an, params, packed=False, substeps=fixed, energy=energy)
    if rep is None:
        if not auto:
            return fixed
        raise SceneError(
            "substeps='auto' picks the substep count from concrete k and c, but rollout "
            "was traced with abstract parameters (inside jax.jit, vmap or grad). Give the "
            "count: sim.rollout(params, steps, substeps=N) with N = "
            "sim.stability(concrete_params).substeps_needed, or compile with substeps=N; "
            "the rollout's State.aux['unstable'] flag then says whether N was enough.")
    if auto:
        n = rep.substeps_needed
        if n > MAX_AUTO_SUBSTEPS:
            raise StabilityError(
                f"substeps='auto' would need {_count(n)} substeps per step of dt={an.dt:g} s "
                f"(safe step {rep.safe_dt:.3g} s, {rep.limiting}): too slow. Lower the "
                "stiffness, raise the mass, or use integrator='implicit_euler'.",
                stable_dt=rep.safe_dt, substeps=n)
        return n
    if not rep.safe:
        h = rep.inner_dt
        if not rep.safe_dt > 0.0 or rep.substeps_needed > MAX_AUTO_SUBSTEPS:
            raise StabilityError(
                f"integrator {an.integrator.name!r} has no practical step here: the safe step "
                f"is {rep.safe_dt:.3g} s (w_max <= {rep.omega_max:.4g} rad/s, C/m <= "
                f"{rep.damping_rate:.4g} 1/s, set by {rep.limiting or 'the springs and contacts'}"
                f"), " + (f"{_count(rep.substeps_needed)} substeps per step of {an.dt:g} s"
                          if rep.safe_dt > 0.0 else "too small for any count of substeps") +
                ". Lower that "
                "stiffness, damping or friction, raise the mass, or use "
                "integrator='implicit_euler' (no step limit).",
                stable_dt=rep.safe_dt, substeps=rep.substeps_needed)
        why = ("unstable" if not rep.stable else
               f"stable but within {1.0 - SAFE_STABLE:.0%} of its stability limit, where "
               "oscillations grow without bound (or, damped, stop decaying) as the limit nears"
               if h > SAFE_STABLE * rep.stable_dt * (1.0 + SAFE_TIE) else
               f"stable but past its safe step for contact (needs w h <= {an.contact_wh:g} and "
               f"c h / m <= {SAFE_CH}; here w h = {rep.omega_max * h:.3g}, c h / m = "
               f"{rep.damping_rate * h:.3g}, bounds from the stiffest and most damped contact:"
               " contact energy errors of several % or more)")
        raise StabilityError(
            f"integrator {an.integrator.name!r} is {why} at step {h:.6g} s: the step must be "
            f"at most {_down(rep.safe_dt, 6):.6g} s (linear stability limit "
            f"{rep.stable_dt:.4g} s; w_max <= {rep.omega_max:.4g} rad/s, C/m <= "
            f"{rep.damping_rate:.4g} 1/s, set by {rep.limiting or 'the springs and contacts'})."
            f" Use dt <= {_down(rep.safe_dt, 4):.4g} s, "
            f"compile with substeps={rep.substeps_needed} (or substeps='auto'), or "
            "integrator='implicit_euler'.",
            stable_dt=rep.safe_dt, substeps=rep.substeps_needed)
    return fixed
