"""``diffpen evaluate SCENE.toml --data FILES...``: open-loop accuracy of a scene file on
measured records (position error in % of the body's size, rotation error in degrees; per
record, mean and median)."""
from __future__ import annotations

import sys

from ._common import CLIError, add_start_state_arguments, dump_json, fail, setup_jax


def add_arguments(p) -> None:
    p.add_argument("scene", metavar="SCENE.toml", help="the scene file (its parameter values "
                   "as written, e.g. the output of diffpen fit --out)")
    p.add_argument("--data", nargs="+", metavar="FILE.csv",
                   help="records to evaluate on (default: the scene file's [fit] data)")
    add_start_state_arguments(p)
    p.add_argument("--plot", metavar="DIR", help="draw simulated against measured "
                   "trajectories of the first 4 records into DIR, one PNG each (NAME.png for "
                   "NAME.csv, NNN_NAME.png when names repeat), listed with the scene in "
                   "DIR/plots.json (the PNGs an earlier run listed there that this run does "
                   "not redraw are removed; one run per DIR at a time: a second is refused; "
                   "needs matplotlib)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def run(args) -> int:
    try:
        if not args.scene.lower().endswith(".toml"):
            raise CLIError(f"{args.scene}: give a scene file (.toml)")
        setup_jax()
        from ..evaluate import evaluate_files
        out = evaluate_files(args.scene, args.data, estimate=args.first_state,
                             plot=args.plot, max_frames=args.flight_frames)
    except (CLIError, ValueError, ImportError, OSError) as exc:
        return fail("evaluate", str(exc))
    code = 1 if out.get("unstable") else 0      # records past the safe step: not results
    if out.get("message"):                      # ... or a crumple member collapsed
        print(f"diffpen evaluate: {out['message']}", file=sys.stderr)
    if args.json:
        dump_json(out)
        return code
    pe, re = out["position_error_pct"], out["rotation_error_deg"]
    print(f"diffpen evaluate: {args.scene} on {len(out['records'])} record(s)")
    for r in out["records"]:
        rot = ("" if r["rotation_error_deg"] is None
               else f"   rotation {r['rotation_error_deg']:6.2f} deg")
        print(f"  {r['path']}: {r['frames']} frames, position {r['position_error_pct']:6.2f}%"
              + rot)
    print(f"position error: mean {pe['mean']:.2f}%, median {pe['median']:.2f}% (of the body's "
          "size)")
    if re is not None:
        print(f"rotation error: mean {re['mean']:.2f} deg, median {re['median']:.2f} deg")
    print(f"rollouts: {out['seconds'] * 1e3:.1f} ms after {out['compile_seconds']:.2f} s "
          "compilation")
    for p in out.get("plots", []):
        print(f"plot: {p}")
    return code
