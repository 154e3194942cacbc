"""Records made by rolling a simulator out (:func:`synthetic_record`): poses, velocities and
noise in the format of measured records, for tests and examples (fit with another
integrator and time step than the record was made with).
"""
from __future__ import annotations

import numpy as np

import diffpen as dp

from .errors import FitError
from .pose import body_size, qmul, rotmat

__all__ = ["synthetic_record"]


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
                q = qmul(dq, q)
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
                w = np.einsum("tji,tj->ti", rotmat(rot), ww)        # R^T w: body frame
                w = w + 10 * noise / body_size(sim.scene, i) * rng.standard_normal(w.shape)
        out[name] = BodyRecord(position=p, quaternion=q, velocity=v, angular_velocity=w)
    return Record(path=path, t=t, bodies=out)
