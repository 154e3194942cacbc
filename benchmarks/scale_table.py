"""The batched-ball table: diffpen against the plain floor at batch 1, 1024 and 65536.

    python benchmarks/scale_table.py [--batches 1 1024 65536] [--steps 2000] [--json OUT]

For each batch size, in one process, after compilation, medians of interleaved turns
(``tuning.reports.timing.interleaved_times``, ``jax.block_until_ready``), float32, the ball of the
bench (radius 0.1 m, 1 kg, dropped from 1 m, dt = 1 ms, k in 5e3..2e4 N/m, c = 20 N s/m):

* stepping: the final state only (``save_every=steps``), against the floor's final ``z``;
* recording: the (steps, B) height trajectory (``observe=``, ``jax.vmap(..., out_axes=1)``:
  time-major), against the floor recording the same way;
* gradient: ``jax.vmap(dp.value_and_grad(loss, (0, 1)))`` of ``loss = sum(z^2)`` over the
  recorded heights (forward mode), against the floor's loss the same way;
* natural: the code a user writes first, ``jax.vmap(lambda k, c: sim.rollout(sim.params(k=k,
  c=c), steps).position[-1, 0, 2])``, against the floor's final ``z``;
* fast: :func:`tuning.ball_fast.ball_heights` (the batched ball path sweeps use), recording,
  against the floor recording.

The floor is :func:`tuning.reports.floors.plain_ball_floor`: scalar ``z`` and ``v`` per ball, hard
``max(d, 0)``. Batch 1 uses ``jax.jit`` without ``vmap``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp
from tuning.reports import floors, timing
from tuning.scenes import ball_scene


def measure(batch: int, steps: int, repeats: int) -> dict:
    from tuning import ball_fast
    dt, dtype = 1e-3, jnp.float32
    scene = ball_scene(radius=0.1, mass=1.0, height=1.0, gravity=9.81)
    sim = dp.compile(scene, dt=dt, dtype=dtype, unroll=1 if batch == 1 else 4)
    ks = jnp.asarray(np.geomspace(5e3, 2e4, batch), dtype)
    cs = jnp.full((batch,), 20.0, dtype)

    def height(s):
        return s.position[0, 2]

    def stepping(k, c):
        return sim.rollout(sim.params(k=k, c=c), steps, save_every=steps).position[-1, 0, 2]

    def recording(k, c):
        return sim.rollout(sim.params(k=k, c=c), steps, observe=height).observed

    def natural(k, c):
        # measured as a user writes it first: its PerformanceWarning is expected here
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", dp.PerformanceWarning)
            return sim.rollout(sim.params(k=k, c=c), steps).position[-1, 0, 2]

    unroll = 8 if batch == 1 else 1     # the floor's fastest forms (see tuning.reports.bench._ball)

    def floor_final(k, c):
        return floors.plain_ball_floor(k, c, steps=steps, dt=dt, record=False, unroll=unroll)

    def floor_rec(k, c, unroll=unroll):
        return floors.plain_ball_floor(k, c, steps=steps, dt=dt, unroll=unroll)

    def grad_of(fn):
        return dp.value_and_grad(lambda k, c: jnp.sum(fn(k, c) ** 2), (0, 1))

    if batch == 1:
        lift = jax.jit
        lift_rec = jax.jit
        args = (ks[0], cs[0])
    else:
        def lift(f):
            return jax.jit(jax.vmap(f))

        def lift_rec(f):
            return jax.jit(jax.vmap(f, out_axes=1))
        args = (ks, cs)
    fast = jax.jit(lambda k, c: ball_fast.ball_heights(sim, k, c, steps))
    fast_args = (jnp.atleast_1d(args[0]), jnp.atleast_1d(args[1]))
    pairs = {
        "stepping": (lift(stepping), lift(floor_final), args),
        "recording": (lift_rec(recording), lift_rec(floor_rec), args),
        "gradient": (lift(grad_of(recording)),
                     lift(grad_of(lambda k, c: floor_rec(k, c, 1))), args),
        "natural": (lift(natural), lift(floor_final), args),
        "fast": (fast, jax.jit(jax.vmap(lambda k, c: floor_rec(k, c, 1), out_axes=1)),
                 fast_args),
    }
    row = dict(batch=batch, steps=steps, load=os.getloadavg()[0])
    for name, (f, floor, a) in pairs.items():
        t = timing.interleaved_times({"diffpen": f, "floor": floor}, a, repeats=repeats)
        row[name] = dict(diffpen_s=t["diffpen"], floor_s=t["floor"],
                         ratio=t["diffpen"] / t["floor"])
        print(f"batch {batch:6d} {name:10s} diffpen {t['diffpen']:.3e} s  floor "
              f"{t['floor']:.3e} s  ratio {t['diffpen'] / t['floor']:.2f}", file=sys.stderr,
              flush=True)
    row["load_end"] = os.getloadavg()[0]
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 1024, 65536])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", help="write the rows to this file")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = [measure(b, args.steps, args.repeats) for b in args.batches]
    print(f"{time.perf_counter() - t0:.0f} s in all", file=sys.stderr)
    if args.json:
        from tuning.sweep import atomic_write
        atomic_write(args.json, lambda fh: fh.write(json.dumps(rows, indent=1).encode()))
    else:
        print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
