"""``diffpen sweep``: every (k, c) of a log-spaced grid for the ball scene, or every point of
a grid over a scene file's parameters (``diffpen sweep SCENE.toml [--param PATH LO HI]
[--data FILES]``, :mod:`tuning.scene_sweep`), with jax.vmap in chunks; writes the .npz and
its .csv atomically as the chunks finish and at the end (:mod:`tuning.sweep_files`), resumes
an interrupted sweep, and draws a heatmap with the target contour."""
from __future__ import annotations

import math
import os

from ._common import (CLIError, add_cluster_arguments, add_start_state_arguments,
                      check_cluster_arguments, count, dump_json, fail, finite, in_cluster,
                      join_cluster, positive, setup_jax)

METRICS = ("apex_heights", "settling_time", "max_penetration", "contact_durations",
           "restitution")
#: a scene file's sweep over records also offers these
RECORD_METRICS = ("position_error_pct", "position_error_median", "rotation_error_deg",
                  "rotation_error_median")
#: the ball sweep's defaults (None on the command line: given or not is told apart)
BALL_DEFAULTS = {"k": [1e3, 1e5], "c": [1.0, 100.0], "radius": 0.1, "mass": 1.0, "drop": 1.0,
                 "duration": 2.0, "dt": 1e-3, "settle_tol": 1e-3}


def add_arguments(p) -> None:
    p.add_argument("scene", nargs="?", metavar="SCENE.toml", help="sweep a scene file's "
                   "parameters instead of the built-in ball: its [fit] params over "
                   "[fit.bounds], or --param; against --data records (position and rotation "
                   "errors), else the bounce of its [fit] body (the built-in ball sweeps "
                   "the linear law: for another law or integrator write the ball as a scene "
                   "file, law = \"no_tension\" ...)")
    p.add_argument("--param", nargs=3, action="append", metavar=("PATH", "LO", "HI"),
                   help="with SCENE.toml: a parameter leaf (e.g. contact.board.k) and its "
                   "range; repeat for more axes (log-spaced for positive leaves, linear for "
                   "offsets)")
    p.add_argument("--data", nargs="+", metavar="FILE.csv", help="with SCENE.toml: records "
                   "to evaluate every point on (default: the scene file's [fit] data); a "
                   "record whose rollout goes past the safe step is left out of that point's "
                   "errors (the unstable_records column; JSON points_with_unstable_records: "
                   "the points where some but not all records were left out; where all "
                   "were, the point is NaN and counted in unstable)")
    add_start_state_arguments(p, "with SCENE.toml --data: ")
    p.add_argument("--k", type=positive("--k"), nargs=2, default=None,
                   metavar=("KMIN", "KMAX"), help="stiffness range, N/m (default 1e3 1e5)")
    p.add_argument("--c", type=positive("--c"), nargs=2, default=None,
                   metavar=("CMIN", "CMAX"), help="damping range, N s/m (default 1 100)")
    p.add_argument("--n", type=count("--n", minimum=2), nargs="+", default=None, metavar="N",
                   help="grid points per axis (one value for all, or one per axis; default "
                   "64, 16 with SCENE.toml)")
    p.add_argument("--radius", type=positive("--radius"), default=None,
                   help="m (default 0.1)")
    p.add_argument("--mass", type=positive("--mass"), default=None, help="kg (default 1)")
    p.add_argument("--drop", type=positive("--drop"), default=None,
                   help="initial centre height, m (default 1)")
    p.add_argument("--duration", type=positive("--duration"), default=None,
                   help="rollout length, s (default 2)")
    p.add_argument("--dt", type=positive("--dt"), default=None,
                   help="time step, s (default 1e-3)")
    p.add_argument("--settle-tol", type=positive("--settle-tol"), default=None,
                   help="settling band, m (default 1e-3)")
    p.add_argument("--chunk", type=count("--chunk"), default=None, help="points per vmapped "
                   "call (bounds memory; default 512, 32 with SCENE.toml)")
    p.add_argument("--out", default="sweep.npz", help="results .npz (default: sweep.npz in "
                   "the current folder; a .csv is written beside it); an interrupted sweep "
                   "with the same settings resumes from it, "
                   "a file of other settings is refused, and so is a .csv there that is not "
                   "its table")
    p.add_argument("--fresh", action="store_true", help="overwrite an existing --out file "
                   "instead of resuming it")
    p.add_argument("--plot", metavar="FILE.png", help="heatmap of --metric over (k, c)")
    p.add_argument("--metric", default=None, choices=METRICS + RECORD_METRICS,
                   help="metric of the heatmap (default apex_heights: the first apex; "
                   "position_error_pct for a scene file's sweep over records)")
    p.add_argument("--target", type=finite("--target"),
                   help="draw this level of --metric as a contour")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_cluster_arguments(p)


def run(args) -> int:
    try:
        if args.scene is not None:
            return _run_scene(args)
        if args.param or args.data or args.first_state or args.flight_frames:
            raise CLIError("--param, --data, --first-state and --flight-frames sweep a scene "
                           "file: give SCENE.toml first")
        for name, value in BALL_DEFAULTS.items():
            if getattr(args, name) is None:
                setattr(args, name, value)
        args.n = args.n or [64]
        args.chunk = args.chunk or 512
        args.metric = args.metric or "apex_heights"
        if args.metric not in METRICS:
            raise CLIError(f"--metric {args.metric} needs a scene file's sweep over records; "
                           f"the ball's metrics are {', '.join(METRICS)}")
        return _run(args)
    except (CLIError, ValueError, ImportError, OSError) as exc:
        return fail("sweep", str(exc))


#: ball-steps per second assumed for the time estimate (float64 sweep with metrics on a
#: 2-core CPU measured ~3e7/s; a conservative figure)
RATE = 1e7
#: bytes per point and step of a chunk's live arrays (recorded heights and the metrics'
#: intermediates; generous)
CHUNK_BYTES = 64
#: float columns per point kept in memory, the .npz and the .csv
COLUMNS = 18


def check_size(points: int, steps: int, chunk: int, memory: float | None = None) -> dict:
    """Estimates of a sweep's memory and time; raises CLIError when it cannot fit
    (:func:`tuning.sweep_files.refuse_oversized`, as a scene file's sweep)."""
    from diffpen.checks import human_time

    from ..sweep_files import refuse_oversized
    results = points * COLUMNS * 8 * 3            # in memory, the .npz and the .csv table
    live = min(chunk, points) * steps * CHUNK_BYTES
    seconds = points * steps / RATE
    refuse_oversized(points, results, f"a chunk of {min(chunk, points)} points x {steps} steps",
                     live, f"about {human_time(seconds)} of compute ({points} points x {steps}"
                     f" steps at ~{RATE:.0e} ball-steps/s)", "lower --n",
                     "lower --chunk or --duration, or raise --dt", error=CLIError,
                     memory=memory)
    return {"points": points, "steps": steps, "result_bytes": results, "chunk_bytes": live,
            "seconds": seconds}


def _run(args) -> int:
    if len(args.n) not in (1, 2) or min(args.n) < 2:
        raise CLIError("--n takes one or two integers >= 2 (points per axis)")
    nk, nc = (args.n * 2)[:2]
    if args.k[0] >= args.k[1] or args.c[0] >= args.c[1]:
        raise CLIError("ranges must be given as MIN MAX with MIN < MAX")
    if not args.drop > args.radius:
        raise CLIError(f"--drop {args.drop} m must exceed --radius {args.radius} m")
    steps = int(round(args.duration / args.dt))
    if steps < 3:
        raise CLIError(f"--duration {args.duration:g} s is only {steps} step(s) of --dt "
                       f"{args.dt:g} s: give a duration of at least 3 steps "
                       f"({3 * args.dt:g} s; the ball needs "
                       f"{math.sqrt(2 * (args.drop - args.radius) / 9.81):.3g} s to reach "
                       "the ground)")
    w_max = math.sqrt(args.k[1] / args.mass) * args.dt
    from diffpen.stability import stable_dt       # the one home of the step limit
    if not stable_dt("semi_implicit_euler", args.k[1] / args.mass,
                     args.c[1] / args.mass) > args.dt:
        raise CLIError(f"k={args.k[1]:g} N/m, c={args.c[1]:g} N s/m is past the stability limit "
                       f"of dt={args.dt:g} s (k dt^2 + 2 c dt < 4 m): lower --dt or the ranges")
    est = check_size(nk * nc, steps, args.chunk)
    _check_outputs(args)
    check_cluster_arguments(args)
    setup_jax()
    import diffpen as dp        # before the join starts JAX's backend (diffpen's XLA options)
    # process 0 alone writes and prints; in a cluster it checks its outputs after the join
    quiet = join_cluster(args, lambda: _check_outputs(args, files=True)) \
        and not _is_writer()
    import numpy as np

    from ..bounce import bounce_metrics_fn
    from ..io import describe_simulator
    from ..scenes import ball_scene
    from ..stable import contact_unstable
    from ..sweep import grid_points, sweep
    scene = ball_scene(radius=args.radius, mass=args.mass, height=args.drop)
    sim = dp.compile(scene, args.dt)
    mfn = bounce_metrics_fn(sim, steps, n_apex=3, settle_tol=args.settle_tol)

    def finalize(m, pts):
        # settling not reached within the rollout: NaN, not the rollout's end
        m["settling_time"] = np.where(m["settled"], m["settling_time"], np.nan)
        if "unstable" not in m:     # an evaluator without the flag: its parameter form
            p = sim.params(contact={"default": (1.0, 1.0)})
            p = p._replace(contact={"default": p.contact["default"]._replace(
                k=pts[:, 0], c=pts[:, 1])})
            m["unstable"] = np.asarray(contact_unstable(sim, p))
        return m
    ks = np.geomspace(args.k[0], args.k[1], nk)
    cs = np.geomspace(args.c[0], args.c[1], nc)
    names = ["contact.default.k", "contact.default.c"]
    axes = {names[0]: ks, names[1]: cs}
    points, shape = grid_points(axes)
    key = dict(describe_simulator(sim), model="ball on plane z=0", radius=args.radius,
               mass=args.mass, drop=args.drop, gravity=9.81, duration=args.duration,
               steps=steps, settle_tol=args.settle_tol, n_apex=3)
    if est["seconds"] > 60 and not args.json:
        import sys

        from diffpen.checks import human_time
        sys.stderr.write(f"diffpen sweep: {nk * nc} points x {steps} steps: about "
                         f"{human_time(est['seconds'])} at ~{RATE:.0e} ball-steps/s\n")
    res = sweep(mfn, sim.params(k=1e4, c=10.0), points, names, chunk=args.chunk, out=args.out,
                resume=not args.fresh, key=key, keys=list(METRICS) + ["settled"], shape=shape,
                axes=axes, progress=False if args.json or quiet else None, finalize=finalize)
    metric = res.metrics[args.metric]
    grid = (metric[:, 0] if metric.ndim > 1 else metric).reshape(shape)
    if quiet:
        return 0
    if args.plot:
        from ..plots import heatmap
        label = {"apex_heights": "first apex (m)", "settling_time": "settling time (s)",
                 "max_penetration": "max penetration (m)",
                 "contact_durations": "first contact duration (s)",
                 "restitution": "first restitution"}[args.metric]
        heatmap(args.plot, ks, cs, grid, metric=label, target=args.target,
                title=f"{label}: {nk}x{nc} sweep, {args.duration:g} s ball, dt={args.dt:g} s")
    drawn = _target_drawn(args, grid)
    finite_ = np.isfinite(grid)
    unsettled = _unsettled(res)
    out = {"points": int(points.shape[0]), "grid": [nk, nc], "evaluated": res.evaluated,
           "seconds": res.seconds, "out": args.out,
           "csv": args.out[:-4] + ".csv", "plot": args.plot,
           "metric": args.metric,
           "range": [float(np.nanmin(grid)), float(np.nanmax(grid))] if finite_.any() else None,
           "w0_dt_max": w_max, "unstable": res.unstable, "unsettled": unsettled}
    if drawn is not None:
        out["target_drawn"] = drawn
    if args.json:
        dump_json(out)
        return 0
    print(f"diffpen sweep: {nk} x {nc} grid, k {args.k[0]:g}..{args.k[1]:g} N/m, c "
          f"{args.c[0]:g}..{args.c[1]:g} N s/m (log-spaced), {args.duration:g} s ball at "
          f"dt={args.dt:g} s")
    print(f"computed {res.evaluated} of {points.shape[0]} points in {res.seconds:.2f} s "
          f"(the rest resumed from {args.out})" if res.evaluated < points.shape[0] else
          f"computed {res.evaluated} points in {res.seconds:.2f} s (compilation included)")
    if out["range"]:
        print(f"{args.metric}: {out['range'][0]:.4g} .. {out['range'][1]:.4g} over the grid")
    if unsettled:
        print(f"{unsettled} points did not settle within {args.duration:g} s: their "
              "settling_time is NaN" + (f" (besides the {res.unstable} past the safe "
                                        "step)" if res.unstable else ""))
    if res.unstable:
        print(f"{res.unstable} points are past the explicit step's safe limit (w0 dt > 0.5 or "
              "c dt / m > 1): their metrics are NaN (lower --dt to compute them)")
    print(f"wrote {args.out} and {out['csv']}" + (f"; heatmap {args.plot}" if args.plot else ""))
    if w_max > 0.25:
        print(f"note: w0 dt reaches {w_max:.2f} at the stiff end; above ~0.25 the explicit "
              "step's error in restitution exceeds ~0.5% (lower --dt for accuracy there)")
    return 0


def _unsettled(res) -> int:
    """Points within the safe step that did not settle (those past it are counted apart, in
    ``res.unstable``: their ``settled`` is False, not a result)."""
    import numpy as np
    n = res.points.shape[0]
    settled = np.asarray(res.metrics["settled"], bool).reshape(n, -1).all(axis=1)
    unstable = np.asarray(res.metrics.get("unstable", np.zeros(n, bool)),
                          bool).reshape(n, -1).any(axis=1)
    return int(np.sum(res.done & ~settled & ~unstable))


def _is_writer() -> bool:
    from ..distributed import is_writer
    return is_writer()


def _target_drawn(args, values) -> bool | None:
    """Whether ``--target``'s contour is drawn on ``--plot`` (None without ``--target``): only
    a level strictly inside the finite values' range has one. When it is not, one line on
    standard error says so (the plot alone would not)."""
    if args.target is None or not args.plot:
        return None
    import sys

    import numpy as np
    v = np.asarray(values, float)
    ok = bool(np.isfinite(v).any()) and float(np.nanmin(v)) < args.target < float(np.nanmax(v))
    if not ok:
        span = (f"{np.nanmin(v):.4g} .. {np.nanmax(v):.4g}" if np.isfinite(v).any()
                else "no finite values")
        sys.stderr.write(f"diffpen sweep: --target {args.target:g} is outside the grid's "
                         f"{args.metric} ({span}): no contour on {args.plot}; widen the grid "
                         "or give a level inside that range\n")
    return ok


def _run_scene(args) -> int:
    """``diffpen sweep SCENE.toml``: :func:`tuning.scene_sweep.sweep_scene_file`.

    Against records, ``unstable`` (JSON) counts the points where every record's rollout went
    past the safe step (their metrics are NaN), and ``points_with_unstable_records`` the
    points where some but not all were (left out of that point's errors, which are over the
    other records; per point in the ``unstable_records`` column)."""
    if not args.scene.lower().endswith(".toml"):
        raise CLIError(f"{args.scene}: give a scene file (.toml)")
    ball_only = [f"--{n.replace('_', '-')}" for n in BALL_DEFAULTS if getattr(args, n)
                 is not None]
    if ball_only:
        raise CLIError(f"{', '.join(ball_only)} set the built-in ball's sweep; a scene file "
                       "sweeps --param PATH LO HI (its dt, duration and bodies are in the file)")
    _check_outputs(args)
    check_cluster_arguments(args)
    axes = [(p, finite(f"--param {p} LO")(lo), finite(f"--param {p} HI")(hi))
            for p, lo, hi in (args.param or [])]
    setup_jax()
    import diffpen  # noqa: F401 - before the join starts JAX's backend (its XLA options)
    quiet = join_cluster(args, lambda: _check_outputs(args, files=True)) \
        and not _is_writer()
    import numpy as np

    from ..distributed import from_process_zero
    from ..scene_sweep import sweep_scene_file

    def check(plan):            # before anything is computed or written
        kept, names = plan["metrics"], list(plan["axes"])
        if not plan["data"] and (args.first_state or args.flight_frames):
            raise CLIError("--first-state and --flight-frames set how records start; this "
                           "sweep has none (give --data FILES, or [fit] data in the file)")
        from ..io import check_distinct     # the file's own [fit] data are inputs too
        # checked by process 0, the one that writes; its error stops every process
        from_process_zero(lambda: check_distinct(
            {"--out": args.out, "--out's table": args.out[:-4] + ".csv",
             "--plot": args.plot}, inputs=plan["data"]))
        if (args.metric or kept[0]) not in kept:
            raise CLIError(f"--metric {args.metric} is not measured by this sweep; it "
                           f"measures {', '.join(kept)}")
        if args.plot and len(names) != 2:
            raise CLIError(f"--plot draws a sweep over two parameters; this one has "
                           f"{len(names)}: {', '.join(names)}")
    res, info = sweep_scene_file(args.scene, args.data or (), axes or None,
                                 n=args.n or [16], out=args.out, resume=not args.fresh,
                                 chunk=args.chunk or 32, estimate=args.first_state,
                                 max_frames=args.flight_frames,
                                 progress=False if args.json or quiet else None, check=check)
    if quiet:
        return 0
    kept = info["metrics"]
    metric = args.metric or kept[0]
    values = np.asarray(res.metrics[metric], float)
    values = values[:, 0] if values.ndim > 1 else values
    names = list(info["axes"])
    finite_ = np.isfinite(values)
    best = None
    if finite_.any():
        i = int(np.nanargmin(values))
        best = {"value": float(values[i]),
                "point": {n: float(res.points[i, j]) for j, n in enumerate(names)}}
    if args.plot:
        from ..plots import heatmap
        ax0, ax1 = (info["axes"][n] for n in names)
        logs = tuple(bool(a[0] > 0 and np.allclose(np.diff(np.log(a)), np.log(a[1] / a[0])))
                     for a in (ax0, ax1))
        heatmap(args.plot, ax0, ax1, values.reshape(res.shape), metric=metric,
                target=args.target, labels=tuple(names), log=logs,
                point=None if best is None else tuple(best["point"].values()),
                title=f"{metric}: {len(ax0)} x {len(ax1)} sweep of "
                      f"{os.path.basename(args.scene)}"
                      + (f", {info['records']} record{'s' if info['records'] != 1 else ''}"
                         if info["records"] else ""))
    out = {"scene": args.scene, "points": int(res.points.shape[0]),
           "grid": [len(a) for a in info["axes"].values()],
           "axes": {n: [float(a[0]), float(a[-1])] for n, a in info["axes"].items()},
           "records": info["records"], "metrics": kept, "metric": metric,
           "evaluated": res.evaluated, "seconds": res.seconds, "out": args.out,
           "csv": args.out[:-4] + ".csv", "plot": args.plot,
           "range": [float(np.nanmin(values)), float(np.nanmax(values))]
           if finite_.any() else None, "lowest": best, "unstable": res.unstable}
    if "settled" in res.metrics:        # the bounce: as the ball's sweep reports it
        out["unsettled"] = _unsettled(res)
    left = np.asarray(res.metrics.get("unstable_records", np.zeros(0)))
    partial = np.zeros(0, bool)
    if left.size:   # records past the safe step, left out of a point's errors: the points
        # that still have a result (all records left out: counted in res.unstable)
        left = left.reshape(left.shape[0], -1)[:, 0]
        flagged = np.asarray(res.metrics.get("unstable", np.zeros(left.shape[0], bool)),
                             bool).reshape(left.shape[0], -1).any(axis=1)
        partial = res.done & ~flagged & (left > 0) & (left < info["records"])
        out["points_with_unstable_records"] = int(np.count_nonzero(partial))
    crushed = np.asarray(res.metrics.get("collapsed_records", np.zeros(0)))
    if crushed.size:    # a plastic spring collapsed (diffpen.terms.plastic): past the model
        out["points_with_collapsed_records"] = int(np.count_nonzero(
            res.done & (crushed.reshape(crushed.shape[0], -1)[:, 0] > 0)))
    if args.json:
        dump_json(out)
        return 0
    against = (f"{info['records']} record(s)" if info["records"] else "the bounce of its "
               "[fit] body")
    print(f"diffpen sweep: {args.scene}, {' x '.join(map(str, out['grid']))} grid against "
          f"{against}")
    for n, a in info["axes"].items():
        print(f"  {n}: {a[0]:.4g} .. {a[-1]:.4g} ({len(a)} points)")
    print(f"computed {res.evaluated} of {out['points']} points in {res.seconds:.2f} s"
          + (f" (the rest resumed from {args.out})" if res.evaluated < out["points"] else ""))
    if best is not None:
        where = ", ".join(f"{n} = {v:.4g}" for n, v in best["point"].items())
        print(f"{metric}: {out['range'][0]:.4g} .. {out['range'][1]:.4g}; lowest at {where}")
    if res.unstable:
        print(f"{res.unstable} points are past the scene's safe step: their metrics are NaN "
              "(lower dt in the scene file to compute them)")
    if out.get("points_with_collapsed_records"):
        print(f"{out['points_with_collapsed_records']} points crushed a plastic spring of some "
              "record below 5% of its length (the collapsed_records column), past what the "
              "model describes (no self-contact): their errors are not to be trusted")
    if out.get("points_with_unstable_records"):
        print(f"{out['points_with_unstable_records']} points left out records whose rollouts "
              f"went past the safe step (up to {int(left[partial].max())} of "
              f"{info['records']}; the unstable_records column): their errors are over the "
              "other records")
    if out.get("unsettled"):
        print(f"{out['unsettled']} points did not settle within the scene's duration: their "
              "settling_time is NaN" + (f" (besides the {res.unstable} past the safe "
                                        "step)" if res.unstable else ""))
    print(f"wrote {args.out} and {out['csv']}" + (f"; heatmap {args.plot}" if args.plot else ""))
    return 0


def _check_outputs(args, files: bool | None = None) -> None:
    """``--out`` (a ``.npz``), its ``.csv`` and ``--plot`` (a figure type) writable, none of
    them an input (the scene file, a record) nor the same file as another, checked by
    process 0 (the one that writes) before anything is computed: running alone, before JAX is
    set up; in a cluster, once every process has joined (``files=True``, through
    :func:`._common.join_cluster`), so that its error stops every process, not process 0
    alone while the others wait for it. ``files=None``: the files are checked unless the
    arguments describe a cluster."""
    if args.target is not None and not args.plot:
        raise CLIError("--target marks a contour on the --plot heatmap; give --plot FILE.png "
                       "too")
    writer = not in_cluster(args) if files is None else files
    if writer:
        from ..io import check_output
        check_output(args.out, what="--out")
    if not args.out.endswith(".npz"):
        raise CLIError(f"--out {args.out} must end in .npz (a .csv is written beside it)")
    if writer:
        from ..io import check_distinct, check_plot
        table = args.out[:-4] + ".csv"
        check_output(table, what="--out's table", derived_from="--out")
        if args.plot:
            check_plot(args.plot, what="--plot")
        scene = getattr(args, "scene", None)
        check_distinct({"--out": args.out, "--out's table": table, "--plot": args.plot},
                       inputs=[scene, *(getattr(args, "data", None) or [])])
        if args.plot:
            from ..plots import require_matplotlib
            require_matplotlib()
