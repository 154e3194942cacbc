"""Records padded into one batch and rolled out together (used by :mod:`tuning.trajfit`).

:func:`prepare` turns records into one padded :class:`Batch`: each record's start state
(:func:`tuning.first_state.first_state`), the frame times as indices into one rollout, and
masks for missing samples and for records shorter than the longest;
:func:`prepare_buckets` makes several batches of similar duration. :func:`simulate` rolls
every record out from its own start state under ``jax.vmap`` (one compiled function for
all) and samples positions and orientations at the frame times (linear interpolation when
the frames do not fall on steps).
"""
from __future__ import annotations

import dataclasses
import functools
import math
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp
from diffpen.params import cast as _cast
from diffpen.integrators import implicit_euler, kick_then_drift

from .first_state import FLIGHT_FRAMES, first_state
from .errors import FitError
from .pose import body_size
from .start_refine import with_start_offsets

__all__ = ["Batch", "prepare", "prepare_buckets", "simulate", "start_states", "lag_start",
           "layout_of", "with_arrays", "typed_params"]


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
    lag: the integrator's velocity lag, s (0: none).  lagged: (R, n_bodies) bool, the bodies a
    record does not observe: :func:`simulate` moves their start velocities by ``-lag`` times
    their accelerations at the parameters it rolls out (None: no such body).
    rotation: whether any orientation is measured (None: read from ``quat_mask``; set by
    :func:`layout_of`, whose batches hold no arrays).
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
    lag: float = 0.0
    lagged: np.ndarray | None = None
    rotation: bool | None = None

    @property
    def has_rotation(self) -> bool:
        if self.rotation is not None:
            return self.rotation
        return bool(self.quat_mask.any())


#: The :class:`Batch` fields :func:`simulate` and :func:`tuning.pose.pose_residuals` read as
#: arrays: a compiled program takes them as arguments (:func:`layout_of`).
ARRAY_FIELDS = ("start", "index", "frac", "pos", "pos_mask", "quat", "quat_mask", "weight",
                "size", "time", "lagged")


def layout_of(batch: Batch) -> tuple[tuple, Batch, dict]:
    """``(key, layout, arrays)``: what a program compiled for ``batch`` fixes and what it
    takes as arguments. ``layout`` is ``batch`` without its arrays (``ARRAY_FIELDS`` None,
    ``rotation`` set); ``key`` (hashable) holds everything static that :func:`simulate` and
    :func:`tuning.pose.pose_residuals` read (rollout length and saves, observed bodies,
    record count of the loss, lag, rotation, whether some body's velocity is lagged); array
    shapes are the compiled program's own business. :func:`with_arrays` puts them back."""
    arrays = {f: getattr(batch, f) for f in ARRAY_FIELDS if getattr(batch, f) is not None}
    layout = dataclasses.replace(batch, **{f: None for f in ARRAY_FIELDS},
                                 rotation=batch.has_rotation)
    key = (batch.steps, batch.save_every, tuple(int(i) for i in np.asarray(batch.bodies)),
           batch.n_records, float(batch.lag), batch.has_rotation, batch.lagged is None)
    return key, layout, arrays


def typed_params(params, dtype):
    """``params`` with every leaf of ``dtype`` (``diffpen.params.cast``, as a rollout casts
    them): a program compiled for :func:`layout_of`'s arguments takes the params as an
    argument, and a Python-number leaf (``with_leaves(params, {name: 12.0})``, weakly typed)
    would compile it once more."""
    return jax.tree_util.tree_map(lambda v: _cast(dtype, v), params)


def with_arrays(layout: Batch, arrays: dict) -> Batch:
    """The batch of :func:`layout_of`'s ``layout`` with ``arrays`` (traced ones too)."""
    return dataclasses.replace(layout, **arrays)


#: Observed bodies whose first pose lies farther than this (m; or 10% of the smallest observed
#: body's size) from the scene file's start, in a scene with bodies the record does not
#: observe, make :func:`prepare` warn: those start at the scene file's pose.
MOVED_START = 0.01
#: ... or move faster than this (m/s, their mean) against the scene file's start velocities
MOVED_SPEED = 0.1
#: Observed bodies whose first pose lies farther than this many times the largest observed
#: body's size from the scene file's start make :func:`prepare` warn of the records' units
#: (a record in cm of a box on world-anchored springs blew up, the fit blaming dt)
FAR_START = 10.0


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
    seen = {}
    for n in names:
        if n not in bodies:
            raise FitError(f"record body {n!r} is not in bodies {sorted(bodies)}.")
        i = bodies[n]
        if not 0 <= i < scene.n_bodies:
            raise FitError(f"record body {n!r} maps to body {i}, not in the scene "
                           f"({scene.n_bodies} bodies).")
        if seen.setdefault(i, n) != n:
            raise FitError(f"record bodies {seen[i]!r} and {n!r} both map to body {i}: "
                           "observe each scene body under one name.")
    return {n: bodies[n] for n in names}


def _far(scene, moves, limit: float) -> bool:
    """Whether the observed bodies' moves from the scene file's start (B, 3 m) can matter
    beyond ``limit`` m: any move, in a scene tied to the world besides its planes (springs to
    world points, fixed spheres, pinned bodies), else a move across some plane (a ball
    started 3 m along an infinite floor is the same ball)."""
    tied = (any(sp.b is None for sp in scene.springs + scene.anchored_springs)
            or scene.fixed_spheres or any(b.pinned for b in scene.bodies))
    if tied:
        return float(np.max(np.linalg.norm(moves, axis=1))) > limit
    return any(float(np.max(np.abs(moves @ np.asarray(pl.normal, float)))) > limit
               for pl in scene.planes)


def prepare(sim: dp.Simulator, records, *, bodies: dict | None = None,
            estimate: str = "record", max_frames: int = FLIGHT_FRAMES,
            cache: dict | None = None, scene=None) -> Batch:
    """Pad ``records`` into a :class:`Batch` for ``sim`` (see :func:`first_state` for
    ``estimate``). ``cache``: a dict that keeps the first states across calls on the same
    record objects (a tumbling box's torque-free fit takes 25-110 ms a record), e.g. the
    evaluation batch and the fit's buckets of one fit. ``scene``: the scene the first
    states are estimated against (default ``sim.scene``; e.g. with fitted plane offsets).
    ``bodies``: ``{record body name: scene body index}``; default: the only free body for
    one-body records, else names that are indices. Bodies a record does not
    observe start from the scene file's state, their velocities moved by the integrator's
    lag as the observed ones' are (:func:`first_state`), their accelerations taken by
    :func:`simulate` at the parameters it rolls out (``Batch.lagged``): a fit moves them
    with its parameters, and its result does not depend on where it started."""
    if not records:
        raise FitError("no records: give at least one record file.")
    if scene is None:
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
    starts, blind, moved, far = [], [], [], []
    free = np.array([not b.pinned for b in scene.bodies])
    lagged = np.zeros((R, scene.n_bodies), bool)
    s_init = sim.init_state()
    # kick-then-drift integrators trace a fitted path from the velocity h / 2 before it (h the
    # inner step; for substeps="auto", whose count depends on the parameters, dt: one substep)
    rec = sim.analysis.integrator
    lag = (0.5 * sim.analysis.inner_dt
           if kick_then_drift(rec) or rec.make is implicit_euler else 0.0)
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
            key = (id(rec), name, int(idx[b]), estimate, max_frames, lag)
            if cache is not None and key in cache:
                p0, v0, q0, w0 = cache[key][1]
            else:
                try:
                    p0, v0, q0, w0 = first_state(scene, int(idx[b]), rec.t, p, q,
                                                 br.velocity, br.angular_velocity,
                                                 estimate=estimate, max_frames=max_frames,
                                                 lag=lag)
                except FitError as exc:             # say which file and body
                    raise FitError(f"{rec.path}, body {name!r}: {exc}") from None
                if cache is not None:               # the record is kept: its id stays its own
                    cache[key] = (rec, (p0, v0, q0, w0))
            if q is None and scene.bodies[idx[b]].rigid:
                blind.append(f"{os.path.basename(rec.path)} ({name})")
            if scene.bodies[idx[b]].pinned:      # observed, never moved: no velocities
                v0 = None if v0 is None else np.zeros(3)
                w0 = None if w0 is None else np.zeros(3)
            try:
                state = sim.state_from(state, body=int(idx[b]), position=p0, velocity=v0,
                                       orientation=q0, angular_velocity=w0, frame="world")
            except dp.SceneError as exc:            # e.g. a first pose inside the ground
                raise FitError(f"{rec.path}, body {name!r}, first state: {exc}") from None
        seen = [int(idx[b]) for b, name in enumerate(names) if name in rec.bodies]
        rest = free.copy()
        rest[seen] = False
        if seen:
            base = os.path.basename(rec.path)
            moves = np.asarray(state.position)[seen] - np.asarray(s_init.position)[seen]
            shift = np.max(np.linalg.norm(moves, axis=1))
            # their mean velocity (a start estimated from noisy frames is off body by body)
            speed = np.linalg.norm(np.mean(np.asarray(state.velocity)[seen]
                                           - np.asarray(s_init.velocity)[seen], axis=0))
            if _far(scene, moves, FAR_START * float(np.max(size))):
                far.append(f"{base} ({shift:.3g} m)")
            # the unobserved bodies start where and as the scene file puts them: say so when
            # the record starts the observed ones far from there or moving otherwise (their
            # links then start stretched, or moving against them: a rope's k 15% off)
            off = ([f"{shift * 1e3:.3g} mm"] if rest.any() and shift > max(
                MOVED_START, 0.1 * float(np.min(size))) else []) + (
                [f"velocity {speed:.3g} m/s off"] if rest.any() and speed > MOVED_SPEED else [])
            if off:                     # one entry per record (its count is the records')
                moved.append(f"{base} ({', '.join(off)})")
        if lag:
            lagged[r] = True
            lagged[r, [int(idx[b]) for b, name in enumerate(names) if name in rec.bodies]] = False
        starts.append(state)
    if moved:
        warnings.warn(f"{len(moved)} record(s) start their observed bodies far from the scene "
                      f"file's positions or velocities: {', '.join(moved[:5])}"
                      + (", ..." if len(moved) > 5 else "") + ". The bodies a record does "
                      "not observe start where and as the scene file puts them, so the "
                      "springs or contacts joining them to the observed ones start strained "
                      "or moving against them (the fitted values absorb it); place the scene "
                      "file's bodies at the records' first pose and velocity (one scene file "
                      "per way of starting), or observe them.", stacklevel=2)
    if far:
        warnings.warn(f"{len(far)} record(s) start their observed bodies more than "
                      f"{FAR_START:g} times their size from the scene file's positions: "
                      f"{', '.join(far[:5])}" + (", ..." if len(far) > 5 else "") + ". Check "
                      "that the records are in metres and in the scene's frame: the planes, "
                      "fixed spheres and anchored springs stay where the scene file puts "
                      "them.", stacklevel=2)
    if blind:
        warnings.warn(f"{len(blind)} record(s) have no orientation columns (qw, qx, qy, qz) "
                      f"for a rigid body: {', '.join(blind[:5])}"
                      + (", ..." if len(blind) > 5 else "") + ". Those bodies start from the "
                      "scene file's orientation and angular velocity, not from the record's; "
                      "measure the orientation too to fit or evaluate their rotation.",
                      stacklevel=2)
    start = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *starts)
    valid = pmask.sum(axis=(1, 2)) + qmask.sum(axis=(1, 2))
    if np.any(valid == 0):
        bad = [records[r].path for r in np.nonzero(valid == 0)[0]]
        raise FitError(f"records {bad} have no measured sample of the scene's bodies.")
    return Batch(start, int(steps), int(save_every), index, frac, pos, pmask, quat, qmask,
                 1.0 / np.maximum(pmask.sum(axis=(1, 2)), 1.0), idx, names, size, times,
                 np.array([len(r.t) for r in records]), [r.path for r in records],
                 lag=lag, lagged=lagged if lagged.any() else None)


def lag_start(sim: dp.Simulator, state, observed, lag: float, params=None):
    """``state`` with the velocities (m/s, rad/s) of the bodies not in ``observed`` (body
    indices; the scene file's velocities, read as the motion's rates) moved by ``-lag``
    (s) times their accelerations there (at the scene file's
    parameters), as :func:`first_state` moves the observed ones: every body starts from the
    velocity the integrator steps from (a 5 x 5 cloth observed at 4 nodes, its other nodes
    at the scene file's rest while the observed ones took the lag, fitted c 10% low; 1.3%
    with it). ``params``: where the accelerations are taken (default ``sim.params()``)."""
    rest = np.ones(len(sim.scene.bodies), bool)
    rest[list(observed)] = False
    if not rest.any():
        return state
    if params is None:
        try:
            params = sim.params()
        except dp.SceneError as exc:
            raise FitError(f"the bodies a record does not observe start from the scene's "
                           f"velocities less the integrator's lag, which needs the scene's "
                           f"parameters: {exc} Pass them as lag_start(..., params=...).") from None
    return _lag(sim, params, state, jnp.asarray(rest), lag, _acceleration(sim))


def _lag(sim, params, state, rest, lag: float, accel=None):
    """``state`` with the velocities of the bodies where ``rest`` ((n_bodies,) bool) moved by
    ``-lag`` times their accelerations at ``params`` (traceable: jit, vmap, grad)."""
    a, alpha = (accel or sim.acceleration)(params, state)
    m = rest[:, None]
    w = state.angular_velocity
    if w is not None and alpha is not None:
        w = jnp.where(m, w - lag * alpha, w)
    return state._replace(velocity=jnp.where(m, state.velocity - lag * a, state.velocity),
                          angular_velocity=w)


@functools.lru_cache(maxsize=4)
def _acceleration(sim: dp.Simulator):
    """``sim.acceleration`` compiled once per simulator (eagerly it took 2.5 s on a cloth)."""
    return jax.jit(lambda params, state: sim.acceleration(params, state))


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


# --------------------------------------------------------------------------- rollouts
@functools.lru_cache(maxsize=None)
def _observer(bodies: tuple, rot: bool):
    """``observe(state)`` of the bodies' poses, one function object per (bodies, rot): the
    rollout's compiled program is keyed by it, so repeated calls reuse it."""
    idx = np.asarray(bodies, dtype=np.int32)

    def observe(s):
        return (s.position[idx], s.orientation[idx] if rot else None)
    return observe


def simulate(sim: dp.Simulator, params, batch: Batch, *, with_flag: bool = False,
             offsets=None, with_collapse: bool = False):
    """Positions (R, T, B, 3) m and orientations (R, T, B, 4) (None without rotation) of the
    batch's bodies at the frame times, each record rolled out from its own start state.
    With ``with_flag`` also (R,) bool: the record's rollout went past its safe step
    (``State.aux["unstable"]``, :func:`tuning.stable.rollout_unstable`); such poses are not
    a result. With ``with_collapse`` (after it) also (R,) bool: a plastic spring of the
    record's rollout collapsed (``State.aux["plastic_collapsed"]``,
    :mod:`diffpen.terms.plastic`; False without plastic springs). ``offsets``: start-state
    offsets added to every record's observed bodies
    (:func:`tuning.start_refine.with_start_offsets`). Pure: jit, grad and jacfwd it."""
    from diffpen.terms.plastic import COLLAPSED

    from .stable import rollout_unstable
    idx = batch.bodies
    rot = sim.scene.has_rotation and batch.has_rotation
    start = start_states(sim, params, batch)
    if offsets is not None:
        start = with_start_offsets(sim, start, batch, offsets, sim.scene.has_rotation)
    observe = _observer(tuple(int(i) for i in np.asarray(idx).reshape(-1)), bool(rot))

    def one(state, index, frac):
        traj = sim.rollout(params, batch.steps, state, save_every=batch.save_every,
                           observe=observe, check_finite=False, check_stability=False)
        p = jnp.concatenate([state.position[idx][None], traj.observed[0]])
        pa, pb = p[index], p[jnp.minimum(index + 1, p.shape[0] - 1)]
        f = frac[:, None, None].astype(p.dtype)
        pos = pa + f * (pb - pa)
        bad = (rollout_unstable(sim, traj, params),) if with_flag else ()
        if with_collapse:
            flag = traj.aux.get(COLLAPSED)
            bad += (jnp.asarray(False) if flag is None else jnp.asarray(flag)[-1] > 0,)
        if not rot:
            return (pos, None) + bad
        q = jnp.concatenate([state.orientation[idx][None], traj.observed[1]])
        qa, qb = q[index], q[jnp.minimum(index + 1, q.shape[0] - 1)]
        qb = jnp.where(jnp.sum(qa * qb, -1, keepdims=True) < 0, -qb, qb)
        qi = qa + f * (qb - qa)
        return (pos, qi / jnp.linalg.norm(qi, axis=-1, keepdims=True)) + bad
    return jax.vmap(one)(start, jnp.asarray(batch.index), jnp.asarray(batch.frac))


def start_states(sim: dp.Simulator, params, batch: Batch):
    """The records' start states (leading axis R) that :func:`simulate` rolls out at
    ``params``: ``batch.start`` with the velocities of the bodies a record does not observe
    moved by the integrator's lag at ``params`` (``Batch.lagged``; the observed ones took
    theirs from the record). Pure: jit, grad and vmap it."""
    if batch.lagged is None or not batch.lag:
        return batch.start
    return jax.vmap(lambda s, m: _lag(sim, params, s, m, batch.lag))(
        batch.start, jnp.asarray(batch.lagged))
