"""The event-exact one-contact step of the linear, no_tension and Hunt-Crossley laws: the force
with which a kick-then-drift step (semi-implicit Euler) lands on the continuous motion's
position at the next step time, also when a contact starts or ends inside the step.

Semi-implicit Euler's positions are exact samples ``X_n`` of a continuous motion exactly when
every step's force is ``F_n = m (a - (X_{n+1} - 2 X_n + X_{n-1}) / h^2)`` (``a`` the other
acceleration along the normal): the force is the motion's second difference. Its velocity is
the secant ``(X_n - X_{n-1}) / h``, so the state ``(d_n, vn_n)`` holds the last two samples,
``d_{n-1} = d_n + h vn_n``, and those fix the continuous motion through them (a two-point
problem). :func:`linear_events` rebuilds that motion, follows it to ``t_{n+1}`` and returns
the force above. Along the normal the motion is a gravity parabola while apart and a damped
spring under its load while in contact (``d'' = a - w0^2 d - b d'``, ``w0^2 = k / m``,
``b = c / m``); by the signs of ``d_{n-1}`` and ``d_n``:

* apart over the last step: the parabola through both samples; where it reaches ``d = 0``
  before ``t_{n+1}`` (a quadratic), the spring from the crossing on;
* in contact over the last step: the spring's motion through both samples; where it leaves
  before ``t_{n+1}`` (the exit time by Newton's method), the parabola from the exit on;
* entered or left during the last step: the crossing time and speed solve the two samples'
  equations (Newton's method on two unknowns, from the straight line through the samples).

no_tension (:func:`no_tension_events`) ends contact where the force ``k d + c d'`` reaches 0
(the release, inside the surface), after which the body flies free: the spring through both
samples where it pushes at both, else the parabola where the body is out of contact at both,
else the crossing or the release within the last step, by the same solve.

Hunt-Crossley (:func:`hunt_crossley_events`, ``d'' = a - max(d^n (w2 + b d'), 0)`` in
contact) has no closed-form motion: the same cases are solved along a classical Runge-Kutta
flow of twelve steps, the motion through both samples in contact by shooting on its rate at
``t`` (one Newton step with the flow's derivative, one chord step). Each flow starts or ends
at a contact start or end located within the step (the parabola's root, or Newton's method
on the exit time and on the crossing's time and rate, as above), never across one, and its
steps are graded towards the ends where the contact is (``(j / S)^2``): ``d^n`` is not smooth
at ``d = 0``, and equal steps across or next to it leave errors that change with where the
impact falls in the step, which the derivatives of later apexes amplify (d apex 3 / dk 15% off
with one Runge-Kutta flow across the contact start, 0.8% with located ends and equal steps,
0.16% graded). Measured on the Hertz ball (1 kg, n 1.5, k 1e6, c 3e4, dt 1e-3, six impact
phases, ``event_phase_errors``): apexes 1-3 within 3.4e-6, derivatives of apexes and contact
durations within 0.16% (the centred record: up to 4% / 6%); n = 1 (k 3e4, c 3e3) within
1.7e-4; positions through a bounce 8e-8 m off the continuous motion (centred 6.5e-5 m). The
clamp ``max(., 0)`` acting inside contact (separating faster than ``k / c``) is not located,
only followed by the flow. The cases that need Newton's method share one solve and all cases
one last flow (with separate solves: reverse-mode compile 24 s, 1024 batched ~150x). Cost
against the centred record (float32, 3000 steps, one process, three runs): a bouncing Hertz
ball 1.0-1.5x forward, 0.7-1.05x forward-mode gradient; a ball resting in contact, where
every step shoots, 9-10x; 1024 batched balls 3.6-4.3x (~95x before the batched step
gathered the lanes that need the shooting and the solve, :func:`diffpen.lanes.by_lanes`);
compile 1.0 s forward, 2.8 s forward-mode, 14 s reverse-mode (XLA's default options).

The spring's motion over a time ``tau`` is the exponential of its 3x3 augmented matrix,
computed in arithmetic only (Taylor series at ``tau / 16``, then four squarings; XLA's
``exp``/``sin`` differ in their last bits between batch layouts, and sharded fits must equal
single-device ones bit for bit). Inside contact the result equals the exact record's
(:func:`diffpen.one_contact.linear_exact`); where a contact starts or ends it is the continuous
motion too, so the step's positions, and their derivatives with respect to ``k``, ``c`` and the
state, are those of the continuous system with its contact events located exactly: apex
heights, contact times and their derivatives at any impact phase, to rounding (an earlier
prototype integrated the force along the same path by quadrature, at ~50x the cost).

Assumes what the one-contact records assume (one contact per body, the load constant over a
step, semi-implicit Euler's lag ``h / 2``), and at most one contact start and one end within
two steps (a contact shorter than about two steps is approximate; the explicit stability
limit keeps ``w0 h < 2``, a contact of at least ``pi / w0 > 1.57 h``).

The crossing's time and rate (Newton's method) are differentiated implicitly
(``jax.lax.custom_root``, :func:`_root`): the derivative of the root comes from the residuals'
derivatives at the root, not from the differentiated iterations. Derivatives of every order
equal the differentiated iterations' to 5e-14 (float64, a 0.3 kg ball's loss, Hessians by
``jax.hessian`` and ``jacfwd(jacfwd)``, linear, no_tension and Hertz); a bouncing ball's
reverse-mode gradient costs 3.3x the default record's instead of 6.6x, its forward-mode
gradient 1.47x instead of 1.76x (float32, 20000 steps, c 0.5: one process, 15 interleaved
runs), 1024 batched balls 0.87 s instead of 1.13 s forward mode, 1.5 s instead of 2.6 s
reverse mode.

Cost against the default (centred) record on the quick-start ball (float32, one rollout;
measured before the implicit derivatives above):
linear 1.75-1.83x forward, 1.47-1.51x forward-mode gradient; no_tension 1.67-1.74x and
1.54-1.64x: only the steps next to a crossing run the Newton solve (``lax.cond``). Under
``jax.vmap``, where a ``lax.cond`` runs both branches on every lane, the step gathers the
lanes next to a crossing and solves those only (:func:`diffpen.lanes.by_lanes`): 1024
batched balls (float32, 2000 steps, heights recorded) 16-21x the default record forward
(linear; 84-90x before), no_tension 12-24x (84x), Hertz 3.6-4.3x (94x). Their forward-mode
gradients still differentiate every lane's solve (1024 balls ~50x). Opt-in for these costs (README,
"Event-exact contact").
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from .lanes import by_lanes
from .window import _power

__all__ = ["spring_flow", "event_step_factors", "linear_events", "no_tension_events",
           "hunt_crossley_events"]

_TERMS = 10     # Taylor terms of exp(A tau / 16); |w0 tau|, |b tau| <= 4 (tau <= 2 h inside the
#                explicit limits w0 h < 2, b h < 2) give 0.25^11 / 11! ~ 6e-15
_SQUARINGS = 4
_NEWTON = 4


@jax.jit
def spring_flow(tau, w2, b):
    """The damped spring's motion over a time ``tau`` s (either sign), ``d'' = a - w2 d - b
    d'``: ``(m11, m12, m21, m22, q1, q2)`` with ``d(tau) = m11 d0 + m12 u0 + a q1`` and
    ``d'(tau) = m21 d0 + m22 u0 + a q2`` from ``(d0, u0)`` (m, m/s; ``w2`` 1/s^2, ``b`` 1/s;
    the load ``a`` m/s^2 enters linearly). Elementwise over broadcast arrays."""
    dtype = jnp.result_type(tau, w2, b)     # a Python float tau takes the rates' dtype
    t = jnp.asarray(tau, dtype) * (1.0 / 2 ** _SQUARINGS)
    t, w2, b = jnp.broadcast_arrays(t, jnp.asarray(w2, dtype), jnp.asarray(b, dtype))
    one, zero = jnp.ones_like(t), jnp.zeros_like(t)

    def taylor(i, m):                       # P <- I + (A t / j) P, augmented column with it
        m11, m12, m21, m22, q1, q2 = m
        s = t / (_TERMS - i).astype(t.dtype)
        return (1.0 + s * m21, s * m22,
                -s * (w2 * m11 + b * m21), 1.0 - s * (w2 * m12 + b * m22),
                s * q2, s * (1.0 - w2 * q1 - b * q2))

    def square(_, m):                       # (M, q) <- (M M, M q + q)
        m11, m12, m21, m22, q1, q2 = m
        return (m11 * m11 + m12 * m21, m11 * m12 + m12 * m22,
                m21 * m11 + m22 * m21, m21 * m12 + m22 * m22,
                m11 * q1 + m12 * q2 + q1, m21 * q1 + m22 * q2 + q2)
    m = jax.lax.fori_loop(0, _TERMS, taylor, (one, zero, zero, one, zero, zero))
    return jax.lax.fori_loop(0, _SQUARINGS, square, m)


def _safe(x, ok):
    return jnp.where(ok, x, 1.0)


def _along(p, x0, u0, a):
    """Depth and rate after a :func:`spring_flow` ``p`` from ``(x0, u0)`` under the load ``a``."""
    return p[0] * x0 + p[1] * u0 + a * p[4], p[2] * x0 + p[3] * u0 + a * p[5]


def _solve_2x2(j11, j12, j21, j22, r1, r2):
    """``J^-1 (r1, r2)`` for ``J = [[j11, j12], [j21, j22]]``, elementwise (a singular ``J``
    taken as having determinant 1)."""
    det = j11 * j22 - j12 * j21
    det = _safe(det, det != 0.0)
    return (j22 * r1 - j12 * r2) / det, (j11 * r2 - j21 * r1) / det


def _tangent_solve(g, y):
    """``g^-1 y`` for the linearised residuals ``g`` of :func:`_root` (one 2x2 system per
    element: ``g``'s columns from unit tangents of ``s`` and of ``v``)."""
    one, zero = jnp.ones_like(y[0]), jnp.zeros_like(y[0])
    (j11, j21), (j12, j22) = g((one, zero)), g((zero, one))
    return _solve_2x2(j11, j12, j21, j22, *y)


def _root(system, init, h):
    """The root ``(s, v)`` of ``system(s, v) -> ((r1, r2), (j11, j12, j21, j22))`` (its
    residuals and their Jacobian), elementwise: Newton's method from ``init``, ``s`` kept
    inside ``[0, h]``. Its derivatives are implicit (``jax.lax.custom_root``): the residuals'
    derivatives at the root, not ``_NEWTON`` differentiated iterations."""
    def newton(_, z):
        (r1, r2), jac = system(*z)
        ds, dv = _solve_2x2(*jac, r1, r2)
        return jnp.clip(z[0] - ds, 0.0, h), z[1] - dv

    return jax.lax.custom_root(lambda z: system(*z)[0], init,
                               lambda _, z: jax.lax.fori_loop(0, _NEWTON, newton, z),
                               _tangent_solve)


def _entry_time(x, U, a, h):
    """Time (s, in ``[0, h]``) until the parabola ``x + U s + a s^2 / 2`` from ``x <= 0``
    reaches the surface (``h`` where it does not within the step)."""
    xn = jnp.minimum(x, 0.0)
    disc = U * U - 2.0 * a * xn
    pos = disc > 0.0            # (a square root's derivative stays finite where unused)
    den = U + jnp.where(pos, jnp.sqrt(_safe(disc, pos)), 0.0)
    return jnp.clip(-2.0 * xn / _safe(den, den > 0.0), 0.0, h)


@jax.jit
def event_step_factors(k, c, inv_mass, h):
    """The spring's motion a step back and a step ahead, ``(spring_flow(-h), spring_flow(h))``
    for ``w2 = k inv_mass``, ``b = c inv_mass``: per-contact constants of a rollout, which it
    computes once, before its loop (``ContactLaw.step_factors``)."""
    heavy = inv_mass > 0.0
    im = _safe(inv_mass, heavy)
    return spring_flow(-h, k * im, c * im), spring_flow(h, k * im, c * im)


def _stay(x, xp, a, flows):
    """In contact over the last step: the spring's motion through both samples, followed for
    ``h`` (``flows`` :func:`event_step_factors`); its depth there (m) and its rate at ``t``
    (m/s)."""
    back, ahead = flows
    un = (xp - back[0] * x - a * back[4]) / back[1]
    return _along(ahead, x, un, a)[0], un


def _cases(x, u, a, h):
    """What the two samples say (depth ``x`` at ``t``, ``xp = x - h u`` at ``t - h``): ``xp``,
    in contact at ``t - h`` and at ``t``, left / entered / stayed over the last step, and the
    parabola through both (its rate ``U`` at ``t``, its depth ``x_free`` at ``t + h``, the
    time ``s1`` until it reaches the surface, :func:`_entry_time`)."""
    xp = x - h * u
    was_in, now_in = xp > 0.0, x > 0.0
    left, entered, stayed = was_in & ~now_in, ~was_in & now_in, was_in & now_in
    U = u + 0.5 * a * h
    return (xp, was_in, now_in, left, entered, stayed, U, x + h * u + a * h * h,
            _entry_time(x, U, a, h))


def _crossing(x, u, w2, b, a, h, flows):
    """The continuous motion's depth at ``t + h`` (m) through the samples ``x`` at ``t`` and
    ``xp = x - h u`` at ``t - h`` (``u`` the secant rate of penetration, m/s; ``a`` the other
    acceleration into contact, m/s^2), every case (module docstring). The three cases that
    need Newton's method share one solve, and all cases one last flow: one spring flow per
    iteration and contact whichever case it is in (what ``jax.vmap`` runs for every case)."""
    xp, was_in, now_in, left, entered, stayed, U, x_free, s1 = _cases(x, u, a, h)
    # apart over the last step: the parabola through both samples (U its rate at t), then
    # the spring from the crossing s1 later (x_free the parabola's depth at t + h)
    # in contact over the last step: the spring's motion (rate un at t), leaving s later
    x_stay, un = _stay(x, xp, a, flows)
    # Newton's method on (s, v): in contact over the last step, s the exit time (v = un);
    # entered during it, s the time since the crossing and v the rate there (the parabola
    # back to xp, the spring from the crossing to x); left during it, s the time since the
    # exit and v the exit rate (the parabola from the exit to x, the spring back to xp).
    # Started from the straight line through the samples.
    s0 = jnp.where(stayed, h * x / _safe(x - x_stay, x - x_stay > 0.0),
                   jnp.where(entered, h * x / _safe(x - xp, x - xp > 0.0),
                             -h * x / _safe(xp - x, xp - x > 0.0)))
    x0 = jnp.where(stayed, x, 0.0)

    def system(s, v):
        p = spring_flow(jnp.where(left, s - h, s), w2, b)
        d, r = _along(p, x0, v, a)
        g = h - s
        r1 = jnp.where(stayed, d, jnp.where(entered, -v * g + 0.5 * a * g * g - xp,
                                             v * s + 0.5 * a * s * s - x))
        r2 = jnp.where(stayed, v - un, d - jnp.where(entered, x, xp))
        j11 = jnp.where(stayed, r, jnp.where(entered, v - a * g, v + a * s))
        j12 = jnp.where(stayed, 0.0, jnp.where(entered, -g, s))
        j21, j22 = jnp.where(stayed, 0.0, r), jnp.where(stayed, 1.0, p[1])
        return (r1, r2), (j11, j12, j21, j22)
    s, v = _root(system, (jnp.clip(s0, 0.0, h), jnp.where(stayed, un, u)), h)
    # the last flow: apart, from the crossing s1 to t + h; stayed, to the exit s (its rate);
    # entered, from the crossing to t + h
    tau = jnp.where(stayed, s, jnp.where(entered, s + h, h - s1))
    d, r = _along(spring_flow(tau, w2, b), x0, jnp.where(now_in | stayed, v, U + a * s1), a)
    x_i = jnp.where(x_free <= 0.0, x_free, d)
    x_ii = jnp.where(x_stay >= 0.0, x_stay, r * (h - s) + 0.5 * a * (h - s) ** 2)
    x_iv = x + h * (v + a * s) + 0.5 * a * h * h
    return jnp.where(was_in, jnp.where(now_in, x_ii, x_iv), jnp.where(now_in, d, x_i))


_CROSSING = by_lanes(_crossing)


def _next_depth(x, u, w2, b, a, h, flows):
    """``_crossing``, with the common cases first: apart over both steps and the next (the
    parabola; also returns True there: no force) and in contact over both and the next (the
    spring alone). One rollout (no batch) then runs the crossing's Newton solve only in the
    steps that need it; under ``jax.vmap`` only on the lanes that need it
    (:func:`diffpen.lanes.by_lanes`)."""
    xp = x - h * u
    x_free = x + h * u + a * h * h
    apart = (x_free <= 0.0) & (x <= 0.0) & (xp <= 0.0)

    def not_apart(_):
        stay = _stay(x, xp, a, flows)[0]
        lanes = (x > 0.0) & (xp > 0.0) & (stay >= 0.0)
        return jax.lax.cond(jnp.all(lanes), lambda _: stay,
                            lambda _: _CROSSING(~apart & ~lanes, jnp.where(apart, x_free, stay),
                                                x, u, w2, b, a, h, flows), None)
    nxt = jax.lax.cond(jnp.all(apart), lambda _: x_free, not_apart, None)
    return nxt, apart


def _events_force(next_depth, d, vn, k, c, h, inv_mass, accel, factors, pointwise,
                  flows: bool = True):
    """``m (a - (X_{n+1} - d - h u) / h^2)`` for ``next_depth(x, u, w2, b, a, h, flows) ->
    (X_{n+1}, free)``; exactly 0 where ``free``; ``pointwise`` where ``inv_mass`` is 0.
    ``flows``: the motion takes :func:`event_step_factors` (computed here where ``factors``
    is None)."""
    heavy = inv_mass > 0.0
    im = _safe(inv_mass, heavy)
    w2, b, a, u = k * im, c * im, -accel, -vn
    if factors is None and flows:
        factors = event_step_factors(k, c, inv_mass, h)
    nxt, free = next_depth(d, u, w2, b, a, h, factors)
    force = (a - (nxt - d - h * u) / (h * h)) / im
    return jnp.where(heavy, jnp.where(free, 0.0, force), pointwise)


@jax.jit
def linear_events(d, vn, k, c, h, lag, inv_mass, accel, factors=None):
    """The linear law's event-exact one-contact force (N): ``m (a - (X_{n+1} - d_n - h
    u_n) / h^2)``, ``X_{n+1}`` the continuous motion's depth at the next step time through
    the last two positions (module docstring); exactly 0 while the body stays apart. ``d``
    m, ``vn`` m/s separating, ``k`` N/m, ``c`` N s/m, ``h`` s, ``inv_mass`` 1/kg (the
    contact's effective inverse mass), ``accel`` m/s^2 (the other separating acceleration);
    elementwise. ``lag`` is semi-implicit Euler's ``h / 2`` (the records are used only
    there); ``factors``: :func:`event_step_factors` computed beforehand (a rollout computes
    them once, outside its loop), or None to compute them here."""
    return _events_force(_next_depth, d, vn, k, c, h, inv_mass, accel, factors,
                         jnp.where(d > 0.0, k * d - c * vn, 0.0))


def _no_tension_crossing(x, u, w2, b, a, h, flows):
    """:func:`_crossing` for the no_tension law: contact is where ``x > 0`` and the force
    ``w2 x + b u`` (per unit mass) pushes; it starts at ``x = 0`` and ends where the force
    reaches 0 (the release, ``x_r = -b v / w2`` for a release rate ``v``), after which the
    body flies free, still inside the surface for a while. By the two samples: the spring
    through both where it pushes at both, else the parabola through both where the body is
    out of contact at both, else entered (``xp <= 0 < x``) or released during the last step
    (the spring to the release, then the parabola: Newton's method on the release time and
    rate)."""
    xp = x - h * u
    U = u + 0.5 * a * h                        # the parabola's rate at t
    x_free = x + h * u + a * h * h
    x_stay, un = _stay(x, xp, a, flows)
    back = flows[0]
    up = back[2] * x + back[3] * un + a * back[5]     # the spring's rate at t - h

    def pushes(d, r):
        return (d > 0.0) & (w2 * d + b * r > 0.0)
    spring = pushes(x, un) & pushes(xp, up)
    free = ~spring & ~pushes(x, U) & ~pushes(xp, U - a * h)
    entered = ~spring & ~free & (xp <= 0.0)
    released = ~spring & ~free & ~entered
    s1 = _entry_time(x, U, a, h)
    inv_w2 = 1.0 / _safe(w2, w2 > 0.0)
    f_now, f_prev = w2 * x + b * un, w2 * xp + b * up
    f_next = w2 * x_stay + b * _along(flows[1], x, un, a)[1]
    s0 = jnp.where(spring, h * f_now / _safe(f_now - f_next, f_now - f_next > 0.0),
                   jnp.where(entered, h * x / _safe(x - xp, x - xp > 0.0),
                             -h * f_now / _safe(f_prev - f_now, f_prev - f_now > 0.0)))
    x0 = jnp.where(spring, x, 0.0)

    def system(s, v):
        xr = -b * v * inv_w2                     # the release depth of a release rate v
        p = spring_flow(jnp.where(released, s - h, s), w2, b)
        start = jnp.where(spring, x, jnp.where(entered, 0.0, xr))
        d, r = _along(p, start, v, a)
        acc = a - w2 * d - b * r
        g = h - s
        r1 = jnp.where(spring, w2 * d + b * r,
                       jnp.where(entered, -v * g + 0.5 * a * g * g - xp,
                                 xr + v * s + 0.5 * a * s * s - x))
        r2 = jnp.where(spring, v - un, d - jnp.where(entered, x, xp))
        j11 = jnp.where(spring, w2 * r + b * acc,
                        jnp.where(entered, v - a * g, v + a * s))
        j12 = jnp.where(spring, 0.0, jnp.where(entered, -g, s - b * inv_w2))
        j21 = jnp.where(spring, 0.0, r)
        j22 = jnp.where(spring, 1.0, jnp.where(entered, p[1], p[1] - b * inv_w2 * p[0]))
        return (r1, r2), (j11, j12, j21, j22)
    s, v = _root(system, (jnp.clip(s0, 0.0, h), jnp.where(spring, un, u)), h)
    tau = jnp.where(spring, s, jnp.where(entered, s + h, h - s1))
    d, r = _along(spring_flow(tau, w2, b), x0, jnp.where(spring | entered, v, U + a * s1), a)
    x_apart = jnp.where((x > 0.0) | (x_free <= 0.0), x_free, d)
    x_spring = jnp.where(f_next > 0.0, x_stay, d + r * (h - s) + 0.5 * a * (h - s) ** 2)
    x_released = x + h * (v + a * s) + 0.5 * a * h * h
    nxt = jnp.where(spring, x_spring, jnp.where(free, x_apart,
                                                 jnp.where(entered, d, x_released)))
    return nxt, free & ((x > 0.0) | (x_free <= 0.0))


def _no_tension_crossing_lanes(x, u, w2, b, a, h, flows):
    """:func:`_no_tension_crossing` with its contact-free flag as 0 / 1 (for
    :func:`diffpen.lanes.by_lanes`)."""
    nxt, free = _no_tension_crossing(x, u, w2, b, a, h, flows)
    return nxt, jnp.where(free, 1.0, 0.0).astype(nxt.dtype)


_NO_TENSION_CROSSING = by_lanes(_no_tension_crossing_lanes)


def _no_tension_next(x, u, w2, b, a, h, flows):
    """:func:`_no_tension_crossing`, with the common cases first (as :func:`_next_depth`):
    apart over both steps and the next, and pushing at ``t - h``, ``t`` and ``t + h``."""
    xp = x - h * u
    x_free = x + h * u + a * h * h
    apart = (x_free <= 0.0) & (x <= 0.0) & (xp <= 0.0)

    def not_apart(_):
        stay, un = _stay(x, xp, a, flows)
        back, ahead = flows
        up = back[2] * x + back[3] * un + a * back[5]
        un1 = _along(ahead, x, un, a)[1]
        lanes = ((xp > 0.0) & (x > 0.0) & (stay > 0.0) & (w2 * xp + b * up > 0.0)
                 & (w2 * x + b * un > 0.0) & (w2 * stay + b * un1 > 0.0))

        def general(_):
            fill = (jnp.where(apart, x_free, stay), jnp.where(apart, 1.0, 0.0).astype(x.dtype))
            nxt, free = _NO_TENSION_CROSSING(~apart & ~lanes, fill, x, u, w2, b, a, h, flows)
            return nxt, free > 0.5
        return jax.lax.cond(jnp.all(lanes), lambda _: (stay, jnp.zeros_like(apart)), general,
                            None)
    return jax.lax.cond(jnp.all(apart), lambda _: (x_free, apart), not_apart, None)


@jax.jit
def no_tension_events(d, vn, k, c, h, lag, inv_mass, accel, factors=None):
    """:func:`linear_events` for the no_tension law (``F = max(k d - c vn, 0)`` in contact):
    the force whose step lands on the continuous motion through contact start, release and
    the free flight after it (:func:`_no_tension_crossing`); exactly 0 while the body flies
    free."""
    return _events_force(_no_tension_next, d, vn, k, c, h, inv_mass, accel, factors,
                         jnp.maximum(jnp.where(d > 0.0, k * d - c * vn, 0.0), 0.0))


# --------------------------------------------------------------------------- Hunt-Crossley
_RK_SUBSTEPS = 12  # Runge-Kutta steps per flow: derivatives within 0.16% on the Hertz ball
#                    (0.3% at 8, 0.05% at 16; errors fall as S^-4 with the graded steps)
_SHOOTING = 2      # Newton steps on the rate (one with the slope, one chord step)


def _hc_accel(x, r, kr, cr, a, n):
    """Acceleration into contact (m/s^2) at depth ``x`` (m) and rate ``r`` (m/s):
    ``a - max(x^n (kr + cr r), 0)`` in contact, ``a`` apart (``kr``, ``cr`` per unit mass)."""
    pos = x > 0.0
    p = _power(_safe(x, pos), n)
    return a - jnp.where(pos, jnp.maximum(p * (kr + cr * r), 0.0), 0.0)


def _hc_flow(x, r, tau, kr, cr, a, n, to_end):
    """Depth and rate after ``tau`` s (either sign) of the Hunt-Crossley motion from ``(x,
    r)``: classical Runge-Kutta in ``_RK_SUBSTEPS`` steps (exact for the free parabola),
    graded as ``(j / S)^2`` away from the flow's start, or, where ``to_end`` (a bool, or an
    array of them), towards its end: the end where a contact starts or ends, where ``x^n``
    is not smooth."""
    def t_of(j):
        q = j / _RK_SUBSTEPS
        return tau * jnp.where(to_end, 1.0 - (1.0 - q) ** 2, q * q)

    def rk4(j, z):
        x, r = z
        s = t_of(j + 1.0) - t_of(j * 1.0)
        a1 = _hc_accel(x, r, kr, cr, a, n)
        x2, r2 = x + 0.5 * s * r, r + 0.5 * s * a1
        a2 = _hc_accel(x2, r2, kr, cr, a, n)
        x3, r3 = x + 0.5 * s * r2, r + 0.5 * s * a2
        a3 = _hc_accel(x3, r3, kr, cr, a, n)
        x4, r4 = x + s * r3, r + s * a3
        a4 = _hc_accel(x4, r4, kr, cr, a, n)
        return (x + (s / 6.0) * (r + 2.0 * r2 + 2.0 * r3 + r4),
                r + (s / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4))
    return jax.lax.fori_loop(0, _RK_SUBSTEPS, rk4, (x, r))


def _hc_next(n):
    """``next_depth`` (as :func:`_next_depth`) of the Hunt-Crossley law of exponent ``n``."""
    def flow(x, r, tau, kr, cr, a, to_end):
        return _hc_flow(x, r, tau, kr, cr, a, n, to_end)

    def flow_dv(x, r, tau, kr, cr, a, to_end):
        """flow's depth and rate, and the depth's derivative w.r.t. the starting rate"""
        (y, ry), (dy, _) = jax.jvp(lambda v: flow(x, v, tau, kr, cr, a, to_end), (r,),
                                   (jnp.ones_like(r),))
        return y, ry, dy

    def shoot(x, xp, u, kr, cr, a, h):
        """The rate at ``t`` of the contact motion through ``x`` at ``t`` and ``xp`` at
        ``t - h``: Newton's method from ``u + h acc / 2`` with its first slope kept (the
        slope changes by O(h^2) over the iterations)."""
        r = u + 0.5 * h * _hc_accel(x, u, kr, cr, a, n)
        y, _, dy = flow_dv(x, r, -h, kr, cr, a, True)
        dy = _safe(dy, dy != 0.0)
        r = r - (y - xp) / dy

        def chord(_, r):
            return r - (flow(x, r, -h, kr, cr, a, True)[0] - xp) / dy
        return jax.lax.fori_loop(0, _SHOOTING - 1, chord, r)

    def general(x, u, kr, cr, a, h, un, x_stay):
        """Every case (as :func:`_crossing`), given the contact motion's rate ``un`` at ``t``
        through both samples and its depth ``x_stay`` at ``t + h``: the cases that need
        Newton's method share one solve, and all cases one last flow."""
        xp, _, _, left, entered, stayed, U, x_free, s1 = _cases(x, u, a, h)
        # Newton's method on (s, v): in contact over the last step, s the exit time (v = un;
        # the flow from x towards the exit); entered during it, s the time since the
        # crossing and v the rate there (the parabola back to xp, the flow from the crossing
        # on to x); left during it, s the time since the exit and v the exit rate (the
        # parabola on to x, the flow from the exit back to xp)
        x0 = jnp.where(stayed, x, 0.0)

        def system(s, v):
            g = h - s
            y, ry, dy = flow_dv(x0, v, jnp.where(left, -g, s), kr, cr, a, stayed)
            r1 = jnp.where(stayed, y, jnp.where(entered, -v * g + 0.5 * a * g * g - xp,
                                                 v * s + 0.5 * a * s * s - x))
            r2 = jnp.where(stayed, v - un, y - jnp.where(entered, x, xp))
            j11 = jnp.where(stayed, ry, jnp.where(entered, v - a * g, v + a * s))
            j12 = jnp.where(stayed, dy, jnp.where(entered, -g, s))
            j21, j22 = jnp.where(stayed, 0.0, ry), jnp.where(stayed, 1.0, dy)
            return (r1, r2), (j11, j12, j21, j22)
        s0 = jnp.where(stayed, h * x / _safe(x - x_stay, x - x_stay > 0.0),
                       jnp.where(entered, h * x / _safe(x - xp, x - xp > 0.0),
                                 -h * x / _safe(xp - x, xp - x > 0.0)))
        s, v = _root(system, (jnp.clip(s0, 0.0, h), jnp.where(stayed, un, u)), h)
        # the last flow: apart, from the parabola's crossing s1 to t + h; stayed, to the exit
        # s (its rate there); entered, from the crossing to t + h
        d, r = flow(x0, jnp.where(stayed | entered, v, U + a * s1),
                    jnp.where(stayed, s, jnp.where(entered, s + h, h - s1)), kr, cr, a, stayed)
        x_i = jnp.where(x_free <= 0.0, x_free, d)
        x_ii = jnp.where(x_stay >= 0.0, x_stay, r * (h - s) + 0.5 * a * (h - s) ** 2)
        x_iv = x + h * (v + a * s) + 0.5 * a * h * h
        return jnp.where(stayed, x_ii, jnp.where(entered, d, jnp.where(left, x_iv, x_i)))

    def stay_motion(x, xp, u, kr, cr, a, h):
        """the contact motion through both samples: its rate at ``t``, its depth at
        ``t + h``"""
        un = shoot(x, xp, u, kr, cr, a, h)
        return un, flow(x, un, h, kr, cr, a, True)[0]
    crossing, motion = by_lanes(general), by_lanes(stay_motion)

    def next_depth(x, u, kr, cr, a, h, _factors):
        xp = x - h * u
        x_free = x + h * u + a * h * h
        apart = (x_free <= 0.0) & (x <= 0.0) & (xp <= 0.0)

        def not_apart(_):
            un, x_stay = motion(~apart, (u, x), x, xp, u, kr, cr, a, h)
            lanes = (x > 0.0) & (xp > 0.0) & (x_stay >= 0.0)
            return jax.lax.cond(
                jnp.all(lanes), lambda _: x_stay,
                lambda _: crossing(~apart & ~lanes, jnp.where(apart, x_free, x_stay),
                                   x, u, kr, cr, a, h, un, x_stay), None)
        return jax.lax.cond(jnp.all(apart), lambda _: x_free, not_apart, None), apart
    return next_depth


def hunt_crossley_events(exponent: float, force):
    """Hunt-Crossley's event-exact one-contact record for the exponent ``n`` (``F = max(d^n
    (k - c vn), 0)``): ``events(d, vn, k, c, h, lag, inv_mass, accel, factors=None)`` with
    :func:`linear_events`' arguments and units (``k`` N/m^n, ``c`` N s/m^(n+1)), the force
    (N) whose step lands on the continuous motion's depth at the next step time (module
    docstring, "Hunt-Crossley"); exactly 0 while the body stays apart. ``force(d, vn, k,
    c)``: the law's pointwise force, what a contact without inertia (``inv_mass`` 0) takes."""
    nxt = _hc_next(float(exponent))

    @jax.jit
    def events(d, vn, k, c, h, lag, inv_mass, accel, factors=None):
        return _events_force(nxt, d, vn, k, c, h, inv_mass, accel, None, force(d, vn, k, c),
                             flows=False)
    return events
