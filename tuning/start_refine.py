"""Record fits that refine every record's start state with the parameters
(``fit_records(refine_start=True)``, ``diffpen fit --first-state refine``).

A record's start velocities are estimated from its first frames (:func:`tuning.first_state`:
the record's velocity columns, or a quadratic over its first 5 frames where the body is not in
free flight), its start pose is row 0's. From noisy marker positions the velocities are off by
about the noise over the frame interval, and the fit bends the parameters to explain the motion
that starts: a rope's damping fitted 9-70% off from 0.2 mm noise at 5 ms frames. Refined, the
start position and velocity and, for a rigid body with orientation columns, its orientation
and angular velocity (world frame) of every observed body that is not pinned are nuisance
parameters of each record (row 0's pose is as noisy as the frames after it: on springs, its
error starts an oscillation whose decay the damping is fitted to), fitted with the parameters
by variable projection. At each evaluation (parameters ``x``):

1. the residuals' derivatives w.r.t. each record's start offsets at its estimated start (one
   forward-mode pass; the offsets of all records share their tangents, since a record's
   residuals depend on its own start only) give each record one Gauss-Newton step of its
   start (:func:`start_steps`: the estimate's error is not small against the residuals, so
   the projection is not taken at the estimate itself);
2. from the moved starts, the derivatives w.r.t. the parameters and the offsets (a second
   pass) are projected, record by record, off the offsets' columns (:func:`project_starts`):
   ``r - J_s (J_s^T J_s)^-1 J_s^T r`` and the same of the parameters' Jacobian (Kaufman's
   variable projection), on which Levenberg-Marquardt fits the parameters alone.

Gauss-Newton on the projected problem is the joint problem (parameters and every record's
start) with the starts eliminated (the Schur complement), so the fit's standard errors take
in the starts' uncertainty. The reported accuracy (``diffpen evaluate``) starts from the
estimate as before.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["offset_columns", "active_offsets", "with_start_offsets", "start_steps",
           "project_starts"]


def offset_columns(batch, rotating: bool) -> int:
    """How many start offsets a record of ``batch`` has: 6 per observed body (its position
    and velocity) and 6 more per body (orientation and angular velocity) where the batch has
    orientations and the scene rotates."""
    return len(np.asarray(batch.bodies)) * (12 if rotating and batch.has_rotation else 6)


def active_offsets(sim, batch) -> int:
    """How many start offsets the records of ``batch`` fit in all (the masks of
    :func:`with_start_offsets`): 6 per record and body observed in its first frame and not
    pinned, 6 more where that frame has its orientation and the scene rotates."""
    moving = np.array([not sim.scene.bodies[int(i)].pinned for i in np.asarray(batch.bodies)])
    n = 6 * int(np.sum((np.asarray(batch.pos_mask)[:, 0, :] > 0) & moving))
    if sim.scene.has_rotation and batch.has_rotation:
        n += 6 * int(np.sum((np.asarray(batch.quat_mask)[:, 0, :] > 0) & moving))
    return n


def _turned(q, theta):
    """``q`` turned by the small world-frame rotation vector ``theta`` (first order, then
    normalised: exact in value and derivative at ``theta = 0``, where the fit takes them)."""
    w, v = q[..., :1], q[..., 1:]
    dq = 0.5 * jnp.concatenate([-jnp.sum(theta * v, -1, keepdims=True),
                                w * theta + jnp.cross(theta, v)], axis=-1)
    out = q + dq
    return out / jnp.linalg.norm(out, axis=-1, keepdims=True)


def with_start_offsets(sim, start, batch, u, rotating: bool):
    """The records' start states ``start`` (leading axis R) with the offsets ``u`` ((S,) for
    every record alike, or (R, S); S :func:`offset_columns`: per body (x, y, z) m, then per
    body (vx, vy, vz) m/s; with rotation then per body a world-frame rotation vector, rad,
    and (wx, wy, wz) rad/s) added to every record's bodies that are observed in its first
    frame and not pinned (the rotations where that frame has an orientation). Offsets shared
    by the records give every record's derivatives from one tangent each (a record's
    residuals depend on its own start only). Traceable."""
    idx = np.asarray(batch.bodies)
    B = len(idx)
    moving = jnp.asarray([not sim.scene.bodies[int(i)].pinned for i in idx],
                         start.position.dtype)
    seen = ((jnp.asarray(batch.pos_mask)[:, 0, :] > 0) * moving)[:, :, None]     # (R, B, 1)
    u = u[None] if u.ndim == 1 else u                  # shared (S,) or per record (R, S)
    part = [u[:, 3 * B * j:3 * B * (j + 1)].reshape(-1, B, 3)
            for j in range(u.shape[1] // (3 * B))]
    pos, vel = start.position, start.velocity
    start = start._replace(position=pos.at[:, idx].add((part[0] * seen).astype(pos.dtype)),
                           velocity=vel.at[:, idx].add((part[1] * seen).astype(vel.dtype)))
    if rotating and batch.has_rotation:
        turned = ((jnp.asarray(batch.quat_mask)[:, 0, :] > 0) * moving)[:, :, None]
        q, w = start.orientation, start.angular_velocity
        start = start._replace(
            orientation=q.at[:, idx].set(_turned(q[:, idx], (part[2] * turned).astype(q.dtype))),
            angular_velocity=w.at[:, idx].add((part[3] * turned).astype(w.dtype)))
    return start


def _coefficients(r, jac_params, jac_starts, record, n_records: int):
    """Each record's least-squares coefficients of ``[jac_params | r]`` on its rows of
    ``jac_starts``: (n_records, S, P + 1). Each record's ``S x S`` normal matrix takes a ridge
    of 1e-12 of its largest diagonal entry, so an offset its rows do not see (a body
    observed only later) stays 0."""
    rhs = jnp.concatenate([jac_params, r[:, None]], axis=1)                   # (N, P + 1)
    normal = jax.ops.segment_sum(jac_starts[:, :, None] * jac_starts[:, None, :], record,
                                 num_segments=n_records)                     # (R, S, S)
    proj = jax.ops.segment_sum(jac_starts[:, :, None] * rhs[:, None, :], record,
                               num_segments=n_records)                       # (R, S, P + 1)
    diag = jnp.diagonal(normal, axis1=1, axis2=2)
    ridge = 1e-12 * jnp.max(diag, axis=1, keepdims=True) + jnp.finfo(r.dtype).tiny
    eye = jnp.eye(normal.shape[1], dtype=r.dtype)
    return jnp.linalg.solve(normal + ridge[:, :, None] * eye, proj), rhs


def start_steps(r, jac_starts, record, n_records: int):
    """Each record's Gauss-Newton step of its start offsets, (n_records, S): what minimises
    its rows of ``r + jac_starts step`` (arguments as :func:`project_starts`)."""
    coef, _ = _coefficients(r, jnp.zeros((r.shape[0], 0), r.dtype), jac_starts, record,
                            n_records)
    return -coef[:, :, 0]


def project_starts(r, jac_params, jac_starts, record, n_records: int):
    """Variable projection of the records' start offsets: ``(r', J')`` with each record's
    rows projected off its own start offsets' columns. ``r`` (N,) residuals, ``jac_params``
    (N, P), ``jac_starts`` (N, S) their derivatives w.r.t. the offsets (a row's entries are
    its own record's), ``record`` (N,) each row's record (0 .. n_records - 1)."""
    coef, rhs = _coefficients(r, jac_params, jac_starts, record, n_records)
    out = rhs - jnp.einsum("ns,nsq->nq", jac_starts, coef[record])
    return out[:, -1], out[:, :-1]
