"""``diffpen report``: trust reports.

    diffpen report stability [--quick] [--json] [--scenes ball chain] [--dtypes ...]
    diffpen report accuracy  [--quick] [--json] [--plot FILE.png] [--tol TOL] [--k K --c C ...]
    diffpen report gradients [--quick] [--json]

``stability`` prints the extreme-case matrix (every case with its outcome); ``accuracy`` the
error against run time of every integrator (work-precision) and, with ``--tol``, the cheapest
integrator and dt that meet it for the given ball; ``gradients`` the gradient error against
dt and smoothing width and the largest finite-difference step that agrees with jax.grad.
"""
from __future__ import annotations

import dataclasses
import math
import sys

from ._common import count, dump_json, fail, finite, positive, setup_jax


def add_arguments(p) -> None:
    p.add_argument("what", choices=["stability", "accuracy", "gradients"],
                   help="stability: extreme-case matrix; accuracy: work-precision; "
                        "gradients: gradient error and finite-difference agreement")
    p.add_argument("--quick", action="store_true",
                   help="a smaller run (the ends of each range / fewer dt values)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="FILE.png",
                   help="accuracy: write the log-log work-precision diagram here")
    p.add_argument("--tol", type=positive("--tol"),
                   help="accuracy: recommend the cheapest integrator and dt whose relative "
                        "apex-height error on the ball is <= TOL (default: no recommendation)")
    p.add_argument("--k", type=positive("--k"), default=1e4, help="ball contact k, N/m "
                   "(default %(default)g; gradients: the last table's ball; the event tables "
                   "keep their fixed cases)")
    p.add_argument("--c", type=finite("--c"), default=20.0, help="ball contact c, N s/m (default %(default)g)")
    p.add_argument("--mass", type=positive("--mass"), default=1.0, help="ball mass, kg (default %(default)g)")
    p.add_argument("--radius", type=positive("--radius"), default=0.1, help="ball radius, m (default %(default)g)")
    p.add_argument("--drop", "--height", dest="height", type=positive("--drop"), default=1.0,
                   help="ball drop height of the centre, m, as diffpen fit's and sweep's "
                        "--drop (--height: the same; default %(default)g)")
    p.add_argument("--scenes", nargs="+", default=["ball", "chain"], choices=["ball", "chain"],
                   help="stability: scenes of the matrix")
    p.add_argument("--dtypes", nargs="+", default=["float32", "float64"],
                   choices=["float32", "float64"], help="stability: dtypes of the matrix")
    p.add_argument("--integrators", nargs="+", default=None,
                   help="integrators (default: all four)")
    p.add_argument("--repeats", type=count("--repeats"), default=5,
                   help="accuracy: timed runs per point after compilation (median reported; "
                        "default %(default)s)")


#: the flags each report reads (besides --quick and --json); any other is refused, not ignored
USES = {"stability": {"scenes", "dtypes", "integrators"},
        "accuracy": {"plot", "tol", "k", "c", "mass", "radius", "height", "integrators",
                     "repeats"},
        "gradients": {"k", "c", "mass", "radius", "height"}}


def _unused_flags(args) -> list:
    """The flags given (not at their defaults) that ``args.what``'s report does not read."""
    import argparse
    p = argparse.ArgumentParser()
    add_arguments(p)
    defaults = vars(p.parse_args([args.what]))
    return [f"--{name}" for name in ("plot", "tol", "k", "c", "mass", "radius", "height",
                                     "scenes", "dtypes", "integrators", "repeats")
            if name not in USES[args.what] and getattr(args, name) != defaults[name]]


def run(args) -> int:
    from diffpen.integrators import INTEGRATORS
    unused = _unused_flags(args)
    if unused:
        reads = ", ".join(f"--{n}" for n in sorted(USES[args.what]))
        return fail("report", f"{', '.join(unused)} {'is' if len(unused) == 1 else 'are'} "
                              f"not read by the {args.what} report (it reads --quick, --json, "
                              f"{reads}); drop {'it' if len(unused) == 1 else 'them'}")
    integs = tuple(args.integrators or ("semi_implicit_euler", "verlet", "rk4",
                                        "implicit_euler"))
    bad = [i for i in integs if i not in INTEGRATORS]
    if bad:
        return fail("report", f"unknown integrator(s) {bad}; choose from "
                              f"{sorted(INTEGRATORS)}")
    if args.c < 0 or not math.isfinite(args.c):
        return fail("report", f"--c must be a finite number >= 0, got {args.c}")
    if args.what == "gradients" and args.c == 0:
        return fail("report", "--c must be > 0 for the gradients report: its central "
                              "differences step c both ways, and a negative c is refused")
    if args.height <= args.radius:
        return fail("report", "--drop (--height) must be above --radius (the ball starts "
                              "above the plane)")
    if args.plot:
        from ..io import OutputError, check_plot
        try:
            check_plot(args.plot, what="--plot")
        except OutputError as exc:
            return fail("report", str(exc))
        try:
            from ..plots import require_matplotlib
            require_matplotlib()
        except ImportError as exc:
            return fail("report", str(exc))
    setup_jax(x64=True)
    if args.what == "stability":
        return _stability(args, integs)
    if args.what == "accuracy":
        return _accuracy(args, integs)
    return _gradients(args)


# --------------------------------------------------------------------------- stability
def _stability(args, integs) -> int:
    from tuning.reports.extreme import extreme_cases, stability_matrix, summarize_matrix

    from ..progress import Progress
    cases = extreme_cases(scenes=tuple(args.scenes), dtypes=tuple(args.dtypes),
                          integrators=integs, quick=args.quick)
    # a bar on a terminal, a line every 5 s otherwise (a log file got one 4 kB line of \r)
    bar = Progress(len(cases), "diffpen report stability", enabled=not args.json,
                   value="done")

    def progress(i, n, row):
        bar.update(i, i / max(n, 1))
    try:
        rows = stability_matrix(cases, progress=progress)
    finally:
        bar.close()
    summary = summarize_matrix(rows)
    if args.json:
        dump_json({"summary": summary, "rows": rows})
        return 0 if summary.get("FAIL", 0) == 0 else 1
    head = (f"{'scene':6} {'dtype':7} {'integrator':19} {'case':38} {'k':>7} {'m':>7} "
            f"{'zeta':>5} {'dt':>7}  outcome")
    print(head)
    print("-" * len(head))
    for r in rows:
        out = r["outcome"]
        if out == "ok":
            out += (f" (energy {r['energy_growth']:+.2g}, pen {r['max_penetration']:.2g} m"
                    + (f", e {r['restitution']:.3f}" if "restitution" in r else "") + ")")
        elif out == "refused":
            out += f": {r['detail'].split(': ', 1)[-1]}"
            if "remedy" in r:
                out += f" -> {r['remedy_detail'].split(':')[0]}: {r['remedy']}"
                if r["remedy"] != "ok":
                    out += f" ({r['remedy_detail']})"
        else:
            out += f": {r['detail']}"
        print(f"{r['scene']:6} {r['dtype']:7} {r['integrator']:19} {r['label'][:38]:38} "
              f"{r['k']:7.0e} {r['mass']:7.0e} {r['zeta']:5g} {r['dt']:7.0e}  {out}")
    print()
    print("summary: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    print("ok = ran sane (finite, energy not growing beyond tolerance, penetration bounded, "
          "restitution <= 1, finite dk/dc); refused = clear StabilityError before running, "
          "then re-run with its advice; FAIL = a sanity check failed.")
    return 0 if summary.get("FAIL", 0) == 0 else 1


# --------------------------------------------------------------------------- accuracy
def _accuracy(args, integs) -> int:
    from tuning.reports.accuracy import (BallSpec, accuracy, horizon, plot_accuracy,
                                         recommend)
    if args.repeats < 1:
        return fail("report", "--repeats must be >= 1")
    spec = BallSpec(k=args.k, c=args.c, mass=args.mass, radius=args.radius,
                    height=args.height)
    try:            # simulated long enough for its apexes and settling (3 s at least)
        spec = dataclasses.replace(spec, T=horizon(spec))
    except ValueError as exc:
        return fail("report", str(exc))
    n_dt = 4 if args.quick else 6

    def progress(*a):
        if not args.json:
            sys.stderr.write(".")
            sys.stderr.flush()
    res = accuracy(ball=spec, integrators=integs, n_dt=n_dt, repeats=args.repeats,
                   progress=progress)
    if not args.json:
        sys.stderr.write("\n")
    rec = recommend(res, args.tol) if args.tol else None
    if args.plot:
        try:
            plot_accuracy(res, args.plot)
        except ImportError as e:
            return fail("report", str(e))
    if args.json:
        dump_json(dict(res, recommendation=rec, tol=args.tol))
        return 0
    labels = {"ball": "ball: max rel. error of the first apex heights",
              "spring": "damped spring: max |x - x_exact| / x0",
              "chain": "hanging chain: max tip error / length"}
    for name, per in res["problems"].items():
        print(f"\n{labels[name]}  (time: median wall time of the whole rollout)")
        print(f"  {'integrator':19} {'dt (s)':>10} {'error':>10} {'time (s)':>10}")
        for integ, pts in per.items():
            for p in pts:
                extra = ""
                if p.get("substeps", 1) not in (None, 1):
                    extra = f"  (substeps {p['substeps']})"
                if "note" in p:
                    extra += f"  refused ({p['note']})"
                elif "settling_error" in p:
                    extra += f"  settling-time error {p['settling_error']:.2g} s"
                print(f"  {integ:19} {p['dt']:10.3g} {p['error']:10.3g} {p['time']:10.3g}"
                      + extra)
    if res["widths"]:
        print("\nball, semi-implicit Euler at dt = "
              f"{res['widths'][0]['dt']:g} s: smoothing width against apex error")
        for w in res["widths"]:
            if "note" in w:
                print(f"  width {w['width']:8.1e} m   refused ({w['note']})")
                continue
            print(f"  width {w['width']:8.1e} m   apex error {w['error']:.3g}   settling-time "
                  f"error {w['settling_error']:.2g} s")
    for d in res["default"]:
        if "note" in d:
            print(f"\ndefault (semi_implicit_euler, dt = 1e-3 s, smoothing {d['smoothing']:g} "
                  f"m, {d['dtype']}): refused ({d['note']}) at this --k / --c; "
                  "see the dt ladder above")
            continue
        print(f"\ndefault (semi_implicit_euler, dt = 1e-3 s, smoothing {d['smoothing']:g} m, "
              f"{d['dtype']}): apex error {d['error']:.3g}, settling-time error "
              f"{d['settling_error']:.2g} s, {d['time'] * 1e3:.3g} ms for {d['steps']} steps "
              f"({d['time_per_step'] * 1e6:.3g} us/step)")
    if args.tol:
        if rec is None:
            print(f"\n--tol {args.tol:g}: no integrator and dt in this ladder meets it; try "
                  "smaller dt (rk4 converges fastest)")
        else:
            print(f"\n--tol {args.tol:g}: cheapest is {rec['integrator']} at dt = "
                  f"{rec['dt']:.3g} s (error {rec['error']:.3g}, {rec['time'] * 1e3:.3g} ms)")
    if args.plot:
        print(f"\nwrote {args.plot}")
    return 0


# --------------------------------------------------------------------------- gradients
def _gradients(args) -> int:
    from tuning.reports.accuracy import BallSpec
    from tuning.reports.gradient_check import gradient_report
    spec = BallSpec(k=args.k, c=args.c, mass=args.mass, radius=args.radius,
                    height=args.height, T=2.0)
    kw = dict(dts=(1e-3,), widths=(0.0, 1e-3)) if args.quick else {}
    try:
        rows = gradient_report(spec=spec, **kw)
    except ValueError as exc:
        return fail("report", str(exc))
    from tuning.reports.gradient_check import EVENT_CASES, event_gradient_rows, event_gradient_table
    ev_dts = (1e-3,) if args.quick else (1e-3, 1e-4)
    events = event_gradient_rows(EVENT_CASES, ev_dts)
    exact = event_gradient_rows(EVENT_CASES, ev_dts, events=True)
    if args.json:
        dump_json({"rows": rows, "events": events, "event_exact": exact})
        return 0
    print("event metrics (apex heights, contact durations, max penetration) against the "
          "continuous derivatives (event-located DOP853 reference), semi-implicit Euler, "
          "default smoothing, on the report's four fixed balls (the cases of docs/"
          "gradients.txt; --k, --c, --mass, --radius and --drop set the last table's ball "
          "only):")
    print(event_gradient_table(events))
    print()
    print("the same with each law's event-exact record (diffpen.laws.get(law, events=True)), "
          "the default record's figures as 'before':")
    print(event_gradient_table(exact, before=events))
    print()
    print("ball dropped from {:g} m, k = {:g} N/m, c = {:g} N s/m; apex = first rebound apex, "
          "z_T = height at 2 s".format(spec.height, spec.k, spec.c))
    print(f"  {'dt (s)':>8} {'width (m)':>9} {'quantity':8} {'wrt':3} {'jax.grad':>12} "
          f"{'continuous':>12} {'rel.err':>8} {'largest FD step agreeing (1%)':>30}")
    for r in rows:
        step = r["largest_agreeing_rel_step"]
        print(f"  {r['dt']:8.2g} {r['width']:9.1e} {r['quantity']:8} {r['param']:3} "
              f"{r['grad']:12.4g} {r['reference']:12.4g} {r['grad_rel_error']:8.2g} "
              f"{('none' if step is None else f'{step:.0e}'):>30}")
    return 0
