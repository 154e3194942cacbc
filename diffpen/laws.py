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

**Centred Hunt-Crossley** also takes the window along the centre's motion ``d - vc s`` and
the damper's speed ``vc + a s`` varying inside it (:func:`diffpen.window.window_moments`):
with ``d^n`` nonlinear, the window along the lagging ``vn`` gives more force while a body
decelerates into contact than while it leaves. Hertz ball (1 kg, n 1.5, k 1e6, c 3e4) at
dt 1e-3: apexes +0.02 / +0.04 / +0.05% off the continuous ones (-0.74 / -1.36 / -1.90%
before; undamped, 0.00% against -0.42% per bounce), the derivatives of apexes 2-3 within
4.6% over impact phases (12.7% before). It takes three windows per contact: against the
single window of before, 1.20x a batch-1 rollout, 1.35x / 1.72x forward / reverse-mode
gradients, and 0.23x batched (the windows' half-integer powers are now square roots times
integer powers, :mod:`diffpen.window`). The linear laws need neither: the mean
of a linear depth is the same along either path, and the same two changes made the 0.3 kg
ball's apexes worse (0.68% against 0.47%).

**Damping at the window's centre** (``ContactLaw.centred``; ``linear(centred=True)``,
``no_tension(centred=True)``, ``hunt_crossley(n, centred=True)`` or ``get(name,
centred=True)``; ``diffpen.compile`` takes it for a law named by a string on scenes of one
contact, :func:`diffpen.checks.one_contact_per_body`). Semi-implicit Euler's velocity is the
mean over the step that ended, half a step behind the position the force is evaluated at,
and a damper fed with it dissipates too much (apexes 0.3-0.9% low at dt 1e-3 on the
quick-start ball with the plain step average). A centred
record evaluates the law's velocity dependence at the centre speed
``vc = vn + (h / 2) (F / m_eff + g_n)`` and solves for ``F`` (one division per contact by a
denominator >= 1; the window is still taken along ``d - vn s``, so the force stays
continuous). At dt 1e-3 the apexes are then within 0.5% (quick-start ball
+0.04/+0.08/+0.13% against -0.29/-0.59/-0.91%; 0.3 kg ball <= 0.47% against -1.21%, over
where the impact falls in the step) and d duration1 / dc is 0.4% off the continuous
derivative (37% without). Cost against the plain step average (one process, float32,
``benchmarks/step_cost.py``): batch-1 rollouts 1.07-1.21x, forward-mode gradients
1.06-1.07x, reverse-mode 1.18-1.25x, batched (vmap 1024) 0.99-1.16x.

**Exact one-contact records** (``linear(exact=True)``, ``no_tension(exact=True)``; opt-in)
scale the stiffness and the damping by the factors with which a kick-then-drift step
reproduces a damped spring under its load exactly (:func:`exact_step_factors`): ``R k mean
- Q c vn frac + (1 - R) W frac``, ``W = -accel / inv_mass`` the contact's load. While the
window is inside contact semi-implicit Euler's positions are then the continuous motion's at
every step time, whatever ``w h`` and ``c h / m``; only the steps where a contact starts or
ends are approximate. At dt 1e-3 over four impact phases: apexes 1-3 within
+0.03/+0.07/+0.11% (quick-start ball), +0.08/+0.13/+0.15% (0.3 kg ball; the centred record
up to +0.18/+0.36/+0.47%), +0.01/+0.02/+0.04% (2 kg no_tension ball), contact durations and
the largest penetration exact to 0.00-0.04%, and with check_stability=False a ball stays
bounded far past the explicit step limit (k 1e8 at dt 1e-3). The factors depend on ``k``,
``c``, the mass and the step only, in arithmetic and square roots (XLA's ``exp`` and
``sin`` differ in their last bits between batch layouts; sharded fits must equal
single-device ones bit for bit). A rollout computes them once per contact, before its loop
(``ContactLaw.step_factors``, passed in ``Params.extra``; computed inside the step, a
rematerialised reverse-mode step recomputed them and their derivatives at every step,
5.6x). Cost against the centred record (one process, float32, 3000 steps): batch-1 rollout
0.89x, 1024 batched 1.00x, reverse-mode gradient 0.96x, forward-mode 1.25x. They are not
what a named law takes: the derivatives of apexes 2-3 ripple with the impact phase as much
as with the centred record (quick-start ball 6-8% against 10-12%, the 0.3 kg ball's apex 2
39% against 25%, over four phases), and forward-mode gradients cost more.

Why it is not the default everywhere: each contact estimates the centre speed from its own
force and gravity only (``g_n``), which is exact for a body on one contact but not for a
body resting on several (the other contacts' forces are missing from its acceleration). At rest the
damper then sees a speed ``(h / 2) (F / m_eff + g_n)`` that is not 0, and the resting depth
is off by O(c h / m): two stacked 1 kg balls at c 20 N s/m, h 1 ms rest 0.5% (the plane's
contact) and 2% (the pair's) too deep. The plain step average rests exactly at ``m g / k``,
so a named law keeps it wherever a body can feel more than one force besides gravity.
Box corners, sphere-box and box-fixed-sphere pairs take the plain step average either way,
and so do integrators whose velocity does not lag (verlet, rk4, implicit Euler) and smoothed
laws (``smoothing > 0``).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax.numpy as jnp

from .window import window_mean, window_moments

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
    t = jnp.maximum(c * vn, 0.0) / jnp.where(kp, k, 1.0)   # k = 0: t is multiplied by 0
    frac, mean = window_mean(d - t, vn, h)
    return k * mean + jnp.maximum(-c * vn, 0.0) * frac


def _hunt_crossley_averaged(exponent: float):
    def averaged(d, vn, k, c, h):
        """Step average of ``max(k - c vn, 0) max(d, 0)^n``."""
        _, mean = window_mean(d, vn, h, exponent)
        return jnp.maximum(k - c * vn, 0.0) * mean
    return averaged


# --------------------------------------------------------------------------- centred damping
def _linear_centred(d, vn, k, c, h, lag, inv_mass, accel):
    """Step average of the linear law with its damping at the window centre's speed
    ``vc = vn + lag (F inv_mass + accel)``: ``F = k mean - c frac vc`` solved for ``F``,
    ``F = (k mean - c frac (vn + lag accel)) / (1 + c frac lag inv_mass)`` (the window from
    ``vn``). The denominator is >= 1: no division by anything that can vanish, and where
    ``c lag / m`` nears the explicit damping limit the force stays the damper's (a
    one-pass explicit estimate, ``F0 - c frac lag (accel + inv_mass F0)``, scaled the whole
    force by ``1 - c lag / m`` there: an overdamped ball sank to three times its resting
    depth)."""
    frac, mean = window_mean(d, vn, h)
    cf = c * frac
    return (k * mean - cf * (vn + lag * accel)) / (1.0 + cf * (lag * inv_mass))


_HALVINGS = 10


def _expm1_neg(x):
    """``expm1(x)`` for ``x <= 0`` in arithmetic only (scaling and squaring: a Taylor series
    at ``x / 2^10``, then ``m <- m (2 + m)`` ten times, which keeps expm1's accuracy near 0;
    relative error ~1e-15 in float64). Arithmetic, not ``jnp.expm1``: XLA's exp differs in
    its last bits between programs of different batch layouts (the same fit on 1 and on 4
    devices), and sharded results must equal single-device ones bit for bit."""
    y = jnp.maximum(x, -80.0) * (1.0 / 2 ** _HALVINGS)
    m = y * (1.0 + y / 2.0 * (1.0 + y / 3.0 * (1.0 + y / 4.0 * (1.0 + y / 5.0 * (
        1.0 + y / 6.0 * (1.0 + y / 7.0))))))
    for _ in range(_HALVINGS):
        m = m * (2.0 + m)
    return m


def _cos_minus_one(t):
    """``cos(t) - 1`` for ``t >= 0`` in arithmetic only (halving and the double-angle
    ``c <- 2 c (c + 2)``, as :func:`_expm1_neg`)."""
    a2 = (t * (1.0 / 2 ** _HALVINGS)) ** 2
    c = -0.5 * a2 * (1.0 - a2 / 12.0 * (1.0 - a2 / 30.0 * (1.0 - a2 / 56.0)))
    for _ in range(_HALVINGS):
        c = 2.0 * c * (c + 2.0)
    return c


def _expm1_ratio(x):
    """``expm1(x) / x`` (1 at ``x = 0``), without cancellation; ``x <= 0``."""
    small = jnp.abs(x) < 1e-4
    xs = jnp.where(small, -1.0, x)
    return jnp.where(small, 1.0 + x * (0.5 + x * (1.0 / 6.0 + x / 24.0)), _expm1_neg(xs) / xs)


def exact_step_factors(k, c, inv_mass, h):
    """``(R, Q)``: the factors of stiffness and damping with which a kick-then-drift step
    (semi-implicit Euler: ``v += h a(x_n, v_n)``, ``x += h v``) reproduces a damped linear
    spring under constant load exactly at the step times.

    For ``y'' = -w0^2 y - 2 s y'`` (``w0^2 = k inv_mass``, ``s = c inv_mass / 2``) the exact
    samples obey ``y_{n+1} = A1 y_n + A2 y_{n-1}`` with ``A1 = e^{r1 h} + e^{r2 h}``,
    ``A2 = -e^{(r1 + r2) h}`` (``r1, r2`` the roots of ``r^2 + 2 s r + w0^2``), and the step
    gives ``y_{n+1} - 2 y_n + y_{n-1} = h^2 a_n`` with ``y_n - y_{n-1} = h v_n``: so the
    force ``R k (d - d_e) - Q c vn`` about the resting depth ``d_e`` gives exact samples,
    ``R = (1 - e^{r1 h}) (1 - e^{r2 h}) / (w0 h)^2`` and ``Q = (1 - e^{-2 s h}) / (2 s h)``,
    both 1 + O(h^2) and O(h) (``R = 1 - (w0 h)^2 / 12 + ...``). Written without cancellation
    (``expm1``; the complex pair as ``|1 - e^{r h}|^2 = (1 - E)^2 + 4 E sin^2(w_d h / 2)``,
    ``E = e^{-s h}``; a series where ``w_d h`` is near 0, where both forms meet), and finite
    with finite derivatives for every ``k, c >= 0`` (``R = Q = 1`` for a massless or
    infinitely heavy contact, ``inv_mass = 0``).

    Args: k N/m, c N s/m, inv_mass 1/kg (the contact's effective inverse mass), h s.
    Returns: ``(R, Q)``, dimensionless, elementwise."""
    sh = 0.5 * c * inv_mass * h                         # s h
    w2 = k * inv_mass * h * h                           # (w0 h)^2
    x = w2 - sh * sh                                    # (w_d h)^2, < 0 overdamped
    q = _expm1_ratio(-2.0 * sh)
    # near critical (|x| small against sh^2, at most 1e-2): a series in x
    near = jnp.abs(x) <= 1e-2 * jnp.minimum(sh * sh, 1.0)
    # underdamped and near critical: ((1 - E)^2 + 4 E S) / w2, S = sin^2(sqrt(x) / 2)
    one_minus_e = sh * _expm1_ratio(-sh)
    e = 1.0 - one_minus_e
    big = (x > 0.0) & ~near
    xb = jnp.where(big, x, 1.0)
    xs = jnp.where(big, 0.0, x)
    four_s = jnp.where(big, -2.0 * _cos_minus_one(jnp.sqrt(xb)),
                       xs * (1.0 - xs / 12.0 + xs * xs / 360.0))
    num = one_minus_e * one_minus_e + e * four_s
    tiny = w2 < 1e-30
    r_complex = jnp.where(tiny, 1.0 - xs / 12.0, num / jnp.where(tiny, 1.0, w2))
    # overdamped: phi(r1 h) phi(r2 h), r1 h = -w2 / (sh + sq), r2 h = -(sh + sq)
    over = (x < 0.0) & ~near
    sq = jnp.sqrt(jnp.where(over, -x, 1.0))
    r_real = _expm1_ratio(-w2 / (sh + sq)) * _expm1_ratio(-(sh + sq))
    return jnp.where(over, r_real, r_complex), q


def _exact_terms(k, c, h, inv_mass, accel, factors=None):
    """``(R k, Q c, load)`` of :func:`exact_step_factors`, ``load = -(1 - R) accel / inv_mass``
    the resting depth's share (``R k d_e = -R accel / inv_mass`` moved to where ``k d``
    balances the load: at rest the force is the load ``-accel / inv_mass`` exactly).
    ``factors``: ``(R, Q)`` computed beforehand (a rollout computes them once, outside its
    loop), or None to compute them here."""
    r, q = exact_step_factors(k, c, inv_mass, h) if factors is None else factors
    heavy = inv_mass > 0.0
    weight = jnp.where(heavy, -accel / jnp.where(heavy, inv_mass, 1.0), 0.0)
    return r * k, q * c, (1.0 - r) * weight


def _linear_exact(d, vn, k, c, h, lag, inv_mass, accel, factors=None):
    """Step average of the linear law, exact for one contact of a kick-then-drift step:
    ``F = R k mean + (W (1 - R) - Q c vn) frac`` (:func:`exact_step_factors`; ``W =
    -accel / inv_mass`` the contact's load, the window from ``vn``). Deep in contact the step
    then reproduces the damped spring's motion exactly at the step times, whatever ``w h``
    and ``c h / m`` (semi-implicit Euler's velocity lags the position by ``lag = h / 2``,
    which the factors take in); at rest the force is the load exactly. Contact start and
    end keep the window's continuity."""
    rk, qc, load = _exact_terms(k, c, h, inv_mass, accel, factors)
    frac, mean = window_mean(d, vn, h)
    return rk * mean + (load - qc * vn) * frac


def _no_tension_exact(d, vn, k, c, h, lag, inv_mass, accel, factors=None):
    """The no_tension step average (:func:`_no_tension_averaged`: the clamp offset and the
    window of ``d - t`` from ``vn``) with the exact factors of :func:`_linear_exact`:
    ``max(R k mean - Q c frac min(vn, 0) + (1 - R) W frac, 0)``, ``t = max(Q c vn, 0) /
    (R k)`` (the linear law's form while approaching; continuous at ``vn = 0``)."""
    rk, qc, load = _exact_terms(k, c, h, inv_mass, accel, factors)
    kp = rk > 0.0
    t = jnp.maximum(qc * vn, 0.0) / jnp.where(kp, rk, 1.0)
    frac, mean = window_mean(d - t, vn, h)
    return jnp.maximum(rk * mean + (load - qc * jnp.minimum(vn, 0.0)) * frac, 0.0)


def _hunt_crossley_centred(exponent: float):
    def centred(d, vn, k, c, h, lag, inv_mass, accel):
        """``(k - c v) d^n`` averaged over the window along the centre's motion: the centre
        speed ``vc = vn + lag (F0 inv_mass + accel)`` from the step average with the damping
        at ``vc`` solved for, ``F0 = max(k - c (vn + lag accel), 0) mean / (1 + c lag
        inv_mass mean)`` (the window along ``d - vn s``), and the separating acceleration
        ``a = F0 inv_mass + accel``; then the window taken along ``d - vc s`` with the speed
        ``vc + a s`` inside it: ``max(k mean - c (vc mean + a moment), 0)``
        (:func:`diffpen.window.window_moments`).

        Both corrections are what a nonlinear depth term needs and the linear laws do not:
        the mean of ``d^n`` along a path through the lagging speed ``vn`` is larger while the
        body decelerates into contact than while it leaves (undamped Hertz ball, dt 1e-3:
        0.42% of the apex lost per bounce; 0.00% along ``vc``), and ``d^n`` and the speed
        vary together inside the window (their covariance, ``a moment``; without it the
        damped Hertz ball's apexes were -0.34 / -0.62 / -0.86%, with it +0.02 / +0.04 /
        +0.05%). (A pointwise ``d^n`` for ``F0`` costs less, 0.8x, with the same values but
        derivatives of apexes 2-3 up to 12% off over impact phases, against 4.6%.)"""
        _, pw = window_mean(d, vn, h, exponent)
        f0 = (jnp.maximum(k - c * (vn + lag * accel), 0.0) * pw
              / (1.0 + (c * lag * inv_mass) * pw))
        a = f0 * inv_mass + accel
        vc = vn + lag * a
        mean, moment = window_moments(d, vc, h, exponent)
        return jnp.maximum(k * mean - c * (vc * mean + a * moment), 0.0)
    return centred


def _no_tension_centred(d, vn, k, c, h, lag, inv_mass, accel):
    """The no_tension step average (:func:`_no_tension_averaged`: window and clamp offset
    ``t = max(c vn, 0) / k`` from ``vn``) with the damping's change to the centre speed
    ``vc - vn = lag (F inv_mass + accel)`` taken at the window's slope ``frac`` and solved
    for ``F``: ``F = max((F0 - c frac lag accel) / (1 + c frac lag inv_mass), 0)``,
    ``F0 = k mean - c frac min(vn, 0)`` (the linear law's form while approaching;
    continuous at ``vn = 0``)."""
    kp = k > 0.0
    t = jnp.maximum(c * vn, 0.0) / jnp.where(kp, k, 1.0)
    frac, mean = window_mean(d - t, vn, h)
    cf = c * frac
    f0 = k * mean - cf * (jnp.minimum(vn, 0.0) + lag * accel)
    return jnp.maximum(f0 / (1.0 + cf * (lag * inv_mass)), 0.0)


# --------------------------------------------------------------------------- records
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
    takes_exponent: True when :func:`get` builds the law for a given ``exponent``
      (``hunt_crossley``); the others have n = 1 fixed, and an exponent given for them is an
      error of the caller's (a scene file refuses it).
    step_factors: ``step_factors(k, c, inv_mass, h) -> factors``, what ``centred`` takes as
      its ``factors=`` keyword when given (:func:`exact_step_factors` for the exact
      records): per-contact constants of the rollout, which a rollout computes once, before
      its loop, instead of at every (rematerialised) step. None: ``centred`` needs none.

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


def linear(centred: bool = False, exact: bool = False) -> ContactLaw:
    """``F = k d - c vn`` in contact (may pull at the end of contact); closed forms
    ``t_c = pi / w_d``, ``e = exp(-pi zeta / sqrt(1 - zeta^2))``. ``centred``: damping at
    the step window's centre speed; ``exact``: a one-contact record that steps the damped
    spring exactly (:func:`exact_step_factors`; module docstring)."""
    one = _linear_exact if exact else _linear_centred if centred else None
    return ContactLaw("linear", linear_contact, _linear_averaged, _linear_energy, _linear_rest,
                      _linear_stiffness, 1.0, "linear", one, pulls=True,
                      step_factors=exact_step_factors if exact else None)


def no_tension(centred: bool = False, exact: bool = False) -> ContactLaw:
    """``F = max(k d - c vn, 0)`` in contact (never pulls); Schwager & Poschel's closed
    forms. ``centred``: damping at the step window's centre speed; ``exact``: a one-contact
    record that steps the damped spring exactly while it pushes (module docstring)."""
    one = _no_tension_exact if exact else _no_tension_centred if centred else None
    return ContactLaw("no_tension", no_tension_contact, _no_tension_averaged, _linear_energy,
                      _linear_rest, _linear_stiffness, 1.0, "no_tension", one,
                      step_factors=exact_step_factors if exact else None)


def hunt_crossley(exponent: float = 1.0, centred: bool = False) -> ContactLaw:
    """``F = max(k - c vn, 0) d^n`` (Hunt-Crossley; ``n = 1.5`` is Hertz), ``n >= 1``.
    ``centred``: damping at the step window's centre speed (module docstring)."""
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
    return ContactLaw("hunt_crossley", force, _hunt_crossley_averaged(n), energy, rest,
                      stiffness, n, None, _hunt_crossley_centred(n) if centred else None,
                      damping_exponent=n, takes_exponent=True)


#: Contact laws by name, for ``diffpen.compile(..., law=NAME)``: the records (Hunt-Crossley
#: with n = 1; :func:`get` builds it for another exponent). Each is callable as its pointwise
#: force ``(d, vn, k, c, width)``, as the plain functions this mapping held before.
CONTACT_LAWS = {
    "linear": linear(),
    "no_tension": no_tension(),
    "hunt_crossley": hunt_crossley(),
}


def get(law, exponent: float = 1.0, centred: bool = False) -> ContactLaw:
    """The :class:`ContactLaw` for ``law``: a record (returned as is) or a name in
    :data:`CONTACT_LAWS` (``exponent`` goes to ``hunt_crossley``; ``centred`` builds the
    name's record with its damping at the step window's centre). Raises ValueError naming
    the choices otherwise."""
    if isinstance(law, ContactLaw):
        return law
    if isinstance(law, str) and law in CONTACT_LAWS:
        if law == "hunt_crossley":
            return hunt_crossley(exponent, centred)
        return {"linear": linear, "no_tension": no_tension}[law](True) if centred \
            else CONTACT_LAWS[law]
    raise ValueError(f"unknown contact law {law!r}; choose one of {sorted(CONTACT_LAWS)} or "
                     "pass a diffpen.laws.ContactLaw record.")
