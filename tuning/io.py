"""Result files: output checks before computing, atomic writes, a lock per output, leftovers
of killed runs, and the key of everything that determines a result.

* :func:`check_output` says, before anything is computed, why a path cannot be written
  (missing parent folder, a directory, no write permission); :func:`check_plot` also that
  a figure can be saved under that name (a file type matplotlib writes);
  :func:`check_distinct` that no output is one of the run's inputs or another output.
* :func:`atomic_write` writes through a temporary file in the output's own folder and
  ``os.replace`` (a crash never leaves a half-written file; the temporary file is never put
  anywhere else, e.g. in ``/``); :func:`save_figure_file` saves a figure that way. Every
  path is followed through symbolic links to the file they name.
* :class:`OutputLock` holds an exclusive ``fcntl`` lock on ``.<name>.lock`` beside the output
  for the whole run: a second writer of the same output is refused at once with the first
  writer's pid. The kernel drops the lock when a process dies, so a killed run never blocks
  the next one.
* :func:`clean_orphans` removes the temporary files a killed writer left behind (call it while
  holding the lock: no live writer of that output can own them then).
* :func:`result_key` / :func:`key_differences`: a result file stores a JSON key of everything
  that determines it (scene, law, integrator, dt, duration, metrics, grid, dtype, version);
  a run resumes from a file only when the keys are equal, and otherwise says what differs.
"""
from __future__ import annotations

import errno
import glob
import hashlib
import json
import math
import os
import sys
import tempfile
from typing import Callable

import numpy as np

__all__ = ["OutputError", "check_output", "check_plot", "check_distinct", "PLOT_TYPES",
           "atomic_write", "save_figure_file", "OutputLock", "clean_orphans",
           "result_key", "key_digest", "key_differences", "describe_simulator", "version",
           "source_digest", "runtime",
           "TMP_PREFIX"]

#: prefix of the temporary files of :func:`atomic_write` (``.tmp-XXXX<basename>``)
TMP_PREFIX = ".tmp-"


class OutputError(ValueError):
    """An output path that cannot be written, or is held by another writer. The message says
    what to change (raised before anything is computed)."""


def version() -> str:
    """The installed diffpen version (part of every result key)."""
    try:
        from importlib.metadata import version as _v
        return _v("diffpen")
    except Exception:  # noqa: BLE001 - a plain checkout without metadata
        return "unknown"


def source_digest() -> str:
    """SHA-256 (16 hex digits) of the Python source on disk of the ``diffpen`` and ``tuning``
    packages this process imported: every regular ``.py`` file under them (by relative path
    and bytes; names and folders starting with ``.`` and ``__pycache__`` left out: an
    editor's lock file, a notebook's checkpoints), read at each call (~4 ms). A file edited
    on disk counts at once, also where this process still runs the module it imported
    before the edit (restart or reload it before writing results). Part of every result
    key beside :func:`version`: the version number stays the same while the code changes (an
    editable install, a ``git pull``), and a resumed sweep or fit would otherwise mix rows
    computed by two versions of the code. Any edit changes it, comments too, and so does a
    stray ``.py`` file."""
    import diffpen
    h = hashlib.sha256()
    for pkg in (diffpen, sys.modules[__package__]):
        root = os.path.dirname(os.path.abspath(pkg.__file__))
        files = []
        for folder, dirs, names in os.walk(root):
            dirs[:] = sorted(d for d in dirs if d != "__pycache__" and not d.startswith("."))
            files += [p for p in (os.path.join(folder, n) for n in names
                                  if n.endswith(".py") and not n.startswith("."))
                      if os.path.isfile(p)]
        for path in sorted(files):
            h.update(os.path.relpath(path, os.path.dirname(root)).encode() + b"\0")
            with open(path, "rb") as fh:
                h.update(hashlib.sha256(fh.read()).digest())
    return h.hexdigest()[:16]


def runtime() -> dict:
    """``{"jax": ..., "jaxlib": ..., "backend": ...}``: what compiles and runs the programs
    (part of every result key: another XLA, or a GPU instead of the CPU, rounds differently)."""
    import jax
    try:
        import jaxlib
        lib = jaxlib.__version__
    except Exception:  # noqa: BLE001 - jaxlib is a dependency of jax
        lib = "unknown"
    return {"jax": jax.__version__, "jaxlib": lib, "backend": jax.default_backend()}


def file_digest(path: str) -> str:
    """SHA-256 (16 hex digits) of a file's bytes: a key field that names a changed input, and
    what tells two record files with the same contents apart from two records."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


# --------------------------------------------------------------------------- paths
def check_output(path, *, what: str = "output", ext: str | None = None,
                 derived_from: str | None = None) -> str:
    """Check that ``path`` can be written as a file; return it as an absolute path.

    Raises :class:`OutputError` naming ``what`` (e.g. ``"--out"``; ``ext``: the file type its
    example name suggests, default by ``what``) when the path is empty, is
    a directory, its parent folder does not exist or is not a folder, or either cannot be
    written. The folder is probed by creating a temporary file there and removing it
    (:func:`os.access` passes for root in read-only folders and on filesystems that ignore
    it, and the write then failed after the computation); the output itself is not
    touched. ``derived_from``: the option or argument the path's name
    follows from (e.g. ``"--out"`` for the ``.csv`` table beside ``--out NAME.npz``): its
    name cannot be given, so a directory or a read-only file there is to be moved or
    removed, or that option changed.
    """
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise OutputError(f"{what} must be a file path, got {path!r}.")
    # a symbolic link's target is what gets written (os.replace onto the link itself
    # turned it into a plain file beside the target, which kept the interrupted run's rows)
    p = os.path.realpath(os.fspath(path))
    if derived_from and os.path.isdir(p):
        raise OutputError(f"{what} {path} is a directory: its name follows from "
                          f"{derived_from}, so move or remove that folder, or choose another "
                          f"{derived_from}.")
    if os.path.isdir(p) or str(path).endswith(os.sep):
        raise OutputError(f"{what} {path} is a directory: give a file name inside it, e.g. "
                          f"{os.path.join(str(path), 'result' + (ext or _ext(what)))}.")
    folder = os.path.dirname(p)
    if not os.path.exists(folder):
        raise OutputError(f"{what} {path}: the folder {folder} does not exist; create it "
                          "first or choose another path.")
    if not os.path.isdir(folder):
        raise OutputError(f"{what} {path}: {folder} is not a folder.")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {path}: the folder {folder} is not writable; choose "
                          "another path.")
    try:            # named as atomic_write names its files: clean_orphans finds a leftover
        fd, probe = tempfile.mkstemp(prefix=TMP_PREFIX, suffix=os.path.basename(p), dir=folder)
    except OSError as exc:
        raise OutputError(f"{what} {path}: cannot create a file in {folder} "
                          f"({exc.strerror}); choose another path.") from None
    os.close(fd)
    os.unlink(probe)
    if os.path.exists(p) and not os.access(p, os.W_OK):
        raise OutputError(f"{what} {path} exists and is not writable; " + (
            f"make it writable, move it, or choose another {derived_from}." if derived_from
            else "choose another path."))
    return p


def _ext(what: str) -> str:
    return ".png" if "plot" in what else ".npz"


#: file types a figure can be saved as (matplotlib's Agg backend writes all of them)
PLOT_TYPES = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".eps", ".ps", ".tif", ".tiff")


def check_plot(path, *, what: str = "--plot") -> str:
    """:func:`check_output` for a figure, and its name must end in one of :data:`PLOT_TYPES`
    (matplotlib picks the format from it: an unknown one fails only once the figure is
    drawn, after the computation, and a name without one is written with ``.png`` added,
    another file than the one named). Returns the absolute path."""
    p = check_output(path, what=what, ext=".png")
    if os.path.splitext(p)[1].lower() not in PLOT_TYPES:
        raise OutputError(f"{what} {path}: a figure's name must end in one of "
                          f"{', '.join(PLOT_TYPES)} (it sets the file type), e.g. "
                          f"{os.path.splitext(str(path))[0]}.png.")
    return p


def _same_file(a: str, b: str) -> bool:
    a, b = os.path.abspath(os.fspath(a)), os.path.abspath(os.fspath(b))
    if os.path.exists(a) and os.path.exists(b):
        return os.path.samefile(a, b)
    return os.path.normcase(os.path.realpath(a)) == os.path.normcase(os.path.realpath(b))


def check_distinct(outputs: dict, inputs=()) -> None:
    """Refuse, before anything is computed, an output that is one of the ``inputs`` (a scene
    file, a record: it would be overwritten) or the same file as another output (one would
    overwrite the other). ``outputs``: {what it is (e.g. ``"--out"``): path}; None paths are
    skipped. Raises :class:`OutputError` naming both."""
    named = [(w, p) for w, p in outputs.items() if p]
    for i, (what, path) in enumerate(named):
        for src in inputs:
            if src and _same_file(path, src):
                raise OutputError(f"{what} {path} is one of the inputs ({src}): writing it "
                                  "would overwrite it; choose another name.")
        for other, opath in named[:i]:
            if _same_file(path, opath):
                raise OutputError(f"{what} {path} is the same file as {other} {opath}: one "
                                  "would overwrite the other; choose another name.")


def plain_mode(path) -> None:
    """Give ``path`` the permissions a plain ``open(path, "w")`` would (``0o666`` less the
    umask): ``tempfile.mkstemp`` makes its files owner-only."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def atomic_write(path, write: Callable, check: Callable | None = None) -> None:
    """Write a file atomically: ``write(fileobj)`` into a temporary file in the same folder,
    flush and fsync it, then ``os.replace`` it onto ``path``. The file gets the permissions a
    plain ``open(path, "w")`` would give it (``mkstemp`` alone makes it owner-only). The
    parent folder must exist (see :func:`check_output`). A symbolic link is followed: its
    target is replaced and the link kept. ``check(temporary path)``, when given, reads the
    written file back before the rename; an exception it raises leaves ``path`` as it was."""
    p = os.path.realpath(os.fspath(path))
    folder = os.path.dirname(p)
    fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, suffix=os.path.basename(p), dir=folder)
    try:
        plain_mode(tmp)
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        if check is not None:
            check(tmp)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_figure_file(fig, path, **savefig) -> None:
    """``fig.savefig(path, **savefig)`` written atomically (:func:`atomic_write`): a run
    stopped while drawing leaves the figure that was there, not an empty or half-written
    file. The file type follows the name's extension (:data:`PLOT_TYPES`)."""
    fmt = os.path.splitext(os.fspath(path))[1][1:].lower() or "png"
    atomic_write(path, lambda fh: fig.savefig(fh, format=fmt, **savefig))


def clean_orphans(path) -> list:
    """Remove temporary files of :func:`atomic_write` for ``path`` left by a killed writer.

    Only call it while holding :class:`OutputLock` on ``path`` (a live writer's temporary file
    would otherwise be removed). Returns the removed paths."""
    p = os.path.realpath(os.fspath(path))
    folder, base = os.path.dirname(p), os.path.basename(p)
    removed = []
    for f in glob.glob(os.path.join(glob.escape(folder), glob.escape(TMP_PREFIX) + "*"
                                    + glob.escape(base))):
        name = os.path.basename(f)
        # mkstemp's name: prefix + 8 random characters + basename
        if len(name) == len(TMP_PREFIX) + 8 + len(base):
            try:
                os.unlink(f)
                removed.append(f)
            except FileNotFoundError:
                pass
    return removed


class OutputLock:
    """Exclusive lock on an output path for one writer (``with OutputLock(path): ...``).

    The lock is an ``fcntl.flock`` on ``.<basename>.lock`` beside the output, holding the
    writer's pid; the file is removed on release. A second writer raises
    :class:`OutputError` at once (no waiting). A killed writer's lock is released by the
    kernel; its stale lock file is taken over.
    """

    def __init__(self, path, *, what: str = "output"):
        # the target of a symbolic link: writers through the link and through the file
        # itself take the same lock
        p = os.path.realpath(os.fspath(path))
        self.path = p
        self.what = what
        self.lock_path = os.path.join(os.path.dirname(p), "." + os.path.basename(p) + ".lock")
        self._fd = None

    def acquire(self) -> "OutputLock":
        import fcntl
        while True:
            try:
                fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:      # e.g. a folder that takes no new files (/proc)
                raise OutputError(f"{self.what} {self.path}: cannot create a file in "
                                  f"{os.path.dirname(self.lock_path)} ({exc.strerror}); "
                                  "choose another path.") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise
                pid = ""
                try:
                    with open(self.lock_path) as fh:
                        pid = fh.read().strip()
                except OSError:
                    pass
                raise OutputError(
                    f"{self.what} {self.path} is being written by another process"
                    + (f" (pid {pid})" if pid else "") + f" holding {self.lock_path}: wait for "
                    "it to finish or choose another output path.") from None
            # the file may have been unlinked by the previous holder between open and flock
            try:
                same = os.fstat(fd).st_ino == os.stat(self.lock_path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        import fcntl
        try:
            os.unlink(self.lock_path)
        except FileNotFoundError:
            pass
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# --------------------------------------------------------------------------- keys
def _plain(v):
    """JSON-safe, canonical form of a key value (floats kept exactly via repr)."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in sorted(v.items(), key=lambda kv: str(kv[0]))}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        if v.ndim == 0:
            return _plain(v.item())
        if v.size > 16:
            return "sha256:" + hashlib.sha256(
                np.ascontiguousarray(v, dtype=np.float64).tobytes()).hexdigest()[:16]
        return [_plain(x) for x in v.tolist()]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return repr(f) if not math.isfinite(f) else f
    if v is None or isinstance(v, str):
        return v
    try:
        return _plain(np.asarray(v))
    except Exception:  # noqa: BLE001
        return repr(v)


def result_key(**fields) -> dict:
    """A canonical, JSON-safe key of the fields that determine a result; adds ``version``,
    ``source`` (:func:`source_digest`: the code that computed it) and ``runtime``
    (:func:`runtime`: jax, jaxlib and the backend).

    Arrays longer than 16 values are stored as their SHA-256 digest."""
    key = {k: _plain(v) for k, v in fields.items()}
    key.setdefault("version", version())
    key.setdefault("source", source_digest())
    key.setdefault("runtime", runtime())
    return dict(sorted(key.items()))


def key_digest(key: dict) -> str:
    """SHA-256 of a key's canonical JSON."""
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def key_differences(old: dict | None, new: dict) -> list:
    """``["field: file has A, this run has B", ...]`` for every field that differs. Fields
    holding dicts, and lists of dicts or lists of equal length, are compared entry by entry
    (``simulator.scene``, ``records.3.pos``), so that only what differs is named; values
    longer than 120 characters are cut."""
    if old is None:
        return ["the file has no key (written by an older version or another program)"]
    out = []
    _differences("", old, new, out)
    return [line + ((" (the file was written before keys held it)"
                     if 'file has "<absent>"' in line else _WHY[field])
                    if field in _WHY else "")
            for line, field in ((ln, ln.split(":")[0].split(".")[0]) for ln in out)]


#: what a difference in these key fields means, added to its line
_WHY = {"source": " (the diffpen or tuning source changed since the file was written, by some "
                  "edit: resuming could mix results of two versions of the code)",
        "runtime": " (another jax, jaxlib or device computes it, rounding differently)"}


def _differences(name: str, a, b, out: list) -> None:
    if a == b:
        return
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            _differences(f"{name}.{k}" if name else str(k), a.get(k, "<absent>"),
                         b.get(k, "<absent>"), out)
        return
    if (isinstance(a, list) and isinstance(b, list) and len(a) == len(b)
            and any(isinstance(v, (dict, list)) for v in a + b)):
        for i, (u, v) in enumerate(zip(a, b)):
            _differences(f"{name}.{i}", u, v, out)
        return
    sa, sb = json.dumps(a), json.dumps(b)
    if len(sa) > 120:
        sa = sa[:117] + "..."
    if len(sb) > 120:
        sb = sb[:117] + "..."
    out.append(f"{name}: file has {sa}, this run has {sb}")


def describe_simulator(sim) -> dict:
    """Key fields of a compiled :class:`diffpen.Simulator`: the scene's records (bodies,
    springs, colliders, materials, gravity), law, integrator, dt, substeps, smoothing, dtype."""
    scene = sim.scene
    records = {k: repr(v) for k, v in sorted(vars(scene).items()) if not k.startswith("_")}
    return {"scene": hashlib.sha256(json.dumps(records, sort_keys=True).encode()).hexdigest()[:16],
            "n_bodies": int(sim.n_bodies), "law": sim.law, "integrator": sim.integrator,
            "dt": float(sim.dt), "smoothing": float(sim.smoothing),
            "exponent": float(getattr(sim, "exponent", 1.0)),
            "broadphase": repr(getattr(sim, "broadphase", None)),
            "substeps": repr(getattr(sim, "substeps", 1)),
            "dtype": str(np.dtype(sim.dtype))}
