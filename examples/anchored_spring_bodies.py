"""Two rigid boxes joined by an anchored spring, hanging from a world point: a tumbling
double pendulum.

Run:  python examples/anchored_spring_bodies.py [--quick]
      [--out examples/images/anchored_spring_bodies.png] [--gif]

The paper's ``Spring_c``: each spring end is fixed in a body (anchor in body coordinates);
the force acts along the anchor-to-anchor axis, with damping on the relative anchor velocity
``v + w x r``, at each body's own anchor, equal and opposite, so it makes both bodies turn.
Box A hangs from a world point by a spring at one of its top corners; box B hangs from A's
opposite bottom corner by a spring at the middle of its top face. The script prints the
total energy (kinetic + rotational + gravity + springs), which the spring dampers and a
light air drag on the boxes drain, and the anchors' final x positions, which line up under
the world point (x = 0) as the chain comes to rest. Saves a strip of side views (x-z) and the
energy over time as a PNG and, with ``--gif``, an animation. Needs the ``plot`` extra
(matplotlib).
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import diffpen as dp
from diffpen.geometry import box_corners
from diffpen.rigid import inertia_diagonal, quat_to_matrix
from _common import example_parser, example_pyplot, save_gif, save_strip

G = 9.81
TOP = (0.0, 0.0, 2.0)                     # world anchor, m
HALF_A, HALF_B = (0.2, 0.1, 0.1), (0.1, 0.1, 0.15)
ANCHOR_TOP_A = (-0.2, 0.0, 0.1)           # top corner of A (body frame), m
ANCHOR_BOT_A = (0.2, 0.0, -0.1)           # opposite bottom corner of A
ANCHOR_TOP_B = (0.0, 0.0, 0.15)           # middle of B's top face
K, C = 400.0, 4.0                         # N/m, N s/m of both springs
DRAG = 1.0                                # N s/m, air drag on each box's centre velocity
EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def build():
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    a = scene.add_box(HALF_A, 2.0, (0.3, 0.0, 1.7), orientation=(0.95, 0.0, 0.3, 0.0))
    b = scene.add_box(HALF_B, 1.0, (0.75, 0.0, 1.6), orientation=(0.9, 0.1, -0.4, 0.0),
                      angular_velocity=(0.0, 2.0, 0.0))
    scene.add_anchored_spring(a, None, ANCHOR_TOP_A, TOP, k=K, c=C, rest_length=0.3,
                              group="link")
    scene.add_anchored_spring(b, a, ANCHOR_TOP_B, ANCHOR_BOT_A, rest_length=0.2,
                              group="link")
    scene.add_drag([a, b], c=DRAG)
    return scene, a, b


def main(argv=None) -> int:
    ap = example_parser(" ".join(__doc__.split("\n\n")[0].split()), "examples/images/anchored_spring_bodies.png",
                        gif_help="also write an animated GIF next to --out")
    args = ap.parse_args(argv)

    scene, a, b = build()
    dt, seconds = 1e-3, (4.0 if args.quick else 12.0)
    sim = dp.compile(scene, dt=dt)
    steps, save = int(round(seconds / dt)), 20
    t0 = time.perf_counter()
    traj = sim.rollout(sim.params(), steps, save_every=save)
    print(f"two boxes: {steps} steps of {dt} s in {time.perf_counter() - t0:.2f} s (incl. "
          f"compile); terms {sim.terms}")
    x, q = np.asarray(traj.position), np.asarray(traj.orientation)
    v, w = np.asarray(traj.velocity), np.asarray(traj.angular_velocity)
    rot = np.asarray(quat_to_matrix(q))                                  # (t, 2, 3, 3)
    energy = total_energy(scene, x, v, w, rot)
    print(f"energy: {energy[0]:.3f} J at start -> {energy[-1]:.3f} J after {seconds} s "
          f"(spring dampers and drag dissipate; never rises by more than "
          f"{max(np.max(np.diff(energy)), 0.0):.2e} J between frames)")
    pa = x[-1, a] + rot[-1, a] @ ANCHOR_TOP_A
    pab = x[-1, a] + rot[-1, a] @ ANCHOR_BOT_A
    pb = x[-1, b] + rot[-1, b] @ ANCHOR_TOP_B
    print(f"final anchors x: A top {pa[0]:+.4f}, A bottom {pab[0]:+.4f}, B top {pb[0]:+.4f} m "
          "(at rest all lie below the world point, x = 0)")
    print(f"final speeds: {np.round(np.linalg.norm(v[-1], axis=-1), 4)} m/s, "
          f"{np.round(np.linalg.norm(w[-1], axis=-1), 4)} rad/s")
    _draw(scene, x, rot, np.asarray(traj.time), energy, pathlib.Path(args.out), args.gif)
    return 0


def anchors(x, rot):
    """World anchor points of the two springs per frame: (t, 4, 3) m."""
    return np.stack([np.broadcast_to(TOP, x[:, 0].shape),
                     x[:, 0] + np.einsum("tij,j->ti", rot[:, 0], ANCHOR_TOP_A),
                     x[:, 0] + np.einsum("tij,j->ti", rot[:, 0], ANCHOR_BOT_A),
                     x[:, 1] + np.einsum("tij,j->ti", rot[:, 1], ANCHOR_TOP_B)], axis=1)


def total_energy(scene, x, v, w, rot):
    """Kinetic + rotational + gravitational + spring energy per frame, J."""
    e = np.zeros(len(x))
    for i, body in enumerate(scene.bodies):
        inertia = inertia_diagonal(body)
        w_body = np.einsum("tji,tj->ti", rot[:, i], w[:, i])
        e += 0.5 * body.mass * np.sum(v[:, i] ** 2, -1) + 0.5 * np.sum(inertia * w_body ** 2, -1)
        e += body.mass * G * x[:, i, 2]
    p = anchors(x, rot)
    for (u, s), spring in zip(((0, 1), (2, 3)), scene.anchored_springs):
        stretch = np.linalg.norm(p[:, u] - p[:, s], axis=-1) - spring.rest_length
        e += 0.5 * K * stretch ** 2
    return e


def _draw(scene, x, rot, t, energy, out, gif):
    if example_pyplot(out) is None:
        return
    corners = [x[:, i, None, :] + np.einsum("tij,kj->tki", rot[:, i], box_corners(h))
               for i, h in enumerate((HALF_A, HALF_B))]
    p = anchors(x, rot)
    frames = np.unique(np.searchsorted(t, [0.0, 0.4, 0.8, 1.5, 3.0, t[-1]]).clip(0, len(t) - 1))

    def draw(ax, f):
        _frame(ax, [c[f] for c in corners], p[f], t[f])

    def energy_panel(ax):
        ax.plot(t, energy, color="tab:purple")
        ax.set_xlabel("t (s)")
        ax.set_ylabel("total energy (J)")
    save_strip(draw, frames, out, extra=energy_panel,
               figsize=(2.0 * (len(frames) + 1) + 0.8, 3.0),
               title="two rigid boxes joined by anchored springs (side view x-z)")
    if gif:
        save_gif(draw, range(0, len(t), max(1, len(t) // 80)), out, figsize=(3.0, 3.6), fps=20)


def _frame(ax, boxes, p, t):
    for c, color in zip(boxes, ("tab:blue", "tab:orange")):
        for a, b in EDGES:
            ax.plot(c[[a, b], 0], c[[a, b], 2], color=color, lw=1.1)
    for u, s in ((0, 1), (2, 3)):
        ax.plot(p[[u, s], 0], p[[u, s], 2], color="k", lw=0.8, ls=(0, (2, 1)))
    ax.plot(p[:, 0], p[:, 2], "k.", ms=4)
    ax.plot([TOP[0]], [TOP[2]], "ks", ms=5)
    ax.set_xlim(-1.0, 1.0)
    ax.set_ylim(0.4, 2.1)
    ax.set_aspect("equal")
    ax.set_title(f"t = {t:.1f} s", fontsize=9)
    ax.set_xlabel("x (m)")


if __name__ == "__main__":
    raise SystemExit(main())
