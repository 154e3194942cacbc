"""A sweep's results and their files: :class:`SweepResult`, the ``.npz`` (every result and
the key) and the ``.csv`` table written beside it as a sweep runs (:class:`_Pair`: when each is
due, and what a stopped sweep writes), and reading them back (:func:`load_sweep`, and the
checks :func:`tuning.sweep.sweep` makes before resuming one). Every file is replaced whole
through :func:`tuning.io.atomic_write`.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np

from .io import atomic_write
from .progress import uninterrupted

__all__ = ["SweepError", "SweepResult", "load_sweep", "CSV_EVERY_S", "NPZ_COST_FACTOR",
           "CSV_ON_STOP_S", "UNSTABLE"]

#: name of the optional per-point metric that flags a rollout past its safe step (from
#: ``traj.aux["unstable"][-1]``); points where it is true are returned as NaN (bool metrics
#: False) and counted.
UNSTABLE = "unstable"


class SweepError(ValueError):
    """A sweep that cannot run as asked (e.g. ``out`` holds another sweep's results)."""


class SweepWriteError(SweepError, OSError):
    """A sweep's file that could not be written (a full disk): the message names it and
    what the files on disk hold."""


def refuse_oversized(points: float, results: float, chunk: str, live: float, work: str,
                     lower_n: str, lower_chunk: str, *, error=SweepError,
                     memory: float | None = None) -> None:
    """Refuse a sweep that cannot fit, before anything is made or compiled: ``results``
    (bytes of the ``points`` points' rows, held in memory, the .npz and the .csv) or ``live``
    (bytes of one chunk's arrays; ``chunk`` says what a chunk is, e.g. "a chunk of 1024
    points x 2000 steps") past half of ``memory`` (default: this machine's). The results'
    message gives ``work`` (the compute, in words) too; each says what to lower
    (``lower_n``, ``lower_chunk``).
    No sweep is refused for its time alone, which a faster device may cut many times.
    Raises ``error`` (:class:`SweepError`; the CLI passes its own)."""
    from diffpen.checks import human_bytes, memory_bytes
    mem = memory_bytes() if memory is None else memory
    if results > 0.5 * mem:
        raise error(f"{points:.0f} points need about {human_bytes(results)} for the results "
                    f"alone (this machine has {human_bytes(mem)}) and {work}: {lower_n}")
    if live > 0.5 * mem:
        raise error(f"{chunk} needs about {human_bytes(live)} (this machine has "
                    f"{human_bytes(mem)}): {lower_chunk}")


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


#: seconds between rewrites of the .csv during a sweep (at least 10x its write time): after
#: every chunk, 65536 points took 56 of 61 s writing text.
CSV_EVERY_S = 30.0

#: the .npz is rewritten once the chunks since its last write took this many times its own
#: write time (so at most ~5% of a sweep goes to writing it, and a run killed outright loses
#: at most that much work): rewritten after every chunk, a 1e6-point sweep's 107 MB file
#: took 0.18 s a chunk against 0.006 s of computing, 30x slower.
NPZ_COST_FACTOR = 20.0

#: a stopped sweep (Ctrl-C, SIGTERM, an error) leaves its .csv as it was when writing it
#: would take longer than this (s; its last write, or 0.5 us a value): a 9e6-point table
#: took 51 s, past the 30 s SLURM allows between SIGTERM and SIGKILL. The .npz is written;
#: a rerun resumes and writes the table.
CSV_ON_STOP_S = 10.0


class _Pair:
    """The .npz and .csv of a running sweep, each rewritten when due (:data:`CSV_EVERY_S`,
    :data:`NPZ_COST_FACTOR`) and both when it ends or stops (:data:`CSV_ON_STOP_S`)."""

    def __init__(self, out: str, res: SweepResult):
        self.out, self.res = out, res
        self.npz_at = self.csv_at = time.perf_counter()
        self.npz_cost = self.csv_cost = 0.0
        self.npz_stale = self.csv_stale = False
        self.saved = int(res.done.sum())     # points done in the .npz on disk

    def chunk_done(self) -> None:
        self.npz_stale = self.csv_stale = True
        now = time.perf_counter()
        if now - self.npz_at >= NPZ_COST_FACTOR * self.npz_cost:
            self.write(csv=now - self.csv_at >= max(CSV_EVERY_S, 10.0 * self.csv_cost))

    def write(self, csv: bool = True) -> None:
        with uninterrupted():
            if self.npz_stale:
                t0 = time.perf_counter()
                self._guarded(_save_npz, self.out)
                self.npz_at = time.perf_counter()
                self.npz_cost, self.npz_stale = self.npz_at - t0, False
                self.saved = int(self.res.done.sum())
            if csv and self.csv_stale:
                t0 = time.perf_counter()
                self._guarded(_save_csv, os.path.splitext(self.out)[0] + ".csv")
                self.csv_at = time.perf_counter()
                self.csv_cost, self.csv_stale = self.csv_at - t0, False

    def _guarded(self, save, path: str) -> None:
        """``save(out, res)``; an OSError (a full disk) is raised again as a
        :class:`SweepError` naming the file and what the last complete .npz holds."""
        try:
            save(self.out, self.res)
        except OSError as exc:
            kept = (f"{self.out} holds the {self.saved} points written before (each file "
                    "is replaced whole or not at all), and a rerun of the same sweep resumes "
                    "from it" if self.saved else
                    f"{self.out} is as it was before this run (each file is replaced whole or "
                    "not at all)")
            raise SweepWriteError(f"could not write {path}: {exc.strerror or exc}. {kept}: "
                                  "free space there or give another output path.") from exc

    def stop(self, stopped: bool) -> None:
        """Write what is stale; a stopped sweep skips a .csv that takes too long."""
        values = self.res.points.size + sum(v.size for v in self.res.metrics.values())
        slow = max(self.csv_cost, 0.5e-6 * values) > CSV_ON_STOP_S
        self.write(csv=not (stopped and slow))
        if self.csv_stale:
            csv_path = os.path.splitext(self.out)[0] + ".csv"
            what = ("was left as it was" if os.path.exists(csv_path) else "was not written")
            print(f"sweep stopped: {self.out} holds the {int(self.res.done.sum())} points "
                  f"done; its table {csv_path} {what} (writing it takes "
                  f"~{max(self.csv_cost, 0.5e-6 * values):.0f} s). Rerun the same sweep: it "
                  "resumes and writes the table.", file=sys.stderr)


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
    """Whether ``csv_path`` is the table :class:`_Pair` wrote beside the sweep file ``out``:
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
