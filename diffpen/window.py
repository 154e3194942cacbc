"""The step window: hat-weighted means of a contact's penetration over one integrator step.

Why (``diffpen.laws.ContactLaw.averaged`` is built on it): a contact that
starts or ends inside a step makes a pointwise force jump between steps, so the step is a
discontinuous function of the state and its derivative misses the contact events. Instead, each
contact applies the mean of its force over the window ``s in [-h, h]`` around the evaluation,
weighted by the hat ``1 - |s| / h`` of the step grid, along the straight path of the
penetration ``d(s) = d - vn s`` (``h`` the integrator's inner step). In the leapfrog view of
semi-implicit Euler (and verlet) the kicks ``h F_n`` then carry the force history's impulse
and its first moment, so the velocity and the position after a contact event do not depend on
where in the step the event fell (:func:`window_mean`). The mean is a continuous function of
``d``, ``vn``, ``k`` and ``c`` through contact start and end, and its derivative carries the
event terms (the saltation of a contact starting or ending inside the window). Deep in contact
(the window entirely inside) it equals the pointwise law: ``k d - c vn`` is linear in ``s``.
Closed forms are written piecewise, without dividing by ``vn`` and without cancellation.

Here: :func:`window_mean` ``(frac, mean)`` of the path ``d(s) = d - vn s`` over
``s in [-h, h]``, per contact (scalars or elementwise arrays; ``d`` m, ``vn`` m/s separating,
``h`` the inner step, s). For the linear laws (exponent 1) with a static step it carries
closed-form derivatives (a custom JVP, equal to autodiff to rounding, fewer operations: what
keeps reverse-mode rollout gradients at the pointwise law's cost); other exponents are
differentiated by autodiff.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from .lanes import lined_up

__all__ = ["window_mean", "window_moments"]


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _power(x, p: float):
    """``x ** p`` for ``x >= 0`` and a static exponent ``p``: for integer and half-integer
    ``p >= 1`` (Hertz's 1.5 and the window's 3.5 ...) as an integer power times ``sqrt(x)``
    (``p = 0.5``: ``sqrt(x)``), which XLA evaluates several times faster than the general
    ``pow`` (an exp and a log); the general ``pow`` otherwise. Derivative ``p x^(p - 1)`` (a
    rule of its own: the product's ``x^k / (2 sqrt(x))`` would be 0 / 0 at ``x = 0``)."""
    twice = 2.0 * p
    if p == 0.5:
        return jnp.sqrt(x)
    if twice != round(twice) or p < 1.0:
        return x ** p
    out = x ** int(p)
    return out * jnp.sqrt(x) if twice % 2 else out


@_power.defjvp
def _power_jvp(p, primals, tangents):
    (x,), (dx,) = primals, tangents
    slope = p * _power(x, p - 1.0) if p != 1.0 else jnp.ones_like(x)
    return _power(x, p), slope * dx


def _power_mean_inside(d, delta, n: float):
    """Hat-weighted mean of ``x^n`` over ``[d - delta, d + delta]``, ``0 <= delta <= d``
    (``d > 0``), without the cancellation of the second difference for a narrow window:
    with ``u = delta / d``, ``d^n sum_j C(n, 2j) u^(2j) 2 / ((2j + 1)(2j + 2))`` (six terms,
    relative error < 1e-13) for ``u < 0.2``, the second difference of
    ``x^(n+2) / ((n+1)(n+2))`` divided by ``delta^2`` otherwise."""
    u = delta / d
    small = u < 0.2
    us = jnp.where(small, u, 0.0)
    u2 = us * us
    series, coef, term = jnp.ones_like(us), 1.0, jnp.ones_like(us)
    for j in range(1, 6):
        coef *= (n - 2 * j + 2) * (n - 2 * j + 1) / ((2 * j) * (2 * j - 1))
        term = term * u2
        series = series + coef * 2.0 / ((2 * j + 1) * (2 * j + 2)) * term
    # the unselected branch on safe values (double where): d - dl > 0, so no negative base
    # meets a fractional power (its NaN would reach reverse-mode gradients through where)
    dd = jnp.where(small, 2.0, d)
    dl = jnp.where(small, 1.0, delta)
    p = n + 2.0
    direct = ((_power(dd + dl, p) - 2.0 * _power(dd, p) + _power(dd - dl, p))
              / ((n + 1.0) * p * dl * dl))
    return jnp.where(small, _power(d, n) * series, direct)


def _window_linear_parts(d, vn, h, autodiff: bool = True, guard: bool = True):
    """:func:`window_mean` for exponent 1 with its intermediates:
    ``(frac, mean, u, delta, on, pos)``.

    d >= 0: ``1 - u^2 / 2`` and ``d + e u^2 / 6`` with ``e = max(-a, 0)`` (0 for a window
    inside); d < 0: ``u^2 / 2`` and ``e u^2 / 6`` with ``e = max(b, 0)`` (0 apart); both
    are ``e = max(delta - |d|, 0)``; ``u = e / delta <= 1``, ``delta = |vn| h``. With
    ``autodiff`` the ramps are written with ``where`` so that autodiff takes a tie (d = 0)
    on the side d >= 0, where the window is differentiable; without it (the closed-form
    derivatives' primal) as ``|d|`` and ``max(d, 0)``: the same numbers in fewer
    operations (batched stepping about 10% faster). Where e = 0 nothing is divided (double
    where: a still contact, delta = 0, has finite derivatives in float32 too); delta is
    floored at 1e-15 m where e > 0, so the derivative of u stays finite in float32 (only
    sub-femtometre windows change). The guard also keeps the division off a batch-1 step's
    critical path (the compiled select branches around it: 0.055 against 0.078 ms for 3000
    steps unguarded); ``guard=False`` (the closed-form path only) leaves the selects out,
    for batched steps (:func:`_closed_parts`)."""
    delta = jnp.abs(vn) * h
    on = d >= 0.0
    if autodiff:
        e = jnp.maximum(delta - jnp.where(on, d, -d), 0.0)
        ramp = jnp.where(on, d, 0.0)
    else:
        e = jnp.maximum(delta - jnp.abs(d), 0.0)
        ramp = jnp.maximum(d, 0.0)
    pos = e > 0.0
    if guard or autodiff:
        u = jnp.where(pos, e / jnp.where(pos, jnp.maximum(delta, 1e-15), 1.0), 0.0)
    else:               # the same values (e = 0 gives u = 0), no select: see _closed_parts
        u = e / jnp.maximum(delta, 1e-15)
    u2 = 0.5 * u * u
    frac = jnp.where(on, 1.0 - u2, u2)
    mean = ramp + e * u2 * (1.0 / 3.0)
    return frac, mean, u, delta, on, pos


def _window_linear(d, vn, h):
    """:func:`window_mean` for exponent 1: ``(frac, mean)`` (differentiated by autodiff)."""
    return _window_linear_parts(d, vn, h)[:2]


@functools.lru_cache(maxsize=None)
def _closed_parts(h: float):
    """``(d, vn) -> (frac, mean, u, delta, on, pos, u / delta)`` of the closed-form path for
    the static step ``h``, batched without the select around the division.

    One rollout's step keeps the double ``where`` around ``e / delta``: XLA CPU compiles it
    to a branch, which keeps the division off the critical path of a batch-1 step. Under
    ``jax.vmap`` (a ``custom_vmap`` rule) the division is taken on every lane, where the
    selects only cost: ``e / max(delta, 1e-15)`` is the same number (``u = 0`` where
    ``e = 0``; finite always, ``e <= delta``). Batched stepping of 1024 balls 13% faster,
    batch 1 unchanged; only primal values pass through here (derivatives come from
    :func:`_window_linear_jvp`), so the rule needs no autodiff."""
    def parts(d, vn, guard):
        frac, mean, u, delta, on, pos = _window_linear_parts(d, vn, h, autodiff=False,
                                                             guard=guard)
        floor = jnp.maximum(delta, 1e-15)
        du = jnp.where(pos, u / jnp.where(pos, floor, 1.0), 0.0) if guard else u / floor
        return frac, mean, u, delta, on, pos, du

    @custom_vmap
    def closed(d, vn):
        return parts(d, vn, True)

    @closed.def_vmap
    def _batched(axis_size, in_batched, d, vn):
        d, vn = lined_up(axis_size, in_batched, (d, vn))
        return parts(d, vn, False), (True,) * 7

    # derivatives of these values (second-order derivatives of the window) by autodiff of
    # the guarded form: a custom_vmap function has none of its own
    @jax.custom_jvp
    def differentiable(d, vn):
        return closed(d, vn)

    @differentiable.defjvp
    def _jvp(primals, tangents):
        return closed(*primals), jax.jvp(lambda a, b: parts(a, b, True), primals, tangents)[1]
    return differentiable


def _window_linear_closed(d, vn, h):
    """The same values, the primal of the closed-form derivatives (a static step)."""
    return _closed_parts(h)(d, vn)[:2]


_window_linear_static = jax.custom_jvp(_window_linear_closed, nondiff_argnums=(2,))


@_window_linear_static.defjvp
def _window_linear_jvp(h, primals, tangents):
    """Closed-form derivatives of the linear window (``h`` static), the same values as
    differentiating :func:`_window_linear` (tested) with a fraction of its operations (no
    derivative of ``max``/``where`` ties, one quotient more): with ``s = +-1`` on either side
    of the boundary (``e = delta - s d`` where the window crosses) and ``r = u^2 / 2``,
    ``d frac / d d = u / delta``, ``d frac / d delta = -s u (1 - u) / delta``,
    ``d mean / d d = frac`` (the mean of the ramp's slope) and
    ``d mean / d delta = r - u^3 / 3``, ``d delta / d vn = h sign(vn)``. Reverse-mode
    gradients of the quick-start rollout cost 0.97-1.01x the pointwise law of before with
    it, 1.30-1.36x without (benchmarks/step_cost.py). The rule's values come from the
    guarded form, not the batched-only :func:`_closed_parts` (its ``custom_vmap`` inside a
    rollout's scan made every second derivative through reverse mode crash, e.g.
    ``jax.hessian`` of a rollout); batched forward-mode gradients cost the same (0.96x the
    plain floor at batch 1024)."""
    d, vn = primals
    dd, dvn = tangents
    frac, mean, u, delta, on, pos = _window_linear_parts(d, vn, h, autodiff=False)
    du = jnp.where(pos, u / jnp.where(pos, jnp.maximum(delta, 1e-15), 1.0), 0.0)  # u / delta
    ddelta = (h * jnp.sign(vn)) * dvn
    dfrac = du * dd - jnp.where(on, du, -du) * (1.0 - u) * ddelta
    dmean = frac * dd + (u * u) * (0.5 - u * (1.0 / 3.0)) * ddelta
    return (frac, mean), (dfrac, dmean)


def window_mean(d, vn, h, exponent: float = 1.0):
    """Hat-weighted means over the window ``s in [-h, h]`` of the path ``d(s) = d - vn s``.

    The weight is the hat ``(1 - |s| / h) / h`` (the linear B-spline of the step grid): a
    force history represented by kicks ``h F_n`` at the step times with these weights keeps
    both its impulse and its first moment (where in time it acts), so where the contact
    starts or ends inside a step changes neither the velocity nor the position that follows.
    (A box window keeps only the impulse: the positions then depend on the phase of the
    contact event within the step to O(h^3), which shows as an O(h) error of derivatives.)

    Returns ``(frac, mean)``: the weighted fraction of the window in contact (``d(s) > 0``)
    and the weighted mean of ``max(d(s), 0)^exponent``. With ``delta = |vn| h`` and
    ``a, b = d -+ delta``, piecewise and without dividing by ``vn``:

    * inside (``a >= 0``): ``1`` and ``d`` (exponent 1; :func:`_power_mean_inside` else);
    * apart (``b <= 0``): exactly ``0`` and ``0`` (zero derivatives too);
    * ``a < 0 <= d``: ``1 - a^2 / (2 delta^2)`` and ``d + |a|^3 / (6 delta^2)``
      (``(b^(n+2) - 2 d^(n+2)) / ((n+1)(n+2) delta^2)``);
    * ``d < 0 < b``: ``b^2 / (2 delta^2)`` and ``b^3 / (6 delta^2)``
      (``b^(n+2) / ((n+1)(n+2) delta^2)``);

    the second differences of ``max(x, 0)^2 / 2`` and ``max(x, 0)^(n+2) / ((n+1)(n+2))``,
    written so that nothing cancels (``|a|, |b| <= delta`` where they are divided by
    ``delta^2``). Both are continuous in ``d``, ``vn`` and ``h`` (C1 in ``d`` for the mean);
    unselected branches are masked before any division or power (double ``where``), so
    gradients are finite everywhere. Deep in contact the mean of a force linear in ``s``
    (``k d - c vn``) is the pointwise force.

    Args:
      d: penetration at the window's centre, m.  vn: separating normal speed, m/s.
      h: the integrator's inner step, s (> 0).  exponent: n >= 1 (static).
    """
    n = float(exponent)
    if n == 1.0:
        if isinstance(h, (int, float)):             # a static step: closed-form derivatives
            return _window_linear_static(d, vn, float(h))
        return _window_linear(d, vn, h)
    delta = jnp.abs(vn) * h
    a, b = d - delta, d + delta
    inside = a >= 0.0
    upper = (d >= 0.0) & ~inside
    lower = (d < 0.0) & (b > 0.0)
    dl = jnp.where(upper | lower, delta, 1.0)
    inv2 = 1.0 / (dl * dl)
    au = jnp.where(upper, a, 0.0)
    bl = jnp.where(lower, b, 0.0)
    one = jnp.ones_like(d)
    frac = jnp.where(inside, one, jnp.where(upper, 1.0 - 0.5 * au * au * inv2,
                                            0.5 * bl * bl * inv2))
    q = 1.0 / ((n + 1.0) * (n + 2.0))
    pos = inside & (d > 0.0)
    mean_in = jnp.where(pos, _power_mean_inside(jnp.where(pos, d, 1.0),
                                                jnp.where(pos, delta, 0.0), n), 0.0)
    bu = jnp.where(upper, b, 1.0)
    du = jnp.where(upper, d, 0.0)
    mean_up = (_power(bu, n + 2.0) - 2.0 * _power(du, n + 2.0)) * q * inv2
    mean_lo = jnp.where(lower, _power(jnp.where(lower, b, 1.0), n + 2.0), 0.0) * q * inv2
    mean = jnp.where(inside, mean_in, jnp.where(upper, mean_up, mean_lo))
    return frac, mean


def window_moments(d, vn, h, exponent: float = 1.0):
    """``(mean, moment)``: the hat-weighted means over the window ``s in [-h, h]`` along
    ``d(s) = d - vn s`` of ``max(d(s), 0)^exponent`` (m^n; :func:`window_mean`'s mean) and of
    ``s max(d(s), 0)^exponent`` (m^n s), its first moment about the window's centre: what a
    quantity varying linearly in the window (a damper's speed ``vc + a s``) adds to it.

    Both from the next exponent's mean ``M = mean_{n+1}``: ``dM / dd = (n + 1) mean`` and
    ``dM / dvn = -(n + 1) moment`` (the path depends on ``d`` and ``vn`` only through
    ``d - vn s``), differentiated by autodiff: one window of powers for the two. Exactly 0
    apart (zero derivatives too); deep in contact ``moment = -vn h^2 / 6`` for exponent 1.
    Continuous in ``d``, ``vn`` and ``h``, finite derivatives wherever :func:`window_mean`
    has them.

    Args:
      d: penetration at the window's centre, m.  vn: separating normal speed, m/s.
      h: the integrator's inner step, s (> 0).  exponent: n >= 1 (static).
    """
    n = float(exponent)
    d, vn = jnp.broadcast_arrays(jnp.asarray(d), jnp.asarray(vn))

    def mean_next(x, v):
        return window_mean(x, v, h, n + 1.0)[1]
    one, zero = jnp.ones_like(d), jnp.zeros_like(d)
    by_d = jax.jvp(mean_next, (d, vn), (one, zero))[1]
    by_v = jax.jvp(mean_next, (d, vn), (zero, one))[1]
    return by_d / (n + 1.0), -by_v / (n + 1.0)
