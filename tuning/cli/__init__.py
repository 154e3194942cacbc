"""The ``diffpen`` command line. Only this package parses arguments and prints.

Each subcommand lives in its own module ``tuning.cli.<name>`` defining
``add_arguments(parser)`` and ``run(args) -> int``; modules are imported lazily so that
``diffpen --help`` stays fast.
"""
from __future__ import annotations

import argparse
import re
import importlib
import os
import sys

from ..progress import clear_pending, interrupt, pending

#: subcommand -> (module, one-line help)
COMMANDS = {
    "fit": ("tuning.cli.fit", "fit contact stiffness and damping to targets or a measured "
                              "trajectory (default: the built-in ball scene)"),
    "evaluate": ("tuning.cli.evaluate", "open-loop accuracy of a scene file on measured records"),
    "simulate": ("tuning.cli.simulate", "roll out a built-in scene or a scene file and report "
                                        "metrics"),
    "sweep": ("tuning.cli.sweep", "batched sweep over (k, c) of the ball, or over a scene "
                                  "file's parameters, with vmap; writes .npz + .csv"),
    "report": ("tuning.cli.report", "stability, accuracy and gradient-error reports"),
    "bench": ("tuning.cli.bench", "speed benchmarks against baselines measured in the same "
                                  "process"),
}


#: a negative number in any notation (-2, -0.5, -.5, -1e-2, -2.5E+3)
_NEGATIVE = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def _negative_numbers(parser: argparse.ArgumentParser) -> None:
    """Let ``parser`` read ``-1e-2`` as a value, as it reads ``-0.01`` (argparse's own pattern
    leaves out exponents, so ``--param NAME -1e-2 1e-2`` was refused as a missing value)."""
    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = _NEGATIVE


def build_parser(available=None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diffpen", description="Differentiable penalty-contact simulation: tune stiffness "
                                    "and damping.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (modname, helptext) in COMMANDS.items():
        if available is not None and name not in available:
            continue
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name == modname:
                continue  # subcommand not installed in this build
            raise
        p = sub.add_parser(name, help=helptext, description=helptext)
        _negative_numbers(p)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = None
    try:
        wanted = None
        if argv and argv[0] in COMMANDS:
            wanted = {argv[0]}          # import only the subcommand asked for
        parser = build_parser(wanted)
        args = parser.parse_args(argv)
        if not getattr(args, "_run", None):
            parser.print_help()
            return 2
        try:
            status = int(args._run(args) or 0)
        except Exception as exc:        # a collective failed: another process is gone
            from ._common import cluster_stopped
            status = cluster_stopped(argv[0], exc)
            if status is None:
                raise
        clear_pending()             # an interrupt lost too late to stop the run
        if status != 0:
            # in a cluster, the others stop at once instead of waiting for this process
            from ..distributed import mark_failed
            mark_failed(f"diffpen {argv[0]} exited with status {status}", status)
        return status
    except KeyboardInterrupt as exc:
        clear_pending()
        # long runs write their results atomically as they go: nothing half-written is
        # left, and a sweep or a fit of records with --out resumes where it stopped
        hint = ""
        command = "diffpen " + argv[0] if argv else "diffpen"
        if args is None:                # still importing or reading the command line
            pass
        elif argv[0] == "sweep":
            hint = "; rerun the same command to resume the sweep"
        elif argv[0] == "fit" and getattr(args, "out", None):
            # a fit of records (--out needs them) keeps its progress beside --out
            from ..fit_checkpoint import checkpoint_path
            if os.path.exists(checkpoint_path(args.out)):
                hint = ("; rerun the same command" + (" without --fresh" if args.fresh else "")
                        + " to resume the fit")
        # a progress bar may hold the line
        what = "terminated" if isinstance(exc, Terminated) else "interrupted"
        print(("\n" if sys.stderr.isatty() else "") + f"{command}: {what}{hint}",
              file=sys.stderr)
        status = TERMINATED if isinstance(exc, Terminated) else INTERRUPTED
        # in a cluster, the others stop within seconds instead of waiting for this process
        # in a collective, and this one ends without waiting for them (both processes hung)
        from ..distributed import mark_failed
        mark_failed(f"{command} {what}", status)
        return status


#: the exit status of an interrupted command (128 + SIGINT, as a shell reports it)
INTERRUPTED = 130

#: the exit status of a command ended by SIGTERM (128 + 15)
TERMINATED = 143


class Terminated(KeyboardInterrupt):
    """SIGTERM reached the command (a batch scheduler's time limit, ``kill``): it ends as a
    Ctrl-C does (results written so far kept, the hint to resume), with :data:`TERMINATED`."""


def _on_sigterm(signum, frame):
    interrupt(Terminated)


def _on_sigint(signum, frame):
    interrupt(KeyboardInterrupt)


def _quiet_unraisable(unraisable) -> None:
    """``sys.unraisablehook`` of the command: an interrupt its handlers raised where Python
    cannot pass it on (inside JAX's garbage-collection callback, in a command's first
    second) is not printed as a 10-line "Exception ignored in: _xla_gc_callback" traceback;
    it is pending and raised again at the next progress report
    (:func:`tuning.progress.raise_pending`). Everything else goes to Python's own hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and pending():
        return
    sys.__unraisablehook__(unraisable)


def install_handlers() -> None:
    """The command's handlers: SIGTERM and SIGINT raise through
    :func:`tuning.progress.interrupt` (:class:`Terminated`, ``KeyboardInterrupt``), and an
    interrupt Python had to drop is not printed (:func:`_quiet_unraisable`)."""
    import signal
    signal.signal(signal.SIGTERM, _on_sigterm)
    signal.signal(signal.SIGINT, _on_sigint)
    sys.unraisablehook = _quiet_unraisable


def entry() -> None:
    """The ``diffpen`` command (and ``python -m tuning.cli``): :func:`main`, then exit with
    its status. SIGTERM is handled as SIGINT is (:class:`Terminated`): under SLURM a job
    past its time limit gets SIGTERM first, and a sweep or fit of records then says how to
    resume. Both handlers raise through :func:`tuning.progress.interrupt`, so a Ctrl-C that
    Python dropped (raised inside a garbage-collection callback) is raised again at the next
    progress report. An interrupted or terminated command runs the exit handlers and ends without
    tearing its modules down: a Ctrl-C that landed inside JAX's runtime made that teardown
    crash in jaxlib (exit 139, a segmentation fault, after "interrupted") in about half the
    interrupted fits on a loaded machine."""
    install_handlers()
    status = main()
    if status in (INTERRUPTED, TERMINATED):
        import atexit
        sys.stdout.flush()
        sys.stderr.flush()
        atexit._run_exitfuncs()
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":
    entry()
