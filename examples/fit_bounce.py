"""Trampoline vs swamp: the same ball fitted to a bouncy and to a sinking target.

A 0.1 m, 1 kg ball is dropped from a centre height of 1 m onto the plane z = 0.

* trampoline: first apex 0.6 m (of the lowest point) and a settling time of 4.8 s;
* swamp: the ball sinks 8 cm into the floor and is still (within 1 mm of rest) after 1.0 s.

Each fit checks its targets against the scene, starts from closed-form guesses and runs
Levenberg-Marquardt on the exact metrics. Two (k, c) pairs meet the swamp's two targets: an
overdamped one that never rebounds (k ~ 300 N/m, damping ratio ~ 1.3) and an underdamped one
that rebounds about 5 cm and is still by 1.0 s all the same (k ~ 1255 N/m, damping ratio
~ 0.35). The targets cannot tell them apart; the start decides, so the swamp starts from a
soft k0 = 300 N/m (from the default start LM reaches neither: it ends still bouncing). Prints the fitted
k, c, damping ratio and the achieved metrics; draws both trajectories to --plot when
matplotlib is installed.

Run: python examples/fit_bounce.py [--plot FILE.png]
"""
import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import diffpen as dp  # noqa: E402
from tuning import scenes  # noqa: E402
from tuning.bounce import fit_bounce  # noqa: E402
from tuning.io import save_figure_file  # noqa: E402

TARGETS = {
    "trampoline": {"apex_heights": [0.6], "settling_time": 4.8},
    "swamp": {"max_penetration": 0.08, "settling_time": 1.0},
}
#: start stiffness per fit (None: the closed-form guess); see the module docstring
K0 = {"trampoline": None, "swamp": 300.0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--plot", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                   "images", "fit_bounce.png"),
                    help="figure path (default examples/images/fit_bounce.png; '' for none)")
    args = ap.parse_args(argv)
    results = {}
    for name, targets in TARGETS.items():
        t0 = time.perf_counter()
        res = fit_bounce(scenes.ball().scene, targets, dt=1e-3, k0=K0[name])
        wall = time.perf_counter() - t0
        k = float(res.params.contact["default"].k)
        c = float(res.params.contact["default"].c)
        zeta = float(dp.physical.damping_ratio(k, c, 1.0))
        results[name] = res
        print(f"{name:10s} k = {k:9.2f} N/m   c = {c:7.3f} N s/m   damping ratio {zeta:.3f}"
              f"   ({'reached' if res.reached else 'NOT reached'}, {wall:.1f} s)")
        for metric, target in res.targets.items():
            got = res.achieved[metric]
            got = got[0] if isinstance(got, list) else got
            target = target[0] if isinstance(target, list) else target
            print(f"{'':10s}   {metric:16s} target {target:8.4f}   achieved {got:8.5f}"
                  f"   ({100 * (got / target - 1):+.3f}%)")
    if not args.plot:
        return
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("(matplotlib not installed: no figure)")
        return
    sim = dp.compile(scenes.ball().scene, 1e-3)
    fig, ax = plt.subplots(figsize=(9, 4))
    for name, res in results.items():
        steps = 6000 if name == "trampoline" else 1500
        tr = sim.rollout(res.params, steps, sim.init_state())
        t = np.concatenate([[0.0], np.asarray(tr.time)])
        h = np.concatenate([[1.0], np.asarray(tr.position[:, 0, 2])]) - 0.1
        ax.plot(t, h, lw=1.0, label=f"{name}: k={float(res.params.contact['default'].k):.4g}"
                                    f" N/m, c={float(res.params.contact['default'].c):.3g} N s/m")
        ax.axvline(res.achieved["settling_time"], ls=":", lw=0.8,
                   color=ax.lines[-1].get_color())
    ax.axhline(0.6, color="k", ls="--", lw=0.6, label="trampoline apex target 0.6 m")
    ax.axhline(-0.08, color="k", ls="-.", lw=0.6, label="swamp penetration target 8 cm")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("lowest point above the floor (m)")
    ax.set_title("Same ball, two targets (dotted: achieved settling times)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = args.plot
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    save_figure_file(fig, out, dpi=120)
    print(f"figure: {out}")


if __name__ == "__main__":
    main()
