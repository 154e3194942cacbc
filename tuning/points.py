"""The points of a parameter sweep (:mod:`tuning.sweep`): every combination of a grid's
axes, or random points in a box (log-uniform for positive leaves)."""
from __future__ import annotations

import numpy as np

__all__ = ["grid_points", "random_points"]


def grid_points(axes: dict) -> tuple[np.ndarray, tuple]:
    """All combinations of ``axes = {path: values}`` (first axis slowest).

    Returns (points (N, P), shape)."""
    if not axes:
        raise ValueError("grid_points: give at least one axis, {path: values}.")
    vals = [np.asarray(v, float).reshape(-1) for v in axes.values()]
    for name, v in zip(axes, vals):
        if v.size == 0 or not np.all(np.isfinite(v)):
            raise ValueError(f"grid_points: axis {name!r} must hold finite values, got "
                             f"{axes[name]!r}.")
    mesh = np.meshgrid(*vals, indexing="ij")
    return np.stack([m.reshape(-1) for m in mesh], axis=1), tuple(len(v) for v in vals)


def random_points(bounds: dict, n: int, *, log: bool = True, seed: int = 0) -> np.ndarray:
    """``n`` random points in the box ``bounds = {path: (lo, hi)}`` (log-uniform when ``log``).

    Returns (n, P): the points only (they have no grid shape; :func:`grid_points` returns
    ``(points, shape)``)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0 or not bounds:
        raise ValueError(f"random_points: n must be a whole number of points >= 0, got {n!r}."
                         if bounds else "random_points: give at least one {path: (lo, hi)}.")
    rng = np.random.default_rng(seed)
    cols = []
    for name, (lo, hi) in bounds.items():
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"random_points: bounds of {name!r} must be finite with lo < hi, "
                             f"got ({lo}, {hi}).")
        if log and lo <= 0.0:
            raise ValueError(f"random_points: bounds of {name!r} are ({lo}, {hi}); log-uniform "
                             "points need lo > 0: pass log=False for a signed leaf (e.g. a "
                             "plane offset) or a lower bound above 0.")
        u = rng.random(n)
        cols.append(np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo))) if log
                    else lo + u * (hi - lo))
    return np.stack(cols, axis=1)
