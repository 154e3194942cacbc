"""``diffpen bench``: speed of diffpen against baselines measured in the same process."""
from __future__ import annotations

import json
import sys


#: ``tuning.reports.bench.CASES``' names, listed here so that ``--help`` does not import JAX
#: (tests/test_bench.py checks that the two agree)
KNOWN_CASES = ("ball_b1", "ball_b1024", "ball_b1024_rows", "ball_b65536",
               "ball_b65536_rows", "chain", "cloth32", "cloth64", "jelly10", "spheres1000",
               "spheres10000")


def add_arguments(p) -> None:
    p.add_argument("cases", nargs="*", metavar="CASE",
                   help="cases to run (default: all; with --quick a CI-sized subset). "
                        "Known: " + " ".join(KNOWN_CASES))
    p.add_argument("--quick", action="store_true",
                   help="CI-sized: fewer steps, batch <= 256, the quick subset of cases")
    p.add_argument("--json", action="store_true", help="print JSON rows instead of a table")
    p.add_argument("--float64", action="store_true", help="also run every case in float64")
    p.add_argument("--repeats", type=int, default=5,
                   help="timed runs per figure after compilation (median reported; default "
                        "%(default)s)")


_COLUMNS = [("case", "{}"), ("dtype", "{}"), ("batch", "{}"), ("steps", "{}"),
            ("compile_s", "{:.2f}"), ("forward_s", "{:.3g}"), ("steps_per_s", "{:.3g}"),
            ("grad_s", "{:.3g}"), ("grad_over_forward", "{:.2f}"), ("grad_mode", "{}"),
            ("reverse_over_forward", "{:.2f}"), ("vs_floor", "{:.2f}"),
            ("grad_vs_floor", "{:.2f}"), ("reverse_vs_floor", "{:.2f}"),
            ("vs_band_floor", "{:.2f}"), ("vs_numpy", "{:.3f}"),
            ("stepping_per_s", "{:.3g}"), ("stepping_vs_floor", "{:.2f}"),
            ("natural_vs_floor", "{:.2f}"),
            ("memory_bytes", "{:.3g}"),
            ("grad_memory_bytes", "{:.3g}")]


def _table(rows) -> str:
    head = [c for c, _ in _COLUMNS]
    body = [[fmt.format(r[c]) if r.get(c) is not None else "-" for c, fmt in _COLUMNS]
            for r in rows]
    widths = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(head)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(head, widths))]
    lines += ["  ".join(x.rjust(w) for x, w in zip(b, widths)) for b in body]
    return "\n".join(lines)


def run(args) -> int:
    import jax
    if args.float64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from tuning.reports import bench
    if args.repeats < 1:
        print("diffpen bench: --repeats must be >= 1", file=sys.stderr)
        return 2
    unknown = [c for c in args.cases if c not in bench.CASES]
    if unknown:
        print(f"diffpen bench: unknown case(s) {unknown}; choose from {sorted(bench.CASES)}",
              file=sys.stderr)
        return 2
    dtypes = (jnp.float32, jnp.float64) if args.float64 else (jnp.float32,)
    progress = None if args.json else (lambda s: print(f"running {s} ...", file=sys.stderr))
    rows = bench.run(args.cases or None, dtypes=dtypes, quick=args.quick,
                     repeats=args.repeats, progress=progress)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        print(_table(rows))
        if args.quick:
            print("\n--quick: CI-sized runs (batch <= 256, fewer steps; the batch and steps "
                  "columns say what ran), not the full-size figures the case names stand for.")
        print("\nvs_floor: forward time / a plain hand-written lax.scan of the same physics "
              "(tuning.reports.floors: for the ball scalar z and v per ball, hard contact; for "
              "spring networks x, y, z arrays, a gather per spring and a segment_sum per node); "
              "vs_band_floor (spring networks): forward time / the same hand-written in "
              "diffpen's own lattice layout (dense slices added in place), the fastest form "
              "found; "
              "vs_numpy: forward time / vectorised NumPy (< 1 is faster); steps_per_s counts "
              "ball-steps (batch x steps) for batched balls, sphere-steps (spheres x steps) "
              "for the sphere cases, steps otherwise; grad_s uses "
              "diffpen.value_and_grad's choice (grad_mode), reverse_over_forward is reverse "
              "mode's time over the forward time, reverse_vs_floor over the floor's reverse "
              "mode; stepping_per_s (ball cases) is the rate of "
              "the same rollout returning only its final state, stepping_vs_floor its time over "
              "the floor doing the same; natural_vs_floor: the time of "
              "sim.rollout(...).position[-1, 0, 2] (every state recorded) over the floor's "
              "stepping.")
    return 0
