"""The start state of a record: pose and velocities of one body from its first frames.

:func:`first_state` takes the pose of row 0 and the record's velocity columns, or fits
them by least squares to the first frames (a gravity parabola for a body in free flight,
before it nears a plane; a quadratic otherwise), less the integrator's velocity lag, for
:func:`tuning.record_batch.prepare`.
"""
from __future__ import annotations

import math

import numpy as np

from diffpen.geometry import box_corners
from diffpen.rigid import inertia_diagonal

from .errors import FitError
from .pose import exp_quat, qconj, qmul, rotmat, rotvec

__all__ = ["first_state", "flight_frames", "torque_free", "FLIGHT_FRAMES"]

#: Default cap on the free-flight frames of a start-state fit: in practice the whole first
#: flight (a gravity parabola and torque-free rotation are its exact motion, so every frame of
#: it averages noise out). It was 20: a ball dropped from 1 m and recorded at 500 Hz with 1 mm
#: noise (no velocity columns) started 0.04 s into its 0.43 s fall and fitted k 6.3% and c
#: 3.2% low, 15 standard errors off (0.4% and 0.1% with its whole first flight); the cube
#: tosses' fit and held-out errors moved by under 0.05% and 0.01 deg (20 against 60 frames;
#: 14.8% / 18.8 deg with 10, before the velocity lag below).
FLIGHT_FRAMES = 1000


#: the first flight's frame cap where its end cannot be seen in the record: the scene holds
#: other bodies this one can touch, whose motion the record need not observe (20, the cap
#: every flight had before it became the whole flight)
UNSEEN_CONTACT_FRAMES = 20


def flight_frames(scene, index, pos, quat, margin: float) -> int:
    """How many leading frames body ``index`` is clear of every plane and fixed sphere by
    ``margin`` m.

    ``pos``: (T, 3) observed centre, m (NaN where missing); ``quat``: (T, 4) orientations
    or None (then the body's bounding radius is used, as for a frame whose orientation is
    missing). A frame without a position is skipped, not the end of the flight: the count
    runs to the last frame clear of every collider before the first one that is not. Where
    the body can touch other bodies of the scene, whose motion a record need not observe, at
    most :data:`UNSEEN_CONTACT_FRAMES` (a ball dropped onto a fixed sphere in a scene without
    planes had its parabola fitted through the impact: 2784% evaluated, k fitted 0.18)."""
    b = scene.bodies[index]
    if not b.collide:
        return len(pos)
    corners = None if b.half_extents is None else box_corners(b.half_extents)
    n = 0
    for f in range(len(pos)):
        if not np.all(np.isfinite(pos[f])):
            continue
        if corners is not None and quat is not None and np.all(np.isfinite(quat[f])):
            pts = pos[f] + corners @ rotmat(quat[f]).T
            reach = 0.0
        else:
            pts, reach = pos[f][None], b.radius      # a box's: its bounding sphere
        gaps = [float(np.min(pts @ np.array(pl.normal))) - pl.offset - reach
                for pl in scene.planes]
        gaps += [float(np.min(np.linalg.norm(pts - np.array(fs.center), axis=1))) - fs.radius
                 - reach for fs in scene.fixed_spheres]
        if gaps and min(gaps) < margin:
            break
        n = f + 1
    others = any(j != index and o.collide and (o.radius > 0.0 or b.radius > 0.0)
                 for j, o in enumerate(scene.bodies))     # two particles never touch
    return min(n, UNSEEN_CONTACT_FRAMES) if others else n


def torque_free(q0, w0, inertia, times, *, max_angle: float = 0.1):
    """Orientations of a torque-free rigid body: Euler's equations ``I dw/dt = (I w) x w`` in
    the body frame and ``dq/dt = q (0, w) / 2``, classical Runge-Kutta, each interval between
    two sample times cut into steps that turn the body by at most ``max_angle`` rad.

    Args:
      q0: (..., 4) start orientations (w, x, y, z), body to world.  w0: (..., 3) start
        angular velocities, rad/s, BODY frame.  inertia: (3,) principal moments, kg m^2.
      times: (T,) sample times, s, ascending from >= 0 (the start is t = 0).
    Returns:
      (..., T, 4) unit quaternions at ``times``.
    """
    inertia = np.asarray(inertia, dtype=float)
    q = np.asarray(q0, dtype=float)
    w = np.asarray(w0, dtype=float)

    def rate(q, w):
        dw = np.cross(inertia * w, w) / inertia
        dq = 0.5 * qmul(q, np.concatenate([np.zeros_like(w[..., :1]), w], axis=-1))
        return dq, dw

    out, t = [], 0.0
    for t_next in np.asarray(times, dtype=float):
        span = t_next - t
        if span > 0.0:
            speed = float(np.max(np.linalg.norm(w, axis=-1)))
            n = max(1, int(math.ceil(span * speed / max_angle)))
            h = span / n
            for _ in range(n):
                k1q, k1w = rate(q, w)
                k2q, k2w = rate(q + 0.5 * h * k1q, w + 0.5 * h * k1w)
                k3q, k3w = rate(q + 0.5 * h * k2q, w + 0.5 * h * k2w)
                k4q, k4w = rate(q + h * k3q, w + h * k3w)
                q = q + h / 6.0 * (k1q + 2.0 * k2q + 2.0 * k3q + k4q)
                w = w + h / 6.0 * (k1w + 2.0 * k2w + 2.0 * k3w + k4w)
                q = q / np.linalg.norm(q, axis=-1, keepdims=True)
            t = t_next
        out.append(q)
    return np.stack(out, axis=-2)


def _refine_rotation(q0, w_body, inertia, times, quats, iters: int = 8):
    """Gauss-Newton fit of the start orientation and BODY-frame angular velocity of a
    torque-free body to observed orientations ``quats`` (T, 4) at ``times`` (T,) s from the
    start: residuals the rotation vectors of ``q_data q_model^-1`` (rad), parameters a
    world-frame turn of ``q0`` and ``w_body`` (start: ``w_body``, the rate of the first
    frames). A tumbling body's rate changes within a few frames, so the fit grows its
    window (6, 12, 24, ... frames), each from the fit before. Returns ``(q0, w_body)``."""
    x = np.concatenate([np.zeros(3), w_body])
    sizes = sorted({min(len(times), 6 * 2 ** j) for j in range(8)})
    for size in sizes:
        x = _gauss_newton_rotation(x, q0, inertia, times[:size], quats[:size], iters)
    return qmul(exp_quat(x[:3]), q0), x[3:]


def _gauss_newton_rotation(x, q0, inertia, times, quats, iters: int):
    """:func:`_refine_rotation` on one window: ``x`` = (turn of ``q0`` (3), body rate (3))."""
    def model(xs):                                     # xs (B, 6) -> (B, T, 4)
        qs = qmul(exp_quat(xs[:, :3]), q0[None])
        return torque_free(qs, xs[:, 3:], inertia, times)

    def residual(qm):                                  # (B, T, 4) -> (B, 3 T)
        r = rotvec(qmul(quats[None], qconj(qm)))
        return r.reshape(len(qm), -1)

    eps = 1e-6
    r = residual(model(x[None]))[0]
    cost, lam = float(r @ r), 1e-6
    for _ in range(iters):
        xs = np.vstack([x, x + eps * np.eye(6)])
        rs = residual(model(xs))
        J = (rs[1:] - rs[:1]).T / eps                  # (3 T, 6)
        JtJ, g = J.T @ J, J.T @ rs[0]
        step = -np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), g)
        r_new = residual(model((x + step)[None]))[0]
        cost_new = float(r_new @ r_new)
        if cost_new < cost:
            done = cost - cost_new < 1e-6 * cost
            x, cost, lam = x + step, cost_new, lam * 0.1
            if done:
                break
        else:
            lam *= 10.0
    return x


def _taylor(tt, y, degree: int):
    """Least-squares polynomial of ``degree`` through samples ``y`` (n, 3) at times ``tt``
    (n,) s from row 0: ``(value, rate, second derivative)`` at ``t = 0`` ((3, 3); the
    second derivative 0 for ``degree < 2``)."""
    span = max(float(np.max(np.abs(tt))), 1e-300)        # times in units of the window
    V = np.vander(tt / span, degree + 1, increasing=True)
    c = np.linalg.lstsq(V, y, rcond=None)[0]
    c = np.concatenate([c, np.zeros((max(0, 3 - len(c)), y.shape[1]))])
    return np.stack([c[0], c[1] / span, 2.0 * c[2] / span ** 2])


def _free_flight(scene, index) -> bool:
    """True when nothing but gravity and contact acts on body ``index`` (no spring, drag)."""
    for s in (*scene.springs, *scene.anchored_springs, *scene.plastic_springs):
        if index in (s.a, s.b):
            return False
    return not any(d.body == index for d in scene.drags)


def first_state(scene, index, t, pos, quat=None, vel=None, omega_body=None, *,
                estimate: str = "fit", max_frames: int = FLIGHT_FRAMES, margin: float = 0.005,
                lag: float = 0.0):
    """Start pose and velocities of one body from the first frames of its record.

    Args:
      scene: the :class:`diffpen.Scene`.  index: the body.
      t: (T,) s.  pos: (T, 3) m (NaN where missing).  quat: (T, 4) or None.
      vel: (T, 3) m/s world or None.  omega_body: (T, 3) rad/s body frame or None.
      estimate: ``"record"``: pose of row 0 and the record's velocity columns of row 0 (a
        fit of the first frames where a column is missing); ``"fit"``: pose and velocities
        fitted by least squares to the first frames -- for a body in free flight (no
        spring or drag on it) a gravity parabola ``p0 + v t + g t^2 / 2`` over the frames
        before it comes within ``margin`` m of a plane (at most ``max_frames``; rows with a
        missing sample are left out of the fit, not the end of the flight), with
        torque-free rotation (:func:`torque_free`: a constant angular velocity for equal
        principal moments, Euler's equations otherwise); for a body that is not in free
        flight (a spring or drag on it, or fewer than 3 frames clear of every plane: it
        starts on a plane) a quadratic over ``min(5, T)`` frames, for the positions and for
        the rotation since row 0 (a rate and an angular acceleration: a constant rate put a
        box released at rest on two springs, 5 ms frames, at 5.9 rad/s and its fit k 27%
        off); ``"refine"``: as ``"record"`` (a record fit then refines the velocities with
        the parameters: :mod:`tuning.start_refine`).
        Finite-difference velocity columns are biased (the cube records' row-0 vertical
        velocity by about +0.023 m/s): ``"fit"`` avoids that bias.
      lag: s, the integrator's velocity lag: ``h / 2`` for semi-implicit and implicit Euler
        (inner step h; :func:`tuning.record_batch.prepare` takes ``h = dt`` for
        ``substeps="auto"``, whose count depends on the parameters), whose steps
        ``x += h v_new`` (and ``q`` turned by ``h w_new``) trace the path
        ``p0 + v t + a t^2 / 2`` only from the velocity ``v - a h / 2`` (0 for verlet and
        rk4). Velocities are returned as ``v - lag a`` and angular velocities as
        ``w - lag alpha`` (world frame), whatever their source: ``v``, ``w`` the rates of
        the path at row 0 (fitted, or the record's columns, which measure that rate) and
        ``a``, ``alpha`` its accelerations (gravity and the torque-free ``alpha`` in free
        flight; else the quadratic's, or the slope of a quadratic through the columns of
        those frames where the record has them). Without it a ball dropped from rest and
        recorded by the simulator itself started at -g h / 2 and the fit moved k by 2%,
        and exact velocity columns of a rope recorded by rk4 moved k by -1.4% and c by
        -3.2% (-0.1% and +0.3% with the lag).
    Returns:
      ``(position (3,), velocity (3,), orientation (4,) or None, omega_world (3,) or None)``.
    """
    if estimate not in ("record", "fit", "refine"):
        raise FitError(f"first-state estimate must be 'record', 'fit' or 'refine', got "
                       f"{estimate!r}.")
    if estimate == "refine":            # the estimate a fit then refines (tuning.start_refine)
        estimate = "record"
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
        # a body that starts on or near a plane (fewer than 3 frames clear of it) is not in
        # free flight: the gravity parabola would lift it (by about g t / 2 per frame); a
        # missing sample within the flight is left out of the fit, not its end (a box toss
        # at 148 Hz with row 2 empty got a quadratic over 5 frames and evaluated 34.5% /
        # 14.8 deg off at the true parameters instead of 3.1% / 1.4 deg)
        free = np.count_nonzero(ok[:n]) >= 3
    if not free:
        # a quadratic over 5 frames (below): on records of the tests' box hung on two
        # springs, released at rest, 5 ms frames, no velocity columns, 0.2 mm noise, k and c
        # came out 3% and 15% off (rms over 6 records), against 9% and 28% over 3 frames,
        # 9% and 40% over 4, 4% and 14% over 7 and 7-19%, 28-67% from cubics over 5-7;
        # noise-free it starts 0.025 m/s and 1.2 rad/s off (3 frames: 0.005, 0.24; 1 ms
        # frames: 0.001 m/s, 0.04 rad/s)
        n = min(5, len(t))
    use = np.nonzero(ok[:n])[0]
    if len(use) < 2:
        use = np.arange(1)
    accel = np.zeros(3)                 # the acceleration of the fitted path, m/s^2
    if free and len(use) >= 2:
        A = np.stack([np.ones(len(use)), tt[use]], axis=1)
        coef = np.linalg.lstsq(A, pos[use] - 0.5 * g * tt[use, None] ** 2, rcond=None)[0]
        accel = g
    elif len(use) >= 2:
        coef = _taylor(tt[use], pos[use], min(2, len(use) - 1))
        accel = coef[2]
    else:
        coef = np.stack([pos[0], np.zeros(3)])
    fitted_v = coef[1] - lag * accel    # the velocity from which the steps trace the path
    p0, v0 = (pos[0], None) if estimate == "record" else (coef[0], fitted_v)
    if estimate == "record" and vel is not None and np.all(np.isfinite(vel[0])):
        if not free:
            okv = np.nonzero(np.all(np.isfinite(vel[:n]), axis=1))[0]
            if len(okv) >= 2:           # the columns' own slope
                accel = _taylor(tt[okv], vel[okv], min(2, len(okv) - 1))[1]
        v0 = vel[0] - lag * accel
    if v0 is None:
        v0 = fitted_v
    if quat is None:
        return p0, v0, None, None
    q = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    okq = np.all(np.isfinite(q), axis=1)
    if not okq[0]:
        raise FitError("the first data row has no orientation (qw, qx, qy, qz): the rollout "
                       "starts from it. Trim the record so that it starts with a complete "
                       "pose, or fill those cells.")
    useq = np.nonzero(okq[:n])[0]
    alpha = np.zeros(3)                 # the angular acceleration of the fitted turn, world
    if len(useq) >= 2:
        # the mean rate over the frames from the turns between consecutive ones (each well
        # below pi: a rotation since row 0 wraps past pi after 0.13 s at 25 rad/s), then a
        # fit of the small rotations that rate leaves (a sign-flipped quaternion is the
        # same rotation): a line in free flight, else the same polynomial as the positions
        turns = rotvec(qmul(q[useq[1:]], qconj(q[useq[:-1]])))
        w0 = turns.sum(axis=0) / (tt[useq[-1]] - tt[useq[0]])
        pred = qmul(exp_quat(w0[None] * (tt[useq] - tt[0])[:, None]), q[0][None])
        rv = rotvec(qmul(q[useq], qconj(pred)))
        sol = _taylor(tt[useq], rv, 1 if free else min(2, len(useq) - 1))
        w_fit, a0, alpha = w0 + sol[1], sol[0], sol[2]
    else:
        w_fit, a0 = np.zeros(3), np.zeros(3)
    q_fit = qmul(exp_quat(a0), q[0])
    inertia = inertia_diagonal(scene.bodies[index])
    if free and len(useq) >= 3 and np.ptp(inertia) > 1e-9 * np.max(inertia):
        # a body with unequal principal moments does not turn at a constant rate in free
        # flight: fit its torque-free motion (a constant rate is exact for equal moments)
        early = turns[:5].sum(axis=0) / (tt[useq[min(5, len(useq) - 1)]] - tt[useq[0]])
        q_fit, wb = _refine_rotation(q_fit, rotmat(q_fit).T @ early, inertia, tt[useq],
                                     q[useq])
        w_fit = rotmat(q_fit) @ wb
        alpha = rotmat(q_fit) @ (np.cross(inertia * wb, wb) / inertia)   # Euler's equations
    if estimate == "record":
        q0 = q[0]
        if omega_body is not None and np.all(np.isfinite(omega_body[0])):
            if not free:
                okw = np.nonzero(np.all(np.isfinite(omega_body[:n]), axis=1)
                                 & okq[:n])[0]
                if len(okw) >= 2:       # the columns' own slope, in the world frame
                    ww = np.einsum("tij,tj->ti", rotmat(q[okw]), omega_body[okw])
                    alpha = _taylor(tt[okw], ww, min(2, len(okw) - 1))[1]
            w0 = rotmat(q0) @ omega_body[0] - lag * alpha
        else:
            w0 = w_fit - lag * alpha
    else:
        q0 = q_fit
        w0 = w_fit - lag * alpha
    return p0, v0, q0, w0

