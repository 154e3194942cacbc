"""The pose loss of :mod:`tuning.trajfit`: residuals of simulated poses against records.

Per record ``r``, observed body ``b`` and valid frame ``f``::

    e_pos = (p_sim - p_data) / L_b                    (3,)  L_b: the body's size, m
    e_rot = w_rot * rotvec(q_sim^-1 q_data)            (3,)  rad, small-angle 2 vec(q) sign(w)

and the cost is ``sum_r mean_{f, b} (|e_pos|^2 + |e_rot|^2) / R``: every record counts
equally whatever its length, missing samples count for nothing. ``L_b`` is the largest
dimension of a rigid body (a box's longest edge, a sphere's diameter) and, for particles,
the largest extent of the observed particles at the start (the rope's length, the cloth's
width). The default ``w_rot = (180 / pi) / 100 = 0.573`` per radian makes one degree count
as much as 1% of ``L_b``: the units :mod:`tuning.evaluate` reports.

Also the quaternion helpers (w, x, y, z) the records' poses need: products, conjugates,
rotation matrices and rotation vectors, in numpy (``qmul``...) and jax (``_qmul_j``).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import jax.numpy as jnp
import numpy as np

import diffpen as dp

if TYPE_CHECKING:
    from .record_batch import Batch

__all__ = ["ROT_WEIGHT", "body_size", "rotation_angle", "pose_residuals", "residual_records",
           "qmul", "qconj", "rotmat", "rotvec", "exp_quat"]

#: default weight of the rotation residual, per radian, against the position in units of
#: the body size: one degree counts as much as 1% of the size.
ROT_WEIGHT = (180.0 / math.pi) / 100.0


# --------------------------------------------------------------------------- bodies
def body_size(scene: dp.Scene, index: int, observed: Sequence[int] = ()) -> float:
    """The length (m) errors of body ``index`` are measured against: a box's longest edge,
    a sphere's diameter; for a particle, the largest extent of the ``observed`` bodies'
    start positions (the rope, the cloth), or 1 m when that is zero."""
    b = scene.bodies[index]
    if b.half_extents is not None:
        return 2.0 * max(b.half_extents)
    if b.kind == "sphere" and b.radius > 0:
        return 2.0 * b.radius
    observed = list(observed) or [index]
    pts = np.array([scene.bodies[i].position for i in observed])
    ext = float(np.max(pts.max(axis=0) - pts.min(axis=0))) if len(pts) > 1 else 0.0
    return ext if ext > 0 else 1.0


# --------------------------------------------------------------------------- quaternions
def qmul(a, b):
    """Hamilton product of quaternions (..., 4) = (w, x, y, z), NumPy."""
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def qconj(q):
    """Conjugate (the inverse of a unit quaternion) of quaternions (..., 4)."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def rotmat(q):
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4), float64 NumPy (computed
    on the host: float64 whether or not JAX runs with x64)."""
    return dp.rigid.quat_to_matrix(np.asarray(q, dtype=np.float64), xp=np)


def rotvec(q):
    """Rotation vectors (..., 3) rad of unit quaternions (..., 4)."""
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, q[..., :1])
    return np.where(s > 1e-12, q[..., 1:] * ang / np.where(s > 1e-12, s, 1.0),
                    2.0 * q[..., 1:])


def exp_quat(v):
    """Unit quaternions (..., 4) of rotation vectors v (..., 3) rad."""
    v = np.asarray(v, dtype=float)
    a = np.linalg.norm(v, axis=-1, keepdims=True)
    small = a < 1e-12
    sinc = np.where(small, 0.5, np.sin(0.5 * a) / np.where(small, 1.0, a))
    return np.concatenate([np.where(small, 1.0, np.cos(0.5 * a)), sinc * v], axis=-1)

def _qmul_j(a, b):
    w1, x1, y1, z1 = (a[..., i] for i in range(4))
    w2, x2, y2, z2 = (b[..., i] for i in range(4))
    return jnp.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                      w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                      w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                      w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


# --------------------------------------------------------------------------- loss
def rotation_angle(q_sim, q_data):
    """Angle (rad) of ``q_sim^-1 q_data`` for unit quaternions (..., 4):
    ``2 atan2(|v|, |w|)`` of the relative quaternion ``(w, v)``, accurate near 0 (the
    arccos of the dot product read identical float32 orientations as 0.009 deg apart on
    average, up to 0.056 deg)."""
    q_sim, q_data = jnp.asarray(q_sim), jnp.asarray(q_data)
    dq = _qmul_j(q_sim * jnp.array([1.0, -1.0, -1.0, -1.0], q_sim.dtype), q_data)
    return 2.0 * jnp.arctan2(jnp.linalg.norm(dq[..., 1:], axis=-1), jnp.abs(dq[..., 0]))


def _norm_residual(e, eps: float = 1e-3):
    """Per-sample scalar residual whose square is ``sqrt(|e|^2 + eps^2)`` (~ ``|e|``)."""
    return (jnp.sum(e * e, axis=-1) + eps * eps) ** 0.25


def residual_records(batch: Batch, loss: str = "l2", rotating: bool = True) -> np.ndarray:
    """The record (0 .. R-1) of each row of :func:`pose_residuals` for ``batch``, in its
    order: positions (R, T, B, 3 components, or 1 for ``loss="l1"``), then rotations the same
    way when the scene rotates (``rotating``) and the batch has orientations."""
    R, T, B = batch.pos.shape[:3]
    block = np.repeat(np.arange(R), T * B * (1 if loss == "l1" else 3))
    return np.concatenate([block, block]) if (rotating and batch.has_rotation) else block


def pose_residuals(pos, quat, batch: Batch, *, rot_weight: float = ROT_WEIGHT,
                   horizon=None, loss: str = "l2", decay: float | None = None):
    """The pose-loss residuals (flat vector) of simulated ``pos`` / ``quat`` against the
    batch (see the module docstring); ``horizon`` (s, traced ok): frames after it weigh 0;
    ``decay`` (s, static, None = off): each frame's cost weighs ``exp(-t / decay)`` (``t``
    from the record's first frame; residuals scaled by its square root), so the early, less
    chaotic part of a long record counts most.
    ``loss="l1"``: one residual per sample whose square is the error's norm (smoothed by
    1e-3 at zero), so the cost is the mean error itself, the quantity
    :mod:`tuning.evaluate` reports, and a record that drifts apart weighs less than in
    the squared loss."""
    w = jnp.sqrt(jnp.asarray(batch.weight / (batch.n_records or len(batch.weight))))[
        :, None, None]
    live = 1.0 if horizon is None else (jnp.asarray(batch.time) <= horizon)[:, :, None]
    if decay is not None:
        # residuals scaled by exp(-t / 2 decay): the cost of a frame by exp(-t / decay)
        live = live * jnp.exp(-0.5 * jnp.asarray(batch.time) / float(decay))[:, :, None]
    pm = jnp.asarray(batch.pos_mask) * live
    e_pos = (pos - batch.pos) / jnp.asarray(batch.size)[None, None, :, None]
    if loss == "l1":
        out = [(_norm_residual(e_pos) * w * pm).reshape(-1)]
    else:
        out = [(e_pos * (w * pm)[..., None]).reshape(-1)]
    if quat is not None and batch.has_rotation:
        qm = jnp.asarray(batch.quat_mask) * live
        dq = _qmul_j(quat * jnp.array([1.0, -1.0, -1.0, -1.0]), jnp.asarray(batch.quat))
        sgn = jnp.where(dq[..., :1] < 0, -1.0, 1.0)
        e_rot = 2.0 * sgn * dq[..., 1:] * rot_weight
        if loss == "l1":
            out.append((_norm_residual(e_rot) * w * qm).reshape(-1))
        else:
            out.append((e_rot * (w * qm)[..., None]).reshape(-1))
    return jnp.concatenate(out)

