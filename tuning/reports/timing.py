"""Wall-time measurement of the benchmarks and reports: medians after a warm-up, calls
taken in turns so that every function sees the same machine load, each timed call right after
an untimed one of the same function (``jax.block_until_ready`` throughout), and XLA's memory
analysis of a compiled executable. Pure timing: nothing here knows a scene."""
from __future__ import annotations

import time
from typing import Callable

import jax
import numpy as np

__all__ = ["median_time", "settled_time", "interleaved_times", "memory_bytes"]


def median_time(fn: Callable, *args, repeats: int = 5) -> float:
    """Median wall time (s) of ``fn(*args)`` over ``repeats`` runs after one warm-up run
    (``jax.block_until_ready`` on its result; NumPy results pass through)."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def settled_time(fn: Callable, args: tuple) -> float:
    """Wall time (s) of one ``fn(*args)`` (``jax.block_until_ready``) taken right after an
    untimed call of the same function: the measurement unit of :func:`interleaved_times` and
    ``benchmarks/step_cost.py``. A call timed right after a different program reads slower
    (caches, the thread pool), whatever ran before it."""
    jax.block_until_ready(fn(*args))                # settle: the same program just ran
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def interleaved_times(fns: dict, args: tuple, repeats: int = 5,
                      budget_s: float = 20.0) -> dict:
    """Median wall time (s) of each ``fn(*args)`` in ``fns`` (None entries skipped), after a
    warm-up call each, with the timed calls taken in turns (fn1, fn2, ..., fn1, fn2, ...) so
    that every function sees the same machine load: ``repeats`` rounds, more (up to 200) when
    a round takes under ~0.5 s / repeats, fewer (3 at least) when the rounds would take over
    ``budget_s`` seconds in all.

    Every timed call directly follows an untimed call of the same function: a call timed
    right after a different program reads slower (caches, the thread pool; measured: the
    same batch-1 rollout 1.2x slower after a batch-1 gradient and 2.3x after a batch-1024
    rollout), which would bias each ratio by which function happens to come first."""
    live = {k: f for k, f in fns.items() if f is not None}
    times = {k: [] for k in live}

    def timed(f):
        return settled_time(f, args)
    first = 0.0
    for k, f in live.items():
        times[k].append(timed(f))
        first += times[k][-1]
    # short calls get more rounds (up to ~0.5 s in all): their medians are noisier; long
    # ones fewer, so that a case takes about budget_s at most (two calls per timed one)
    rounds = max(repeats, min(200, int(0.5 / max(first, 1e-9))))
    if 2.0 * first * rounds > budget_s:
        rounds = max(3, int(budget_s / (2.0 * first)))
    for _ in range(rounds - 1):
        for k, f in live.items():
            times[k].append(timed(f))
    return {k: float(np.median(v)) for k, v in times.items()}


def memory_bytes(compiled) -> int | None:
    """Arguments + outputs + temporaries of a compiled XLA executable, bytes (None if the
    backend gives no analysis)."""
    try:
        m = compiled.memory_analysis()
    except Exception:            # backends without memory analysis
        return None
    if m is None:
        return None
    return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
               - m.alias_size_in_bytes)
