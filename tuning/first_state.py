"""The start state of a record: pose and velocities of one body from its first frames.

:func:`first_state` takes the pose of row 0 and the record's velocity columns, or fits
them by least squares to the first frames (a gravity parabola for a body in free flight,
before it nears a plane), for :func:`tuning.record_batch.prepare`.
"""
from __future__ import annotations

import numpy as np

from diffpen.geometry import box_corners

from .errors import FitError
from .pose import exp_quat, qconj, qmul, rotmat, rotvec

__all__ = ["first_state", "flight_frames"]


def flight_frames(scene, index, pos, quat, margin: float) -> int:
    """How many leading frames body ``index`` is clear of every plane by ``margin`` m.

    ``pos``: (T, 3) observed centre, m; ``quat``: (T, 4) orientations or None (then the
    body's bounding radius is used)."""
    b = scene.bodies[index]
    if not scene.planes:
        return len(pos)
    corners = None if b.half_extents is None else box_corners(b.half_extents)
    n = 0
    for f in range(len(pos)):
        if not np.all(np.isfinite(pos[f])):
            break
        if corners is not None and quat is not None and np.all(np.isfinite(quat[f])):
            pts = pos[f] + corners @ rotmat(quat[f]).T
            reach = 0.0
        else:
            pts, reach = pos[f][None], b.radius
        gap = min(float(np.min(pts @ np.array(pl.normal))) - pl.offset - reach
                  for pl in scene.planes)
        if gap < margin:
            break
        n += 1
    return n


def _free_flight(scene, index) -> bool:
    """True when nothing but gravity and contact acts on body ``index`` (no spring, drag)."""
    for s in (*scene.springs, *scene.anchored_springs, *scene.plastic_springs):
        if index in (s.a, s.b):
            return False
    return not any(d.body == index for d in scene.drags)


def first_state(scene, index, t, pos, quat=None, vel=None, omega_body=None, *,
                estimate: str = "fit", max_frames: int = 10, margin: float = 0.005):
    """Start pose and velocities of one body from the first frames of its record.

    Args:
      scene: the :class:`diffpen.Scene`.  index: the body.
      t: (T,) s.  pos: (T, 3) m (NaN where missing).  quat: (T, 4) or None.
      vel: (T, 3) m/s world or None.  omega_body: (T, 3) rad/s body frame or None.
      estimate: ``"record"``: pose of row 0 and the record's velocity columns of row 0 (a
        fit of the first frames where a column is missing); ``"fit"``: pose and velocities
        fitted by least squares to the first frames -- for a body in free flight (no
        spring or drag on it) a gravity parabola ``p0 + v t + g t^2 / 2`` over the frames
        before it comes within ``margin`` m of a plane (at most ``max_frames``, at least 3),
        with a constant angular velocity; otherwise a quadratic over ``min(5, T)`` frames.
        Finite-difference velocity columns are biased (the cube records' row-0 vertical
        velocity by about +0.023 m/s): ``"fit"`` avoids that bias.
    Returns:
      ``(position (3,), velocity (3,), orientation (4,) or None, omega_world (3,) or None)``.
    """
    if estimate not in ("record", "fit"):
        raise FitError(f"first-state estimate must be 'record' or 'fit', got {estimate!r}.")
    ok = np.all(np.isfinite(pos), axis=1)
    if not ok[0]:
        raise FitError("the first data row has no position (x, y, z): the rollout starts "
                       "from it. Trim the record so that it starts with a complete pose, or "
                       "fill those cells.")
    tt = t - t[0]
    g = np.array(scene.gravity)
    free = _free_flight(scene, index)
    if free:
        n = flight_frames(scene, index, pos[:max_frames], None if quat is None
                           else quat[:max_frames], margin)
        n = max(3, min(n, max_frames))
    else:
        n = min(5, len(t))
    use = np.nonzero(ok[:n])[0]
    if len(use) < 2:
        use = np.arange(1)
    A = np.stack([np.ones(len(use)), tt[use]], axis=1)
    if free and len(use) >= 2:
        coef = np.linalg.lstsq(A, pos[use] - 0.5 * g * tt[use, None] ** 2, rcond=None)[0]
    elif len(use) >= 3:
        A3 = np.concatenate([A, 0.5 * tt[use, None] ** 2], axis=1)
        coef = np.linalg.lstsq(A3, pos[use], rcond=None)[0][:2]
    elif len(use) == 2:
        coef = np.linalg.lstsq(A, pos[use], rcond=None)[0]
    else:
        coef = np.stack([pos[0], np.zeros(3)])
    p0, v0 = (pos[0], None) if estimate == "record" else (coef[0], coef[1])
    if estimate == "record" and vel is not None and np.all(np.isfinite(vel[0])):
        v0 = vel[0]
    if v0 is None:
        v0 = coef[1]
    if quat is None:
        return p0, v0, None, None
    q = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    okq = np.all(np.isfinite(q), axis=1)
    if not okq[0]:
        raise FitError("the first data row has no orientation (qw, qx, qy, qz): the rollout "
                       "starts from it. Trim the record so that it starts with a complete "
                       "pose, or fill those cells.")
    useq = np.nonzero(okq[:n])[0]
    rv = rotvec(qmul(q[useq], qconj(q[0])[None]))          # world rotation since row 0
    # continuous rotation vectors (a unit quaternion and its negative are one rotation)
    if len(useq) >= 2:
        B = np.stack([np.ones(len(useq)), tt[useq]], axis=1)
        sol = np.linalg.lstsq(B, rv, rcond=None)[0]
        w_fit, a0 = sol[1], sol[0]
    else:
        w_fit, a0 = np.zeros(3), np.zeros(3)
    if estimate == "record":
        q0 = q[0]
        if omega_body is not None and np.all(np.isfinite(omega_body[0])):
            w0 = rotmat(q0) @ omega_body[0]
        else:
            w0 = w_fit
    else:
        q0 = qmul(exp_quat(a0), q[0])
        w0 = w_fit
    return p0, v0, q0, w0

