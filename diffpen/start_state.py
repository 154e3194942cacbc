"""Start states of a compiled simulator: the scene's initial :class:`diffpen.State`
(:func:`init_state`) and a state with some bodies' pose and velocities replaced
(:func:`state_from`), as pure array updates.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import stability as _stability
from .errors import SceneError
from .state import State


def init_state(sim) -> State:
    """``sim.init_state()``: see :meth:`diffpen.Simulator.init_state`."""
    b = sim.scene.bodies
    ctx = sim.context
    q, w = sim._rigid.init(b) if sim._rigid is not None else (None, None)
    aux = {k: ctx.const(v) for k, v in ctx.aux_init.items()}
    aux[_stability.FLAG] = jnp.zeros((), bool)
    return State(time=jnp.zeros((), sim.dtype),
                 position=ctx.const([x.position for x in b]),
                 velocity=ctx.const([x.velocity for x in b]),
                 orientation=q, angular_velocity=w, aux=aux)


def state_from(sim, state: State | None = None, *, body=0, position=None, velocity=None,
               orientation=None, angular_velocity=None, frame: str = "body") -> State:
    """``sim.state_from(...)``: see :meth:`diffpen.Simulator.state_from` (arguments, units)."""
    if frame not in ("body", "world"):
        raise SceneError(f"frame must be 'body' or 'world', got {frame!r}.")
    idx = np.atleast_1d(np.asarray(body))
    if idx.dtype.kind not in "iu" or idx.ndim != 1 or np.any(idx < 0) or np.any(
            idx >= sim.n_bodies):
        raise SceneError(f"body must be a body index or a list of them in 0.."
                         f"{sim.n_bodies - 1}, got {body!r}.")
    if (orientation is not None or angular_velocity is not None) and (
            sim._rigid is None or not all(sim.scene.bodies[i].rigid for i in idx)):
        raise SceneError("orientation and angular_velocity can be set for rigid bodies "
                         "only (scene.add_box / scene.add_rigid_sphere).")
    pinned = [j for j, i in enumerate(idx) if sim.pinned[i]]
    for given in (velocity, angular_velocity):
        if not pinned or given is None or isinstance(given, jax.core.Tracer):
            continue
        rows = np.broadcast_to(np.asarray(given, dtype=float), (len(idx), 3))
        moving = [j for j in pinned if np.any(rows[j] != 0.0)]
        if moving:
            raise SceneError(f"body {int(idx[moving[0]])} is pinned (fixed in space, it never "
                             "moves): it takes no velocity. Set velocities of free bodies "
                             "only (zero is accepted), or unpin it in the scene.")
    s = sim.init_state() if state is None else state

    def rows(v, width):
        return jnp.broadcast_to(jnp.asarray(v, sim.dtype), (len(idx), width))
    upd = {}
    if position is not None:
        upd["position"] = s.position.at[idx].set(rows(position, 3))
    if velocity is not None:
        upd["velocity"] = s.velocity.at[idx].set(rows(velocity, 3))
    q = s.orientation
    if orientation is not None:
        qn = rows(orientation, 4)
        q = q.at[idx].set(qn / jnp.linalg.norm(qn, axis=-1, keepdims=True))
        upd["orientation"] = q
    if angular_velocity is not None:
        w = rows(angular_velocity, 3)
        if frame == "body":
            from .rigid import quat_to_matrix
            w = jnp.einsum("bij,bj->bi", quat_to_matrix(q[idx]), w)
        upd["angular_velocity"] = s.angular_velocity.at[idx].set(w)
    return s._replace(**upd)
