"""The default step's cost against another checkout of diffpen, in one process.

    git worktree add /tmp/diffpen-old aa36fa9        # the checkout to compare with
    python benchmarks/step_cost.py /tmp/diffpen-old [--reps 40] [--centred]

Both packages are loaded side by side (diffpen imports itself relatively, so a checkout's
``diffpen/`` loads under another module name), each compiles the same quick-start ball
(radius 0.1 m, 1 kg, dropped from 1 m onto a plane, k = 1e4 N/m, c = 20 N s/m, default
contact settings, float32, dt = 1 ms, 3000 steps), and five workloads run in interleaved
turns after compilation (``jax.block_until_ready``; medians; each timed call follows an
untimed call of the same function, and the checkouts alternate which goes first):

* forward, batch 1: the height trajectory (``observe=``);
* forward-mode and reverse-mode gradient of ``sum(z^2)`` w.r.t. (k, c);
* forward, batch 1024 (``jax.vmap``; k in 5e3..2e4 N/m) with c batched too, and with c shared.

Prints each median and its ratio to the first checkout. ``--centred`` adds this checkout
with ``diffpen.laws.linear(centred=True)``. This is the measurement behind issue 12's
"the default step stays within 1.3x of its cost" (docs/gradients.txt, "Cost").
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from tuning.reports.timing import settled_time

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STEPS = 3000


def load(path: str, alias: str):
    """The package ``path/diffpen`` as module ``alias``."""
    spec = importlib.util.spec_from_file_location(
        alias, os.path.join(path, "diffpen", "__init__.py"),
        submodule_search_locations=[os.path.join(path, "diffpen")])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[alias] = mod
    spec.loader.exec_module(mod)
    return mod


def workloads(dp, law=None) -> dict:
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("ball", k=1e4, c=20.0)
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0), material="ball")
    scene.add_plane(material="ball")
    sim = dp.compile(scene, dt=1e-3, dtype=jnp.float32, **({"law": law} if law else {}))

    def heights(k, c):
        return sim.rollout(sim.params(k=k, c=c), steps=STEPS,
                           observe=lambda s: s.position[0, 2]).observed

    def loss(k, c):
        return jnp.sum(heights(k, c) ** 2)

    k0, c0 = jnp.float32(1e4), jnp.float32(20.0)
    kb = jnp.asarray(np.geomspace(5e3, 2e4, 1024), jnp.float32)
    cb = jnp.full((1024,), 20.0, jnp.float32)
    w = {"forward, batch 1": (jax.jit(heights), (k0, c0)),
         "forward-mode gradient": (jax.jit(jax.jacfwd(loss, argnums=(0, 1))), (k0, c0)),
         "reverse-mode gradient": (jax.jit(jax.grad(loss, argnums=(0, 1))), (k0, c0)),
         "batch 1024, k and c": (jax.jit(jax.vmap(heights)), (kb, cb)),
         "batch 1024, k (c shared)": (jax.jit(jax.vmap(lambda k: heights(k, c0))), (kb,))}
    for f, a in w.values():
        jax.block_until_ready(f(*a))
    return w


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", help="the checkout to compare with (a directory holding diffpen/)")
    ap.add_argument("--new", default=HERE, help="this checkout (default: the repository)")
    ap.add_argument("--reps", type=int, default=40, help="interleaved turns (default 40)")
    ap.add_argument("--centred", action="store_true",
                    help="also time the new checkout with laws.linear(centred=True)")
    args = ap.parse_args(argv)
    old, new = load(args.old, "diffpen_old"), load(args.new, "diffpen_new")
    runs = [("old", workloads(old)), ("new", workloads(new))]
    if args.centred:
        runs.append(("new centred", workloads(new, new.laws.linear(centred=True))))
    times = {name: {label: [] for label, _ in runs} for name in runs[0][1]}
    for rep in range(args.reps):
        for name in times:
            # each timed call right after an untimed call of the same function, checkouts in
            # alternating order: a call timed right after another program reads slower (the
            # SAME code measured 1.9x slower right after a batch-1024 workload)
            order = runs if rep % 2 == 0 else runs[::-1]
            for label, w in order:
                f, a = w[name]
                times[name][label].append(settled_time(f, a))
    print(f"{STEPS} steps of the quick-start ball, float32, medians of {args.reps} "
          f"interleaved turns; load average {os.getloadavg()[0]:.1f}")
    for name, per in times.items():
        med = {label: float(np.median(t)) for label, t in per.items()}
        cells = "  ".join(f"{label} {m * 1e3:7.3f} ms" for label, m in med.items())
        ratios = "  ".join(f"{label}/old {m / med['old']:.2f}x"
                           for label, m in med.items() if label != "old")
        print(f"  {name:26s} {cells}   {ratios}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
