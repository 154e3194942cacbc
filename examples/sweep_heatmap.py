"""A 64 x 64 sweep of the 2 s ball scene over (k, c) with jax.vmap, and heatmaps of the first
apex and the maximum penetration with target contours.

Results go to sweep_heatmap.npz (+ .csv) in the current folder (``--out`` to choose): run it
twice and the second run resumes from the file (nothing is recomputed). The file carries a key
of everything that determines it, so a file of other settings is refused, never mixed in
(``--fresh`` overwrites it); a second run writing the same file at the same time is refused.
Figures: sweep_apex.png and sweep_penetration.png in --figures (default examples/images;
needs matplotlib).

Run: python examples/sweep_heatmap.py [--out FILE.npz] [--fresh] [--n N]
"""
import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import diffpen as dp  # noqa: E402
from tuning.bounce import bounce_metrics_fn  # noqa: E402
from tuning.io import describe_simulator  # noqa: E402
from tuning.scenes import ball_scene  # noqa: E402
from tuning.sweep import grid_points, sweep  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def run(n=64, duration=2.0, dt=1e-3, out="sweep_heatmap.npz", fresh=False,
        figures=os.path.join(HERE, "images")):
    if figures:             # the figures' folder first: a missing one must not cost the sweep
        os.makedirs(figures, exist_ok=True)
    sim = dp.compile(ball_scene(radius=0.1, mass=1.0, height=1.0), dt)
    mfn = bounce_metrics_fn(sim, int(round(duration / dt)), n_apex=2)
    ks, cs = np.geomspace(1e3, 1e5, n), np.geomspace(1.0, 100.0, n)
    axes = {"contact.default.k": ks, "contact.default.c": cs}
    points, shape = grid_points(axes)
    t0 = time.perf_counter()
    key = dict(describe_simulator(sim), model="ball dropped from 1 m", duration=duration,
               n_apex=2, settle_tol=1e-3)
    res = sweep(mfn, sim.params(k=1e4, c=10.0), points, list(axes), chunk=512, out=out,
                resume=not fresh, key=key, shape=shape, axes=axes,
                keys=["apex_heights", "max_penetration", "settled", "settling_time"])
    wall = time.perf_counter() - t0
    print(f"{n} x {n} sweep of the {duration:g} s ball (dt={dt:g} s): {res.evaluated} points "
          f"computed in {wall:.2f} s (compilation included)"
          + (", the rest resumed from the file" if res.evaluated < len(points) else ""))
    apex = res.grid("apex_heights", 0)
    pen = res.grid("max_penetration")
    print(f"first apex {np.nanmin(apex):.4f}..{np.nanmax(apex):.4f} m, max penetration "
          f"{np.nanmin(pen) * 1e3:.2f}..{np.nanmax(pen) * 1e3:.1f} mm")
    if not figures:
        return
    try:
        from tuning.plots import heatmap
        heatmap(os.path.join(figures, "sweep_apex.png"), ks, cs, apex,
                metric="first apex (m)", target=0.4,
                title=f"first apex over (k, c), {n}x{n}, contour: 0.4 m")
        heatmap(os.path.join(figures, "sweep_penetration.png"), ks, cs, pen,
                metric="max penetration (m)", target=0.01,
                title=f"max penetration over (k, c), {n}x{n}, contour: 1 cm")
        print(f"figures: {os.path.join(figures, 'sweep_apex.png')}, sweep_penetration.png")
    except ImportError as exc:
        print(exc)


def main(argv=None):
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--out", default="sweep_heatmap.npz", help="results .npz (+ .csv)")
    ap.add_argument("--fresh", action="store_true", help="overwrite --out instead of resuming")
    ap.add_argument("--n", type=int, default=64, help="grid points per axis (default 64)")
    ap.add_argument("--figures", default=os.path.join(HERE, "images"),
                    help="folder for the two heatmaps (default examples/images; '' for none)")
    a = ap.parse_args(argv)
    run(n=a.n, out=a.out, fresh=a.fresh, figures=a.figures)


if __name__ == "__main__":
    main()
