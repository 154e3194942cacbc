"""Fit any scene's parameters to measured motion: many records at once.

A *record* (:func:`tuning.records.read_record`) holds the times ``t`` (T,) s and, per observed
body, positions (T, 3) m with NaN for missing samples and optionally orientations (T, 4)
(w, x, y, z), world velocities (T, 3) m/s and BODY-frame angular velocities (T, 3) rad/s.

Pipeline (each step a public function):

1. :func:`prepare` turns records into one padded :class:`Batch`: each record's start state
   (:func:`first_state`: pose from row 0, velocities from the record's columns or estimated
   from the first frames), the frame times as indices into one rollout, and masks for
   missing samples and for records shorter than the longest.
2. :func:`simulate` rolls every record out from its own start state under ``jax.vmap``
   (one compiled function for all) and samples positions and orientations at the frame
   times (linear interpolation when the frames do not fall on steps).
3. :func:`pose_residuals` compares them with the measurements (the pose loss below).
4. :func:`fit_records` runs Levenberg-Marquardt on the chosen leaves of the params (signed
   leaves such as plane offsets in linear space, positive ones in log space) with a
   forward-mode Jacobian through the rollouts, optionally over a growing horizon, and
   reports standard errors, correlations and the parameter directions the records do not
   determine.

Pose loss. Per record ``r``, observed body ``b`` and valid frame ``f``::

    e_pos = (p_sim - p_data) / L_b                    (3,)  L_b: the body's size, m
    e_rot = w_rot * rotvec(q_sim^-1 q_data)            (3,)  rad, small-angle 2 vec(q) sign(w)

and the cost is ``sum_r mean_{f, b} (|e_pos|^2 + |e_rot|^2) / R``: every record counts
equally whatever its length, missing samples count for nothing. ``L_b`` is the largest
dimension of a rigid body (a box's longest edge, a sphere's diameter) and, for particles,
the largest extent of the observed particles at the start (the rope's length, the cloth's
width). The default ``w_rot = (180 / pi) / 100 = 0.573`` per radian makes one degree count
as much as 1% of ``L_b``: the units :mod:`tuning.evaluate` reports.
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .fit import FitError, Progress
from .lm import levenberg_marquardt
from .params import leaf_paths

__all__ = ["Free", "Batch", "TrajFitResult", "leaf_names", "get_leaf", "with_leaves",
           "body_size", "first_state", "prepare", "prepare_buckets", "simulate", "pose_residuals",
           "fit_records", "ROT_WEIGHT"]

#: default weight of the rotation residual, per radian, against the position in units of
#: the body size: one degree counts as much as 1% of the size.
ROT_WEIGHT = (180.0 / math.pi) / 100.0


# --------------------------------------------------------------------------- params leaves
#: ``{"contact.board.k": key path, ...}`` of a params pytree (see :mod:`tuning.params`)
leaf_names = leaf_paths


def _normalise(name: str) -> str:
    """``contact['board'].k`` (a ``jax.tree_util.keystr``) or ``contact.board.k`` -> dotted."""
    s = re.sub(r"\[['\"]?([^\]'\"]+)['\"]?\]", r".\1", name.strip())
    return s.lstrip(".")


def get_leaf(params, name: str):
    """The value of the leaf ``name`` (dotted or ``keystr`` form) of ``params``."""
    names = leaf_names(params)
    key = _normalise(name)
    if key not in names:
        raise FitError(f"parameter {name!r} is not a leaf of this scene's params; leaves: "
                       f"{sorted(names)}.")
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        if path == names[key]:
            return leaf
    raise AssertionError(key)


def with_leaves(params, values: dict):
    """``params`` with the leaves named in ``values`` (``{name: value}``) replaced; values
    may be tracers (used inside jit / grad / jacfwd)."""
    names = leaf_names(params)
    want = {names[_normalise(n)]: v for n, v in values.items()}
    flat, tree = jax.tree_util.tree_flatten_with_path(params)
    return jax.tree_util.tree_unflatten(tree, [want.get(p, leaf) for p, leaf in flat])


@dataclasses.dataclass(frozen=True)
class Free:
    """One fitted leaf of the params.

    name: dotted leaf name (``contact.board.k``, ``extra.friction.board``,
      ``extra.plane_offset.ground``, ``springs.rope.c``, ...).
    lo, hi: bounds in the leaf's unit.
    log: fit in log space (positive leaves: stiffness, damping, friction) or linear space
      (signed leaves: offsets). Default: log unless ``lo`` <= 0 or the name is an offset.
    """
    name: str
    lo: float = -math.inf
    hi: float = math.inf
    log: bool | None = None

    def resolved(self) -> "Free":
        name = _normalise(self.name)
        log = self.log
        if log is None:
            log = not ("offset" in name or self.lo < 0.0)
        lo, hi = float(self.lo), float(self.hi)
        if log and lo == -math.inf:
            lo = 0.0
        if log and lo < 0.0:
            raise FitError(f"{name}: a log-space parameter needs lo >= 0, got {lo}; give "
                           "log=false for a signed parameter.")
        if not lo < hi:
            raise FitError(f"{name}: bounds must satisfy lo < hi, got [{lo}, {hi}].")
        return Free(name, lo, hi, bool(log))

    def to_x(self, v):
        return np.log(v) if self.log else v

    def from_x(self, x):
        return jnp.exp(x) if self.log else x

    def x_bounds(self):
        if self.log:
            return (math.log(self.lo) if self.lo > 0 else -np.inf,
                    math.log(self.hi) if self.hi < math.inf else np.inf)
        return self.lo, self.hi


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


def _qmul(a, b):
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def _qconj(q):
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _rotmat(q):
    return np.asarray(dp.rigid.quat_to_matrix(jnp.asarray(q, dtype=jnp.float64)))


def _rotvec(q):
    """Rotation vectors (..., 3) rad of unit quaternions (..., 4)."""
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, q[..., :1])
    return np.where(s > 1e-12, q[..., 1:] * ang / np.where(s > 1e-12, s, 1.0),
                    2.0 * q[..., 1:])


def _exp_quat(v):
    a = np.linalg.norm(v)
    if a < 1e-12:
        return np.array([1.0, *(0.5 * v)])
    return np.array([math.cos(a / 2), *(v / a * math.sin(a / 2))])


def _flight_frames(scene, index, pos, quat, margin: float) -> int:
    """How many leading frames body ``index`` is clear of every plane by ``margin`` m."""
    b = scene.bodies[index]
    if not scene.planes:
        return len(pos)
    n = 0
    for f in range(len(pos)):
        if not np.all(np.isfinite(pos[f])):
            break
        if b.half_extents is not None and quat is not None and np.all(np.isfinite(quat[f])):
            h = np.array(b.half_extents)
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                                for sz in (-1, 1)]) * h
            pts = pos[f] + corners @ _rotmat(quat[f]).T
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
        raise FitError("a record's first row has no position for an observed body: trim the "
                       "record so that it starts with a complete pose.")
    tt = t - t[0]
    g = np.array(scene.gravity)
    free = _free_flight(scene, index)
    if free:
        n = _flight_frames(scene, index, pos[:max_frames], None if quat is None
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
        raise FitError("a record's first row has no orientation for an observed body.")
    useq = np.nonzero(okq[:n])[0]
    rv = _rotvec(_qmul(q[useq], _qconj(q[0])[None]))          # world rotation since row 0
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
            w0 = _rotmat(q0) @ omega_body[0]
        else:
            w0 = w_fit
    else:
        q0 = _qmul(_exp_quat(a0), q[0])
        w0 = w_fit
    return p0, v0, q0, w0


# --------------------------------------------------------------------------- batch
@dataclasses.dataclass
class Batch:
    """Records padded into arrays for one vmapped rollout (R records, T frames, B bodies).

    start: a :class:`diffpen.State` whose leaves have a leading axis R.
    steps: rollout length in steps (static).  save_every: steps between saved states.
    index: (R, T) int, saved-state index at or before each frame (0 = the start state).
    frac: (R, T) interpolation weight towards the next saved state.
    pos: (R, T, B, 3) m.  pos_mask: (R, T, B) 1 where measured.
    quat: (R, T, B, 4).  quat_mask: (R, T, B) 1 where measured (all 0 without quaternions).
    weight: (R,) per-record weight ``1 / (number of valid samples)``.
    n_records: how many records the loss averages over (R, or all the buckets' records
    when this batch is one of :func:`prepare_buckets`).
    bodies: (B,) body indices.  names: B body names.  size: (B,) m.  time: (R, T) s from
    each record's first frame.  length: (R,) frames per record.  paths: R record paths.
    """
    start: dp.State
    steps: int
    save_every: int
    index: np.ndarray
    frac: np.ndarray
    pos: np.ndarray
    pos_mask: np.ndarray
    quat: np.ndarray
    quat_mask: np.ndarray
    weight: np.ndarray
    bodies: np.ndarray
    names: list
    size: np.ndarray
    time: np.ndarray
    length: np.ndarray
    paths: list
    n_records: int = 0

    @property
    def has_rotation(self) -> bool:
        return bool(self.quat_mask.any())


def _body_map(scene, records, bodies):
    names = list(dict.fromkeys(n for r in records for n in r.bodies))
    if bodies is None:
        free = [i for i, b in enumerate(scene.bodies) if not b.pinned]
        if len(names) == 1 and len(free) == 1:
            return {names[0]: free[0]}
        bodies = {}
        for n in names:
            try:
                bodies[n] = int(n)
            except (TypeError, ValueError):
                raise FitError(f"record body {n!r}: give bodies={{name: body index}} (or name "
                               "the scene's bodies) to say which body it is.") from None
    for n in names:
        if n not in bodies:
            raise FitError(f"record body {n!r} is not in bodies {sorted(bodies)}.")
        i = bodies[n]
        if not 0 <= i < scene.n_bodies:
            raise FitError(f"record body {n!r} maps to body {i}, not in the scene "
                           f"({scene.n_bodies} bodies).")
    return {n: bodies[n] for n in names}


def prepare(sim: dp.Simulator, records, *, bodies: dict | None = None,
            estimate: str = "record", max_frames: int = 10) -> Batch:
    """Pad ``records`` into a :class:`Batch` for ``sim`` (see :func:`first_state` for
    ``estimate``). ``bodies``: ``{record body name: scene body index}``; default: the only
    free body for one-body records, else names that are indices."""
    if not records:
        raise FitError("no records: give at least one record file.")
    scene = sim.scene
    bmap = _body_map(scene, records, bodies)
    names = list(bmap)
    idx = np.array([bmap[n] for n in names], dtype=np.int32)
    size = np.array([body_size(scene, i, idx) for i in idx])
    R, B = len(records), len(names)
    T = max(len(r.t) for r in records)
    durations = [float(r.t[-1] - r.t[0]) for r in records]
    frame_dt = float(np.median(np.concatenate([np.diff(r.t) for r in records
                                                if len(r.t) > 1] or [np.array([sim.dt])])))
    save_every = max(1, int(round(frame_dt / sim.dt)))
    ratio = [(r.t - r.t[0]) / (save_every * sim.dt) for r in records]
    if not all(np.allclose(u, np.round(u), atol=1e-6) for u in ratio):
        save_every = 1
    n_saves = int(math.ceil(max(durations) / (save_every * sim.dt) - 1e-9)) + 1
    steps = max(1, n_saves) * save_every
    index = np.zeros((R, T), np.int32)
    frac = np.zeros((R, T))
    pos = np.zeros((R, T, B, 3))
    pmask = np.zeros((R, T, B))
    quat = np.tile(np.array([1.0, 0, 0, 0]), (R, T, B, 1))
    qmask = np.zeros((R, T, B))
    times = np.zeros((R, T))
    starts = []
    s_init = sim.init_state()
    for r, rec in enumerate(records):
        n = len(rec.t)
        u = (rec.t - rec.t[0]) / (save_every * sim.dt)
        i0 = np.clip(np.floor(u + 1e-9).astype(int), 0, steps // save_every - 1)
        index[r, :n] = i0
        frac[r, :n] = np.clip(u - i0, 0.0, 1.0)
        frac[r, :n] = np.where(np.abs(frac[r, :n]) < 1e-9, 0.0, frac[r, :n])
        times[r, :n] = rec.t - rec.t[0]
        state = s_init
        for b, name in enumerate(names):
            br = rec.bodies.get(name)
            if br is None:
                continue
            p = np.asarray(br.position, float)
            pos[r, :n, b] = np.nan_to_num(p)
            pmask[r, :n, b] = np.all(np.isfinite(p), axis=1)
            q = None if br.quaternion is None else np.asarray(br.quaternion, float)
            if q is not None and scene.bodies[idx[b]].rigid:
                okq = np.all(np.isfinite(q), axis=1)
                quat[r, :n, b] = np.where(okq[:, None], np.nan_to_num(q), quat[r, :n, b])
                qmask[r, :n, b] = okq
            else:
                q = None
            p0, v0, q0, w0 = first_state(scene, int(idx[b]), rec.t, p, q, br.velocity,
                                         br.angular_velocity, estimate=estimate,
                                         max_frames=max_frames)
            state = sim.state_from(state, body=int(idx[b]), position=p0, velocity=v0,
                                   orientation=q0, angular_velocity=w0, frame="world")
        starts.append(state)
    start = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *starts)
    valid = pmask.sum(axis=(1, 2)) + qmask.sum(axis=(1, 2))
    if np.any(valid == 0):
        bad = [records[r].path for r in np.nonzero(valid == 0)[0]]
        raise FitError(f"records {bad} have no measured sample of the scene's bodies.")
    return Batch(start, int(steps), int(save_every), index, frac, pos, pmask, quat, qmask,
                 1.0 / np.maximum(pmask.sum(axis=(1, 2)), 1.0), idx, names, size, times,
                 np.array([len(r.t) for r in records]), [r.path for r in records])


# --------------------------------------------------------------------------- rollouts
def simulate(sim: dp.Simulator, params, batch: Batch, *, with_flag: bool = False):
    """Positions (R, T, B, 3) m and orientations (R, T, B, 4) (None without rotation) of the
    batch's bodies at the frame times, each record rolled out from its own start state.
    With ``with_flag`` also (R,) bool: the record's rollout went past its safe step
    (``State.aux["unstable"]``, :func:`tuning.stable.rollout_unstable`); such poses are not
    a result. Pure: jit, grad and jacfwd it."""
    from .stable import rollout_unstable
    idx = batch.bodies
    rot = sim.scene.has_rotation and batch.has_rotation

    def observe(s):
        return (s.position[idx], s.orientation[idx] if rot else None)

    def one(state, index, frac):
        traj = sim.rollout(params, batch.steps, state, save_every=batch.save_every,
                           observe=observe, check_finite=False, check_stability=False)
        p = jnp.concatenate([state.position[idx][None], traj.observed[0]])
        pa, pb = p[index], p[jnp.minimum(index + 1, p.shape[0] - 1)]
        f = frac[:, None, None].astype(p.dtype)
        pos = pa + f * (pb - pa)
        bad = (rollout_unstable(sim, traj, params),) if with_flag else ()
        if not rot:
            return (pos, None) + bad
        q = jnp.concatenate([state.orientation[idx][None], traj.observed[1]])
        qa, qb = q[index], q[jnp.minimum(index + 1, q.shape[0] - 1)]
        qb = jnp.where(jnp.sum(qa * qb, -1, keepdims=True) < 0, -qb, qb)
        qi = qa + f * (qb - qa)
        return (pos, qi / jnp.linalg.norm(qi, axis=-1, keepdims=True)) + bad
    return jax.vmap(one)(batch.start, jnp.asarray(batch.index), jnp.asarray(batch.frac))


def _qmul_j(a, b):
    w1, x1, y1, z1 = (a[..., i] for i in range(4))
    w2, x2, y2, z2 = (b[..., i] for i in range(4))
    return jnp.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                      w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                      w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                      w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def rotation_angle(q_sim, q_data):
    """Angle (rad) of ``q_sim^-1 q_data`` for unit quaternions (..., 4)."""
    d = jnp.abs(jnp.sum(q_sim * q_data, axis=-1))
    return 2.0 * jnp.arccos(jnp.clip(d, 0.0, 1.0))


def _norm_residual(e, eps: float = 1e-3):
    """Per-sample scalar residual whose square is ``sqrt(|e|^2 + eps^2)`` (~ ``|e|``)."""
    return (jnp.sum(e * e, axis=-1) + eps * eps) ** 0.25


def pose_residuals(pos, quat, batch: Batch, *, rot_weight: float = ROT_WEIGHT,
                   horizon=None, loss: str = "l2"):
    """The pose-loss residuals (flat vector) of simulated ``pos`` / ``quat`` against the
    batch (see the module docstring); ``horizon`` (s, traced ok): frames after it weigh 0.
    ``loss="l1"``: one residual per sample whose square is the error's norm (smoothed by
    1e-3 at zero), so the cost is the mean error itself, the quantity
    :mod:`tuning.evaluate` reports, and a record that drifts apart weighs less than in
    the squared loss."""
    w = jnp.sqrt(jnp.asarray(batch.weight / (batch.n_records or len(batch.weight))))[
        :, None, None]
    live = 1.0 if horizon is None else (jnp.asarray(batch.time) <= horizon)[:, :, None]
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


# --------------------------------------------------------------------------- fit
@dataclasses.dataclass
class TrajFitResult:
    """Outcome of :func:`fit_records`.

    params: fitted :class:`diffpen.Params`.  values: ``{name: value}`` of the fitted leaves.
    stderr: ``{name: standard error}`` (Gauss-Newton ``s^2 (J^T J)^-1``; the residuals of
      one record are correlated in time, so these are lower bounds; inf for a parameter
      the records do not depend on).
    correlation: (p, p) parameter correlation matrix (rows/columns in ``names`` order; NaN
      in the rows of parameters the records do not depend on).
    undetermined: directions of the fitted (log/linear) parameters the records leave
      undetermined: ``[{"eigenvalue_ratio": r, "direction": {name: coeff}}]`` for the
      eigenvectors of the scaled ``J^T J`` with eigenvalue below ``1e-8`` x the largest.
    cost_start, cost: pose loss (mean over records) before and after.
    horizons: the horizons (s) fitted in turn.  iterations: LM iterations in all.
    history: cost after each iteration.  seconds: wall time.  message: LM's last word.
    unstable: records whose rollout at the fitted values ran past the safe step; when > 0
      ``cost`` is NaN and the message says so: the fit is not a result.
    """
    params: dp.Params
    names: list
    values: dict
    stderr: dict
    correlation: np.ndarray
    undetermined: list
    cost_start: float
    cost: float
    horizons: list
    iterations: int
    history: list
    seconds: float
    message: str
    unstable: int = 0

    def as_dict(self) -> dict:
        return {"fitted": self.values, "stderr": self.stderr,
                "correlation": {a: {b: float(self.correlation[i, j])
                                    for j, b in enumerate(self.names)}
                                for i, a in enumerate(self.names)},
                "undetermined": self.undetermined, "cost_start": self.cost_start,
                "cost": self.cost, "horizons": self.horizons, "iterations": self.iterations,
                "seconds": self.seconds, "message": self.message, "unstable": self.unstable}


def prepare_buckets(sim: dp.Simulator, records, *, buckets: int = 3, **kw) -> list:
    """:func:`prepare` the records in ``buckets`` batches of similar duration (sorted by
    duration, equal counts), each rolled out only as long as its longest record: records of
    0.5-3 s then cost about their own length, not the longest one's. The pose loss over the
    list is the loss over all records (each batch averages over all of them). ``kw``: as
    :func:`prepare`."""
    if not records:
        raise FitError("no records: give at least one record file.")
    order = sorted(range(len(records)), key=lambda i: float(records[i].t[-1] - records[i].t[0]))
    groups = [g for g in np.array_split(np.array(order), max(1, min(buckets, len(records))))
              if len(g)]
    out = []
    for g in groups:
        b = prepare(sim, [records[i] for i in g], **kw)
        b.n_records = len(records)
        out.append(b)
    return out


def fit_records(sim: dp.Simulator, params, batch, free: Sequence[Free], *,
                rot_weight: float = ROT_WEIGHT, horizons: Sequence[float | None] = (None,),
                loss: str = "l2", maxiter: int = 30,
                progress: bool | None = None) -> TrajFitResult:
    """Fit the ``free`` leaves of ``params`` to all records of ``batch`` (a :class:`Batch`
    or the list :func:`prepare_buckets` makes) jointly.

    Levenberg-Marquardt on :func:`pose_residuals` with a forward-mode Jacobian
    (``jax.jacfwd``, one tangent per parameter) through the vmapped rollouts. ``horizons``
    (s; None = the whole records): fit the frames up to each horizon in turn, each start
    from the previous fit (a growing horizon for long, chaotic records); changing the
    horizon never recompiles. ``maxiter`` applies per horizon.
    """
    if loss not in ("l2", "l1"):
        raise FitError(f"loss must be 'l2' or 'l1', got {loss!r}.")
    free = [f.resolved() for f in free]
    if not free:
        raise FitError("nothing to fit: name at least one params leaf in [fit].")
    names = [f.name for f in free]
    if len(set(names)) != len(names):
        raise FitError(f"a parameter is named twice in {names}.")
    x0 = []
    for f in free:
        v = float(np.asarray(get_leaf(params, f.name)))
        if not f.lo <= v <= f.hi:
            raise FitError(f"{f.name} = {v} is outside its bounds [{f.lo}, {f.hi}]: change "
                           "the start value or the bounds.")
        if f.log and v <= 0:
            raise FitError(f"{f.name} = {v}: a log-space parameter must start > 0.")
        x0.append(f.to_x(v))
    lo = np.array([f.x_bounds()[0] for f in free], dtype=float)
    hi = np.array([f.x_bounds()[1] for f in free], dtype=float)
    # the optimiser stays inside the stable region: contact k and c capped at the safe step
    # of one contact on the lightest body (tuning.stable); the flag still judges the result
    from .stable import safe_contact_bounds
    k_max, c_max = safe_contact_bounds(sim)
    for i, f in enumerate(free):
        parts = f.name.split(".")
        cap = (k_max if parts[-1] == "k" else c_max) if (
            parts[0] == "contact" and parts[-1] in ("k", "c")) else math.inf
        if cap < math.inf:
            if x0[i] > f.to_x(cap):
                raise FitError(f"{f.name} starts at {f.from_x(x0[i]):.6g}, past the largest "
                               f"safe value {cap:.6g} for dt = {sim.dt:g} s: start lower, or "
                               "use a smaller dt or more substeps.")
            hi[i] = min(hi[i], float(f.to_x(cap)))

    batches = list(batch) if isinstance(batch, (list, tuple)) else [batch]

    def resid_flag(x, horizon):
        p = with_leaves(params, {f.name: f.from_x(x[i]).astype(sim.dtype)
                                 for i, f in enumerate(free)})
        out = [simulate(sim, p, b, with_flag=True) for b in batches]
        r = jnp.concatenate([pose_residuals(o[0], o[1], b, rot_weight=rot_weight,
                                            horizon=horizon, loss=loss)
                             for o, b in zip(out, batches)])
        return r, sum(jnp.count_nonzero(o[2]) for o in out)   # records past the safe step

    @jax.jit
    def res_jac_flag(x, horizon):
        r, bad = resid_flag(x, horizon)
        return r, jax.jacfwd(lambda xx: resid_flag(xx, horizon)[0])(x), bad

    def res_jac(x, horizon):
        return res_jac_flag(x, horizon)[:2]

    t0 = time.perf_counter()
    x = np.asarray(x0, dtype=float)
    hist, it_all, message = [], 0, ""
    cost_start = None
    bar = Progress(maxiter * len(horizons), label="fit", enabled=progress)
    for hz in horizons:
        h = jnp.asarray(np.inf if hz is None else float(hz))
        res = levenberg_marquardt(lambda xx: res_jac(xx, h), x, lo, hi, maxiter=maxiter,
                                  progress=bar, offset=it_all)
        if cost_start is None:
            cost_start = float(res.cost_history[0])
        x = res.x
        it_all += res.iterations
        hist += [float(c) for c in res.cost_history]
        message = res.message
    bar.close()
    r, J, n_bad = (np.asarray(a) for a in res_jac_flag(jnp.asarray(x), jnp.asarray(np.inf)))
    cost, n_bad = float(r @ r), int(n_bad)
    if n_bad:   # past the safe step: never a result (tuning.stable)
        cost = math.nan
        message = (f"NOT a result: {n_bad} of {sum(len(b.paths) for b in batches)} records "
                   "ran past the safe step at the fitted values (State.aux['unstable']); "
                   f"lower dt or tighten the [fit.bounds] of k / c ({message})")
    values = {f.name: float(f.from_x(x[i])) for i, f in enumerate(free)}
    m = int(np.count_nonzero(np.any(J != 0, axis=1)))
    p = len(free)
    JtJ = J.T @ J
    scale = np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    S = JtJ / np.outer(scale, scale)
    ev, evec = np.linalg.eigh(S)
    undetermined = [{"eigenvalue_ratio": float(ev[i] / max(ev[-1], 1e-300)),
                     "direction": {names[j]: float(evec[j, i]) for j in range(p)}}
                    for i in range(p) if ev[i] < 1e-8 * max(ev[-1], 1e-300)]
    s2 = cost / max(m - p, 1)
    blind = np.diag(JtJ) <= 0.0             # the records do not depend on these at all
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = np.linalg.pinv(S, rcond=1e-12) / np.outer(scale, scale) * s2
        se_x = np.where(blind, np.inf, np.sqrt(np.maximum(np.diag(cov), 0.0)))
        corr = np.where(np.outer(blind, blind) | np.outer(blind, ~blind)
                        | np.outer(~blind, blind), np.nan, cov / np.outer(se_x, se_x))
    stderr = {f.name: float(values[f.name] * se_x[i] if f.log else se_x[i])
              for i, f in enumerate(free)}
    fitted = with_leaves(params, {n: jnp.asarray(v, sim.dtype) for n, v in values.items()})
    return TrajFitResult(fitted, names, values, stderr, corr, undetermined, cost_start, cost,
                         [None if h is None else float(h) for h in horizons], it_all, hist,
                         time.perf_counter() - t0, message, unstable=n_bad)


# --------------------------------------------------------------------------- scene files
def load_records(sf, paths: Sequence[str]):
    """Read record files for scene file ``sf`` (:class:`tuning.scenefile.SceneFile`).

    Returns ``(records, bodies)``: the :class:`tuning.records.Record` list and ``{record
    body name: scene body index}``. The observed bodies are ``[fit] observe`` or the scene's
    named bodies; a record with plain ``x, y, z`` columns belongs to the only one.
    Raises :class:`tuning.records.RecordError` / :class:`FitError` before anything compiles.
    """
    from .records import read_record
    if not paths:
        raise FitError("no records: give --data FILE.csv [FILE.csv ...].")
    observe = list(sf.spec.observe) if sf.spec is not None and sf.spec.observe else [
        n for n in sf.names if "[" not in n]
    records = [read_record(p, body_names=observe or None) for p in paths]
    bodies = {}
    for rec in records:
        for name in rec.bodies:
            if name in bodies:
                continue
            if name in sf.names:
                bodies[name] = sf.names[name]
            elif not observe:
                free = [i for i, b in enumerate(sf.scene.bodies) if not b.pinned]
                if len(free) != 1:
                    raise FitError(f"{rec.path}: the columns name no body and the scene has "
                                   f"{len(free)} free bodies: name the body in the scene "
                                   "(name = ...) and prefix the columns (NAME.x, ...).")
                bodies[name] = free[0]
            else:
                bodies[name] = sf.body_index(name)
    return records, bodies


def check_stable(sim: dp.Simulator, params) -> None:
    """Raise :class:`diffpen.StabilityError` (with the safe step) before any rollout when
    ``sim``'s explicit integrator is past its limit at ``params`` -- the batched rollouts
    run with concrete checks off."""
    if sim.integrator in dp.integrators.IMPLICIT:
        return
    rep = sim.stability(params)
    if not rep.stable:
        raise dp.StabilityError(
            f"the scene's integrator {sim.integrator!r} is unstable at dt = {sim.dt:g} s for "
            f"its start parameters (stable step {rep.stable_dt:.3g} s, set by "
            f"{rep.limiting or 'the springs and contacts'}): lower dt in the scene file or "
            "start from softer k / smaller c.", stable_dt=rep.safe_dt,
            substeps=rep.substeps_needed)


def free_from_spec(spec) -> list:
    """:class:`Free` leaves from a scene file's ``[fit]`` (params, bounds, space)."""
    return [Free(p, *spec.bounds.get(p, (-math.inf, math.inf)),
                 log=spec.space.get(p, "log") == "log") for p in spec.free]


def fit_files(scene_path: str, data: Sequence[str], *, out: str | None = None,
              estimate: str = "record", loss: str = "l2", horizons=(None,),
              maxiter: int | None = None, progress: bool | None = None) -> dict:
    """``diffpen fit SCENE.toml --data FILES...``: fit the scene file's ``[fit] params`` to
    all records jointly (:func:`fit_records`), write the fitted scene to ``out``.

    Returns a JSON-ready summary: ``fitted``, ``stderr``, ``correlation``,
    ``undetermined``, ``cost_start``/``cost``, the accuracy before and after
    (:mod:`tuning.evaluate` summaries), ``records``, ``seconds``, ``out``.
    """
    from .evaluate import evaluate_batch, evaluator
    from .scenefile import load_scene_file
    sf = load_scene_file(scene_path)
    if sf.spec is None or not sf.spec.free:
        raise FitError(f"{scene_path}: say what to fit in a [fit] table, e.g. [fit] params = "
                       "[\"contact.default.k\", \"contact.default.c\"] (the params leaves to "
                       "fit, with optional [fit.bounds]).")
    free = free_from_spec(sf.spec)
    data = list(data) if data else list(sf.spec.data or [])
    records, bodies = load_records(sf, data)
    if out is not None and not os.path.isdir(os.path.dirname(os.path.abspath(out))):
        raise FitError(f"--out {out}: its folder does not exist.")
    t0 = time.perf_counter()
    sim = sf.compile()
    params = sf.params(sim)
    check_stable(sim, params)
    batch = prepare(sim, records, bodies=bodies, estimate=estimate)
    ev_fn = evaluator(sim, batch)
    before = evaluate_batch(sim, params, batch, fn=ev_fn)
    buckets = prepare_buckets(sim, records, bodies=bodies, estimate=estimate)
    res = fit_records(sim, params, buckets, free, loss=loss, horizons=horizons,
                      maxiter=maxiter or sf.spec.maxiter or 30, progress=progress)
    after = evaluate_batch(sim, res.params, batch, fn=ev_fn)
    if out is not None:
        from .fitted_scene import write_fitted
        write_fitted(scene_path, res.values, out)
    summary = res.as_dict()
    summary.update({
        "scene": scene_path, "records": len(records), "bodies": bodies, "estimate": estimate,
        "loss": loss, "before": {"position_error_pct": before.position_error_pct,
                                 "rotation_error_deg": before.rotation_error_deg},
        "after": {"position_error_pct": after.position_error_pct,
                  "rotation_error_deg": after.rotation_error_deg},
        "out": out, "seconds": time.perf_counter() - t0, "fit_seconds": res.seconds,
        "reached": not (res.unstable or after.unstable)})
    return summary


def synthetic_record(sim: dp.Simulator, params, duration: float, every: float, bodies: dict,
                     *, state=None, noise: float = 0.0, seed: int = 0,
                     path: str = "<synthetic>", quaternions: bool = True,
                     velocities: bool = True):
    """A :class:`tuning.records.Record` made by rolling ``sim`` out: poses of ``bodies``
    (``{name: body index}``) every ``every`` s (a multiple of ``sim.dt``) for ``duration``
    s, plus Gaussian noise of ``noise`` m on the positions and ``noise / size`` rad about a
    random axis on the orientations; with ``velocities`` also the velocity columns (world,
    m/s) and body-frame angular velocities (rad/s), with noise ``10 noise`` m/s and
    ``10 noise / size`` rad/s. For tests and examples (records from another integrator and
    time step than the fit uses)."""
    from .records import BodyRecord, Record
    save = int(round(every / sim.dt))
    if save < 1 or abs(save * sim.dt - every) > 1e-9 * every:
        raise FitError(f"every = {every} s must be a multiple of the simulator's dt = "
                       f"{sim.dt} s.")
    n = int(round(duration / every))
    s0 = sim.init_state() if state is None else state
    traj = sim.rollout(params, n * save, s0, save_every=save)
    rng = np.random.default_rng(seed)
    t = np.arange(n + 1) * every
    out = {}
    for name, i in bodies.items():
        p = np.concatenate([np.asarray(s0.position)[None, i], np.asarray(traj.position)[:, i]])
        p = p + noise * rng.standard_normal(p.shape)
        q = None
        if quaternions and traj.orientation is not None and sim.scene.bodies[i].rigid:
            q = np.concatenate([np.asarray(s0.orientation)[None, i],
                                np.asarray(traj.orientation)[:, i]])
            if noise:
                size = body_size(sim.scene, i)
                axis = rng.standard_normal((len(q), 3))
                axis /= np.linalg.norm(axis, axis=1, keepdims=True)
                ang = noise / size * rng.standard_normal((len(q), 1))
                dq = np.concatenate([np.cos(ang / 2), axis * np.sin(ang / 2)], axis=1)
                q = _qmul(dq, q)
            q = q / np.linalg.norm(q, axis=1, keepdims=True)
        v = w = None
        if velocities:
            v = np.concatenate([np.asarray(s0.velocity)[None, i],
                                np.asarray(traj.velocity)[:, i]])
            v = v + 10 * noise * rng.standard_normal(v.shape)
            if traj.angular_velocity is not None and sim.scene.bodies[i].rigid:
                ww = np.concatenate([np.asarray(s0.angular_velocity)[None, i],
                                     np.asarray(traj.angular_velocity)[:, i]])
                rot = np.concatenate([np.asarray(s0.orientation)[None, i],
                                      np.asarray(traj.orientation)[:, i]])
                w = np.einsum("tji,tj->ti", _rotmat(rot), ww)        # R^T w: body frame
                w = w + 10 * noise / body_size(sim.scene, i) * rng.standard_normal(w.shape)
        out[name] = BodyRecord(position=p, quaternion=q, velocity=v, angular_velocity=w)
    return Record(path=path, t=t, bodies=out)
