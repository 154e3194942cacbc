"""Time integrators, one function per method, all with the same signature.

``integrator(accel_fn, dt) -> step(params, state) -> state``

``accel_fn(params, state) -> (a, alpha)`` returns the linear acceleration ``a`` (n, 3) in
m/s^2 and the angular acceleration ``alpha`` (n, 3) in rad/s^2 (``None`` for scenes without
rotating bodies). Integrators only move the state with :func:`kick` (velocities) and
:func:`drift` (positions and orientations), so they work for particles and rigid bodies alike.

``INTEGRATORS`` maps the names accepted by ``diffpen.compile(..., integrator=NAME)`` to
these functions.
"""
from __future__ import annotations

from typing import Callable

import jax.numpy as jnp

from .state import State

__all__ = ["kick", "drift", "semi_implicit_euler", "INTEGRATORS"]


def kick(state: State, acc, h) -> State:
    """Advance velocities by ``h`` seconds of acceleration ``acc = (a, alpha)``."""
    a, alpha = acc
    w = state.angular_velocity
    if w is not None and alpha is not None:
        w = w + h * alpha
    return state._replace(velocity=state.velocity + h * a, angular_velocity=w)


def quat_integrate(q, w, h):
    """Rotate unit quaternions ``q`` (n, 4; w, x, y, z) by world angular velocity ``w`` (n, 3)
    over ``h`` seconds (first order, renormalised)."""
    qw, qv = q[..., :1], q[..., 1:]
    # dq/dt = 1/2 (0, w) * q
    dqw = -0.5 * jnp.sum(w * qv, axis=-1, keepdims=True)
    dqv = 0.5 * (qw * w + jnp.cross(w, qv))
    q = q + h * jnp.concatenate([dqw, dqv], axis=-1)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def drift(state: State, h) -> State:
    """Advance positions (and orientations) by ``h`` seconds at the current velocities."""
    q = state.orientation
    if q is not None:
        q = quat_integrate(q, state.angular_velocity, h)
    return state._replace(time=state.time + h, position=state.position + h * state.velocity,
                          orientation=q)


def semi_implicit_euler(accel_fn: Callable, dt: float):
    """Symplectic (semi-implicit) Euler: ``v += h a(x, v)``, then ``x += h v``.

    One force evaluation per step. Stable for an undamped spring when ``w h < 2``; with
    explicit damping when ``k h^2 + 2 c h < 4 m`` (physics-notes.md section 4).
    """
    def step(params, state: State) -> State:
        return drift(kick(state, accel_fn(params, state), dt), dt)
    return step


#: Integrators by name, for ``diffpen.compile(..., integrator=NAME)``.
INTEGRATORS = {
    "semi_implicit_euler": semi_implicit_euler,
}
