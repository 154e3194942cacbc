"""Fit a cloth's structural stiffness to a target sag with derivatives through the rollout.

A square cloth pinned at its four corners sags under gravity; the sag of its centre node after
it has settled depends on the structural spring stiffness k (N/m). Given a target sag,
``tuning.fit`` (parameter path ``springs.cloth.structural.k``, Levenberg-Marquardt on log k)
finds k in a few iterations; ``--method adam`` runs plain optax Adam on log k instead, with
the derivative from ``jax.jvp`` through ``sim.rollout``. The target is made with a known k
("truth") so the recovered value can be checked.

Run:  python examples/fit_cloth_sag.py [--quick] [--method tuning|adam] [--target-sag 0.12]
"""
from __future__ import annotations

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import diffpen as dp
from diffpen.builders import add_cloth
from _common import HERE, example_pyplot, picture_path, save_figure

GROUP = "cloth.structural"


def build(n: int):
    """An n x n cloth, 0.4 m wide, 0.25 kg, pinned at its corners."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    nodes = add_cloth(scene, n, n, 0.4 / (n - 1), mass=0.25, structural=(20.0, 0.05),
                      shear=(10.0, 0.02), bend=(2.0, 0.0), drag=0.2,
                      pinned=[(0, 0), (0, -1), (-1, 0), (-1, -1)])
    return scene, nodes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--quick", action="store_true", help="looser tolerance, fewer iterations")
    ap.add_argument("--true-k", type=float, default=35.0,
                    help="stiffness (N/m) used to make the target sag")
    ap.add_argument("--target-sag", type=float, default=None,
                    help="target sag of the centre node, m (default: made with --true-k)")
    ap.add_argument("--k0", type=float, default=10.0, help="start value of k, N/m")
    ap.add_argument("--method", choices=("tuning", "adam"), default="tuning",
                    help="tuning.fit (Levenberg-Marquardt on log k, a few iterations) or a "
                         "plain optax Adam loop (gradient descent, ~100 iterations)")
    ap.add_argument("--out", default=str(HERE / "images" / "fit_cloth_sag.png"),
                    type=picture_path, help="the picture (default: %(default)s)")
    args = ap.parse_args(argv)

    # 800 steps = 1.2 s: the drag settles the sag to ~1e-5 relative by then
    n, steps, iters, tol = (5, 800, 100, 1e-8) if args.quick else (5, 800, 300, 1e-12)
    scene, nodes = build(n)
    sim = dp.compile(scene, dt=1.5e-3)
    centre = int(nodes[n // 2, n // 2])
    base = sim.params()

    def sag(k):
        params = base._replace(springs={**base.springs,
                                        GROUP: dp.SpringParams(k, base.springs[GROUP].c)})
        traj = sim.rollout(params, steps, save_every=steps)
        return -traj.position[-1, centre, 2]                     # m, positive downwards

    target = args.target_sag if args.target_sag is not None else float(sag(args.true_k))
    print(f"cloth {n}x{n}, {len(scene.springs)} springs; target sag {target:.5f} m"
          + ("" if args.target_sag is not None else f" (made with k = {args.true_k} N/m)"))

    t0 = time.perf_counter()
    if args.method == "tuning":
        history = _fit_tuning(sim, base, centre, steps, target, args.k0, quick=args.quick)
    else:
        history = _fit_adam(sag, target, args.k0, iters, tol)
    history, losses = history
    k_fit = history[-1, 0]
    achieved = float(sag(k_fit))
    print(f"{args.method}: {len(losses) - 1} iterations in {time.perf_counter() - t0:.1f} s: "
          f"k = {k_fit:.4f} N/m, sag {achieved:.5f} m ({(achieved - target) / target:+.2e} "
          "relative)")
    if args.target_sag is None:
        print(f"recovered k vs truth: {(k_fit - args.true_k) / args.true_k:+.2e} relative")
    _draw(history, losses, target, sag, pathlib.Path(args.out), args.method)
    return 0


def _fit_tuning(sim, base, centre, steps, target, k0, quick):
    """``tuning.fit`` on the parameter path ``springs.cloth.structural.k`` (log space,
    Levenberg-Marquardt with a forward-mode Jacobian). Returns ((k, sag) start and end, loss
    per iteration)."""
    from tuning import fit

    def metrics(params):
        return {"sag": -sim.rollout(params, steps, save_every=steps).position[-1, centre, 2]}
    p0 = base._replace(springs={**base.springs,
                                GROUP: dp.SpringParams(k0, base.springs[GROUP].c)})
    res = fit.fit(metrics, p0, {"sag": target}, free=[f"springs.{GROUP}.k"], method="lm",
                  rtol=1e-4 if quick else 1e-6, progress=False)
    print(f"tuning.fit: {res.message}")
    k = float(res.values[f"springs.{GROUP}.k"])
    sag0 = float(metrics(p0)["sag"])
    return (np.array([(k0, sag0), (k, float(res.achieved["sag"]))]),
            np.asarray(res.loss_history))


def _fit_adam(sag, target, k0, iters, tol):
    """Plain optax: Adam on log k (steps are relative changes of k), step size halved every
    20 iterations, one compiled iteration. Returns ((k, sag) per iteration, loss per
    iteration)."""
    opt = optax.adam(optax.exponential_decay(0.2, transition_steps=20, decay_rate=0.5))

    @jax.jit
    def iteration(theta, state):
        # one parameter: forward mode (jvp) gives the derivative with one rollout and no
        # stored trajectory; reverse mode (jax.grad) gives the same number.
        s, ds = jax.jvp(lambda th: sag(jnp.exp(th)), (theta,), (jnp.ones_like(theta),))
        r = (s - target) / target
        value, grad = r ** 2, 2.0 * r * ds / target
        updates, state = opt.update(grad, state)
        return optax.apply_updates(theta, updates), state, value, s

    theta = jnp.log(jnp.asarray(k0))
    state = opt.init(theta)
    history = []
    for _ in range(iters):
        k_now = float(jnp.exp(theta))
        theta_next, state, value, s_now = iteration(theta, state)
        history.append((k_now, float(value), float(s_now)))
        if value < tol:              # quick: sag within 1e-4 relative; full: 1e-6
            break
        theta = theta_next
    history = np.array(history)
    return history[:, [0, 2]], history[:, 1]


def _draw(history, losses, target, sag, out, method):
    plt = example_pyplot(out)
    if plt is None:
        return
    import matplotlib.ticker
    ks = np.geomspace(history[:, 0].min() * 0.7, history[:, 0].max() * 1.4, 9)
    sags = np.array([float(sag(k)) for k in ks])
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.4))
    a1.semilogx(ks, sags * 100, "-", color="0.5", label="sag(k)")
    a1.axhline(target * 100, color="red", ls="--", label="target")
    a1.plot(history[:, 0], history[:, 1] * 100, "o", ms=4, color="tab:blue",
            label="iterates" if method == "adam" else "start and fit")
    a1.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    a1.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    a1.set_xlabel("structural k (N/m)")
    a1.set_ylabel("centre sag (cm)")
    a1.legend(fontsize=8)
    a2.semilogy(np.maximum(losses, 1e-20), "o-", ms=3)
    a2.set_xlabel("iteration")
    a2.set_ylabel("loss ((sag - target) / target)^2")
    fig.suptitle("fitting cloth stiffness to a target sag ("
                 + ("optax Adam" if method == "adam" else "tuning.fit, Levenberg-Marquardt")
                 + " on log k)")
    fig.tight_layout()
    save_figure(fig, out, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
