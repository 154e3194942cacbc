"""The contact laws' one-contact forms: the damping at the step window's centre speed
(``ContactLaw.centred``) and the step that reproduces a damped spring exactly
(:func:`exact_step_factors`). Each acts on ONE contact, as :mod:`diffpen.laws` does, and
additionally knows the contact's effective inverse mass along the normal (``inv_mass``,
1/kg), its other separating acceleration (``accel``, m/s^2: gravity) and how far
semi-implicit Euler's velocity lags the force's position (``lag``, s): exact for a body on
one contact. :mod:`diffpen.laws` builds its records from these functions
(``linear(centred=True)`` ...); signatures ``f(d, vn, k, c, h, lag, inv_mass, accel)``
with :mod:`diffpen.laws`' conventions and units.

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
``linear(events=True)``, ``no_tension(events=True)`` and ``hunt_crossley(n, events=True)``
(:mod:`diffpen.event_step`) also make the steps where a contact starts or ends exact, and
with them the derivatives of apexes and contact times.

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

import jax
import jax.numpy as jnp

from .window import window_mean, window_moments

__all__ = ["linear_centred", "no_tension_centred", "hunt_crossley_centred",
           "exact_step_factors", "linear_exact", "no_tension_exact", "quotient"]


@jax.custom_jvp
def quotient(num, den):
    """``num / den``, with the derivative ``(dnum - q dden) / den`` (``q`` the quotient): one
    division by ``den`` for both tangents. Autodiff of ``num / den`` takes
    ``dnum / den - num dden den^-2``, whose extra power and products XLA kept apart from the
    step's other work under ``jax.vmap``: reverse-mode gradients of 1024 batched balls with
    the centred linear record took 82-100 ms against 44-56 ms with this rule, with the plain
    no_tension record (its clamp offset ``c vn / k``) 208-221 ms against 86-92 ms (the same
    values, the same derivatives to rounding). The centred records' forces and no_tension's
    offset take it."""
    return num / den


@quotient.defjvp
def _quotient_jvp(primals, tangents):
    num, den = primals
    dnum, dden = tangents
    q = num / den
    return q, (dnum - q * dden) / den


# --------------------------------------------------------------------------- damping at the window's centre
def linear_centred(d, vn, k, c, h, lag, inv_mass, accel):
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
    return quotient(k * mean - cf * (vn + lag * accel), 1.0 + cf * (lag * inv_mass))


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


def linear_exact(d, vn, k, c, h, lag, inv_mass, accel, factors=None):
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


def no_tension_exact(d, vn, k, c, h, lag, inv_mass, accel, factors=None):
    """The no_tension step average (:func:`diffpen.laws._no_tension_averaged`: the clamp offset and the
    window of ``d - t`` from ``vn``) with the exact factors of :func:`linear_exact`:
    ``max(R k mean - Q c frac min(vn, 0) + (1 - R) W frac, 0)``, ``t = max(Q c vn, 0) /
    (R k)`` (the linear law's form while approaching; continuous at ``vn = 0``)."""
    rk, qc, load = _exact_terms(k, c, h, inv_mass, accel, factors)
    kp = rk > 0.0
    t = jnp.maximum(qc * vn, 0.0) / jnp.where(kp, rk, 1.0)
    frac, mean = window_mean(d - t, vn, h)
    return jnp.maximum(rk * mean + (load - qc * jnp.minimum(vn, 0.0)) * frac, 0.0)


def hunt_crossley_centred(exponent: float):
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
        f0 = quotient(jnp.maximum(k - c * (vn + lag * accel), 0.0) * pw,
                       1.0 + (c * lag * inv_mass) * pw)
        a = f0 * inv_mass + accel
        vc = vn + lag * a
        mean, moment = window_moments(d, vc, h, exponent)
        return jnp.maximum(k * mean - c * (vc * mean + a * moment), 0.0)
    return centred


def no_tension_centred(d, vn, k, c, h, lag, inv_mass, accel):
    """The no_tension step average (:func:`diffpen.laws._no_tension_averaged`: window and clamp offset
    ``t = max(c vn, 0) / k`` from ``vn``) with the damping's change to the centre speed
    ``vc - vn = lag (F inv_mass + accel)`` taken at the window's slope ``frac`` and solved
    for ``F``: ``F = max((F0 - c frac lag accel) / (1 + c frac lag inv_mass), 0)``,
    ``F0 = k mean - c frac min(vn, 0)`` (the linear law's form while approaching;
    continuous at ``vn = 0``)."""
    kp = k > 0.0
    t = quotient(jnp.maximum(c * vn, 0.0), jnp.where(kp, k, 1.0))
    frac, mean = window_mean(d - t, vn, h)
    cf = c * frac
    f0 = k * mean - cf * (jnp.minimum(vn, 0.0) + lag * accel)
    return jnp.maximum(quotient(f0, 1.0 + cf * (lag * inv_mass)), 0.0)
