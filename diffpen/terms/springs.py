"""Spring terms: springs between bodies, springs to world points, and velocity drag."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import geometry, laws
from .base import CompileContext, Term, _one, _select, gather, scatter, with_bound
from ..stability import Bound

__all__ = ["spring_bands", "BODY_SPRINGS", "WORLD_SPRINGS", "DRAG"]


def _spring_axis(delta, rel_vel, rest):
    """Stretch (m), stretch rate (m/s) and unit axis for ONE spring."""
    u, length = geometry.safe_unit(delta)
    return length - rest, jnp.sum(u * rel_vel, axis=-1), u


def _spring_vector(ext, rate, u, delta, k, c, zero: np.ndarray):
    """``spring_force(ext, rate, k, c) u`` of (m,) springs, (m, 3), with ``zero`` (m,) the
    static mask of springs whose rest length is 0: those take ``-k delta - c rate u``, the
    same force written so that it stays smooth where the ends meet (``|delta| u`` has a zero
    derivative at ``delta = 0``, which dropped the ``-k I`` of the force's Jacobian: a
    particle started on its zero-length spring's anchor got ``d x(T) / d x0 = +1`` against
    ``cos(w T) = -0.99``). Springs of positive rest length keep the axial form."""
    f = laws.spring_force(ext, rate, k, c)[:, None] * u
    zero = np.asarray(zero, bool)
    if not zero.any():
        return f
    kk = jnp.broadcast_to(jnp.asarray(k), ext.shape)[:, None]
    fz = -kk * delta - (c * rate)[:, None] * u
    return fz if zero.all() else jnp.where(jnp.asarray(zero)[:, None], fz, f)


def spring_bands(ia: np.ndarray, ib: np.ndarray, *, min_fill: float = 0.5,
                 min_size: int = 8):
    """Split springs into *bands* (families with one index offset) and the rest.

    Builders add lattices with contiguous body indices, so the springs of one lattice
    direction join ``a`` to ``a + delta`` for one ``delta``. A band with offset ``delta`` over
    the index range ``[lo, hi)`` is evaluated with dense slices ``x[lo:hi]`` and
    ``x[lo + delta:hi + delta]`` (slots without a spring are masked), and its forces are put
    back with in-place row updates (``lax.dynamic_update_slice``): no gather or scatter in the
    forward or the reverse pass. A family is a band when it has ``>= min_size`` springs
    filling ``>= min_fill`` of its range; all other springs go through the generic gather /
    segment-sum path.

    Args:
      ia, ib: (m,) body indices of the spring ends.
    Returns:
      ``(bands, rest)``: ``bands`` a list of ``(delta, lo, hi, slots)`` where ``slots`` (m_b,)
      are spring ids placed at ``a - lo`` with ``a = min(ia, ib)``; ``rest`` the ids of the
      other springs.
    """
    a = np.minimum(ia, ib)
    delta = np.abs(ib - ia)
    bands, rest = [], []
    for d in np.unique(delta):
        ids = np.nonzero(delta == d)[0]
        lo, hi = int(a[ids].min()), int(a[ids].max()) + 1
        # one spring per slot, and enough of them to be worth a dense range
        if (len(np.unique(a[ids])) == len(ids) and len(ids) >= min_size
                and len(ids) >= min_fill * (hi - lo)):
            bands.append((int(d), lo, hi, ids))
        else:
            rest.extend(ids.tolist())
    return bands, np.array(sorted(rest), dtype=np.int32)


def _add_rows(total, rows, start: int):
    """``total[start:start + len(rows)] += rows`` as a static dynamic-update-slice."""
    z = (0,) * (rows.ndim - 1)
    seg = jax.lax.dynamic_slice(total, (start,) + z, rows.shape)
    return jax.lax.dynamic_update_slice(total, seg + rows, (start,) + z)


def _body_springs(ctx: CompileContext) -> Term | None:
    rows = [(s.a, s.b, s.rest_length, ctx.group_index[s.group])
            for s in ctx.scene.springs if s.b is not None]
    if not rows:
        return None
    ia_all = np.array([r[0] for r in rows], dtype=np.int32)
    ib_all = np.array([r[1] for r in rows], dtype=np.int32)
    gi_all = np.array([r[3] for r in rows], dtype=np.int32)
    rest_all = np.array([r[2] for r in rows], dtype=float)
    n = ctx.n
    bands, rest_ids = spring_bands(ia_all, ib_all)

    band_data = []
    for d, lo, hi, ids in bands:
        slot = np.minimum(ia_all[ids], ib_all[ids]) - lo
        mask = np.zeros(hi - lo)
        mask[slot] = 1.0
        rest_len = np.zeros(hi - lo)
        rest_len[slot] = rest_all[ids]
        gidx = np.zeros(hi - lo, dtype=np.int32)
        gidx[slot] = gi_all[ids]
        gidx[mask == 0.0] = gi_all[ids[0]]
        band_data.append((d, lo, hi, ctx.const(mask), ctx.const(rest_len), gidx,
                          (rest_len == 0.0) & (mask == 1.0)))

    ia, ib, gi = ia_all[rest_ids], ib_all[rest_ids], gi_all[rest_ids]
    rest = ctx.const(rest_all[rest_ids])
    zero = rest_all[rest_ids] == 0.0

    def force(params, state):
        x, v = state.position, state.velocity
        total = None
        for d, lo, hi, mask, rest_len, gidx, zero_b in band_data:
            k, c = ctx.spring_kc(params, gidx)
            x, v = state.position, state.velocity
            delta = x[lo + d:hi + d] - x[lo:hi]       # from the low end to the high end
            dv = v[lo + d:hi + d] - v[lo:hi]
            ext, rate, u = jax.vmap(_spring_axis)(delta, dv, rest_len)
            if zero_b.any():
                f = _spring_vector(ext, rate, u, delta, k, c, zero_b) * mask[:, None]
            else:
                f = (laws.spring_force(ext, rate, k, c) * mask)[:, None] * u
            if total is None:
                total = jnp.zeros((n,) + f.shape[1:], f.dtype)
            # in-place row-block updates: XLA evaluates the band's forces once, in the
            # update (two pads summed in one fusion recompute them per element: 2.9x slower)
            total = _add_rows(total, f, lo + d)
            total = _add_rows(total, -f, lo)
        if len(ia):
            k, c = ctx.spring_kc(params, gi)
            delta = x[ia] - x[ib]
            dv = v[ia] - v[ib]
            ext, rate, u = jax.vmap(_spring_axis)(delta, dv, rest)
            f = _spring_vector(ext, rate, u, delta, k, c, zero)
            fr = scatter(f, ia, n) - scatter(f, ib, n)
            total = fr if total is None else total + fr
        return total, None
    return Term("springs", force)


def _world_springs(ctx: CompileContext) -> Term | None:
    rows = [(s.a, s.anchor, s.rest_length, ctx.group_index[s.group])
            for s in ctx.scene.springs if s.b is None and not ctx.pinned[s.a]]
    if not rows:
        return None
    ia = np.array([r[0] for r in rows], dtype=np.int32)
    anchors = ctx.const([r[1] for r in rows])
    rest = ctx.const([r[2] for r in rows])
    zero = np.array([r[2] for r in rows], dtype=float) == 0.0
    gi = np.array([r[3] for r in rows], dtype=np.int32)
    n = ctx.n

    def force(params, state):
        k, c = ctx.spring_kc(params, gi)
        delta = gather(state.position, ia, n) - anchors
        x, xd, u = jax.vmap(_spring_axis)(delta, gather(state.velocity, ia, n), rest)
        return scatter(_spring_vector(x, xd, u, delta, k, c, zero), ia, n), None
    return Term("world_springs", force)


def _drag(ctx: CompileContext) -> Term | None:
    """Velocity drag ``F = -c v`` per body (``scene.add_drag``); ``c`` per drag group in
    ``params.extra["drag"][group]`` (N s/m). Absent (never traced) without drag."""
    rows = [(d.body, d.group) for d in ctx.scene.drags if not ctx.pinned[d.body]]
    if not rows:
        return None
    groups = list(dict.fromkeys(g for _, g in rows))
    bi = np.array([r[0] for r in rows], dtype=np.int32)
    gi = np.array([groups.index(r[1]) for r in rows], dtype=np.int32)
    n = ctx.n

    def force(params, state):
        c = _select([params.extra["drag"][g] for g in groups], gi)
        v = gather(state.velocity, bi, n)
        f = jax.vmap(laws.drag_force, in_axes=(0, None if jnp.ndim(c) == 0 else 0))(v, c)
        return scatter(f, bi, n), None
    return Term("drag", force, extra={"drag": {g: ctx.scene.drag_groups[g] for g in groups}})


def _spring_rows(ctx: CompileContext, springs):
    rows = []
    for s in springs:
        ends = [s.a] if s.b is None else [s.a, s.b]
        both_free = s.b is not None and not ctx.pinned[s.a] and not ctx.pinned[s.b]
        f = 2.0 if both_free else 1.0
        rows += [(i, s.group, f, f, f"spring group {s.group!r}") for i in ends
                 if not ctx.pinned[i]]
    return _one(Bound.of(rows, "springs"))


def _body_springs_bound(ctx: CompileContext):
    """Gershgorin: (sum_j k_ij + sum_{j free} k_ij) / m_i over a body's springs."""
    return _spring_rows(ctx, [s for s in ctx.scene.springs if s.b is not None])


def _world_springs_bound(ctx: CompileContext):
    return _spring_rows(ctx, [s for s in ctx.scene.springs if s.b is None])


def _spring_groups(ctx: CompileContext) -> tuple:
    """The groups of ``scene.springs``, in scene order, including springs that cannot act (a
    world spring on a pinned body): both spring terms read this one scene list (body springs
    and world springs) and declare its groups together, so the ``Params.springs`` keys keep
    the order in which the scene's springs name them."""
    return tuple(dict.fromkeys(s.group for s in ctx.scene.springs))


#: The spring term builders with their stability bounds and groups (see
#: :data:`diffpen.terms.BUILTIN`).
BODY_SPRINGS = with_bound(_body_springs, _body_springs_bound, groups=_spring_groups)
WORLD_SPRINGS = with_bound(_world_springs, _world_springs_bound, groups=_spring_groups)
def _drag_bound(ctx: CompileContext):
    """Drag is a damper to the world: ``c / m_i`` per dragged body (its group's ``c`` in
    ``params.extra["drag"]``), in the damping rows (explicit steps need ``h c / m < 2``)."""
    rows = [(d.body, d.group, 0.0, 1.0, f"drag group {d.group!r}")
            for d in ctx.scene.drags if not ctx.pinned[d.body]]
    return _one(Bound.of(rows, "drag"))


DRAG = with_bound(_drag, _drag_bound)
