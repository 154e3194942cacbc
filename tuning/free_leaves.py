"""The params leaves a fit names and moves: :func:`get_leaf` / :func:`with_leaves` by dotted
name (or ``jax.tree_util.keystr``), and :class:`Free`, one fitted leaf with its bounds and the
space it is fitted in (log for positive leaves, linear for signed ones such as plane
offsets); :func:`free_from_spec` reads them from a scene file's ``[fit]`` table. Used by
:func:`tuning.trajfit.fit_records` (and re-exported there)."""
from __future__ import annotations

import dataclasses
import math
import re

import jax
import jax.numpy as jnp
import numpy as np

from .errors import FitError
from .params import leaf_paths

__all__ = ["Free", "leaf_names", "get_leaf", "with_leaves", "free_from_spec"]

#: ``{"contact.board.k": key path, ...}`` of a params pytree (see :mod:`tuning.params`)
leaf_names = leaf_paths


def _normalise(name: str) -> str:
    """``contact['board'].k`` (a ``jax.tree_util.keystr``) or ``contact.board.k`` -> dotted."""
    s = re.sub(r"\[['\"]?([^\]'\"]+)['\"]?\]", r".\1", name.strip())
    return s.lstrip(".")


def get_leaf(params, name: str):
    """The value of the leaf ``name`` (dotted or ``keystr`` form) of ``params``."""
    names = leaf_names(params)
    key = _normalise(name)
    if key not in names:
        raise FitError(f"parameter {name!r} is not a leaf of this scene's params; leaves: "
                       f"{sorted(names)}.")
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        if path == names[key]:
            return leaf
    raise AssertionError(key)


def with_leaves(params, values: dict):
    """``params`` with the leaves named in ``values`` (``{name: value}``) replaced; values
    may be tracers (used inside jit / grad / jacfwd)."""
    names = leaf_names(params)
    want = {names[_normalise(n)]: v for n, v in values.items()}
    flat, tree = jax.tree_util.tree_flatten_with_path(params)
    return jax.tree_util.tree_unflatten(tree, [want.get(p, leaf) for p, leaf in flat])


@dataclasses.dataclass(frozen=True)
class Free:
    """One fitted leaf of the params.

    name: dotted leaf name (``contact.board.k``, ``extra.friction.board``,
      ``extra.plane_offset.ground``, ``springs.rope.c``, ...).
    lo, hi: bounds in the leaf's unit.
    log: fit in log space (positive leaves: stiffness, damping, friction) or linear space
      (signed leaves: offsets). Default: log unless ``lo`` <= 0 or the name is an offset.
    """
    name: str
    lo: float = -math.inf
    hi: float = math.inf
    log: bool | None = None

    def resolved(self) -> "Free":
        name = _normalise(self.name)
        log = self.log
        if log is None:
            log = not ("offset" in name or self.lo < 0.0)
        lo, hi = float(self.lo), float(self.hi)
        if log and lo == -math.inf:
            lo = 0.0
        if log and lo < 0.0:
            raise FitError(f"{name}: a log-space parameter needs lo >= 0, got {lo}; give "
                           "log=false for a signed parameter.")
        if not lo < hi:
            raise FitError(f"{name}: bounds must satisfy lo < hi, got [{lo}, {hi}].")
        return Free(name, lo, hi, bool(log))

    def to_x(self, v):
        return np.log(v) if self.log else v

    def from_x(self, x):
        return jnp.exp(x) if self.log else x

    def x_bounds(self):
        if self.log:
            return (math.log(self.lo) if self.lo > 0 else -np.inf,
                    math.log(self.hi) if self.hi < math.inf else np.inf)
        return self.lo, self.hi


def free_from_spec(spec) -> list:
    """:class:`Free` leaves from a scene file's ``[fit]`` (params, bounds, space)."""
    return [Free(p, *spec.bounds.get(p, (-math.inf, math.inf)),
                 log=spec.space.get(p, "log") == "log") for p in spec.free]
