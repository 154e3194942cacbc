"""Regenerate docs/bench.json: every `diffpen bench` case (float32, plus float64 for the ball
at batch 1024 and the 32x32 cloth), the many-spheres scaling, the gradient-memory check and
the batched-ball table against the plain floor (``benchmarks/scale_table.py``).

    python benchmarks/write_docs.py [--out docs/bench.json] [--peer newton.json] [--compare]
                                    [--only cases scaling memory scale]

``--peer`` merges rows written by ``benchmarks/peers/newton_cloth.py --json`` (run in that
script's own environment). ``--compare`` also runs the float64 100,000-step gradient
comparison (checkpointed vs plain backprop; minutes and ~5 GB). Run it on a quiet machine:
the figures are medians after compilation, but a loaded machine still skews them. The file is
written atomically; sections not rerun are kept from the existing file.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

from tuning.reports import bench  # noqa: E402
from tuning.sweep import atomic_write  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/bench.json")
    ap.add_argument("--peer", default=None, help="JSON rows from the Newton peer script")
    ap.add_argument("--compare", action="store_true",
                    help="also run the float64 100k-step checkpointed-vs-plain gradient")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--only", nargs="+", choices=("cases", "scaling", "memory", "scale"),
                    default=("cases", "scaling", "memory", "scale"),
                    help="sections to rerun (default: all); the others are kept from --out")
    args = ap.parse_args(argv)
    old = {}
    if os.path.exists(args.out):
        with open(args.out) as f:
            old = json.load(f)

    def progress(s):
        print(f"running {s} ...", file=sys.stderr, flush=True)
    missing = [key for sec, key in (("cases", "cases"), ("scaling", "sphere_scaling"),
                                    ("memory", "gradient_memory"), ("scale", "scale_table"))
               if sec not in args.only and key not in old]
    if missing:
        ap.error(f"{args.out} has no {missing} to keep: rerun those sections too.")
    rows, scaling, memory = old.get("cases"), old.get("sphere_scaling"), old.get("gradient_memory")
    load = dict(old.get("load") or {})
    # which code and day each section was measured on (sections kept keep theirs)
    runs = dict(old.get("runs") or {})
    this_run = _this_run()
    for section in args.only:
        runs[section] = this_run
    if "cases" in args.only:
        load["cases_start"] = os.getloadavg()
        rows = bench.run(list(bench.CASES), dtypes=(jnp.float32,), repeats=args.repeats,
                         progress=progress)
        for name in ("ball_b1024", "cloth32"):
            progress(f"{name} (float64)")
            rows.append(bench.run_case(name, dtype=jnp.float64, repeats=args.repeats))
        load["cases_end"] = os.getloadavg()
    if "scaling" in args.only:
        progress("sphere scaling")
        scaling = bench.sphere_scaling()
    if "memory" in args.only:
        progress("gradient memory")
        memory = [bench.gradient_memory()]
        if args.compare:
            memory.append(bench.gradient_memory(dtype=jnp.float64, compare=True))
        else:
            memory += [m for m in (old.get("gradient_memory") or []) if "max_rel_diff" in m]
    table = old.get("scale_table")
    if "scale" in args.only:
        progress("batched-ball table (benchmarks/scale_table.py)")
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        import scale_table
        table = [scale_table.measure(b, 2000, 5) for b in (1, 1024, 65536)]
    peer = old.get("newton_peer")
    if args.peer:
        with open(args.peer) as f:
            peer = json.load(f)
    doc = dict(machine=f"{os.cpu_count()}-core {platform.machine()}, CPU only",
               jax=jax.__version__, load=load, cases=rows, sphere_scaling=scaling,
               gradient_memory=memory, scale_table=table,
               newton_peer=peer, runs=runs)

    atomic_write(args.out, lambda fh: fh.write(json.dumps(doc, indent=1).encode()))
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _this_run() -> dict:
    """``{"date": UTC date, "commit": git HEAD, "clean": no uncommitted change}`` of the code
    measured (commit and clean None outside a git checkout)."""
    import datetime
    import subprocess
    here = os.path.dirname(os.path.abspath(__file__))

    def git(*cmd):
        try:
            return subprocess.run(["git", *cmd], cwd=here, capture_output=True, text=True,
                                  timeout=10, check=True).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return None
    status = git("status", "--porcelain", "--untracked-files=no")
    return dict(date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
                commit=git("rev-parse", "HEAD"), clean=None if status is None else not status)


if __name__ == "__main__":
    sys.exit(main())
