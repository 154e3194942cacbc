"""The workshop paper's ball-spring chain demo, with its constants and correct force signs.

7 balls of MASS=10, the first fixed at (100, 0, 100) and the last at (500, 0, 100), zero-rest
springs KS=50 between neighbours, drag KD=1 on each ball's velocity, g=9.8 along -z, DT=0.1;
the free balls start scattered (seeded). The paper's listing pushes each ball AWAY from its
neighbours (a sign slip): here springs pull towards them, and the chain settles to the static
equilibrium, which is also solved directly as a linear system and compared.

Run:  python examples/paper_chain.py [--quick] [--steps 2000] [--seed 0] [--out PNG] [--gif]
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import diffpen as dp
from diffpen.builders import PAPER_CHAIN, paper_chain, paper_chain_equilibrium
from _common import example_parser, example_pyplot, positive_int, save_figure, save_gif


def main(argv=None) -> int:
    ap = example_parser(" ".join(__doc__.split("\n\n")[0].split()), "examples/images/paper_chain.png",
                        quick_help="accepted for uniformity; the demo is already quick")
    ap.add_argument("--steps", type=positive_int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    steps = args.steps          # 2000 steps take well under a second; --quick changes nothing
    scene, balls = paper_chain(seed=args.seed)
    sim = dp.compile(scene, dt=PAPER_CHAIN["dt"])
    t0 = time.perf_counter()
    traj = sim.rollout(sim.params(), steps)
    x = np.asarray(traj.position)
    eq = paper_chain_equilibrium()
    err = np.abs(x[-1] - eq).max()
    print(f"{steps} steps of DT={sim.dt} s in {time.perf_counter() - t0:.2f} s (incl. compile)")
    print("ball   final x, y, z (m)                 equilibrium x, y, z (m)")
    for i in balls:
        print(f"{i:4d}   {np.array2string(x[-1, i], precision=4):34s}"
              f"{np.array2string(eq[i], precision=4)}")
    print(f"max |final - equilibrium| = {err:.3g} m")
    _draw(x, eq, np.asarray(traj.time), pathlib.Path(args.out), args.gif)
    return 0


def _draw(x, eq, t, out, gif):
    plt = example_pyplot(out)
    if plt is None:
        return
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.6),
                                  gridspec_kw=dict(width_ratios=[2, 1]))
    shots = [0, 5, 10, 20, 40, 80, len(t) - 1]
    cmap = plt.get_cmap("viridis")
    for n, f in enumerate(shots):
        ax.plot(x[f, :, 0], x[f, :, 2], "-o", color=cmap(n / (len(shots) - 1)), ms=6,
                lw=1, label=f"t = {t[f]:.1f} s")
    ax.plot(eq[:, 0], eq[:, 2], "x", color="red", ms=10, mew=2, label="equilibrium (solved)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title("paper's chain: 7 balls, KS=50, KD=1, DT=0.1")
    ax.legend(fontsize=7, ncol=2)
    err = np.abs(x - eq[None]).max(axis=(1, 2))
    ax2.semilogy(t, err)
    ax2.set_xlabel("t (s)")
    ax2.set_ylabel("max |x - x_eq| (m)")
    ax2.set_title("distance to the static equilibrium")
    save_figure(fig, out, dpi=110)
    if gif:
        def draw(ax, f):
            ax.plot(eq[:, 0], eq[:, 2], "x", color="red", ms=8)
            ax.plot(x[f, :, 0], x[f, :, 2], "-o", color="tab:blue", ms=8)
            ax.set_xlim(50, 550)
            ax.set_ylim(x[..., 2].min() - 10, x[..., 2].max() + 10)
            ax.set_title(f"t = {t[f]:.1f} s", fontsize=9)
        save_gif(draw, range(0, min(len(t), 400), 4), out, figsize=(5, 3), fps=25)


if __name__ == "__main__":
    raise SystemExit(main())
