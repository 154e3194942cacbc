"""Batched parameter sweeps: every point's metrics with ``jax.vmap``, chunked, written
atomically, resumable.

A sweep evaluates ``metrics_fn(params)`` at N points of a few parameters (dotted paths, see
:mod:`tuning.params`). Points are processed in chunks of ``chunk``: one chunk is ONE call of a
pure function of a ``(chunk, P)`` batch of parameter values (``jax.jit(jax.vmap(...))`` by
default; pass ``batch_map=tuning.shard.sharded_map`` to split the batch axis across devices),
so memory stays bounded by the chunk. The last chunk is padded to the same shape, so the
whole sweep compiles once.

After every chunk the results so far are written to ``out`` (``.npz``), and a ``.csv`` beside
it at the end (also of an interrupted run) and every :data:`CSV_EVERY_S` seconds, each through
a temporary file and ``os.replace`` (never half-written; :mod:`tuning.io`). The file carries a
key of everything that determines it (:func:`sweep_key`); calling :func:`sweep` again with the same key and ``out`` resumes:
finished chunks are read back, not recomputed. Another key is refused with the list of what
differs (``resume=False`` overwrites). One writer per output (a lock), checked paths before
any computing, and temporary files of a killed run are removed.

Several processes (:mod:`tuning.distributed`): every process calls :func:`sweep` with the same
points, key and chunk (processes given others stop at once with the same error); each chunk
is split over the devices of all of them and gathered, only process 0 checks, locks, reads (to
resume) and writes ``out``, and every process returns the same result.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from . import distributed
from . import params as P
from .compiled import ProgramCache, frozen_key
from .io import (OutputLock, _plain, atomic_write, check_output, clean_orphans,
                 key_differences, key_digest, result_key)
from .points import grid_points, random_points  # noqa: F401  (public here too)
from .progress import Progress, uninterrupted

__all__ = ["SweepResult", "SweepError", "grid_points", "random_points", "sweep",
           "atomic_write", "load_sweep", "make_evaluator", "sweep_key", "function_key",
           "UNSTABLE"]

#: name of the optional per-point metric that flags a rollout past its safe step (from
#: ``traj.aux["unstable"][-1]``); points where it is true are returned as NaN (bool metrics
#: False) and counted.
UNSTABLE = "unstable"


class SweepError(ValueError):
    """A sweep that cannot run as asked (e.g. ``out`` holds another sweep's results)."""


@dataclasses.dataclass
class SweepResult:
    """Results of :func:`sweep`.

    names: swept parameter paths (P,).  points: (N, P) values, SI units.
    metrics: ``{name: (N, ...) array}`` (nan where not computed or undefined).
    done: (N,) bool, points computed.  shape: grid shape (for grid sweeps) or None; a grid's
    metric reshapes to ``shape + metric.shape[1:]``.  axes: per-parameter grid values.
    seconds: wall time of this call.  evaluated: points computed by this call (the rest were
    read back from ``out``).  key: the key stored with the results (see :func:`sweep_key`).
    unstable: points whose rollout went past its safe step (their float metrics are NaN,
    their bool metrics False).
    """
    names: list
    points: np.ndarray
    metrics: dict
    done: np.ndarray
    shape: tuple | None = None
    axes: dict | None = None
    seconds: float = 0.0
    evaluated: int = 0
    key: dict | None = None
    unstable: int = 0

    def grid(self, metric: str, index: int | None = None) -> np.ndarray:
        """A metric on the grid: shape ``self.shape`` (entry ``index`` of a vector metric)."""
        if self.shape is None:
            raise ValueError("not a grid sweep: use .metrics and .points.")
        v = self.metrics[metric]
        if index is not None:
            v = v[:, index]
        return v.reshape(self.shape + v.shape[1:])


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
            # in the leaf's own dtype: a float64 batch set into float32 params made what
            # the metrics compute from them (a resting height from k) float64
            flat[n] = x[i].astype(jnp.result_type(flat0[n]))
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


def _data(v) -> bool:
    """Plain data (numbers, strings, arrays and lists of them): stored by value in a key."""
    if isinstance(v, np.ndarray):
        return v.dtype.kind in "biuf"
    if v is None or isinstance(v, (bool, int, float, str, np.number, np.bool_)):
        return True
    if isinstance(v, (list, tuple)):
        return all(_data(x) for x in v)
    if isinstance(v, dict):
        return all(isinstance(k, str) and _data(x) for k, x in v.items())
    return False


def _code_key(fn: Callable) -> str:
    """``"module.name sha256:..."``: a digest of a Python function's own code (its bytecode,
    constants and names, those of functions defined in it, and the values of the numbers,
    strings and arrays it closes over or takes as defaults; of anything else only the type).
    A sweep written to ``out`` without ``key=`` stores it for ``finalize=``, so that a rerun
    post-processing its rows another way is refused. What it calls is not followed. Raises
    :class:`SweepError` for a callable without code of its own (a ``functools.partial``, an
    object with ``__call__``)."""
    code = getattr(fn, "__code__", None)
    if code is None:
        raise SweepError(f"a sweep written to out= needs key= when finalize= is not a plain "
                         f"function (got {type(fn).__name__}): say what it does in the key.")
    h = hashlib.sha256()

    def feed(const):
        if hasattr(const, "co_code"):                # the function, or one defined inside
            h.update(const.co_code)
            h.update(repr(const.co_names).encode())
            for c in const.co_consts:
                feed(c)
        elif isinstance(const, tuple):
            h.update(b"(")
            for c in const:
                feed(c)
            h.update(b")")
        elif isinstance(const, frozenset):           # set literals: no stable order
            h.update(repr(sorted(map(repr, const))).encode())
        else:
            h.update(repr(const).encode())
    feed(code)
    values = list(getattr(fn, "__defaults__", None) or ())
    values += sorted((getattr(fn, "__kwdefaults__", None) or {}).items())
    for cell in getattr(fn, "__closure__", None) or ():
        try:
            values.append(cell.cell_contents)
        except ValueError:                           # a cell not yet filled
            values.append(None)
    for v in values:
        h.update((json.dumps(_plain(v)) if _data(v)
                  else type(v).__qualname__).encode())
    name = f"{getattr(fn, '__module__', '')}.{getattr(fn, '__qualname__', type(fn).__name__)}"
    return f"{name} sha256:{h.hexdigest()[:16]}"


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


#: seconds between rewrites of the .csv during a sweep (at least 10x its write time): after
#: every chunk, 65536 points took 56 of 61 s writing text. The .npz follows every chunk.
CSV_EVERY_S = 30.0


def _save(out: str, res: SweepResult, csv: bool = True) -> float:
    """Write the .npz and, with ``csv``, the .csv (each atomic; a command's Ctrl-C waits
    until both are replaced). Returns the seconds the .csv took (0 without it)."""
    with uninterrupted():
        _save_npz(out, res)
        if not csv:
            return 0.0
        t0 = time.perf_counter()
        _save_csv(out, res)
        return time.perf_counter() - t0


def _save_npz(out: str, res: SweepResult) -> None:
    arrays = {"names": np.array(res.names), "points": res.points, "done": res.done,
              "key": np.array(json.dumps(res.key or {})),
              "shape": np.array(res.shape if res.shape is not None else (), dtype=np.int64)}
    for k, v in res.metrics.items():
        arrays[f"metric:{k}"] = v
    if res.axes:
        for i, (k, v) in enumerate(res.axes.items()):
            arrays[f"axis:{k}"] = np.asarray(v)
    atomic_write(out, lambda fh: np.savez(fh, **arrays))


def _save_csv(out: str, res: SweepResult) -> None:
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
        # 17 significant digits: every float64 reads back as the value simulated
        np.savetxt(fh, table, delimiter=",", fmt="%.17g")
    atomic_write(csv_path, write_csv)


class _Unreadable(Exception):
    """A file at a sweep's ``out`` that is a zip archive (or empty) but cannot be read
    through: truncated, corrupt. Its message says why."""


#: how a zip archive (an .npz) starts: a first member, or the end record of an empty one
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


def _read_head(path: str) -> tuple:
    """``(key, names)`` of the sweep file at ``path``; ``(None, None)`` for a readable file
    that is not one (not an .npz, or an .npz without a key: foreign). Raises
    :class:`_Unreadable` for an empty file or an .npz that cannot be read (truncated,
    corrupt)."""
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise _Unreadable(exc.strerror or str(exc)) from None
    if not magic:
        raise _Unreadable("it is empty")
    if magic not in _ZIP_MAGIC:
        return None, None                       # not an .npz: another program's file
    try:
        with np.load(path, allow_pickle=False) as f:
            if "key" not in f.files:
                return None, None
            key = json.loads(str(f["key"]))
            names = [str(n) for n in f["names"]]
    except Exception as exc:  # noqa: BLE001 - zipfile, zlib, numpy and json errors alike
        raise _Unreadable(f"{type(exc).__name__}: {exc}") from None
    return (key, names) if isinstance(key, dict) else (None, None)


def _read_key(path: str):
    """The key stored in a sweep file, or None (a readable file that is not a sweep file).
    Raises :class:`_Unreadable` for a file that cannot be read (truncated, corrupt)."""
    return _read_head(path)[0]


def _own_table(csv_path: str, out: str, names=None) -> bool:
    """Whether ``csv_path`` is the table :func:`_save` wrote beside the sweep file ``out``:
    its header is the swept names ... ``done``. The names are those stored in ``out``; when
    ``out`` cannot be read (truncated, corrupt: it can only be overwritten), ``names`` (this
    run's swept names), so that ``resume=False`` replaces both files. False when ``out`` is
    missing or not a sweep file, or the table is not text."""
    if not os.path.exists(out):
        return False
    try:
        _, names = _read_head(out)
    except _Unreadable:
        names = None if names is None else [str(n) for n in names]
    if names is None:
        return False
    try:
        with open(csv_path, "rb") as fh:
            header = fh.readline(1 << 16).decode().strip().split(",")
    except Exception:  # noqa: BLE001 - a table that cannot be read or is not text
        return False
    return len(header) > len(names) and header[:len(names)] == names and header[-1] == "done"


def _unreadable(out: str, csv_path: str, why) -> str:
    return (f"{out} cannot be read ({why}): a truncated or corrupt sweep file, so it cannot "
            f"be resumed. Overwrite it and its table {os.path.basename(csv_path)} with "
            "resume=False (diffpen sweep --fresh), or choose another output path.")


def load_sweep(path: str) -> SweepResult:
    """Read a sweep written by :func:`sweep` (complete or interrupted)."""
    with np.load(path, allow_pickle=False) as f:
        names = [str(n) for n in f["names"]]
        metrics = {k[7:]: f[k] for k in f.files if k.startswith("metric:")}
        axes = {k[5:]: f[k] for k in f.files if k.startswith("axis:")} or None
        shape = tuple(int(s) for s in f["shape"]) or None
        key = json.loads(str(f["key"])) if "key" in f.files else None
        res = SweepResult(names, f["points"], metrics, f["done"], shape, axes, key=key)
    if UNSTABLE in res.metrics:
        res.unstable = int(np.sum(res.done & (np.asarray(res.metrics[UNSTABLE]) > 0)))
    return res


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
        ``settled``) False, and they are counted in ``result.unstable``.
      params0: :class:`diffpen.Params` giving the leaves that are not swept.
      points: (N, P) parameter values, SI units.  names: (P,) leaf paths.
      chunk: points per call (bounds memory; the last chunk is padded, never recompiled).
      out: ``NAME.npz`` path (any other name raises :class:`SweepError`: the table is
        written to ``NAME.csv`` beside it); results and table are written atomically after
        every chunk. The paths are checked before anything is computed (a ``.csv`` there
        that is not the table of the sweep in ``out`` is refused, never overwritten), and an
        exclusive lock (``.<name>.lock`` beside it) keeps a second writer out.
      resume: continue a sweep found at ``out`` when its key equals this sweep's (see
        :func:`sweep_key`); a file with another key raises :class:`SweepError` naming what
        differs, and so does one that cannot be read (truncated, corrupt).
        ``resume=False`` overwrites ``out`` (an unreadable one and its table too).
      key: what determines ``metrics_fn`` beyond the swept leaves (scene, law, integrator,
        dt, duration, metric settings...): stored in the file and compared on resume
        (:func:`tuning.io.describe_simulator` builds most of it). With ``out`` and no key,
        the key is :func:`function_key` of ``metrics_fn`` (or of the function a
        :func:`make_evaluator` evaluator was built from; any other ``evaluate`` needs a
        key) and a digest of ``finalize``'s code: a rerun computing anything else is
        refused, never mixed in.
      keys: metrics to keep (default all; a :func:`make_evaluator` evaluator's own ``keys``
        when it was given some: the key holds the metrics it keeps).
      shape, axes: grid layout (see :func:`grid_points`).
      batch_map: lifts the per-point function to a batch (default
        :func:`tuning.shard.sharded_map`: split over all devices with a ``NamedSharding``;
        ``jax.jit(jax.vmap(f))`` on a single device).
      on_chunk: ``on_chunk(i_chunk, result)`` after each chunk is saved.
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
            key["finalize"] = _code_key(finalize)
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
                        "--fresh) or choose another output path.")
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
    csv_at, csv_cost, stale = time.perf_counter(), 0.0, False
    try:
        for i in range(n_chunks):
            a, b = i * chunk, min((i + 1) * chunk, n)
            if res.done[a:b].all():
                continue
            _run_chunk(res, evaluate, points, a, b, chunk, finalize)
            if out:
                due = time.perf_counter() - csv_at >= max(CSV_EVERY_S, 10.0 * csv_cost)
                stale = True        # until the .csv is written (an interrupt may end _save)
                cost = _save(out, res, csv=due)
                if due:
                    csv_at, csv_cost, stale = time.perf_counter(), cost, False
            bar.update(i + 1, float(res.done.mean()))
            if on_chunk is not None:
                on_chunk(i, res)
    finally:
        if stale:           # the .npz holds chunks the .csv does not: finished or stopped
            with uninterrupted():
                _save_csv(out, res)
    bar.close()
    if out and res.evaluated == 0 and res.done.any():
        # everything was resumed: write the pair again, so that a run killed between
        # replacing the .npz and its .csv does not leave the table a chunk short for good
        _save(out, res)


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
