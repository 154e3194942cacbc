"""A jelly cube (3D spring lattice with edge, face- and body-diagonal springs) dropped onto the
ground, tilted, so it lands on an edge, squashes, bounces and settles.

Run:  python examples/jelly_drop.py [--quick] [--out examples/images/jelly_drop.png] [--gif]
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import diffpen as dp
from diffpen.builders import add_jelly
from _common import example_parser, example_pyplot, save_gif, save_strip


def build(n: int):
    """An n x n x n jelly, 0.2 m wide, 1 kg, corner (0, 0, 0.4) m, rotated 25 degrees about y."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    h = 0.2 / (n - 1)
    nodes = add_jelly(scene, n, n, n, h, mass=1.0, origin=(0.0, 0.0, 0.0),
                      edge=(60.0 * n, 0.05 * n), face=(40.0 * n, 0.03 * n),
                      body=(30.0 * n, 0.02 * n))
    # tilt: rewrite the start positions before compiling (rest lengths stay those of the
    # axis-aligned cube, so the rotated cube is unstressed)
    a = np.deg2rad(25.0)
    rot = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    import dataclasses
    for i in nodes.ravel():
        b = scene.bodies[int(i)]
        p = rot @ (np.array(b.position) - 0.1) + np.array([0.0, 0.0, 0.5])
        scene.bodies[int(i)] = dataclasses.replace(b, position=tuple(p))
    scene.add_plane()
    return scene, nodes


def main(argv=None) -> int:
    ap = example_parser(" ".join(__doc__.split("\n\n")[0].split()), "examples/images/jelly_drop.png",
                        quick_help="coarser lattice, shorter run")
    args = ap.parse_args(argv)

    # 3 s: it bounces until about 2.3 s; its centre is at rest (< 1 cm/s) by 2.8 s, its
    # nodes still wobble (up to 0.15 m/s at 3 s)
    n, seconds = (3, 1.0) if args.quick else (5, 3.0)
    scene, nodes = build(n)
    dt = 5e-4
    sim = dp.compile(scene, dt=dt)
    params = sim.params(k=5e3, c=5.0)
    steps = int(round(seconds / dt))
    t0 = time.perf_counter()
    traj = sim.rollout(params, steps, save_every=20)
    x = np.asarray(traj.position)
    t = np.asarray(traj.time)
    print(f"jelly {n}^3: {scene.n_bodies} nodes, {len(scene.springs)} springs, {steps} steps in "
          f"{time.perf_counter() - t0:.2f} s (incl. compile)")
    zc = x[:, nodes.ravel(), 2].mean(axis=1)
    print(f"centre height: start {zc[0]:.3f} m, lowest {zc.min():.3f} m, end {zc[-1]:.3f} m; "
          f"lowest node at the end z = {x[-1, :, 2].min() * 1e3:.2f} mm")
    _draw(x, nodes, t, pathlib.Path(args.out), args.gif)
    return 0


def _edges(nodes):
    shape = nodes.shape
    out = []
    for i in range(shape[0]):
        for j in range(shape[1]):
            for k in range(shape[2]):
                for d in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
                    q = (i + d[0], j + d[1], k + d[2])
                    if all(a < s for a, s in zip(q, shape)):
                        out.append((nodes[i, j, k], nodes[q]))
    return out


def _draw(x, nodes, t, out, gif):
    if example_pyplot(out) is None:
        return
    edges = _edges(nodes)
    zc = x[:, nodes.ravel(), 2].mean(axis=1)
    first_low = int(np.argmin(zc[: len(zc) // 2]))
    frames = sorted({0, first_low // 2, first_low, (first_low + len(t)) // 3,
                     (2 * len(t)) // 3, len(t) - 1})

    def draw(ax, f):
        _frame(ax, x[f], edges, t[f])
    save_strip(draw, frames, out, title="jelly cube dropped on the ground (side view, x-z)",
               figsize_per_frame=(1.7, 3.0))
    if gif:
        save_gif(draw, range(0, len(t), max(1, len(t) // 60)), out, figsize=(3.2, 3.2), fps=20)


def _frame(ax, x, edges, t):
    from matplotlib.collections import LineCollection
    e = np.asarray(edges)
    segs = np.stack([x[e[:, 0]][:, [0, 2]], x[e[:, 1]][:, [0, 2]]], axis=1)
    ax.add_collection(LineCollection(segs, colors="tab:green", linewidths=0.8, alpha=0.7))
    ax.axhline(0.0, color="k", lw=1)
    ax.set_xlim(-0.25, 0.25)
    ax.set_ylim(-0.03, 0.65)
    ax.set_aspect("equal")
    ax.set_title(f"t = {t:.2f} s", fontsize=9)
    ax.set_xlabel("x (m)")


if __name__ == "__main__":
    raise SystemExit(main())
