"""A square cloth (structural, shear and bend springs) falls onto a fixed sphere standing on the
ground and drapes over it.

Run:  python examples/cloth_drape.py [--quick] [--out examples/images/cloth_drape.png] [--gif]

Cloth nodes are particles: they touch the sphere and the ground (penalty contact, no
friction, no self-collision).
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import diffpen as dp
from diffpen.builders import add_cloth
from _common import example_parser, example_pyplot, save_gif, save_strip

SIZE, R, HEIGHT = 0.8, 0.2, 0.5      # cloth side (m), sphere radius (m), cloth start height (m)


def build(n: int):
    """An n x n cloth, SIZE wide, 0.1 kg, centred over a sphere of radius R resting on z = 0."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    h = SIZE / (n - 1)
    s = (n - 1) / 14.0                     # keep the cloth's stiffness as n changes
    nodes = add_cloth(scene, n, n, h, mass=0.1, origin=(-SIZE / 2, -SIZE / 2, HEIGHT),
                      structural=(30.0 * s, 0.01 * s), shear=(10.0 * s, 0.005 * s),
                      bend=(0.5 * s, 0.0), drag=2e-4 / s ** 2)
    scene.add_fixed_sphere((0.0, 0.0, R), R)
    scene.add_plane()
    return scene, nodes


def main(argv=None) -> int:
    ap = example_parser(" ".join(__doc__.split("\n\n")[0].split()), "examples/images/cloth_drape.png",
                        quick_help="coarser cloth, shorter run")
    args = ap.parse_args(argv)

    n, seconds = (11, 1.2) if args.quick else (21, 2.0)
    scene, nodes = build(n)
    dt = 4e-4
    sim = dp.compile(scene, dt=dt)
    params = sim.params(k=30.0 * (14.0 / (n - 1)) ** 2, c=0.02 * (14.0 / (n - 1)) ** 2)
    steps = int(round(seconds / dt))
    t0 = time.perf_counter()
    traj = sim.rollout(params, steps, save_every=25)
    x = np.asarray(traj.position)
    t = np.asarray(traj.time)
    print(f"cloth {n}x{n}: {len(scene.springs)} springs, {steps} steps of {dt} s in "
          f"{time.perf_counter() - t0:.2f} s (incl. compile); terms {sim.terms}")
    top = x[-1, nodes[n // 2, n // 2]]
    r = np.linalg.norm(x - np.array([0.0, 0.0, R]), axis=2)       # (saved, nodes)
    print(f"centre node at z = {top[2]:.4f} m (sphere top {2 * R} m); deepest sphere "
          f"penetration {max(0.0, R - r.min()) * 1e3:.2f} mm over the saved frames "
          f"({max(0.0, R - r[-1].min()) * 1e3:.2f} mm at the end); corner z = "
          f"{x[-1, nodes[0, 0], 2]:.3f} m")
    _draw(x, nodes, t, pathlib.Path(args.out), args.gif)
    return 0


def _draw(x, nodes, t, out, gif):
    if example_pyplot(out) is None:
        return

    def draw(ax, f):
        _frame(ax, x[f], nodes, t[f])
    save_strip(draw, np.linspace(0, len(t) - 1, 4).astype(int), out,
               title="cloth draped over a fixed sphere", figsize=(12, 3.4), sharey=False,
               dpi=100, projection="3d")
    if gif:
        save_gif(draw, range(0, len(t), max(1, len(t) // 50)), out, figsize=(4, 3.6), fps=15,
                 projection="3d")


def _frame(ax, x, nodes, t):
    u, v = np.mgrid[0:2 * np.pi:24j, 0:np.pi:12j]
    ax.plot_surface(R * np.cos(u) * np.sin(v), R * np.sin(u) * np.sin(v), R + R * np.cos(v),
                    color="0.75", alpha=0.5, linewidth=0)
    p = x[nodes]
    ax.plot_wireframe(p[..., 0], p[..., 1], p[..., 2], color="tab:blue", linewidth=0.6)
    ax.set_xlim(-0.45, 0.45)
    ax.set_ylim(-0.45, 0.45)
    ax.set_zlim(0.0, 0.6)
    ax.set_box_aspect((0.9, 0.9, 0.6))
    ax.view_init(elev=18, azim=-60)
    ax.set_title(f"t = {t:.2f} s", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_zticks([])


if __name__ == "__main__":
    raise SystemExit(main())
