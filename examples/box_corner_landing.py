"""A rigid box dropped onto a corner tips over and settles flat on the ground.

Run:  python examples/box_corner_landing.py [--quick] [--out examples/images/box_corner_landing.png]
      [--gif] [--implicit]

Each box corner below the plane is a penalty contact (force k d - c v_n at the corner, so it
also makes a torque), with smooth Coulomb friction at the corners. At rest four corners
share the weight: each sinks m g / (4 k), which
the script prints next to the simulated value. Saves a strip of side views (x-z) and the
centre height over time as a PNG and, with ``--gif``, an animation. Needs the ``plot`` extra
(matplotlib) for the pictures. ``--implicit`` runs ``implicit_euler`` at dt = 5 ms, 2.5x past
the explicit integrator's stability limit (2 ms here), to the same resting depths.

In float32 (the default) the box keeps a residual of ~1e-5 m/s and ~1e-4 rad/s once it lies
flat: a turn of dt w / 2 = 3e-8 per step is below float32's resolution of a unit quaternion,
so the tilt that would stop that spin no longer changes. In float64 it comes to rest (3e-14
m/s).
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import diffpen as dp
from diffpen.geometry import box_corners
from diffpen.rigid import quat_to_matrix
from _common import example_parser, example_pyplot, save_gif, save_strip

HALF = (0.1, 0.15, 0.2)           # m
MASS = 2.0                        # kg
K, C = 2e4, 60.0                  # N/m, N s/m per corner contact
MU, SLIP = 0.5, 0.05              # smooth Coulomb friction of the ground, slip speed m/s
G = 9.81
#: the 12 edges of a box as pairs of corner indices (corners from geometry.box_corners)
EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def build():
    """The box, tilted so that one corner points down, 0.5 m up, spinning a little."""
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_material("default", friction=MU, slip_speed=SLIP)
    q = np.array([0.88, 0.3, 0.35, 0.1])
    box = scene.add_box(HALF, MASS, (0.0, 0.0, 0.5), orientation=q,
                        angular_velocity=(0.0, 0.0, 1.0))
    scene.add_plane()
    return scene, box


def main(argv=None) -> int:
    ap = example_parser(" ".join(__doc__.split("\n\n")[0].split()), "examples/images/box_corner_landing.png",
                        gif_help="also write an animated GIF next to --out")
    ap.add_argument("--implicit", action="store_true",
                    help="implicit_euler at dt = 5 ms (past the explicit limit)")
    args = ap.parse_args(argv)

    scene, box = build()
    dt, seconds = (5e-3 if args.implicit else 5e-4), (1.5 if args.quick else 3.0)
    sim = dp.compile(scene, dt=dt,
                     integrator="implicit_euler" if args.implicit else "semi_implicit_euler")
    steps, save = int(round(seconds / dt)), (2 if args.implicit else 20)
    t0 = time.perf_counter()
    traj = sim.rollout(sim.params(k=K, c=C), steps, save_every=save)
    x, q = np.asarray(traj.position[:, box]), np.asarray(traj.orientation[:, box])
    print(f"box: {steps} steps of {dt} s ({sim.integrator}) in "
          f"{time.perf_counter() - t0:.2f} s (incl. compile); terms {sim.terms}")
    corners = corner_positions(x, q)                                   # (t, 8, 3)
    low = np.sort(corners[-1, :, 2])
    print(f"first touch at t = {traj.time[np.argmax(corners[:, :, 2].min(1) < 0)]:.3f} s; "
          f"corner depths at rest (m): {np.round(-low[:4], 7)}; "
          f"closed form m g / (4 k) = {MASS * G / (4 * K):.7f} m")
    spin = float(np.linalg.norm(traj.angular_velocity[-1, box]))
    print(f"final centre height {x[-1, 2]:.5f} m (lying on the face of half-height "
          f"{np.round(np.abs(quat_to_matrix(q[-1])).dot(HALF)[2], 4)} m); final speed "
          f"{np.linalg.norm(traj.velocity[-1, box]):.2e} m/s, spin {spin:.2e} rad/s")
    _draw(corners, x, np.asarray(traj.time), pathlib.Path(args.out), args.gif)
    return 0


def corner_positions(x, q):
    """World corners (t, 8, 3) m from centres x (t, 3) and quaternions q (t, 4)."""
    rot = np.asarray(quat_to_matrix(q))
    return x[:, None, :] + np.einsum("tij,kj->tki", rot, box_corners(HALF))


def _draw(corners, x, t, out, gif):
    if example_pyplot(out) is None:
        return
    touch = int(np.argmax(corners[:, :, 2].min(1) < 0.0))
    times = [0.0, t[touch], t[touch] + 0.15, t[touch] + 0.3, t[touch] + 0.5, t[-1]]
    frames = np.unique(np.searchsorted(t, times).clip(0, len(t) - 1))
    xlim = (corners[..., 0].min() - 0.05, corners[..., 0].max() + 0.05)

    def draw(ax, f):
        _frame(ax, corners[f], t[f], xlim)

    def heights(ax):
        ax.plot(t, x[:, 2], color="tab:blue", label="centre")
        ax.plot(t, corners[:, :, 2].min(1), color="tab:red", lw=0.8, label="lowest corner")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("height (m)")
        ax.legend(fontsize=7)
    save_strip(draw, frames, out, extra=heights, figsize_per_frame=(2.3, 2.7),
               title="rigid box landing on a corner and settling (side view x-z)")
    if gif:
        save_gif(draw, range(0, len(t), max(1, len(t) // 60)), out, figsize=(3.2, 3.2), fps=20)


def _frame(ax, c, t, xlim):
    for a, b in EDGES:
        ax.plot(c[[a, b], 0], c[[a, b], 2], color="tab:blue", lw=1.2)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.fill_between([xlim[0] - 1.0, xlim[1] + 1.0], -0.1, 0.0, color="0.85")
    ax.set_xlim(*xlim)
    ax.set_ylim(-0.05, 0.75)
    ax.set_aspect("equal")
    ax.set_title(f"t = {t:.2f} s", fontsize=9)
    ax.set_xlabel("x (m)")


if __name__ == "__main__":
    raise SystemExit(main())
