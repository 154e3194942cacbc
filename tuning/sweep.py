"""Batched parameter sweeps: every point's metrics with ``jax.vmap``, chunked, written
atomically, resumable.

A sweep evaluates ``metrics_fn(params)`` at N points of a few parameters (dotted paths, see
:mod:`tuning.params`). Points are processed in chunks of ``chunk``: one chunk is ONE call of a
pure function of a ``(chunk, P)`` batch of parameter values (``jax.jit(jax.vmap(...))`` by
default; pass ``batch_map=tuning.shard.sharded_map`` to split the batch axis across devices),
so memory stays bounded by the chunk. The last chunk is padded to the same shape, so the
whole sweep compiles once.

After every chunk the results so far are written to ``out`` (``.npz``) and a ``.csv`` beside
it, each through a temporary file and ``os.replace`` (a crash never leaves a half-written
file). Calling :func:`sweep` again with the same points and ``out`` resumes: finished chunks
are read back, not recomputed.

Several processes (:mod:`tuning.distributed`): every process calls :func:`sweep` with the same
points; each chunk is split over the devices of all of them and gathered, only process 0
writes ``out`` (and reads it back to resume), and every process returns the same result.
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from . import distributed
from . import params as P
from .fit import Progress

__all__ = ["SweepResult", "grid_points", "random_points", "sweep", "atomic_write",
           "load_sweep", "make_evaluator"]


@dataclasses.dataclass
class SweepResult:
    """Results of :func:`sweep`.

    names: swept parameter paths (P,).  points: (N, P) values, SI units.
    metrics: ``{name: (N, ...) array}`` (nan where not computed or undefined).
    done: (N,) bool, points computed.  shape: grid shape (for grid sweeps) or None; a grid's
    metric reshapes to ``shape + metric.shape[1:]``.  axes: per-parameter grid values.
    seconds: wall time of this call.  evaluated: points computed by this call (the rest were
    read back from ``out``).
    """
    names: list
    points: np.ndarray
    metrics: dict
    done: np.ndarray
    shape: tuple | None = None
    axes: dict | None = None
    seconds: float = 0.0
    evaluated: int = 0

    def grid(self, metric: str, index: int | None = None) -> np.ndarray:
        """A metric on the grid: shape ``self.shape`` (entry ``index`` of a vector metric)."""
        if self.shape is None:
            raise ValueError("not a grid sweep: use .metrics and .points.")
        v = self.metrics[metric]
        if index is not None:
            v = v[:, index]
        return v.reshape(self.shape + v.shape[1:])


def grid_points(axes: dict) -> tuple[np.ndarray, tuple]:
    """All combinations of ``axes = {path: values}`` (first axis slowest).

    Returns (points (N, P), shape)."""
    vals = [np.asarray(v, float).reshape(-1) for v in axes.values()]
    mesh = np.meshgrid(*vals, indexing="ij")
    return np.stack([m.reshape(-1) for m in mesh], axis=1), tuple(len(v) for v in vals)


def random_points(bounds: dict, n: int, *, log: bool = True, seed: int = 0) -> np.ndarray:
    """``n`` random points in the box ``bounds = {path: (lo, hi)}`` (log-uniform when ``log``).

    Returns (n, P)."""
    rng = np.random.default_rng(seed)
    cols = []
    for lo, hi in bounds.values():
        u = rng.random(n)
        cols.append(np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo))) if log
                    else lo + u * (hi - lo))
    return np.stack(cols, axis=1)


def atomic_write(path: str, write: Callable) -> None:
    """Write a file atomically: ``write(fileobj)`` into a temporary file in the same folder,
    flush and fsync it, then ``os.replace`` it onto ``path``. The file gets the permissions a
    plain ``open(path, "w")`` would give it (``mkstemp`` alone makes it owner-only)."""
    folder = os.path.dirname(os.path.abspath(path)) or "."
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.basename(path), dir=folder)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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

    def one(x):
        flat = dict(flat0)
        for i, n in enumerate(names):
            flat[n] = x[i]
        m = metrics_fn(P.unflatten(params0, flat))
        return {k: jnp.asarray(v) for k, v in m.items() if keys is None or k in keys}
    if batch_map is None:
        from .shard import sharded_map
        batch_map = sharded_map      # every device; jax.jit(jax.vmap(f)) on a single one
    return batch_map(one)


def _digest(names, points) -> str:
    h = hashlib.sha256()
    h.update("\n".join(names).encode())
    h.update(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    return h.hexdigest()


def _save(out: str, res: SweepResult, digest: str) -> None:
    arrays = {"names": np.array(res.names), "points": res.points, "done": res.done,
              "digest": np.array(digest),
              "shape": np.array(res.shape if res.shape is not None else (), dtype=np.int64)}
    for k, v in res.metrics.items():
        arrays[f"metric:{k}"] = v
    if res.axes:
        for i, (k, v) in enumerate(res.axes.items()):
            arrays[f"axis:{k}"] = np.asarray(v)
    atomic_write(out, lambda fh: np.savez(fh, **arrays))
    csv_path = os.path.splitext(out)[0] + ".csv"
    cols, header = [res.points[:, i] for i in range(res.points.shape[1])], list(res.names)
    for k, v in res.metrics.items():
        v2 = v.reshape(v.shape[0], -1)
        for j in range(v2.shape[1]):
            cols.append(v2[:, j])
            header.append(k if v2.shape[1] == 1 else f"{k}[{j}]")
    cols.append(res.done.astype(float))
    header.append("done")
    table = np.stack([np.asarray(c, float) for c in cols], axis=1)

    def write_csv(fh):
        fh.write((",".join(header) + "\n").encode())
        np.savetxt(fh, table, delimiter=",", fmt="%.10g")
    atomic_write(csv_path, write_csv)


def load_sweep(path: str) -> SweepResult:
    """Read a sweep written by :func:`sweep` (complete or interrupted)."""
    with np.load(path, allow_pickle=False) as f:
        names = [str(n) for n in f["names"]]
        metrics = {k[7:]: f[k] for k in f.files if k.startswith("metric:")}
        axes = {k[5:]: f[k] for k in f.files if k.startswith("axis:")} or None
        shape = tuple(int(s) for s in f["shape"]) or None
        return SweepResult(names, f["points"], metrics, f["done"], shape, axes)


def _resumed(out: str, digest: str) -> SweepResult | None:
    """The sweep saved at ``out`` if it holds the same names and points, else None."""
    if not os.path.exists(out):
        return None
    try:
        with np.load(out, allow_pickle=False) as f:
            same = str(f["digest"]) == digest
    except Exception:
        same = False
    return load_sweep(out) if same else None


def sweep(metrics_fn: Callable, params0: dp.Params, points, names: list, *,
          chunk: int = 256, out: str | None = None, resume: bool = True,
          keys: list | None = None, shape: tuple | None = None, axes: dict | None = None,
          batch_map: Callable | None = None, progress: bool | None = None,
          on_chunk: Callable | None = None, evaluate: Callable | None = None) -> SweepResult:
    """Evaluate ``metrics_fn`` at every point, ``chunk`` points per vmapped call.

    Args:
      metrics_fn: traceable ``params -> {metric: scalar or (n,) array}``.
      params0: :class:`diffpen.Params` giving the leaves that are not swept.
      points: (N, P) parameter values, SI units.  names: (P,) leaf paths.
      chunk: points per call (bounds memory; the last chunk is padded, never recompiled).
      out: ``.npz`` path; results (and a ``.csv`` beside it) are written atomically after
        every chunk.  resume: continue an interrupted sweep found at ``out`` (same names and
        points, else it is started afresh).
      keys: metrics to keep (default all).  shape, axes: grid layout (see :func:`grid_points`).
      batch_map: lifts the per-point function to a batch (default
        :func:`tuning.shard.sharded_map`: split over all devices with a ``NamedSharding``;
        ``jax.jit(jax.vmap(f))`` on a single device).
      on_chunk: ``on_chunk(i_chunk, result)`` after each chunk is saved.
      evaluate: a prebuilt :func:`make_evaluator` (reuse it across sweeps of one problem so
        that they share one compiled program).
    Returns: :class:`SweepResult`.
    """
    t0 = time.perf_counter()
    points = np.asarray(points, float)
    if points.ndim != 2 or points.shape[1] != len(names):
        raise ValueError(f"points must have shape (N, {len(names)}), got {points.shape}.")
    if not np.all(np.isfinite(points)) or np.any(points < 0.0):
        raise ValueError("sweep points must be finite and >= 0 (stiffness and damping).")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}.")
    n = points.shape[0]
    digest = _digest(names, points)
    # several processes: all must sweep the same points; process 0 alone reads and writes
    # ``out`` and hands what it resumed to the others (no shared file system needed)
    distributed.check_same("sweep (names and points)", digest.encode())
    writer = distributed.is_writer()
    res = distributed.from_process_zero(lambda: _resumed(out, digest) if out and resume
                                        else None)
    if res is not None:
        res.shape, res.axes = shape, axes
    if evaluate is None:
        evaluate = make_evaluator(metrics_fn, params0, names, keys, batch_map)
    if res is None:
        res = SweepResult(list(names), points, {}, np.zeros(n, bool), shape, axes)
    chunk = min(chunk, n)
    n_chunks = -(-n // chunk)
    bar = Progress(n_chunks, "sweep", progress if writer else False)
    evaluated = 0
    for i in range(n_chunks):
        a, b = i * chunk, min((i + 1) * chunk, n)
        if res.done[a:b].all():
            continue
        batch = points[a:b]
        if b - a < chunk:     # pad to the compiled batch size
            batch = np.concatenate([batch, np.repeat(batch[-1:], chunk - (b - a), axis=0)])
        got = jax.device_get(evaluate(jnp.asarray(batch)))
        for k, v in got.items():
            v = np.asarray(v)[: b - a]
            if k not in res.metrics:
                res.metrics[k] = np.full((n,) + v.shape[1:], np.nan if v.dtype.kind == "f"
                                         else 0, dtype=v.dtype)
            res.metrics[k][a:b] = v
        res.done[a:b] = True
        evaluated += b - a
        if out and writer:
            _save(out, res, digest)
        bar.update(i + 1, float(res.done.mean()))
        if on_chunk is not None:
            on_chunk(i, res)
    bar.close()
    res.seconds = time.perf_counter() - t0
    res.evaluated = evaluated
    return res
