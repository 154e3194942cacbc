"""Batched parameter sweeps: every point's metrics with ``jax.vmap``, chunked, written
atomically, resumable.

A sweep evaluates ``metrics_fn(params)`` at N points of a few parameters (dotted paths, see
:mod:`tuning.params`). Points are processed in chunks of ``chunk``: one chunk is ONE call of a
pure function of a ``(chunk, P)`` batch of parameter values (``jax.jit(jax.vmap(...))`` by
default; pass ``batch_map=tuning.shard.sharded_map`` to split the batch axis across devices),
so memory stays bounded by the chunk. The last chunk is padded to the same shape, so the
whole sweep compiles once.

The results so far are written to ``out`` (``.npz``) after every chunk, or, where rewriting
the whole file costs more than a twentieth of the computing, after the chunks that took 20
times its write time; a ``.csv`` beside it every 30 s; both at the end, also of an
interrupted run (:mod:`tuning.sweep_files`: ``NPZ_COST_FACTOR``, ``CSV_EVERY_S``,
``CSV_ON_STOP_S``). Each is written through a temporary file and ``os.replace`` (never
half-written; :mod:`tuning.io`). The file carries a key of everything that determines it
(:func:`sweep_key`); calling :func:`sweep` again with the same key and ``out`` resumes:
finished chunks are read back, not recomputed. Another key is refused with the list of what
differs (``resume=False`` overwrites). One writer per output (a lock), checked paths before
any computing, and temporary files of a killed run are removed.

Several processes (:mod:`tuning.distributed`): every process calls :func:`sweep` with the same
points, key and chunk (processes given others stop at once with the same error); each chunk
is split over the devices of all of them and gathered, only process 0 checks, locks, reads (to
resume) and writes ``out``, and every process returns the same result.
"""
from __future__ import annotations

import hashlib
import os
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from . import distributed
from . import params as P
from .code_key import code_key
from .compiled import ProgramCache, frozen_key
from .io import (OutputLock, atomic_write, check_output, clean_orphans,
                 key_differences, key_digest, result_key)
from .points import grid_points, random_points  # noqa: F401  (public here too)
from .progress import Progress
from .sweep_files import (UNSTABLE, SweepError, SweepResult, _own_table, _Pair, _read_key,
                          _unreadable, _Unreadable, load_sweep)
# read here as before; they are read (and set) in tuning.sweep_files
from .sweep_files import CSV_EVERY_S, CSV_ON_STOP_S, NPZ_COST_FACTOR  # noqa: F401,E402

__all__ = ["SweepResult", "SweepError", "grid_points", "random_points", "sweep",
           "atomic_write", "load_sweep", "make_evaluator", "sweep_key", "function_key",
           "UNSTABLE"]

def make_evaluator(metrics_fn: Callable, params0: dp.Params, names: list,
                   keys: list | None = None, batch_map: Callable | None = None) -> Callable:
    """``evaluate(batch (B, P)) -> {metric: (B, ...)}``: a pure function of the values batch.

    Each row sets the leaves ``names`` of ``params0``; ``batch_map(fn)`` lifts the
    per-point function to the batch (default :func:`tuning.shard.sharded_map`: the batch
    axis split over every device, identical to ``jax.jit(jax.vmap(fn))`` on one).
    """
    flat0 = P.flatten(params0)
    for n in names:
        if n not in flat0:
            raise ValueError(f"unknown parameter {n!r}; this scene has {list(flat0)}.")
    _once(names)

    def one(x):
        flat = dict(flat0)
        for i, n in enumerate(names):
            flat[n] = x[i]
        # unflatten puts each in its leaf's own float dtype: a float64 batch set into float32
        # params made what the metrics compute from them (a resting height from k) float64
        m = metrics_fn(P.unflatten(params0, flat))
        return {k: jnp.asarray(v) for k, v in m.items()
                if keys is None or k in keys or k == UNSTABLE}
    if batch_map is None:
        from .shard import sharded_map
        batch_map = sharded_map      # every device; jax.jit(jax.vmap(f)) on a single one
    evaluate = batch_map(one)
    try:        # what it computes, for the key of a sweep given only the evaluator
        evaluate.metrics_fn, evaluate.params0 = metrics_fn, params0
        evaluate.keys = None if keys is None else list(keys)
    except AttributeError:   # a batch_map whose result takes no attributes
        pass
    return evaluate


def _once(names) -> None:
    """Refuse a leaf named twice (the last column won: a table then showed values that
    were not the ones simulated)."""
    twice = sorted({str(n) for n in names if list(names).count(n) > 1})
    if twice:
        raise SweepError(f"names gives {twice} more than once: sweep each leaf in one "
                         "column of points.")


#: evaluators :func:`sweep` built, by their arguments (values), the last 8
_EVALUATORS = ProgramCache()


def _shared_evaluator(metrics_fn, params0, names, keys, batch_map) -> Callable:
    """:func:`make_evaluator`, or the one built for equal arguments by an earlier sweep
    (each sweep without ``evaluate=`` compiled a new one: ~2 s). The key holds what
    ``metrics_fn`` computes now (:func:`function_key`, one trace): a function whose
    globals or closure changed since is another program, not the stale one."""
    def build():
        return make_evaluator(metrics_fn, params0, names, keys, batch_map)
    try:
        now = function_key(metrics_fn, params0)
    except Exception:       # noqa: BLE001 - not traceable here: built afresh, errors and all
        return build()
    key = frozen_key(metrics_fn, now, params0, names, keys, batch_map)
    return build() if key is None else _EVALUATORS.get(key, build)


def function_key(metrics_fn: Callable, params0: dp.Params) -> str:
    """A digest of what ``metrics_fn`` computes: the sha256 of its jaxpr traced at
    ``params0`` (the operations, the scene's constants, dt and step counts as literals) and of
    the arrays it closes over. A sweep written to ``out`` without ``key=`` stores it, so that
    a rerun with another scene, dt, duration or metric is refused, not mixed in."""
    # traced through a new function object: JAX keeps the trace of a function it traced
    # before, with the values its globals had then
    return distributed.jaxpr_digest(jax.make_jaxpr(lambda p: metrics_fn(p))(params0)).hex()


def sweep_key(names, points, params0, keys=None, shape=None, key: dict | None = None) -> dict:
    """The key a sweep file carries: ``key`` (what determines ``metrics_fn``: scene, law,
    integrator, dt, duration, metric settings; see :func:`tuning.io.describe_simulator`) plus
    the swept names, the points (a digest), the grid shape, the kept metrics, the values of
    every leaf of ``params0`` that is not swept, the float dtype and the diffpen version."""
    flat = P.flatten(params0) if params0 is not None else {}
    fixed = {}
    dtypes = set()
    for n, v in flat.items():
        a = np.asarray(v)
        dtypes.add(str(a.dtype))
        if n not in names:
            fixed[n] = a
    pts = np.ascontiguousarray(points, dtype=np.float64)
    digest = hashlib.sha256(pts.tobytes()).hexdigest()[:16]
    fields = dict(key or {})
    fields.setdefault("dtype", sorted(dtypes) or [str(jnp.result_type(float))])
    return result_key(**fields, swept=list(names), points_sha256=digest,
                      n_points=int(pts.shape[0]),
                      point_range=[[float(pts[:, i].min()), float(pts[:, i].max())]
                                   for i in range(pts.shape[1])] if pts.size else [],
                      grid=list(shape) if shape is not None else None,
                      metrics=sorted(keys) if keys is not None else "all", fixed=fixed)


def sweep(metrics_fn: Callable, params0: dp.Params, points, names: list, *,
          chunk: int = 256, out: str | None = None, resume: bool = True,
          key: dict | None = None, keys: list | None = None, shape: tuple | None = None,
          axes: dict | None = None, batch_map: Callable | None = None,
          progress: bool | None = False, on_chunk: Callable | None = None,
          evaluate: Callable | None = None, finalize: Callable | None = None) -> SweepResult:
    """Evaluate ``metrics_fn`` at every point, ``chunk`` points per vmapped call.

    Args:
      metrics_fn: traceable ``params -> {metric: scalar or (n,) array}``. A metric named
        ``"unstable"`` (e.g. ``traj.aux["unstable"][-1]``) marks points whose rollout went
        past its safe step: their other float metrics are NaN, their bool metrics (e.g.
        ``settled``) False, and they are counted in ``result.unstable``. Without one (nor
        a ``finalize`` adding it) the sweep warns: nothing is checked.
      params0: :class:`diffpen.Params` giving the leaves that are not swept.
      points: (N, P) parameter values, SI units.  names: (P,) leaf paths.
      chunk: points per call (bounds memory; the last chunk is padded, never recompiled).
      out: ``NAME.npz`` path (any other name raises :class:`SweepError`: the table is
        written to ``NAME.csv`` beside it); results and table are written atomically as
        the chunks finish (see above) and when the sweep ends or stops. The paths are
        checked before anything is computed (a ``.csv`` there that is not the table of the
        sweep in ``out`` is refused, never overwritten), and an exclusive lock
        (``.<name>.lock`` beside it) keeps a second writer out.
      resume: continue a sweep found at ``out`` when its key equals this sweep's (see
        :func:`sweep_key`); a file with another key raises :class:`SweepError` naming what
        differs, and so does one that cannot be read (truncated, corrupt).
        ``resume=False`` overwrites ``out`` (an unreadable one and its table too).
      key: what determines ``metrics_fn`` beyond the swept leaves (scene, law, integrator,
        dt, duration, metric settings...): stored in the file and compared on resume
        (:func:`tuning.io.describe_simulator` builds most of it). With ``out`` and no key,
        the key is :func:`function_key` of ``metrics_fn`` (or of the function a
        :func:`make_evaluator` evaluator was built from; any other ``evaluate`` needs a
        key) and a digest of ``finalize``'s code and what it reads
        (:func:`tuning.code_key.code_key`, which says what it does not cover): a rerun
        computing something else is refused.
      keys: metrics to keep (default all; a :func:`make_evaluator` evaluator's own ``keys``
        when it was given some: the key holds the metrics it keeps).
      shape, axes: grid layout (see :func:`grid_points`).
      batch_map: lifts the per-point function to a batch (default
        :func:`tuning.shard.sharded_map`: split over all devices with a ``NamedSharding``;
        ``jax.jit(jax.vmap(f))`` on a single device).
      on_chunk: ``on_chunk(i_chunk, result)`` after each chunk (its rows are in
        ``result``; the file holds them once it is next written).
      evaluate: a prebuilt :func:`make_evaluator` (reuse it across sweeps of one problem so
        that they share one compiled program).
      finalize: ``finalize(metrics, points) -> metrics`` on each chunk's host arrays
        (``{name: (B, ...)}``, points ``(B, P)``) before they are stored: e.g. NaN for
        undefined values, or an ``"unstable"`` flag computed from the points.
      progress: False (default): print nothing; None or True: progress on stderr (a bar on a
        terminal, else a line every 5 s; what the ``diffpen`` command passes).
    Returns: :class:`SweepResult`.
    """
    t0 = time.perf_counter()
    try:
        points = np.asarray(points, float)
    except (TypeError, ValueError):
        raise SweepError("points must be an (N, P) array of numbers.") from None
    if points.ndim != 2 or points.shape[1] != len(names):
        raise ValueError(f"points must have shape (N, {len(names)}), got {points.shape}.")
    if points.shape[0] == 0:
        raise SweepError("points is empty: give at least one point.")
    _once(names)
    if not np.all(np.isfinite(points)):
        raise ValueError("sweep points must be finite.")
    from .scenefile.leaves import leaf_space
    for j, name in enumerate(names):      # only signed leaves (plane offsets) may be < 0
        if np.any(points[:, j] < 0.0) and leaf_space(str(name), 1.0) == "log":
            raise ValueError(f"sweep points of {name} must be >= 0 (a stiffness, damping, "
                             f"friction, ...), got {float(points[:, j].min()):g}.")
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"chunk must be an int >= 1, got {chunk!r}.")
    n = points.shape[0]
    # the key must say what computes the metrics: derive it for a file (a rerun resumes only
    # the same work) and for a cluster (every process must compute the same function)
    if key is None and (out or distributed.process_count() > 1):
        fn = metrics_fn if metrics_fn is not None else getattr(evaluate, "metrics_fn", None)
        if fn is None:
            why = ("a rerun with other physics would resume into the same file" if out else
                   "processes computing other physics would mix their rows unnoticed")
            raise SweepError(f"a sweep {'written to out=' if out else 'on several processes'} "
                             "needs key= (what determines the metrics: scene, law, dt, "
                             "duration...) when it is given only a prebuilt evaluate=: "
                             f"without one, {why}.")
        p0 = params0 if metrics_fn is not None else getattr(evaluate, "params0", params0)
        key = {"metrics_fn": function_key(fn, p0)}
        if finalize is not None:    # rows post-processed another way are other results
            key["finalize"] = code_key(finalize, SweepError)
    if getattr(evaluate, "keys", None) is not None:     # what a prebuilt evaluator keeps
        keys = evaluate.keys
    full_key = sweep_key(names, points, params0, keys, shape, key)
    # several processes: all must run the same sweep, split the same way (each process fills
    # its devices' rows from its own chunk); process 0 alone checks, locks, reads and writes
    # ``out`` and hands what it resumed to the others (no shared file system)
    distributed.check_same("sweep (key and points)", key_digest(full_key).encode())
    distributed.check_same("chunk (points per call, diffpen sweep --chunk)",
                           str(min(int(chunk), n)).encode())
    distributed.check_same("out (a file on some processes, none on others)",
                           str(bool(out)).encode())
    # the batch size is part of the result: XLA computes a chunk of 1 point unvectorised and
    # larger chunks vectorised, rounding differently (~5e-10), so a resume with another chunk
    # gave a file equal to neither uninterrupted run
    full_key["chunk"] = int(min(int(chunk), n))
    writer = distributed.is_writer()
    lock = None
    try:
        res = None
        if out:
            out = os.path.abspath(os.fspath(out))
            csv_path = os.path.splitext(out)[0] + ".csv"

            def prepare():
                nonlocal lock
                check_output(out, what="sweep output")
                if os.path.splitext(out)[1].lower() != ".npz":   # its table would be itself
                    raise SweepError(
                        f"out={out} must end in .npz: the results are written to NAME.npz "
                        "and their table to NAME.csv beside it; give NAME.npz (e.g. "
                        f"{os.path.splitext(out)[0]}.npz).")
                check_output(csv_path, what="sweep table", derived_from="out")
                lock = OutputLock(out, what="sweep output").acquire()
                clean_orphans(out)
                clean_orphans(csv_path)
                if os.path.exists(csv_path) and not _own_table(csv_path, out, names):
                    raise SweepError(
                        f"{csv_path} exists and is not the table of a sweep in {out}: the "
                        "sweep writes its table there, which would overwrite it. Move it, or "
                        "choose another output path (diffpen sweep --out).")
                old, unreadable = None, None
                if os.path.exists(out):
                    try:
                        old = _read_key(out)
                    except _Unreadable as exc:
                        unreadable = exc
                    else:
                        if old is None:     # another program's file: never overwritten
                            raise SweepError(
                                f"{out} exists and is not a sweep's results file (not an .npz "
                                "holding a sweep's key): the sweep would overwrite it. Move "
                                "it, or choose another output path (diffpen sweep --out).")
                if not (os.path.exists(out) and resume):
                    return None
                if unreadable is not None:
                    raise SweepError(_unreadable(out, csv_path, unreadable)) from None
                diff = key_differences(old, full_key)
                if diff:
                    raise SweepError(
                        f"{out} holds another sweep's results, so it cannot be resumed: "
                        + "; ".join(diff) + ". Overwrite it with resume=False (diffpen sweep "
                        "--fresh) or choose another output path"
                        + (" (to resume it, give its chunk size again: the points of "
                           "one sweep are computed in equal batches, so that a resumed "
                           "sweep equals one uninterrupted run bit for bit)"
                           if any(d.startswith("chunk") for d in diff) else "") + ".")
                try:                    # its key is intact; a member may still be corrupt
                    return load_sweep(out)
                except Exception as exc:  # noqa: BLE001 - zipfile, zlib and numpy errors
                    raise SweepError(_unreadable(out, csv_path,
                                                 f"{type(exc).__name__}: {exc}")) from None
            res = distributed.from_process_zero(prepare)
            if res is not None:
                res.shape, res.axes = shape, axes
        if evaluate is None:    # an earlier sweep's of the same problem (one compile)
            evaluate = _shared_evaluator(metrics_fn, params0, names, keys, batch_map)
        if res is None:
            res = SweepResult(list(names), points, {}, np.zeros(n, bool), shape, axes)
        res.key = full_key
        res.evaluated = 0
        _run_chunks(res, evaluate, points, chunk, out if writer else None,
                    progress if writer else False, on_chunk, finalize)
    finally:
        if lock is not None:
            lock.release()
    res.seconds = time.perf_counter() - t0
    return res


def _run_chunks(res, evaluate, points, chunk, out, progress, on_chunk, finalize) -> None:
    n = points.shape[0]
    chunk = min(chunk, n)
    n_chunks = -(-n // chunk)
    bar = Progress(n_chunks, "sweep chunks", progress, value="done")
    pair = _Pair(out, res) if out else None
    stopped = True
    try:
        for i in range(n_chunks):
            a, b = i * chunk, min((i + 1) * chunk, n)
            if res.done[a:b].all():
                continue
            _run_chunk(res, evaluate, points, a, b, chunk, finalize)
            if pair is not None:
                pair.chunk_done()
            bar.update(i + 1, float(res.done.mean()))
            if on_chunk is not None:
                on_chunk(i, res)
        stopped = False
    finally:
        if pair is not None:    # chunks the files do not hold yet: finished or stopped
            pair.stop(stopped)
    bar.close()
    if out and res.evaluated == 0 and res.done.any():
        # everything was resumed: write the pair again, so that a run killed between
        # replacing the .npz and its .csv does not leave the table a chunk short for good
        pair.npz_stale = pair.csv_stale = True
        pair.write()


def _warn_unchecked() -> None:
    """Warn (once per sweep, at its first chunk) that its metrics hold no ``"unstable"``
    entry: rows past the safe step would be returned as results (a ball swept to k 1e8 N/m
    at dt 1 ms ended 85 m up, counted stable)."""
    import warnings
    warnings.warn("the sweep's metrics hold no 'unstable' entry, so a point whose rollout "
                  "went past its safe step is returned as a result and result.unstable "
                  "counts nothing: return traj.aux['unstable'][-1] as 'unstable' "
                  "(tuning.stable.rollout_unstable), or False where nothing can go unstable.",
                  UserWarning, stacklevel=5)


def _run_chunk(res, evaluate, points, a, b, chunk, finalize) -> None:
    """Evaluate rows ``a:b`` of ``points`` (padded to the compiled ``chunk``) into ``res``."""
    n = points.shape[0]
    batch = points[a:b]
    if b - a < chunk:     # pad to the compiled batch size
        batch = np.concatenate([batch, np.repeat(batch[-1:], chunk - (b - a), axis=0)])
    got = {k: np.asarray(v)[: b - a]
           for k, v in jax.device_get(evaluate(jnp.asarray(batch))).items()}
    if finalize is not None:
        got = {k: np.asarray(v) for k, v in finalize(dict(got), points[a:b]).items()}
    bad = None
    if UNSTABLE in got:   # past the safe step: never returned as a result
        bad = np.asarray(got[UNSTABLE]).reshape(b - a, -1).any(axis=1)
    elif res.evaluated == 0:          # this run's first chunk
        _warn_unchecked()
    for k, v in got.items():
        if bad is not None and k != UNSTABLE and v.dtype.kind in "fb" and bad.any():
            v = np.array(v)        # a blown-up rollout's "settled" is no result either
            v[bad] = np.nan if v.dtype.kind == "f" else False
        if k not in res.metrics:
            res.metrics[k] = np.full((n,) + v.shape[1:], np.nan if v.dtype.kind == "f"
                                     else 0, dtype=v.dtype)
        res.metrics[k][a:b] = v
    res.done[a:b] = True
    res.evaluated += b - a
    if UNSTABLE in res.metrics:
        res.unstable = int(np.sum(res.done & (np.asarray(res.metrics[UNSTABLE])
                                              .reshape(n, -1).any(axis=1))))
