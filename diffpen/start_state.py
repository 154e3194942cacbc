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
from .geometry import quat_to_matrix
from .state import State


def init_state(sim) -> State:
    """``sim.init_state()``: see :meth:`diffpen.Simulator.init_state`."""
    b = sim.scene.bodies
    ctx = sim.context
    q, w = sim._rigid.init(b) if sim._rigid is not None else (None, None)
    aux = {k: ctx.const(v) for k, v in ctx.aux_init.items()}
    aux[_stability.FLAG] = jax.device_put(np.zeros((), bool))
    return State(time=ctx.const(0.0),
                 position=ctx.const([x.position for x in b]),
                 velocity=ctx.const([x.velocity for x in b]),
                 orientation=q, angular_velocity=w, aux=aux)


def _check_rows(name: str, given, width: int, count: int) -> None:
    """``given`` must be ``width`` finite numbers, or ``(count, width)`` of them (one row per
    body): a SceneError naming the argument otherwise (not a broadcasting error from inside
    JAX, nor a NaN from the rollout)."""
    if given is None:
        return
    if isinstance(given, jax.core.Tracer):
        shape = tuple(given.shape)
    else:
        try:
            arr = np.asarray(given, dtype=float)
        except (TypeError, ValueError):
            raise SceneError(f"{name} must be numbers, {width} per body, got {given!r}.") from None
        shape = arr.shape
        if not np.all(np.isfinite(arr)):
            raise SceneError(f"{name} must be finite numbers, got {given!r}: a NaN or inf start "
                             "value would only show up as a rollout's NaN.")
    if shape not in ((width,), (count, width)) and not (count == 1 and shape == (1, width)):
        want = f"({width},)" + (f" or ({count}, {width}), one row per body" if count > 1 else "")
        raise SceneError(f"{name} must have shape {want}, got shape {shape}.")


def state_from(sim, state: State | None = None, *, body=0, position=None, velocity=None,
               orientation=None, angular_velocity=None, frame: str | None = None) -> State:
    """``sim.state_from(...)``: see :meth:`diffpen.Simulator.state_from` (arguments, units)."""
    if angular_velocity is not None and frame is None:
        raise SceneError("state_from(angular_velocity=...) needs frame='body' (the body frame, "
                         "as gyroscopes and the cube records give it) or frame='world' (as "
                         "add_box and add_rigid_sphere take it): one default would silently "
                         "turn the other's spin.")
    if frame not in (None, "body", "world"):
        raise SceneError(f"frame must be 'body' or 'world', got {frame!r}.")
    idx = np.atleast_1d(np.asarray(body))
    if idx.dtype.kind not in "iu" or idx.ndim != 1 or np.any(idx < 0) or np.any(
            idx >= sim.n_bodies):
        raise SceneError(f"body must be a body index or a list of them in 0.."
                         f"{sim.n_bodies - 1}, got {body!r}.")
    if len(set(idx.tolist())) != len(idx):
        raise SceneError(f"body lists a body more than once ({body!r}): give each body once, "
                         "with its own row of values.")
    for name, given, width in (("position", position, 3), ("velocity", velocity, 3),
                               ("orientation", orientation, 4),
                               ("angular_velocity", angular_velocity, 3)):
        _check_rows(name, given, width, len(idx))
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
    if orientation is not None and not isinstance(orientation, jax.core.Tracer):
        norms = np.linalg.norm(np.broadcast_to(np.asarray(orientation, dtype=float),
                                               (len(idx), 4)), axis=-1)
        bad = np.flatnonzero(~(norms > 1e-12) | ~np.isfinite(norms))
        if bad.size:
            raise SceneError(f"orientation of body {int(idx[bad[0]])} has norm "
                             f"{norms[bad[0]]:.3g}: give a unit quaternion (w, x, y, z), "
                             "e.g. (1, 0, 0, 0) for no rotation (it is normalised).")
    if position is not None and not isinstance(position, jax.core.Tracer):
        # a start pose deep inside a plane or fixed sphere: the scene's own overlap rule
        from .overlap import check_start_pose
        pos = np.broadcast_to(np.asarray(position, dtype=float), (len(idx), 3))
        quat = None
        if orientation is not None and not isinstance(orientation, jax.core.Tracer):
            quat = np.broadcast_to(np.asarray(orientation, dtype=float), (len(idx), 4))
        for j, i in enumerate(idx):
            check_start_pose(sim.scene, int(i), pos[j], None if quat is None else quat[j])
    s = sim.init_state() if state is None else state
    # concrete values are updated on the host (numpy) and placed once: eager JAX updates
    # compile a handful of small programs for every new shape; traced ones stay in JAX
    given = (position, velocity, orientation, angular_velocity)
    xp = jnp if any(isinstance(v, jax.core.Tracer) for v in
                    (*given, *jax.tree_util.tree_leaves(s))) else np

    def rows(v, width):
        return xp.broadcast_to(xp.asarray(v, sim.dtype), (len(idx), width))

    def put(a, v):
        if xp is jnp:
            return a.at[idx].set(v)
        a = np.array(a)
        a[idx] = v
        return a
    upd = {}
    if position is not None:
        upd["position"] = put(s.position, rows(position, 3))
    if velocity is not None:
        upd["velocity"] = put(s.velocity, rows(velocity, 3))
    q = s.orientation
    if orientation is not None:
        qn = rows(orientation, 4)
        q = put(q, qn / xp.linalg.norm(qn, axis=-1, keepdims=True))
        upd["orientation"] = q
    if angular_velocity is not None:
        w = rows(angular_velocity, 3)
        if frame == "body":
            w = xp.einsum("bij,bj->bi", quat_to_matrix(xp.asarray(q)[idx], xp=xp), w)
        upd["angular_velocity"] = put(s.angular_velocity, w)
    if xp is np:
        upd = {k: jax.device_put(v) for k, v in upd.items()}
    return s._replace(**upd)
