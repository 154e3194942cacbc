"""Broad phase: find the sphere-sphere and sphere-box pairs that may touch, in fixed capacity.

Pairs that are fixed for the whole run (a body against a plane or a fixed sphere) are decided
when the scene compiles and never pass through here. Pairs between moving bodies are found
by one of these strategies, passed as ``diffpen.compile(scene, dt, broadphase=...)``:

* ``None`` (default): every pair that can move is evaluated (exact; cost ~ number of pairs).
* :class:`AABB`: the static list of all such pairs is pruned by axis-aligned bounding-box
  overlap and compacted into ``max_pairs`` slots before the narrow phase.
* :class:`Grid`: a uniform grid neighbour search (sort by cell, look in the 27 neighbouring
  cells, at most ``max_per_cell`` bodies per cell), then the same AABB test and compaction.
  Cost ~ n log n + 27 n max_per_cell: near linear in the number of bodies.

Capacities are static (changing them recompiles). When more pairs overlap than fit, or a
cell holds more bodies than ``max_per_cell``, contacts would be lost: this is never silent.
``State.aux["broadphase_overflow"]`` becomes 1.0 in the state returned by the first step whose
search overflowed (and already in ``init_state()`` when the scene's initial state does) and
stays 1.0 (sticky, saved in ``Trajectory.aux``); a rollout with concrete values then warns
with :class:`BroadPhaseOverflowWarning`. The broad phase only selects pairs: the forces of the
selected pairs are exactly the narrow phase's, so without overflow the result equals the
all-pairs simulation.

One search per step: each step (each inner step with ``substeps``) searches once, at the state
it starts from; the force evaluation at that state uses the pairs found and the overflow flag
is taken from the same search (the term's ``search`` / ``record``, see
:class:`diffpen.terms.Term`). With semi-implicit Euler, the default, that is the step's only
force evaluation, so a step runs exactly one search. Integrators that evaluate forces several
times per step search again at each other state they evaluate (verlet: 2 searches per step,
rk4: 4; implicit Euler: its Jacobian products too), so every evaluation sees the pairs of its
own state; the flag records the step's first search, i.e. the states between steps.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .errors import SceneError, warn
from .geometry import quat_to_matrix
from .terms.base import CompileContext

__all__ = ["AABB", "Grid", "Pairs", "BroadPhaseOverflowWarning", "aabb", "aabb_overlap",
           "compact", "grid_candidates", "brute_force_pairs", "find_pairs"]

OVERFLOW = "broadphase_overflow"
#: ``jax.named_scope`` of one pair search (:func:`find_pairs`) in traced programs.
SEARCH_SCOPE = "broadphase_search"

# body classes for pair eligibility
_NONE, _SPHERE, _PARTICLE, _BOX = 0, 1, 2, 3
#: which class pairs have a narrow phase (sphere-sphere, sphere/particle-box)
_ALLOWED = np.zeros((4, 4), dtype=bool)
_ALLOWED[_SPHERE, _SPHERE] = True
for _a, _b in ((_SPHERE, _BOX), (_PARTICLE, _BOX)):
    _ALLOWED[_a, _b] = _ALLOWED[_b, _a] = True


class BroadPhaseOverflowWarning(RuntimeWarning):
    """A rollout had more candidate pairs than the broad phase's static capacity."""


@dataclasses.dataclass(frozen=True)
class AABB:
    """Prune all movable pairs by bounding-box overlap into ``max_pairs`` slots.

    Args:
      max_pairs: static capacity of overlapping pairs (int > 0); default: the number of
        movable pairs (never overflows, but saves no narrow-phase work).
      margin: m >= 0 added to every box's half widths (finds pairs slightly early); half the
        contact smoothing width is always added on top.
    """
    max_pairs: int | None = None
    margin: float = 0.0


@dataclasses.dataclass(frozen=True)
class Grid:
    """Uniform-grid neighbour search of fixed capacity.

    Args:
      cell_size: m; at least the largest bounding-box width (2 x largest bounding radius +
        2 margin), the default. A step whose widest box (swept by ``|v| dt``) is wider
        searches with cells that wide, so every overlapping pair lies in neighbouring cells
        (fast bodies crowd the cells instead: reported as overflow when a cell is full).
      max_per_cell: static capacity of one cell (bodies); more is reported as overflow.
      max_pairs: static capacity of overlapping pairs; default 8 per body.
      bounds: ``((x0, y0, z0), (x1, y1, z1))`` m, the gridded region; bodies outside it are
        clamped into the border cells (still correct, just more crowded). Default: the
        initial positions widened by 8 cells on each side.
      margin: m >= 0 added to every box's half widths (half the contact smoothing width is
        always added on top).
    """
    cell_size: float | None = None
    max_per_cell: int = 8
    max_pairs: int | None = None
    bounds: tuple | None = None
    margin: float = 0.0


class Pairs(NamedTuple):
    """Candidate pairs found by a broad phase (all arrays of static length ``capacity``).

    i, j: (capacity,) int32 body indices (i < j); padded slots repeat pair 0.
    valid: (capacity,) bool, real overlapping pairs.  count: int32, overlapping pairs found
    (may exceed capacity).  overflow: bool, some pair was lost (capacity or a full cell).
    """
    i: Any
    j: Any
    valid: Any
    count: Any
    overflow: Any


# --------------------------------------------------------------------------- primitives
def aabb(x, half_widths):
    """Axis-aligned box ``(lo, hi)``, each (..., 3) m, of centre x (..., 3) and half widths."""
    return x - half_widths, x + half_widths


def aabb_overlap(lo_a, hi_a, lo_b, hi_b):
    """Whether two axis-aligned boxes overlap (touching counts), (...,) bool."""
    return jnp.all((lo_a <= hi_b) & (lo_b <= hi_a), axis=-1)


def compact(mask, capacity: int):
    """Indices of the True entries of ``mask`` (P,) in ``capacity`` static slots.

    Returns ``(idx (capacity,) int32, valid (capacity,) bool, count int32)``; padded slots
    hold index 0 and ``valid`` False. ``count > capacity`` means entries were left out.
    """
    (idx,) = jnp.nonzero(mask, size=capacity, fill_value=0)
    count = jnp.sum(mask, dtype=jnp.int32)
    return idx.astype(jnp.int32), jnp.arange(capacity) < count, count


def grid_candidates(x, cell_size: float, origin, dims, max_per_cell: int):
    """Neighbour-grid candidates: for each point, the points of its own cell and of the 13
    neighbouring cells on the "forward" half (larger cell key), so that each unordered pair
    of neighbouring cells is visited once.

    Args:
      x: (m, 3) points, m.  cell_size: m.  origin: (3,) m, corner of cell (0, 0, 0).
      dims: (3,) ints, cells per axis (static); points outside are clamped into the grid.
      max_per_cell: static number of slots looked at per neighbouring cell.
    Returns:
      ``(a, b, ok, full)``: (m, 14 * max_per_cell) point indices ``a < b`` of candidate pairs
      with ``ok`` marking real ones (each unordered pair appears once), and ``full`` (bool)
      whether some cell holds more than ``max_per_cell`` points (candidates were missed).
    """
    m = x.shape[0]
    dims_np = np.asarray(dims, dtype=np.int64)
    dims_j = jnp.asarray(dims_np, dtype=jnp.int32)
    cell = jnp.floor((x - origin) / cell_size).astype(jnp.int32)
    cell = jnp.clip(cell, 0, dims_j - 1)

    def key(c):
        return c[..., 0] + int(dims_np[0]) * (c[..., 1] + int(dims_np[1]) * c[..., 2])

    own = key(cell)
    order = jnp.argsort(own)
    sorted_keys = own[order]
    count = (jnp.searchsorted(sorted_keys, own, side="right", method="scan_unrolled")
             - jnp.searchsorted(sorted_keys, own, side="left", method="scan_unrolled"))
    full = jnp.any(count > max_per_cell)

    # own cell first, then the 13 offsets (dz, dy, dx) > 0 in lexicographic (= key) order
    offsets = jnp.asarray([(0, 0, 0)] + [(dx, dy, dz) for dz, dy, dx in
                                          itertools.product((-1, 0, 1), repeat=3)
                                          if (dz, dy, dx) > (0, 0, 0)], dtype=jnp.int32)
    near = cell[:, None, :] + offsets[None]                                   # (m, 14, 3)
    inside = jnp.all((near >= 0) & (near < dims_j), axis=-1)                  # (m, 14)
    near_key = key(near)
    start = jnp.searchsorted(sorted_keys, near_key.reshape(-1), side="left",
                             method="scan_unrolled").reshape(near_key.shape)
    slot = start[..., None] + jnp.arange(max_per_cell, dtype=start.dtype)     # (m, 14, M)
    slot_c = jnp.minimum(slot, m - 1)
    b = order[slot_c]
    a = jnp.broadcast_to(jnp.arange(m)[:, None, None], b.shape)
    own_cell = (jnp.arange(offsets.shape[0]) == 0)[None, :, None]
    ok = (inside[..., None] & (slot < m) & (sorted_keys[slot_c] == near_key[..., None])
          & ((a < b) | ~own_cell))            # within a cell, each pair from its lower end
    a, b = jnp.minimum(a, b), jnp.maximum(a, b)
    return a.reshape(m, -1), b.reshape(m, -1), ok.reshape(m, -1), full


# --------------------------------------------------------------------------- scene data
def _classes(ctx: CompileContext) -> np.ndarray:
    out = np.zeros(ctx.n, dtype=np.int32)
    for i, b in enumerate(ctx.scene.bodies):
        if not b.collide:
            continue
        if b.kind == "box":
            out[i] = _BOX
        elif b.kind == "sphere" and b.radius > 0.0:
            out[i] = _SPHERE
        else:
            out[i] = _PARTICLE
    return out


def _static_pairs(ctx: CompileContext) -> tuple[np.ndarray, np.ndarray]:
    """Every body pair (i < j) with a narrow phase that is not two pinned bodies."""
    cls = _classes(ctx)
    ia, ib = np.triu_indices(ctx.n, k=1)
    keep = _ALLOWED[cls[ia], cls[ib]] & ~(ctx.pinned[ia] & ctx.pinned[ib])
    return ia[keep].astype(np.int32), ib[keep].astype(np.int32)


def _grid_bodies(ctx: CompileContext) -> np.ndarray:
    cls = _classes(ctx)
    ok = cls != _NONE
    partners = _ALLOWED[cls][:, cls]                    # (n, n) pairs with a narrow phase
    ok &= partners[:, ok].any(axis=1) if ok.any() else ok
    return np.nonzero(ok)[0].astype(np.int32)


def _margin(bp, ctx: CompileContext) -> float:
    """Bounding-box margin, m: the user's ``margin`` plus half the contact smoothing width
    (the smoothed laws already push at a gap of up to ``width / 2``, so such pairs must be
    found)."""
    return bp.margin + 0.5 * ctx.width


def _grid_layout(bp: Grid, ctx: CompileContext, gi: np.ndarray):
    radius = ctx.radius[gi]
    need = 2.0 * (float(radius.max()) + _margin(bp, ctx))
    cell = need if bp.cell_size is None else float(bp.cell_size)
    if bp.bounds is None:
        pos = np.array([ctx.scene.bodies[i].position for i in gi])
        lo, hi = pos.min(axis=0) - 8.0 * cell, pos.max(axis=0) + 8.0 * cell
    else:
        lo, hi = (np.asarray(v, dtype=float) for v in bp.bounds)
    dims = np.maximum(np.ceil((hi - lo) / cell).astype(np.int64), 1)
    return cell, need, lo, hi, dims


def check(bp, ctx: CompileContext) -> None:
    """Validate a broad-phase option against the scene (raises SceneError)."""
    if not isinstance(bp, (AABB, Grid)):
        raise SceneError(f"broadphase must be None, diffpen.broadphase.AABB(...) or "
                         f"diffpen.broadphase.Grid(...), got {bp!r}.")
    if not (math.isfinite(bp.margin) and bp.margin >= 0.0):
        raise SceneError(f"broadphase margin must be >= 0 metres, got {bp.margin!r}.")
    if bp.max_pairs is not None and (not isinstance(bp.max_pairs, (int, np.integer))
                                     or isinstance(bp.max_pairs, bool) or bp.max_pairs < 1):
        raise SceneError(f"broadphase max_pairs must be a positive int, got {bp.max_pairs!r}.")
    if isinstance(bp, Grid):
        if (not isinstance(bp.max_per_cell, (int, np.integer))
                or isinstance(bp.max_per_cell, bool) or bp.max_per_cell < 1):
            raise SceneError(f"Grid max_per_cell must be a positive int, got "
                             f"{bp.max_per_cell!r}.")
        gi = _grid_bodies(ctx)
        if gi.size == 0:
            return
        if bp.bounds is not None:
            try:
                lo, hi = (np.asarray(v, dtype=float).reshape(3) for v in bp.bounds)
            except (TypeError, ValueError):
                raise SceneError(f"Grid bounds must be ((x0, y0, z0), (x1, y1, z1)) metres, "
                                 f"got {bp.bounds!r}.") from None
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
                raise SceneError(f"Grid bounds need finite lo < hi on every axis, got "
                                 f"{bp.bounds!r}.")
        if bp.cell_size is not None and not (math.isfinite(bp.cell_size)
                                             and bp.cell_size > 0.0):
            raise SceneError(f"Grid cell_size must be a positive number of metres, got "
                             f"{bp.cell_size!r}.")
        cell, need, _, _, dims = _grid_layout(bp, ctx, gi)
        if cell < need * (1.0 - 1e-12):
            raise SceneError(f"Grid cell_size={cell} m is smaller than the largest bounding "
                             f"box ({need:.6g} m = 2 x (largest bounding radius + margin + half "
                             "the smoothing width)): "
                             "overlapping bodies could be two cells apart. Use cell_size >= "
                             f"{need:.6g} or leave it None.")
        if int(np.prod(dims)) >= 2 ** 31:
            raise SceneError(f"Grid has {int(np.prod(dims))} cells (>= 2^31): give tighter "
                             "bounds= or a larger cell_size.")


def half_widths(ctx: CompileContext, state, idx: np.ndarray, margin: float):
    """Half widths (len(idx), 3) m of the bodies' axis-aligned bounding boxes: the radius for
    spheres and particles, ``|R| h`` for boxes (R rotation, h half extents); plus, per axis,
    ``|v| dt`` on every axis: the box swept over the step window of the step-averaged
    contact, which acts from a gap of ``|vn| h`` on along the contact's normal, whatever its
    direction (``ctx.step`` = dt; the speed, not each axis' component: a pair closing at an
    angle was dropped). A box's sweep adds its corners' turning speed ``|w| |h|`` (``|h|``
    the half-diagonal): a spinning box's corner reaches a sphere its centre's speed does
    not (a 10 cm box at 100 rad/s missed a ball 5 mm from its face)."""
    bodies = ctx.scene.bodies
    r = ctx.const(ctx.radius[idx] + margin)[:, None]
    boxes = np.array([bodies[i].kind == "box" for i in idx])
    sweep = (jnp.linalg.norm(state.velocity[idx], axis=-1, keepdims=True) * ctx.step
             if ctx.step else 0.0)
    if ctx.step:
        r = r + sweep
    if not boxes.any():
        return jnp.broadcast_to(r, (len(idx), 3))
    half = ctx.const([bodies[i].half_extents if boxes[k] else (0.0, 0.0, 0.0)
                      for k, i in enumerate(idx)])
    rot = quat_to_matrix(state.orientation[idx])
    box_w = jnp.sum(jnp.abs(rot) * half[:, None, :], axis=-1) + margin
    if ctx.step:
        box_w = box_w + sweep
        if state.angular_velocity is not None:     # None: no rotating body in the scene
            turn = (jnp.linalg.norm(state.angular_velocity[idx], axis=-1, keepdims=True)
                    * jnp.linalg.norm(half, axis=-1, keepdims=True))
            box_w = box_w + turn * ctx.step
    return jnp.where(jnp.asarray(boxes)[:, None], box_w, r)


# --------------------------------------------------------------------------- pair search
def find_pairs(bp, ctx: CompileContext, state) -> Pairs:
    """Overlapping candidate pairs of the current state with the static capacity of ``bp``
    (traced under ``jax.named_scope(SEARCH_SCOPE)``)."""
    with jax.named_scope(SEARCH_SCOPE):
        return _find_pairs(bp, ctx, state)


def _find_pairs(bp, ctx: CompileContext, state) -> Pairs:
    if isinstance(bp, AABB):
        ia, ib = _static_pairs(ctx)
        cap = bp.max_pairs or max(len(ia), 1)
        lo, hi = aabb(state.position,
                      half_widths(ctx, state, np.arange(ctx.n), _margin(bp, ctx)))
        mask = aabb_overlap(lo[ia], hi[ia], lo[ib], hi[ib])
        idx, valid, count = compact(mask, cap)
        return Pairs(jnp.asarray(ia)[idx], jnp.asarray(ib)[idx], valid, count, count > cap)
    gi = _grid_bodies(ctx)
    m = len(gi)
    cap = bp.max_pairs or 8 * m
    cell, _, lo0, _, dims = _grid_layout(bp, ctx, gi)
    x = state.position[gi]
    lo, hi = aabb(x, half_widths(ctx, state, gi, _margin(bp, ctx)))
    # neighbouring cells hold every overlapping pair while each box fits in a cell: a box
    # swept wider by a fast body (|v| dt) widens this step's cells to it (the static cell
    # count still covers the bounds; a crowded cell is reported as overflow)
    widest = jnp.max(hi - lo)
    cell = jnp.where(widest > cell * (1.0 + 1e-9), widest, cell)   # rounding keeps the cell
    a, b, ok, full = grid_candidates(x, cell, ctx.const(lo0), dims, bp.max_per_cell)
    a, b, ok = a.reshape(-1), b.reshape(-1), ok.reshape(-1)
    ga, gb = jnp.asarray(gi)[a], jnp.asarray(gi)[b]
    # eligibility per candidate pair from (n,) tables: O(n) constants, not an (n, n) matrix
    cls, pinned = jnp.asarray(_classes(ctx)), jnp.asarray(ctx.pinned)
    allowed = jnp.asarray(_ALLOWED)[cls[ga], cls[gb]] & ~(pinned[ga] & pinned[gb])
    # a < b in grid order = body order (gi is increasing), so ga < gb
    mask = ok & allowed & aabb_overlap(lo[a], hi[a], lo[b], hi[b])
    idx, valid, count = compact(mask, cap)
    return Pairs(ga[idx], gb[idx], valid, count, (count > cap) | full)


def brute_force_pairs(ctx: CompileContext, state, margin: float = 0.0) -> set:
    """Reference: the set of (i, j) pairs with overlapping bounding boxes, by testing all
    pairs (numpy; for tests)."""
    ia, ib = _static_pairs(ctx)
    lo, hi = aabb(state.position, half_widths(ctx, state, np.arange(ctx.n), margin))
    lo, hi = np.asarray(lo), np.asarray(hi)
    keep = np.all((lo[ia] <= hi[ib]) & (lo[ib] <= hi[ia]), axis=-1)
    return {(int(i), int(j)) for i, j in zip(ia[keep], ib[keep])}












def warn_overflow(traj) -> None:
    """Warn when a concrete trajectory's (or ``sim.forces``' search's)
    ``aux["broadphase_overflow"]`` is set."""
    flag = traj.aux.get(OVERFLOW) if isinstance(traj.aux, dict) else None
    if flag is not None and float(np.asarray(flag).reshape(-1)[-1]) > 0.0:
        warn("the broad phase overflowed its static capacity: some contacts were "
                      "not evaluated. Raise max_pairs (or Grid "
                      "max_per_cell), or widen Grid bounds.", BroadPhaseOverflowWarning)




