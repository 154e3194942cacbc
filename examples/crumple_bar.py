"""Crumple zone: a truss bar of plastic members hits a wall, crumples, rebounds and stays
shorter; the same bar with a yield strain it never reaches bounces back whole.

Run:  python examples/crumple_bar.py [--quick] [--out examples/images/crumple_bar.png] [--gif]

Top view, no gravity. Members shorten irreversibly when compressed beyond the yield strain
(diffpen.terms.plastic); the yield strain is a differentiable parameter: ``params.extra["plastic"]``.
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import diffpen as dp
from diffpen.builders import add_crumple_bar
from _common import example_parser, example_pyplot, save_figure, save_gif

WALL = 0.8            # wall plane x = WALL (m)
SPEED = 2.0           # impact speed, m/s


def build(n: int):
    """A truss bar of ``n`` stations, 0.6 m x 0.1 m, 1 kg, moving at SPEED towards the wall."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    nodes = add_crumple_bar(scene, n, (0.0, 0.0, 0.0), (0.6, 0.0, 0.0), mass=1.0,
                            k=400.0 * (n - 1), c=0.05 * (n - 1), yield_strain=0.03, width=0.1,
                            velocity=(SPEED, 0.0, 0.0))
    scene.add_plane(normal=(-1.0, 0.0, 0.0), offset=-WALL)
    return scene, nodes


def main(argv=None) -> int:
    ap = example_parser(" ".join(__doc__.split("\n\n")[0].split()), "examples/images/crumple_bar.png",
                        quick_help="coarser bar, shorter run")
    args = ap.parse_args(argv)

    n, seconds = (6, 0.5) if args.quick else (9, 0.6)
    scene, nodes = build(n)
    dt = 2e-4
    sim = dp.compile(scene, dt=dt)
    steps = int(round(seconds / dt))
    runs = {}
    t0 = time.perf_counter()
    for label, eps in (("plastic, yield strain 0.03", 0.03), ("elastic (yield never reached)",
                                                               0.9)):
        params = sim.params(k=2e4, c=5.0, extra={"plastic": {"bar": eps}})
        traj = sim.rollout(params, steps, save_every=25)
        runs[label] = (np.asarray(traj.position), np.asarray(traj.aux["plastic_rest"]))
    t = np.asarray(traj.time)
    print(f"truss bar: {scene.n_bodies} nodes, {len(scene.plastic_springs)} plastic members; "
          f"2 x {steps} steps of {dt} s in {time.perf_counter() - t0:.2f} s (incl. compile)")
    for label, (x, rest) in runs.items():
        length = _length(x, nodes)
        print(f"{label:32s}: length {length[0]:.3f} m -> shortest {length.min():.3f} m -> "
              f"final {length[-1]:.3f} m ({length[0] - length[-1]:+.3f} m shorter, its "
              f"vibration included); members' rest lengths (the permanent set): "
              f"{rest[-1].sum() / rest[0].sum():.1%} of the initial")
    _draw(runs, nodes, t, pathlib.Path(args.out), args.gif)
    return 0


def _length(x, nodes):
    """Bar length (m): distance between the midpoints of the end stations, per saved step."""
    return np.linalg.norm(x[:, nodes[-1]].mean(axis=1) - x[:, nodes[0]].mean(axis=1), axis=-1)


def _members(nodes):
    n = nodes.shape[0]
    out = [(nodes[i, r], nodes[i + 1, r]) for i in range(n - 1) for r in (0, 1)]
    out += [(nodes[i, 0], nodes[i, 1]) for i in range(n)]
    out += [(nodes[i, 0], nodes[i + 1, 1]) for i in range(n - 1)]
    out += [(nodes[i, 1], nodes[i + 1, 0]) for i in range(n - 1)]
    return np.asarray(out)


def _draw(runs, nodes, t, out, gif):
    plt = example_pyplot(out)
    if plt is None:
        return
    members = _members(nodes)
    x_pl = next(iter(runs.values()))[0]
    length = _length(x_pl, nodes)
    frames = [0, int(np.argmin(length)), len(t) - 1]
    fig = plt.figure(figsize=(11, 4.2))
    grid = fig.add_gridspec(2, 4)
    for row, (label, (x, _)) in enumerate(runs.items()):
        for col, f in enumerate(frames):
            ax = fig.add_subplot(grid[row, col])
            _frame(ax, x[f], members, t[f])
            if col == 0:
                ax.set_ylabel(label.split(",")[0].split(" (")[0], fontsize=9)
    ax = fig.add_subplot(grid[:, 3])
    for label, (x, _) in runs.items():
        ax.plot(t, _length(x, nodes), label=label)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("bar length (m)")
    ax.legend(fontsize=7)
    ax.set_title("length: permanent set", fontsize=9)
    fig.suptitle(f"crumple bar hitting a wall at {SPEED} m/s (top view)")
    save_figure(fig, out, dpi=110)
    if gif:
        def draw(axes, f):
            for ax, (x, _) in zip(axes, runs.values()):
                _frame(ax, x[f], members, t[f])
        save_gif(draw, range(0, len(t), max(1, len(t) // 60)), out, figsize=(4, 3.2), fps=20,
                 nrows=2)


def _frame(ax, x, members, t):
    from matplotlib.collections import LineCollection
    segs = np.stack([x[members[:, 0]][:, :2], x[members[:, 1]][:, :2]], axis=1)
    ax.add_collection(LineCollection(segs, colors="tab:red", linewidths=1.0))
    ax.axvline(WALL, color="k", lw=3)
    ax.set_xlim(-0.75, WALL + 0.05)
    ax.set_ylim(-0.12, 0.12)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f"t = {t:.3f} s", fontsize=8)


if __name__ == "__main__":
    raise SystemExit(main())
