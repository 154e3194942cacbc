"""``diffpen sweep``: every (k, c) of a log-spaced grid for the ball scene, with jax.vmap in
chunks; writes .npz + .csv atomically after every chunk, resumes an interrupted sweep, and
draws a heatmap with the target contour."""
from __future__ import annotations

import math

from ._common import (CLIError, add_cluster_arguments, check_cluster_arguments, dump_json,
                      fail, join_cluster, positive, setup_jax)

METRICS = ("apex_heights", "settling_time", "max_penetration", "contact_durations",
           "restitution")


def add_arguments(p) -> None:
    p.add_argument("--k", type=positive("--k"), nargs=2, default=[1e3, 1e5],
                   metavar=("KMIN", "KMAX"), help="stiffness range, N/m (default 1e3 1e5)")
    p.add_argument("--c", type=positive("--c"), nargs=2, default=[1.0, 100.0],
                   metavar=("CMIN", "CMAX"), help="damping range, N s/m (default 1 100)")
    p.add_argument("--n", type=int, nargs="+", default=[64], metavar="N",
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
    p.add_argument("--chunk", type=int, default=512, help="points per vmapped call "
                   "(bounds memory; default 512)")
    p.add_argument("--out", default="sweep.npz", help="results .npz (a .csv is written "
                   "beside it); an interrupted sweep with the same grid resumes from it")
    p.add_argument("--fresh", action="store_true", help="ignore an existing --out file")
    p.add_argument("--plot", metavar="FILE.png", help="heatmap of --metric over (k, c)")
    p.add_argument("--metric", default="apex_heights", choices=METRICS,
                   help="metric of the heatmap (default apex_heights: the first apex)")
    p.add_argument("--target", type=float, help="draw this level of --metric as a contour")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_cluster_arguments(p)


def run(args) -> int:
    try:
        return _run(args)
    except (CLIError, ValueError, ImportError, OSError) as exc:
        return fail("sweep", str(exc))


def _run(args) -> int:
    if len(args.n) not in (1, 2) or min(args.n) < 2:
        raise CLIError("--n takes one or two integers >= 2 (points per axis)")
    nk, nc = (args.n * 2)[:2]
    if args.k[0] >= args.k[1] or args.c[0] >= args.c[1]:
        raise CLIError("ranges must be given as MIN MAX with MIN < MAX")
    if args.chunk < 1:
        raise CLIError("--chunk must be >= 1")
    if not args.drop > args.radius:
        raise CLIError(f"--drop {args.drop} m must exceed --radius {args.radius} m")
    w_max = math.sqrt(args.k[1] / args.mass) * args.dt
    stable = args.k[1] * args.dt ** 2 + 2 * args.c[1] * args.dt < 4 * args.mass
    if not stable:
        raise CLIError(f"k={args.k[1]:g} N/m, c={args.c[1]:g} N s/m is past the stability limit "
                       f"of dt={args.dt:g} s (k dt^2 + 2 c dt < 4 m): lower --dt or the ranges")
    check_cluster_arguments(args)
    setup_jax()
    quiet = join_cluster(args) and not _is_writer()     # process 0 alone writes and prints
    import numpy as np

    import diffpen as dp

    from ..bounce import bounce_metrics_fn
    from ..sweep import grid_points, sweep
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=args.radius, mass=args.mass, position=(0.0, 0.0, args.drop))
    scene.add_plane()
    sim = dp.compile(scene, args.dt)
    steps = int(round(args.duration / args.dt))
    mfn = bounce_metrics_fn(sim, steps, n_apex=3, settle_tol=args.settle_tol)
    ks = np.geomspace(args.k[0], args.k[1], nk)
    cs = np.geomspace(args.c[0], args.c[1], nc)
    names = ["contact.default.k", "contact.default.c"]
    axes = {names[0]: ks, names[1]: cs}
    points, shape = grid_points(axes)

    def keep(m):     # settling not reached within the rollout: nan, not the rollout's end
        m = dict(m)
        m["settling_time"] = np.where(m["settled"], m["settling_time"], np.nan)
        return m
    res = sweep(mfn, sim.params(k=1e4, c=10.0), points, names, chunk=args.chunk, out=args.out,
                resume=not args.fresh, keys=list(METRICS) + ["settled"], shape=shape,
                axes=axes, progress=False if args.json or quiet else None)
    vals = keep(res.metrics)
    metric = vals[args.metric]
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
    finite = np.isfinite(grid)
    out = {"points": int(points.shape[0]), "grid": [nk, nc], "evaluated": res.evaluated,
           "seconds": res.seconds, "out": args.out,
           "csv": args.out.rsplit(".", 1)[0] + ".csv", "plot": args.plot,
           "metric": args.metric,
           "range": [float(np.nanmin(grid)), float(np.nanmax(grid))] if finite.any() else None,
           "w0_dt_max": w_max}
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
    print(f"wrote {args.out} and {out['csv']}" + (f"; heatmap {args.plot}" if args.plot else ""))
    if w_max > 0.25:
        print(f"note: w0 dt reaches {w_max:.2f} at the stiff end; above ~0.25 the explicit "
              "step's error in restitution exceeds ~0.5% (lower --dt for accuracy there)")
    return 0


def _is_writer() -> bool:
    from ..distributed import is_writer
    return is_writer()
