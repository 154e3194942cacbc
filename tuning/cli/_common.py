"""Helpers shared by the ``diffpen`` subcommands (argument checks, printing, JAX setup)."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys


class CLIError(argparse.ArgumentTypeError):
    """A bad command line: printed as ``diffpen <cmd>: error: ...`` with exit status 2."""


def setup_jax(x64: bool = True) -> None:
    """float64 for fitting accuracy, and a persistent compilation cache that keeps every
    compiled program, however small or quick to compile, so that a second run of the same
    command compiles nothing (most of the default fit's programs are small eager operations
    that take 5-70 ms each to compile: JAX's default thresholds would skip them).

    The cache lives in ``$DIFFPEN_CACHE_DIR``, else ``$JAX_COMPILATION_CACHE_DIR``, else
    ``~/.cache/diffpen/jax``; ``DIFFPEN_CACHE=0`` turns it off."""
    import jax
    if x64:
        jax.config.update("jax_enable_x64", True)
    if os.environ.get("DIFFPEN_CACHE", "1") != "0":
        path = (os.environ.get("DIFFPEN_CACHE_DIR")
                or os.environ.get("JAX_COMPILATION_CACHE_DIR")
                or os.path.join(os.path.expanduser("~"), ".cache", "diffpen", "jax"))
        try:
            os.makedirs(path, exist_ok=True)
            jax.config.update("jax_compilation_cache_dir", path)
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
            jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
        except Exception:        # a read-only home must not stop the command
            pass


def add_cluster_arguments(p) -> None:
    """``--coordinator HOST:PORT --num-processes N --process-id I``: run as one process of a
    cluster (without them a SLURM ``srun`` or Open MPI ``mpirun`` launch is detected)."""
    g = p.add_argument_group("cluster (several processes or hosts; see the README, "
                             "'Beyond one machine')")
    g.add_argument("--coordinator", metavar="HOST:PORT",
                   help="address of process 0, the same on every process")
    g.add_argument("--num-processes", type=int, metavar="N", help="processes in all")
    g.add_argument("--process-id", type=int, metavar="I", help="this process, 0..N-1")
    g.add_argument("--cluster-timeout", type=count("--cluster-timeout"), default=300,
                   metavar="S", help="seconds to wait for every process to join before "
                   "failing (default 300); a process that stops or stays silent for "
                   "min(S, 10) s stops the others (exit status 2)")


def in_cluster(args) -> bool:
    """Whether the arguments (or the launcher's environment) describe several processes."""
    from ..distributed import detect
    return (args.num_processes or 1) > 1 or (args.coordinator is None
                                             and detect() is not None)


def join_cluster(args, check=None) -> bool:
    """Join the cluster the arguments (or the launcher's environment) describe, after
    :func:`setup_jax` and ``import diffpen`` (its XLA options are set before JAX's backend
    starts, which joining does) and before any computation; True when running as one of
    several processes. ``check()``: run by process 0 once every process has joined (its
    checks of the output files); an error it raises stops every process (the others say
    "process 0 stopped: ..."), none is left waiting. Bad flags raise :class:`CLIError`."""
    from ..distributed import from_process_zero, is_writer, join, process_count
    if in_cluster(args):
        _c_stdout_to_stderr()
    try:
        joined = join(args.coordinator, args.num_processes, args.process_id,
                      timeout_s=args.cluster_timeout) and process_count() > 1
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    if joined and check is not None:
        try:
            from_process_zero(check)
        except (CLIError, ValueError, ImportError, OSError) as exc:
            if is_writer():
                raise
            raise CLIError(f"process 0 stopped: {exc}") from None
    if joined:
        _same_arguments(args)
    return joined


#: the options only process 0 of a cluster acts on (it writes the files and the output)
_WRITER_OPTIONS = ("out", "plot", "fresh", "json")


def _same_arguments(args) -> None:
    """Every process of a cluster must be given the same output options
    (:data:`_WRITER_OPTIONS`): only process 0 acts on them, so a process given another
    ``--out`` was ignored without a word while process 0 wrote its own. The same
    :class:`CLIError` on every process otherwise, naming on each the options that differ
    from process 0's. (The options that change the computation are compared by the sweep
    and the fit themselves, which name them.)"""
    import json

    from ..distributed import check_same, from_process_zero
    mine = {k: getattr(args, k) for k in _WRITER_OPTIONS if hasattr(args, k)}
    for k in ("out", "plot"):           # ./s.npz and s.npz are one file
        if isinstance(mine.get(k), str):
            mine[k] = os.path.normpath(mine[k])
    zero = from_process_zero(lambda: mine)
    differ = [k for k in mine if mine.get(k) != zero.get(k)]
    try:
        check_same("set of output options (" + ", ".join("--" + k for k in mine) + ")",
                   json.dumps(mine, sort_keys=True, default=repr).encode())
    except ValueError as exc:
        named = ", ".join("--" + k for k in differ)
        verb = "differs" if len(differ) == 1 else "differ"
        raise CLIError(f"{exc} Only process 0 writes: here {named} {verb} from process 0's."
                       if differ else str(exc)) from None


def _c_stdout_to_stderr() -> None:
    """Send what native code prints on standard output (the cluster transport's "[Gloo]
    Rank 0 is connected ..." lines) to standard error, and keep Python's ``print`` on the
    real standard output: ``--json`` then prints nothing but its JSON object."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = os.fdopen(saved, "w", buffering=1)


def check_cluster_arguments(args) -> None:
    """The cluster flags' consistency, checked before JAX is set up."""
    from ..distributed import check
    try:
        check(args.coordinator, args.num_processes, args.process_id)
    except ValueError as exc:
        raise CLIError(f"--coordinator/--num-processes/--process-id: {exc}") from None


def positive(name: str):
    """argparse type: a finite number > 0."""
    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise CLIError(f"{name} must be a number, got {text!r}") from None
        if not math.isfinite(v) or v <= 0.0:
            raise CLIError(f"{name} must be a finite number > 0, got {text!r}")
        return v
    conv.__name__ = name
    return conv


def law_name(text: str) -> str:
    """argparse type: a contact-law name of :data:`diffpen.laws.CONTACT_LAWS` (diffpen is
    imported only when the option is given, so that ``--help`` stays fast)."""
    from diffpen.laws import CONTACT_LAWS
    if text not in CONTACT_LAWS:
        raise CLIError(f"--law must be one of {sorted(CONTACT_LAWS)}, got {text!r}")
    return text


law_name.__name__ = "--law"


def finite(name: str):
    """argparse type: a finite number (``nan`` and ``inf`` are refused)."""
    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise CLIError(f"{name} must be a number, got {text!r}") from None
        if not math.isfinite(v):
            raise CLIError(f"{name} must be a finite number, got {text!r}")
        return v
    conv.__name__ = name
    return conv


def count(name: str, minimum: int | None = 1):
    """argparse type: an integer (digits, or an exact integer in float notation such as
    ``1e9``), >= ``minimum`` unless that is None; ``1.5``, ``nan`` and words are refused."""
    def conv(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            try:
                f = float(text)
            except ValueError:
                f = math.nan
            if not (math.isfinite(f) and f == int(f)):
                raise CLIError(f"{name} must be an integer, got {text!r}") from None
            v = int(f)
        if minimum is not None and v < minimum:
            raise CLIError(f"{name} must be an integer >= {minimum}, got {text!r}")
        return v
    conv.__name__ = name
    return conv


def add_start_state_arguments(p, scope: str = "") -> None:
    """``--first-state`` and ``--flight-frames``: how each record's start state is taken
    (``diffpen fit SCENE.toml --data`` and ``diffpen evaluate``). ``scope``: a prefix for the
    help texts, e.g. ``"with SCENE.toml --data: "``."""
    p.add_argument("--first-state", choices=["record", "fit", "refine"], default=None,
                   help=f"{scope}each record's start state from row 0 and its velocity "
                        "columns (estimated where missing; default, or the scene file's [fit] "
                        "first_state), or fitted to its first frames (a gravity parabola in "
                        "free flight); refine: as record, and a fit refines every record's "
                        "start velocities with the parameters (records without velocity "
                        "columns; evaluate starts from the estimate)")
    p.add_argument("--flight-frames", type=count("--flight-frames", minimum=3), default=None,
                   metavar="N", help="with --first-state fit: at most N first frames of free "
                   "flight in the fitted parabola (it stops earlier where a body comes within "
                   "5 mm of a plane; default 1000, in practice the whole first flight, or the "
                   "scene file's [fit] flight_frames)")


def fail(cmd: str, message: str) -> int:
    """Print ``diffpen CMD: error: MESSAGE``; exit status 2. In a cluster, an error that says
    another process is gone is printed as that (:func:`cluster_stopped`) instead."""
    stopped = cluster_stopped(cmd, message)
    if stopped is not None:
        return stopped
    sys.stderr.write(f"diffpen {cmd}: error: {message}\n")
    return 2


def cluster_stopped(cmd: str, error) -> int | None:
    """In a cluster, when ``error`` (an exception or its text) is a collective's failure
    because another process is gone: print the line of
    :func:`tuning.distributed.lost_process` (with how to resume a sweep) and return the
    stopped status; else None."""
    from ..distributed import STOPPED_STATUS, lost_process
    lost = lost_process(error)
    if lost is None:
        return None
    hint = "; rerun the same command on every process to resume the sweep" \
        if cmd == "sweep" else ""
    sys.stderr.write(lost[:-1] + hint + ".\n")
    return STOPPED_STATUS


def dump_json(obj) -> None:
    """One JSON object on stdout (nan/inf become null)."""
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    sys.stdout.write(json.dumps(clean(obj)) + "\n")


def fmt(v, unit: str = "", digits: int = 5) -> str:
    """A number (or list) for printing: ``digits`` significant digits, ``n/a`` for nan."""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(fmt(x, "", digits) for x in v) + "]" + (f" {unit}" if unit else "")
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}g}" + (f" {unit}" if unit else "")
