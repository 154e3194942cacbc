"""Pointwise force laws and contact-law records: one pair in, one scalar force out.

Every function here acts on ONE spring or ONE contact (scalars, or arrays that broadcast
elementwise) and knows nothing about bodies, index arrays or the scene. `diffpen.compile`
lifts them to a whole system with `jax.vmap` over static index arrays and a segment sum.

Conventions (SI units throughout):

* ``d``      penetration depth, metres; positive when the shapes overlap.
* ``vn``     relative normal velocity ``n . (v_a - v_b)``, m/s; positive when separating.
* ``k``      stiffness, N/m (Hunt-Crossley: N/m^exponent).
* ``c``      damping, N s/m (Hunt-Crossley: N s/m^(exponent + 1)).
* ``width``  smoothing width, metres. A *static* Python float: 0 gives the exact kink
             ``max(d, 0)``; a positive width replaces the kink by a C1 quadratic blend on
             ``|d| < width / 2``. Every law is exactly 0, with derivative 0, for
             ``d <= -width / 2``.
* ``h``      the integrator's inner step, s (step-averaged forces, below).

The returned contact force is the magnitude along the contact normal, positive pushing the
bodies apart.

A contact law is a :class:`ContactLaw` record holding everything about it: the pointwise force,
its step-averaged force, the elastic energy (the integral of the ramp), the resting depth
(the inverse of the static force), the stiffness seen by the stability analysis, and its name.
Build one with :func:`linear`, :func:`no_tension` or :func:`hunt_crossley`, or write a new
record; ``diffpen.compile(..., law=)`` takes a record or one of the names in
:data:`CONTACT_LAWS`.

**Step-averaged force** (what the integrators use; ``ContactLaw.averaged``): the mean of
the force over the integrator's step window, continuous through contact start and end;
the window's closed forms and their derivatives are :mod:`diffpen.window`
(:func:`window_mean`, re-exported here). Deep in contact it equals the pointwise law for
the linear laws; for Hunt-Crossley with ``n != 1`` the window's mean of ``d^n`` differs from
``d^n`` by ``O((vn h / d)^2)``.

**One-contact forms** (``ContactLaw.centred``: ``linear(centred=True)``,
``no_tension(centred=True)``, ``hunt_crossley(n, centred=True)``, ``get(name,
centred=True)``; the exact records ``linear(exact=True)``, ``no_tension(exact=True)``;
``diffpen.compile`` takes the centred record for a law named by a string on scenes of one
contact): the damping at the step window's centre speed, and the step that reproduces a
damped spring exactly, are :mod:`diffpen.one_contact` (why, figures, costs). The event-exact
records ``linear(events=True)``, ``no_tension(events=True)`` and ``hunt_crossley(n,
events=True)`` (opt-in) are exact through contact start and end too (Hunt-Crossley to its
Runge-Kutta flow's error): :mod:`diffpen.event_step`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax.numpy as jnp
import numpy as np

from .event_step import (event_step_factors, hunt_crossley_events, linear_events,
                         no_tension_events)
from .one_contact import (exact_step_factors, hunt_crossley_centred, linear_centred,
                          linear_exact, no_tension_centred, no_tension_exact, quotient)
from .window import window_mean

__all__ = [
    "ramp",
    "ramp_integral",
    "ramp_inverse",
    "gate",
    "spring_force",
    "drag_force",
    "linear_contact",
    "no_tension_contact",
    "hunt_crossley_contact",
    "window_mean",
    "ContactLaw",
    "linear",
    "no_tension",
    "hunt_crossley",
    "get",
    "exact_step_factors",
    "CONTACT_LAWS",
]


def ramp(d, width: float):
    """C1 ramp approximating ``max(d, 0)``.

    For ``width == 0`` this is exactly ``max(d, 0)``. Otherwise, with ``h = width / 2``::

        0                      d <= -h
        (d + h)^2 / (2 width)  |d| < h
        d                      d >= h

    It is exact outside the blend band, continuous with a continuous first derivative, and
    costs no transcendental function (softplus costs ~6x more in batched rollouts).

    Args:
      d: array, any shape, metres (or any unit: the law is unit-free).
      width: static Python float >= 0, same unit as ``d``.
    """
    if width == 0.0:
        return jnp.maximum(d, 0.0)
    h = 0.5 * width
    # reciprocals folded at trace time: no divide reaches XLA (see gate)
    blend = (d + h) ** 2 * (0.5 / width)
    return jnp.where(d >= h, d, jnp.where(d <= -h, jnp.zeros_like(d), blend))


def ramp_integral(d, width: float, exponent: float = 1.0):
    """``int_{-inf}^d ramp(x, width)^exponent dx`` (m^(exponent + 1)): the contact's elastic
    energy divided by ``k``. Piecewise closed form; 0 for ``d <= -width / 2``."""
    n = float(exponent)
    if width == 0.0:
        r = jnp.maximum(d, 0.0)
        return r ** (n + 1.0) / (n + 1.0)
    h = 0.5 * width
    u = jnp.maximum(d + h, 0.0)
    blend = jnp.minimum(u, width) ** (2.0 * n + 1.0) / ((2.0 * n + 1.0) * (2.0 * width) ** n)
    pos = d >= h
    ds = jnp.where(pos, d, h)
    tail = (ds ** (n + 1.0) - h ** (n + 1.0)) / (n + 1.0)
    return jnp.where(pos, blend + tail, blend)


def ramp_inverse(r, width: float):
    """The depth ``d`` (m) at which ``ramp(d, width) = r`` for ``r >= 0`` (the ramp is one to
    one there): ``r`` past the blend band, ``sqrt(2 width r) - width / 2`` inside it."""
    if width == 0.0:
        return r
    half = 0.5 * width
    return jnp.where(r >= half, r, jnp.sqrt(2.0 * width * jnp.maximum(r, 0.0)) - half)


def gate(d, width: float):
    """Smooth step from 0 (apart) to 1 (in contact) over ``|d| < width / 2``.

    ``width == 0`` gives the hard gate ``d > 0``. Otherwise a cubic smoothstep (C1) in
    ``t = clip((d + width / 2) / width, 0, 1)``. Gates the contact damping so that the damping
    force switches on continuously at impact.
    """
    if width == 0.0:
        return (jnp.asarray(d) > 0.0).astype(jnp.result_type(d))
    u = d * (1.0 / width) + 0.5
    # selects, not clip: clip's derivative splits ties with a division, and XLA will not fuse
    # a divide into the wide tangent update of forward mode (measured: two extra kernels per
    # step, grad/forward 4.0 -> 3.6 on 1024 balls). The smoothstep's slope is 0 at both ends.
    t = jnp.where(u >= 1.0, jnp.ones_like(u), jnp.where(u <= 0.0, jnp.zeros_like(u), u))
    return t * t * (3.0 - 2.0 * t)


def spring_force(stretch, stretch_rate, k, c):
    """Damped spring (Hooke + dashpot): ``F = -k x - c v``.

    Args:
      stretch: ``x = length - rest_length``, metres.
      stretch_rate: ``v = dx/dt``, the rate of change of length along the axis, m/s.
      k: stiffness, N/m.  c: damping, N s/m.

    Returns:
      Signed tension along the axis, newtons; positive pushes the ends apart.
    """
    return -k * stretch - c * stretch_rate


def drag_force(v, c):
    """Linear velocity drag on ONE body: ``F = -c v``.

    Args:
      v: (3,) velocity, m/s.  c: drag coefficient, N s/m (>= 0).
    Returns: (3,) force, newtons.
    """
    return -c * v


# --------------------------------------------------------------------------- pointwise laws
def linear_contact(d, vn, k, c, width: float = 0.0):
    """Linear spring-dashpot penalty contact (the workshop paper's law).

    ``F = k ramp(d) - c gate(d) vn``. May pull (F < 0) at the end of contact, which is what
    gives the classic closed forms ``t_c = pi / w_d``, ``e = exp(-pi zeta / sqrt(1 - zeta^2))``.
    """
    return k * ramp(d, width) - c * gate(d, width) * vn


def no_tension_contact(d, vn, k, c, width: float = 0.0):
    """Linear spring-dashpot that never pulls: ``F = max(k d - c vn, 0)`` in contact.

    With ``width > 0`` the clamp is smoothed by the C1 ramp in force space
    (:func:`_soft_clamp`), whose width shrinks to 0 with the contact, so the force is exactly
    0 for ``d <= -width / 2`` (a fixed force-space width ``k width`` left ``k width / 8``
    acting at any distance), and which leaves the static force ``k ramp(d)`` unchanged.
    Closed forms: Schwager & Poschel (2007), see docs/physics-notes.md section 2.
    """
    f = linear_contact(d, vn, k, c, width)
    if width == 0.0:
        return jnp.maximum(f, 0.0)
    return _soft_clamp(f, k * ramp(d, width), k * width * gate(d, width))


def hunt_crossley_contact(d, vn, k, c, width: float = 0.0, exponent: float = 1.0):
    """Hunt-Crossley contact: ``F = max(d^n (k + c ddot), 0)`` with ``ddot = -vn``.

    In the usual notation ``F = k d^n (1 + a ddot)`` with ``a = c / k`` (s/m). Damping vanishes
    at zero penetration; restitution depends on ``a * v_in`` only. With ``width > 0`` the
    clamp is smoothed in force space as in :func:`no_tension_contact` (0 when apart, the
    static force ``k ramp(d)^n`` unchanged).
    """
    r = ramp(d, width)
    if exponent == 1.0:
        p = r
    else:
        pos = r > 0.0
        p = jnp.where(pos, jnp.where(pos, r, 1.0) ** exponent, 0.0)
    f = p * (k - c * vn)
    if width == 0.0:
        return jnp.maximum(f, 0.0)
    return _soft_clamp(f, k * p, k * width ** exponent * gate(d, width))


def _soft_clamp(f, static, wmax):
    """C1 ``max(f, 0)`` of a contact force ``f`` whose static part (``vn = 0``) is
    ``static >= 0``: the force-space ramp of width ``w = 2 static wmax / (2 static + wmax)``
    (a smooth minimum of ``2 static`` and ``wmax``, N). It is 0 where the contact is apart
    (``static = wmax = 0``: the force and its derivatives are exactly 0), and ``f = static``
    is past the blend (``static >= w / 2``), so the static force, its energy and its resting
    depth are the unclamped law's."""
    den = 2.0 * static + wmax
    pos = den > 0.0
    w = jnp.where(pos, 2.0 * static * wmax / jnp.where(pos, den, 1.0), 0.0)
    return _ramp_traced(f, w)


def _ramp_traced(x, width):
    """``ramp`` with a traced width (force-space clamps): exactly ``max(x, 0)`` where the
    width is 0, finite values and derivatives for any width >= 0."""
    pos = width > 0.0
    w = jnp.where(pos, width, 1.0)
    h = 0.5 * w
    xc = jnp.where(x >= h, h, jnp.where(x <= -h, -h, x))    # selects: see gate
    blend = (xc + h) ** 2 * (0.5 / w)
    smooth = jnp.where(x >= h, x, jnp.where(x <= -h, jnp.zeros_like(x), blend))
    return jnp.where(pos, smooth, jnp.maximum(x, 0.0))


# --------------------------------------------------------------------------- step averages
def _linear_averaged(d, vn, k, c, h):
    """Step average of ``k max(d, 0) - c vn [d > 0]`` (see the module docstring)."""
    frac, mean = window_mean(d, vn, h)
    return k * mean - c * vn * frac


def _no_tension_averaged(d, vn, k, c, h):
    """Step average of ``[d > 0] max(k d - c vn, 0)``. In the window ``vn`` is constant, so
    the force is ``k (d(s) - d*)`` where ``d(s) > t = max(0, d*)``, ``d* = c vn / k``, and 0
    elsewhere: ``k mean(d - t) + max(-c vn, 0) frac(d - t)``."""
    kp = k > 0.0
    t = quotient(jnp.maximum(c * vn, 0.0), jnp.where(kp, k, 1.0))   # k = 0: t times 0
    frac, mean = window_mean(d - t, vn, h)
    return k * mean + jnp.maximum(-c * vn, 0.0) * frac


def _hunt_crossley_averaged(exponent: float):
    def averaged(d, vn, k, c, h):
        """Step average of ``max(k - c vn, 0) max(d, 0)^n``."""
        _, mean = window_mean(d, vn, h, exponent)
        return jnp.maximum(k - c * vn, 0.0) * mean
    return averaged


# --------------------------------------------------------------------------- records
#: ``ContactLaw.safe_wh`` of the event-exact linear and no_tension records (their steps follow
#: the continuous motion through contact start and end, so the energy a held force injects
#: there, what :data:`diffpen.stability.SAFE_WH` bounds, is not made; measured exact up to w h
#: 1.26, with a contact of at least ``pi / (w h) > 2.5`` steps)
EVENTS_SAFE_WH = 1.0


@dataclasses.dataclass(frozen=True)
class ContactLaw:
    """Everything about one contact law (a penalty force along the contact normal).

    Fields (all functions pure ``jax.numpy``, elementwise, differentiable):

    name: str, how reports and ``repr`` name it.
    force: ``force(d, vn, k, c, width=0.0) -> F`` N, the pointwise force (``d`` m, ``vn``
      m/s separating, ``width`` the static smoothing width, m). Exactly 0 for
      ``d <= -width / 2``.
    averaged: ``averaged(d, vn, k, c, h) -> F`` N, the hat-weighted mean of the exact
      (``width = 0``) force over the window ``[-h, h]`` along ``d(s) = d - vn s`` (``h`` the
      integrator's inner step, s; :func:`window_mean`): continuous
      through contact start and end. None: the law has none (the integrators then use the
      pointwise force).
    energy: ``energy(d, k, width=0.0) -> E`` J, the elastic energy stored at depth ``d`` (the
      integral of the static force over depth; 0 when apart).
    resting_depth: ``resting_depth(load, k, width=0.0) -> d`` m, the depth at which the static
      force equals ``load`` N (a body of weight ``load`` resting on the contact).
    stiffness: ``stiffness(k, c, d_ref) -> (k_eff N/m, c_eff N s/m)``, the largest normal
      stiffness and damping of the law for depths up to ``d_ref`` m (what the explicit
      stability bound uses).
    exponent: the depth exponent n (1 for the linear laws; Hunt-Crossley's n).
    closed_form: the name of the family of closed forms in :mod:`diffpen.physical`
      (restitution, contact time) that hold for this law, or None.
    centred: ``centred(d, vn, k, c, h, lag, inv_mass, accel) -> F`` N, the step average with
      the law's velocity dependence evaluated at the speed of the window's centre,
      ``vn + lag (F inv_mass + accel)`` (``lag`` s: how far the given ``vn`` lags the window's
      centre, semi-implicit Euler's ``h / 2``; ``inv_mass`` 1/kg: the contact's effective
      inverse mass along the normal; ``accel`` m/s^2: the other separating acceleration,
      gravity). None (the default records): the damping at the given ``vn``. Opt in with
      ``linear(centred=True)``, ``no_tension(centred=True)``, ``hunt_crossley(n,
      centred=True)``; ``linear(exact=True)`` and ``no_tension(exact=True)`` put the exact
      one-contact step (:func:`exact_step_factors`) in this field.

    pulls: True when the force may be negative (pull) while in contact (``linear``); False
      when it is clamped at 0 (``no_tension``, ``hunt_crossley``).
    damping_exponent: m in the law's form ``F = k d^n - c vn d^m`` inside contact, before any
      clamp: 0 for the linear laws (``k d - c vn``), n for Hunt-Crossley (``(k - c vn) d^n``).
      With ``exponent`` and ``pulls`` it states the law's physics for code that writes it out
      independently (the event-located references of :mod:`tuning.reports.reference`).
    takes_exponent: True for a family built for a given ``exponent`` (``hunt_crossley``;
      by name, :func:`get` passes its ``exponent`` on for that name only); the others have
      n = 1 fixed, and an exponent given for them is an
      error of the caller's (a scene file refuses it).
    step_factors: ``step_factors(k, c, inv_mass, h) -> factors``, what ``centred`` takes as
      its ``factors=`` keyword when given (:func:`exact_step_factors` for the exact
      records): per-contact constants of the rollout, which a rollout computes once, before
      its loop, instead of at every (rematerialised) step. None: ``centred`` needs none.
    one_contact: ``"exact"`` or ``"events"`` for the records whose ``centred`` is a
      one-contact step (``linear(exact=True)``, ``events=True``): valid only for semi-implicit
      Euler, the exact ramp (smoothing 0) and a scene where no body feels more than one force
      besides gravity, which ``diffpen.compile`` checks (a SceneError elsewhere, instead of
      the plain step average in its place). None: any scene.
    safe_wh: the largest ``w h`` (``w^2`` the contact's stiffness over its mass, ``h`` the
      inner step) an explicit step is allowed with this law's contacts, or None for
      :data:`diffpen.stability.SAFE_WH` (0.5: where a contact starts or ends inside a step,
      a force held over the step injects energy ~ ``(w h)^2 / 4``). The event-exact linear
      and no_tension records follow the continuous motion through those steps: 1.0 (their
      apexes and contact times exact to 1e-5 at ``w h`` 0.95, restitution to 1e-15 up to
      1.26).

    A record is callable as its pointwise force: ``law(d, vn, k, c, width)``.
    """
    name: str
    force: Callable
    averaged: Callable | None
    energy: Callable
    resting_depth: Callable
    stiffness: Callable
    exponent: float = 1.0
    closed_form: str | None = None
    centred: Callable | None = None
    pulls: bool = False
    damping_exponent: float = 0.0
    takes_exponent: bool = False
    step_factors: Callable | None = None
    one_contact: str | None = None
    safe_wh: float | None = None

    def __call__(self, d, vn, k, c, width: float = 0.0):
        return self.force(d, vn, k, c, width)

    def step_force(self, d, vn, k, c, width: float = 0.0, h: float | None = None):
        """The force an integrator with inner step ``h`` (s) applies: the step average when
        ``h`` is given, the law has one and ``width == 0``; otherwise the pointwise force
        (``h=None``: the instantaneous force; ``width > 0``: the smoothed pointwise law)."""
        if h is None or width != 0.0 or self.averaged is None:
            return self.force(d, vn, k, c, width)
        return self.averaged(d, vn, k, c, h)

    def centred_force(self, d, vn, k, c, h, lag, inv_mass, accel=0.0, factors=None):
        """The step average (``h`` s) with the damping at the window centre's speed (see
        ``centred``); the plain step average when ``lag`` is 0 or the record has no
        ``centred``.

        Semi-implicit Euler's state velocity is the mean over the step that ended (it lags
        the force evaluation's position by ``h / 2``); a damper evaluated at it dissipates
        too much, by O(c h / m) per contact (apexes 0.3-0.9% low at dt 1e-3 on the
        quick-start ball). Solving for the centre speed removes that bias without dividing
        by anything that can vanish (denominators >= 1)."""
        if self.averaged is None:
            return self.force(d, vn, k, c)
        if self.centred is None or not lag:
            return self.averaged(d, vn, k, c, h)
        if factors is not None:        # the record's step_factors, computed beforehand
            return self.centred(d, vn, k, c, h, lag, inv_mass, accel, factors=factors)
        return self.centred(d, vn, k, c, h, lag, inv_mass, accel)


def _linear_energy(d, k, width=0.0):
    return k * ramp_integral(d, width)


def _linear_rest(load, k, width=0.0):
    return ramp_inverse(load / k, width)


def _linear_stiffness(k, c, d_ref=None):
    return k, c


def linear(centred: bool = False, exact: bool = False, events: bool = False) -> ContactLaw:
    """``F = k d - c vn`` in contact (may pull at the end of contact); closed forms
    ``t_c = pi / w_d``, ``e = exp(-pi zeta / sqrt(1 - zeta^2))``. ``centred``: damping at
    the step window's centre speed; ``exact``: a one-contact record that steps the damped
    spring exactly (:func:`exact_step_factors`; module docstring); ``events``: a one-contact
    record exact through contact start and end too (:mod:`diffpen.event_step`)."""
    if events and (centred or exact):
        raise ValueError("linear(): choose one of centred=True, exact=True, events=True")
    one = (linear_events if events else linear_exact if exact
           else linear_centred if centred else None)
    return ContactLaw("linear", linear_contact, _linear_averaged, _linear_energy, _linear_rest,
                      _linear_stiffness, 1.0, "linear", one, pulls=True,
                      step_factors=(exact_step_factors if exact else event_step_factors
                                    if events else None),
                      one_contact="events" if events else "exact" if exact else None,
                      safe_wh=EVENTS_SAFE_WH if events else None)


def no_tension(centred: bool = False, exact: bool = False, events: bool = False) -> ContactLaw:
    """``F = max(k d - c vn, 0)`` in contact (never pulls); Schwager & Poschel's closed
    forms. ``centred``: damping at the step window's centre speed; ``exact``: a one-contact
    record that steps the damped spring exactly while it pushes (module docstring);
    ``events``: a one-contact record exact through contact start and release too
    (:mod:`diffpen.event_step`)."""
    if events and (centred or exact):
        raise ValueError("no_tension(): choose one of centred=True, exact=True, events=True")
    one = (no_tension_events if events else no_tension_exact if exact
           else no_tension_centred if centred else None)
    return ContactLaw("no_tension", no_tension_contact, _no_tension_averaged, _linear_energy,
                      _linear_rest, _linear_stiffness, 1.0, "no_tension", one,
                      step_factors=(exact_step_factors if exact else event_step_factors
                                    if events else None),
                      one_contact="events" if events else "exact" if exact else None,
                      safe_wh=EVENTS_SAFE_WH if events else None)


def hunt_crossley(exponent: float = 1.0, centred: bool = False,
                  events: bool = False) -> ContactLaw:
    """``F = max(k - c vn, 0) d^n`` (Hunt-Crossley; ``n = 1.5`` is Hertz), ``n >= 1``.
    ``centred``: damping at the step window's centre speed (module docstring); ``events``: a
    one-contact record exact through contact start and end to its Runge-Kutta flow's error
    (:func:`diffpen.event_step.hunt_crossley_events`)."""
    n = float(exponent)
    if not (math.isfinite(n) and n >= 1.0):
        raise ValueError(f"Hunt-Crossley exponent must be a finite number >= 1, got "
                         f"{exponent!r}.")

    def force(d, vn, k, c, width=0.0):
        return hunt_crossley_contact(d, vn, k, c, width, n)

    def energy(d, k, width=0.0):
        return k * ramp_integral(d, width, n)

    def rest(load, k, width=0.0):
        return ramp_inverse((load / k) ** (1.0 / n), width)

    def stiffness(k, c, d_ref):
        # dF/dd = n k d^(n-1), dF/dvn = c d^n: largest at the deepest depth considered
        return n * k * d_ref ** (n - 1.0), c * d_ref ** n
    if events and centred:
        raise ValueError("hunt_crossley(): choose one of centred=True, events=True")
    one = (hunt_crossley_events(n, force) if events else hunt_crossley_centred(n) if centred
           else None)
    return ContactLaw("hunt_crossley", force, _hunt_crossley_averaged(n), energy, rest,
                      stiffness, n, None, one,
                      damping_exponent=n, takes_exponent=True,
                      one_contact="events" if events else None)


#: Contact laws by name, for ``diffpen.compile(..., law=NAME)``: the records (Hunt-Crossley
#: with n = 1; :func:`get` builds it for another exponent). Each is callable as its pointwise
#: force ``(d, vn, k, c, width)``, as the plain functions this mapping held before.
CONTACT_LAWS = {
    "linear": linear(),
    "no_tension": no_tension(),
    "hunt_crossley": hunt_crossley(),
}


def get(law, exponent: float = 1.0, centred: bool = False, events: bool = False) -> ContactLaw:
    """The :class:`ContactLaw` for ``law``: a record (returned as is) or a name in
    :data:`CONTACT_LAWS` (``exponent`` goes to ``hunt_crossley``; ``centred`` builds the
    name's record with its damping at the step window's centre, ``events`` its event-exact
    one-contact record, :mod:`diffpen.event_step`). Raises ValueError naming the choices
    otherwise, and an ``exponent`` other than 1 for any other name, or other than a record's
    own (it was ignored: a linear law asked for with exponent 2.0 ran linear), or not a
    number (``"1.5"`` was read as 1.5, ``True`` as 1)."""
    if isinstance(exponent, (str, bytes, bool, np.bool_)):
        raise ValueError(f"exponent must be a number, got {exponent!r}"
                         + (": write it without quotes." if isinstance(exponent, str) else "."))
    if isinstance(law, ContactLaw):
        if exponent not in (1.0, law.exponent):
            raise ValueError(f"exponent={exponent!r} differs from the contact law record's own "
                             f"({law.exponent:g}): a record carries its exponent; leave the "
                             "exponent out or build the record with the one you want.")
        return law
    if exponent != 1.0 and law != "hunt_crossley":
        raise ValueError(f"exponent={exponent!r} is read by law='hunt_crossley' only "
                         f"(law={law!r} has none): pass law='hunt_crossley' or leave the "
                         "exponent out.")
    if isinstance(law, str) and law in CONTACT_LAWS:
        if law == "hunt_crossley":
            return hunt_crossley(exponent, centred, events)
        if centred or events:
            return {"linear": linear, "no_tension": no_tension}[law](centred, events=events)
        return CONTACT_LAWS[law]
    raise ValueError(f"unknown contact law {law!r}; choose one of {sorted(CONTACT_LAWS)} or "
                     "pass a diffpen.laws.ContactLaw record.")
