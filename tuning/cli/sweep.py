"""``diffpen sweep``: every (k, c) of a log-spaced grid for the ball scene, with jax.vmap in
chunks; writes .npz + .csv atomically after every chunk, resumes an interrupted sweep, and
draws a heatmap with the target contour."""
from __future__ import annotations

import math

from ._common import (CLIError, add_cluster_arguments, check_cluster_arguments, count,
                      dump_json, fail, finite, join_cluster, positive, setup_jax)

METRICS = ("apex_heights", "settling_time", "max_penetration", "contact_durations",
           "restitution")


def add_arguments(p) -> None:
    p.add_argument("--k", type=positive("--k"), nargs=2, default=[1e3, 1e5],
                   metavar=("KMIN", "KMAX"), help="stiffness range, N/m (default 1e3 1e5)")
    p.add_argument("--c", type=positive("--c"), nargs=2, default=[1.0, 100.0],
                   metavar=("CMIN", "CMAX"), help="damping range, N s/m (default 1 100)")
    p.add_argument("--n", type=count("--n"), nargs="+", default=[64], metavar="N",
                   help="grid points per axis (one value for both, or NK NC; default 64)")
    p.add_argument("--radius", type=positive("--radius"), default=0.1, help="m (default 0.1)")
    p.add_argument("--mass", type=positive("--mass"), default=1.0, help="kg (default 1)")
    p.add_argument("--drop", type=positive("--drop"), default=1.0,
                   help="initial centre height, m (default 1)")
    p.add_argument("--duration", type=positive("--duration"), default=2.0,
                   help="rollout length, s (default 2)")
    p.add_argument("--dt", type=positive("--dt"), default=1e-3, help="time step, s")
    p.add_argument("--settle-tol", type=positive("--settle-tol"), default=1e-3,
                   help="settling band, m")
    p.add_argument("--chunk", type=count("--chunk"), default=512, help="points per vmapped call "
                   "(bounds memory; default 512)")
    p.add_argument("--out", default="sweep.npz", help="results .npz (a .csv is written "
                   "beside it); an interrupted sweep with the same settings resumes from it, "
                   "a file of other settings is refused")
    p.add_argument("--fresh", action="store_true", help="overwrite an existing --out file "
                   "instead of resuming it")
    p.add_argument("--plot", metavar="FILE.png", help="heatmap of --metric over (k, c)")
    p.add_argument("--metric", default="apex_heights", choices=METRICS,
                   help="metric of the heatmap (default apex_heights: the first apex)")
    p.add_argument("--target", type=finite("--target"),
                   help="draw this level of --metric as a contour")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_cluster_arguments(p)


def run(args) -> int:
    try:
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


def _gib(b: float) -> str:
    return f"{b / 2 ** 30:.3g} GiB"


def check_size(points: int, steps: int, chunk: int, memory: float | None = None) -> dict:
    """Estimates of a sweep's memory and time; raises CLIError when it cannot fit."""
    from diffpen.checks import human_time, memory_bytes
    memory = memory_bytes() if memory is None else memory
    results = points * COLUMNS * 8 * 3            # in memory, the .npz and the .csv table
    live = min(chunk, points) * steps * CHUNK_BYTES
    seconds = points * steps / RATE
    est = {"points": points, "steps": steps, "result_bytes": results, "chunk_bytes": live,
           "seconds": seconds}
    if results > 0.5 * memory:
        raise CLIError(f"{points} points need about {_gib(results)} for the results alone "
                       f"(this machine has {_gib(memory)}) and about {human_time(seconds)} of "
                       f"compute ({points} points x {steps} steps at ~{RATE:.0e} ball-steps/s):"
                       " lower --n")
    if live > 0.5 * memory:
        raise CLIError(f"a chunk of {min(chunk, points)} points x {steps} steps needs about "
                       f"{_gib(live)} (this machine has {_gib(memory)}): lower --chunk or "
                       "--duration")
    if seconds > 7 * 86400:
        raise CLIError(f"{points} points x {steps} steps would take about {human_time(seconds)}"
                       f" at ~{RATE:.0e} ball-steps/s: lower --n or --duration")
    return est


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
    if getattr(args, "process_id", None) in (None, 0):      # process 0 alone writes
        from ..io import check_output
        check_output(args.out, what="--out")
    if not args.out.endswith(".npz"):
        raise CLIError(f"--out {args.out} must end in .npz (a .csv is written beside it)")
    if getattr(args, "process_id", None) in (None, 0):
        check_output(args.out[:-4] + ".csv", what="--out's table")
        if args.plot:
            check_output(args.plot, what="--plot")
            from ..plots import require_matplotlib
            require_matplotlib()
    check_cluster_arguments(args)
    setup_jax()
    quiet = join_cluster(args) and not _is_writer()     # process 0 alone writes and prints
    import numpy as np

    import diffpen as dp

    from ..io import describe_simulator
    from ..metrics import ball_metrics
    from ..scenes import ball_scene
    from ..stable import contact_unstable, rollout_unstable
    from ..sweep import grid_points, sweep
    scene = ball_scene(radius=args.radius, mass=args.mass, height=args.drop)
    sim = dp.compile(scene, args.dt)

    def mfn(params):
        s0 = sim.init_state()
        # the metrics read every state: the whole trajectory, said explicitly
        traj = sim.rollout(params, steps, s0, save_every=1, check_finite=False)
        m = ball_metrics(sim, traj, params, n_apex=3, settle_tol=args.settle_tol,
                         state0=s0)._asdict()
        m["unstable"] = rollout_unstable(sim, traj, params)      # the traced flag
        return m

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
    finite_ = np.isfinite(grid)
    unsettled = int(np.sum(~np.asarray(res.metrics["settled"], bool)))
    out = {"points": int(points.shape[0]), "grid": [nk, nc], "evaluated": res.evaluated,
           "seconds": res.seconds, "out": args.out,
           "csv": args.out[:-4] + ".csv", "plot": args.plot,
           "metric": args.metric,
           "range": [float(np.nanmin(grid)), float(np.nanmax(grid))] if finite_.any() else None,
           "w0_dt_max": w_max, "unstable": res.unstable, "unsettled": unsettled}
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
              "settling_time is NaN")
    if res.unstable:
        print(f"{res.unstable} points are past the explicit step's safe limit (w0 dt > 0.5 or "
              "c dt / m > 1): their metrics are NaN (lower --dt to compute them)")
    print(f"wrote {args.out} and {out['csv']}" + (f"; heatmap {args.plot}" if args.plot else ""))
    if w_max > 0.25:
        print(f"note: w0 dt reaches {w_max:.2f} at the stiff end; above ~0.25 the explicit "
              "step's error in restitution exceeds ~0.5% (lower --dt for accuracy there)")
    return 0


def _is_writer() -> bool:
    from ..distributed import is_writer
    return is_writer()
