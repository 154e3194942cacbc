"""Records made by rolling a simulator out (:func:`synthetic_record`): poses, velocities and
noise in the format of measured records, for tests and examples (fit with another
integrator and time step than the record was made with).
"""
from __future__ import annotations

import numpy as np

import diffpen as dp
from diffpen.integrators import implicit_euler, kick_then_drift

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
    time step than the fit uses). With semi-implicit or implicit Euler the rollout starts
    from ``state`` (default the scene's) with its velocities less the lag below, so that
    they are the motion's rates at t = 0, as a fit reads a scene's."""
    from .records import BodyRecord, Record
    save = int(round(every / sim.dt))
    if save < 1 or abs(save * sim.dt - every) > 1e-9 * every:
        raise FitError(f"every = {every} s must be a multiple of the simulator's dt = "
                       f"{sim.dt} s.")
    n = int(round(duration / every))
    s0 = sim.init_state() if state is None else state
    rec = sim.analysis.integrator
    lagged = kick_then_drift(rec) or rec.make is implicit_euler
    start = s0
    if lagged:
        # the start's velocities are the motion's rates at t = 0, as a fit reads a scene
        # file's (tuning.record_batch.prepare): the rollout steps from them less the lag
        from .record_batch import lag_start
        start = lag_start(sim, s0, [], 0.5 * sim.analysis.inner_dt, params)
    # every frame's state, the start first: (n + 1, bodies, ...) per field
    if lagged:             # every step, and one past the last frame: the next kick's rates
        traj = sim.rollout(params, n * save + 1, start)
    else:
        traj = sim.rollout(params, n * save, start, save_every=save)
    step = save if lagged else 1

    def frames(field, nxt=0):
        if getattr(traj, field) is None:
            return None
        a = np.concatenate([np.asarray(getattr(start, field))[None],
                            np.asarray(getattr(traj, field))])
        return a[nxt::step][:n + 1]
    fr = {f: frames(f) for f in ("position", "velocity", "orientation", "angular_velocity")}
    if lagged:
        share = 0.5 * sim.analysis.inner_dt / sim.dt     # (h / 2) / dt of the next step
        for f in ("velocity", "angular_velocity"):
            if fr[f] is not None:
                fr[f] = fr[f] + share * (frames(f, 1) - fr[f])
    rng = np.random.default_rng(seed)
    t = np.arange(n + 1) * every
    out = {}
    for name, i in bodies.items():
        p = fr["position"][:, i]
        p = p + noise * rng.standard_normal(p.shape)
        q = None
        if quaternions and fr["orientation"] is not None and sim.scene.bodies[i].rigid:
            q = fr["orientation"][:, i]
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
            v = fr["velocity"][:, i]
            v = v + 10 * noise * rng.standard_normal(v.shape)
            if fr["angular_velocity"] is not None and sim.scene.bodies[i].rigid:
                ww = fr["angular_velocity"][:, i]
                rot = fr["orientation"][:, i]
                w = np.einsum("tji,tj->ti", rotmat(rot), ww)        # R^T w: body frame
                w = w + 10 * noise / body_size(sim.scene, i) * rng.standard_normal(w.shape)
        out[name] = BodyRecord(position=p, quaternion=q, velocity=v, angular_velocity=w)
    return Record(path=path, t=t, bodies=out)
