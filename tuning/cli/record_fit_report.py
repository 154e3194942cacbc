"""What ``diffpen fit SCENE.toml --data FILES...`` prints: a record fit's summary, as one JSON
object or as text (fitted values with their standard errors, the time step's shift,
correlations, undetermined directions, the errors before and after, the status)."""
from __future__ import annotations

import sys

from ._common import dump_json

__all__ = ["print_record_fit"]


def print_record_fit(args, out: dict) -> int:
    """Print a record fit's summary (JSON or text); its exit status."""
    status = 0 if out["reached"] else 1
    if out.get("out_error"):
        status = 2
    if args.json:
        dump_json(out)
        if out.get("out_error"):
            print(f"diffpen fit: error: {out['out_error']} (the fitted values are in the "
                  "JSON above)", file=sys.stderr)
        return status
    print(f"diffpen fit: {args.scene} on {out['records']} record(s) "
          f"({out['estimate']} first state, {args.loss} pose loss)")
    for name, v in out["fitted"].items():
        print(f"fitted:    {name} = {v:.6g} +- {out['stderr'][name]:.2g}")
    if out.get("step_shift"):
        print("time step: towards dt -> 0 the values move by " + ", ".join(
            f"{d:+.2g} ({n})" for n, d in out["step_shift"].items()) + " (in the errors "
            "above, with the records' noise: " + ", ".join(
                f"{e:.2g}" for e in out["stderr_noise"].values()) + ")")
    names = list(out["fitted"])
    if len(names) > 1:
        print("correlations:")
        for a in names:
            print("  " + " ".join(f"{out['correlation'][a][b]:+.2f}" for b in names) + f"  {a}")
    for u in out["undetermined"]:
        d = ", ".join(f"{c:+.2f} {n}" for n, c in u["direction"].items())
        print(f"undetermined direction (eigenvalue ratio {u['eigenvalue_ratio']:.1e}): {d}")
    for key, label in (("before", "start"), ("after", "fitted")):
        pe, re = out[key]["position_error_pct"], out[key]["rotation_error_deg"]
        rot = "" if re is None else (f", rotation mean {re['mean']:.2f} deg (median "
                                     f"{re['median']:.2f})")
        print(f"{label:7s}   position mean {pe['mean']:.2f}% (median {pe['median']:.2f}%)"
              + rot)
    if out["out"]:
        print(f"wrote:     {out['out']}")
    if out["resumed"]:
        print(f"resumed:   {out['resumed']} LM iterations from the progress of an interrupted "
              "run")
    print(f"status:    {out['message']}; {out['iterations']} LM iterations, "
          f"{out['seconds']:.2f} s wall time ({out['fit_seconds']:.2f} s fitting)"
          + ("" if out["reached"] else "; NOT a result: "
             + ("the derivatives blew up" if out.get("diverged") else
                "a rollout ran past the safe step")))
    if out.get("out_error"):
        print(f"diffpen fit: error: {out['out_error']} (the fitted values are printed "
              "above)", file=sys.stderr)
    return status
