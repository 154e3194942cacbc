"""A rope pinned at one end swings down from horizontal and wraps around a fixed peg.

Run:  python examples/rope_swing.py [--quick] [--out examples/images/rope_swing.png] [--gif]

Saves a strip of frames (side view, x-z) as a PNG and, with ``--gif``, an animation.
Needs the ``plot`` extra (matplotlib) for the pictures.
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import diffpen as dp
from diffpen.builders import add_rope
from _common import example_parser, example_pyplot, save_gif, save_strip


def build(n: int):
    """Rope of ``n`` nodes, 1 m long, 0.2 kg, pinned at (0, 0, 1.5), lying along +x; a fixed
    peg of radius 10 cm sits below it."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    nodes = add_rope(scene, n, (0.0, 0.0, 1.5), (1.0, 0.0, 1.5), mass=0.2, k=40.0 * n,
                     c=0.02 * n, bend=(0.2 * n, 0.0), drag=0.002, pinned=[0])
    scene.add_fixed_sphere((0.35, 0.0, 0.95), 0.1)
    scene.add_plane()
    return scene, nodes


def main(argv=None) -> int:
    ap = example_parser(" ".join(__doc__.split("\n\n")[0].split()), "examples/images/rope_swing.png",
                        quick_help="coarser rope, shorter run (seconds)",
                        gif_help="also write an animated GIF next to --out")
    args = ap.parse_args(argv)

    n, seconds = (12, 1.5) if args.quick else (30, 3.0)
    scene, nodes = build(n)
    dt = 5e-4
    sim = dp.compile(scene, dt=dt)
    params = sim.params(k=2e3, c=2.0)
    steps = int(round(seconds / dt))
    save = 20
    t0 = time.perf_counter()
    traj = sim.rollout(params, steps, save_every=save)
    x = np.asarray(traj.position)
    print(f"rope: {n} nodes, {len(scene.springs)} springs, {steps} steps of {dt} s in "
          f"{time.perf_counter() - t0:.2f} s (incl. compile); terms {sim.terms}")
    tip = x[:, nodes[-1]]
    print(f"tip lowest z = {tip[:, 2].min():.3f} m; final tip = {np.round(tip[-1], 3)} m")
    _draw(x, nodes, np.asarray(traj.time), pathlib.Path(args.out), args.gif)
    return 0


def _draw(x, nodes, t, out, gif):
    if example_pyplot(out) is None:
        return

    def draw(ax, f):
        _frame(ax, x[f], nodes, t[f])
    save_strip(draw, np.linspace(0, len(t) - 1, 6).astype(int), out,
               title="rope swinging from a pin onto a fixed peg (side view)")
    if gif:
        save_gif(draw, range(0, len(t), max(1, len(t) // 60)), out, figsize=(3.5, 3.5), fps=20)


def _frame(ax, x, nodes, t):
    import matplotlib.pyplot as plt
    ax.add_patch(plt.Circle((0.35, 0.95), 0.1, color="0.6"))
    p = x[nodes]
    ax.plot(p[:, 0], p[:, 2], "-o", ms=2, color="tab:brown")
    ax.plot([0.0], [1.5], "ks", ms=5)
    ax.set_xlim(-0.8, 1.1)
    ax.set_ylim(0.25, 1.65)
    ax.set_aspect("equal")
    ax.set_title(f"t = {t:.2f} s", fontsize=9)
    ax.set_xlabel("x (m)")


if __name__ == "__main__":
    raise SystemExit(main())
