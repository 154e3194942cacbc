"""Six bounce heights, one batched fit: the damping of a ball for each first-apex target.

A 0.1 m, 1 kg ball is dropped from a centre height of 1 m onto the plane z = 0 (contact
stiffness held at 1e4 N/m). Each row of the batch asks for a different first apex of the
lowest point, from 0.7 m down to 0.05 m; every row starts from the closed-form damping of its
target (tuning.bounce.first_guess_bounce) and all rows are fitted together by one jitted Adam
loop, vmapped over the rows and sharded over every device (tuning.batch_fit.fit_batch).
Prints one line per row: target, achieved apex, fitted damping c and damping ratio.

Run: python examples/fit_batch.py
(with XLA_FLAGS=--xla_force_host_platform_device_count=4 the rows are split over 4 CPU
devices; the results are the same.)
"""
import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffpen as dp  # noqa: E402
from tuning import scenes  # noqa: E402
from tuning.batch_fit import fit_batch  # noqa: E402
from tuning.bounce import bounce_metrics_fn, check_bounce_targets, first_guess_bounce  # noqa: E402

APEXES = [0.7, 0.5, 0.35, 0.2, 0.1, 0.05]    # first-apex targets, m (lowest point)
K = 1e4                                       # contact stiffness, N/m (held)
DT, DURATION = 2e-3, 1.0                      # time step and rollout, s


def main(argv=None):
    argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split())).parse_args(argv)
    scene = scenes.ball().scene
    targets = [{"apex_heights": [a]} for a in APEXES]
    # closed-form start per row (the checks refuse infeasible targets before compiling)
    starts = [{"contact.default.c": first_guess_bounce(check_bounce_targets(scene, t), t,
                                                       k0=K)[1]} for t in targets]
    sim = dp.compile(scene, DT)
    metrics_fn = bounce_metrics_fn(sim, int(round(DURATION / DT)), n_apex=1)
    t0 = time.perf_counter()
    res = fit_batch(metrics_fn, sim.params(k=K, c=1.0), targets, starts,
                    free=["contact.default.c"], maxiter=200)
    wall = time.perf_counter() - t0
    print(f"{len(res)} fits on {res.devices} device(s) in {wall:.1f} s (compilation included)")
    print(f"{'target m':>9s} {'achieved m':>11s} {'error':>8s} {'c N s/m':>9s} {'zeta':>6s}"
          f" {'iters':>5s}  status")
    for i, target in enumerate(APEXES):
        c = float(res.values[i, 0])
        got = float(res.achieved["apex_heights"][i, 0])
        zeta = float(dp.physical.damping_ratio(K, c, 1.0))
        print(f"{target:9.3f} {got:11.5f} {100 * (got / target - 1):+7.3f}% {c:9.3f}"
              f" {zeta:6.3f} {int(res.iterations[i]):5d}  {res.messages[i]}")


if __name__ == "__main__":
    main()
