"""Contact terms of spheres and particles: against planes, against fixed spheres, sphere
against sphere (all pairs), and the pairs a broad phase (:mod:`diffpen.broadphase`: AABB,
Grid) finds. The pair sources only find candidate pairs; the force code is here."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import broadphase as _bp
from .. import geometry
from ..scene import DEFAULT
from ..stability import Bound
from . import friction as _friction
from .base import (CompileContext, Term, _one, _pair_material, _uniform, gather, merge_extra,
                   plane_offset_extra, plane_offsets, scatter, static_dot, static_scale,
                   with_bound)

__all__ = ["PLANE", "FIXED_SPHERE", "SPHERE_SPHERE", "BROADPHASE",
           "sphere_pair_materials"]


def _collider_contact(ctx: CompileContext, name: str, colliders: list, shape_args, *,
                      shape_fn=None, static_normal=None, named=False) -> Term | None:
    """Contacts of every moving, colliding non-box body with every fixed collider of one kind
    (boxes collide by their corners, diffpen.rigid). Give one of:

    * ``shape_fn``: ``shape_fn(x, r, *shape_args(collider))`` gives ``(d, n)`` for one pair;
    * ``static_normal(collider)`` (planes, ``shape_args = (offset,)``): the normal is a
      constant of the step (``static_dot`` / ``static_scale``) and
      ``d = r - (n . x - offset)``, geometry.sphere_plane with its zeros left out; with
      ``named`` the offsets of named planes are params (:func:`plane_offsets`).

    Rows whose collider's material has friction also take it here, from the normal force
    just computed (:func:`diffpen.terms.friction.contact_friction`; the term then returns
    its torque on rigid spheres, and holds rows, not columns)."""
    scene = ctx.scene
    rows = [(i, j, ctx.material_index[col.material])
            for j, col in enumerate(colliders)
            for i in range(ctx.n) if ctx.collide[i] and not ctx.pinned[i]
            and scene.bodies[i].kind != "box"]
    if not rows:
        return None
    bi, ci, mi = (np.array(col, dtype=np.int32) for col in zip(*rows))
    args = [ctx.const(list(a)) for a in zip(*(shape_args(colliders[j]) for j in ci))]
    radii = ctx.const(ctx.radius[bi])
    n = ctx.n
    normal = None if static_normal is None else np.array(
        [static_normal(colliders[j]) for j in ci], dtype=float)
    offset_fn = plane_offsets(ctx, ci) if named else None
    extra, checks = plane_offset_extra(ctx, ci) if named else ({}, {})
    inv_m = _uniform(ctx, ctx.inv_mass(bi))
    g_plane = None if normal is None else _uniform(ctx, ctx.normal_gravity(normal, bi))
    g_vec = ctx.const(ctx.scene.gravity)
    site = ctx.factor_site(mi, inv_m)
    rough = _friction.contact_friction(ctx, bi, [colliders[j].material for j in ci])
    if rough is not None:
        extra = merge_extra(rough[0], extra)
    normals = None if normal is None or rough is None else ctx.const(normal)

    def with_friction(params, state, out, nrm, f):
        if rough is None:
            return out, None
        f_t, tau = rough[1](params, state, nrm, f)
        return out + f_t, tau

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        fac = ctx.step_factors(params, site, h)
        x, v = gather(state.position, bi, n), gather(state.velocity, bi, n)
        if normal is not None:          # the normal is a constant: leave out its zeros
            off = args[0] if offset_fn is None else offset_fn(params)
            d = radii - (static_dot(normal, x) - off)
            f = ctx.contact_force(d, static_dot(normal, v), k, c, h, inv_m, g_plane, fac)
            out = scatter(static_scale(f, normal, as_columns=rough is None), bi, n)
            return with_friction(params, state, out, normals, f)
        d, nrm = jax.vmap(shape_fn)(x, radii, *args)
        f = ctx.contact_force(d, geometry.dot(nrm, v), k, c, h, inv_m,
                              geometry.dot(nrm, g_vec), fac)
        return with_friction(params, state, scatter(f[:, None] * nrm, bi, n), nrm, f)
    return Term(name, force, step_aware=True, extra=extra, checks=checks,
                columns=normal is not None and rough is None)


def _plane_contact(ctx: CompileContext) -> Term | None:
    return _collider_contact(ctx, "contact_plane", ctx.scene.planes,
                             lambda pl: (pl.offset,), static_normal=lambda pl: pl.normal,
                             named=True)


def _fixed_sphere_contact(ctx: CompileContext) -> Term | None:
    return _collider_contact(ctx, "contact_fixed_sphere", ctx.scene.fixed_spheres,
                             lambda fs: (fs.center, fs.radius), shape_fn=geometry.sphere_sphere)


def _gravity_side(pin_a, pin_b, xp=np):
    """Per pair: how gravity separates it along its normal, ``n . g`` times 1 (b pinned),
    -1 (a pinned) or 0 (both free: gravity moves both ends alike)."""
    return xp.where(pin_b & ~pin_a, 1.0, xp.where(pin_a & ~pin_b, -1.0, 0.0))


def _sphere_pair_force(ctx: CompileContext, xa, ra, va, xb, rb, vb, k, c, h, inv_m, g_side,
                       g_vec, factors=None):
    """The contact force (m, 3) N on sphere ``a`` of each pair (``b`` takes its opposite):
    centres ``xa``, ``xb`` (m, 3) m, radii (m,) m, velocities (m, 3) m/s, the pair's summed
    inverse mass (1/kg) and :func:`_gravity_side`; the one pair law of the all-pairs term
    and the broad phase's."""
    d, nrm = jax.vmap(geometry.sphere_sphere)(xa, ra, xb, rb)
    vn = geometry.dot(nrm, va - vb)
    f = ctx.contact_force(d, vn, k, c, h, inv_m, g_side * geometry.dot(nrm, g_vec), factors)
    return f[:, None] * nrm


def _sphere_sphere_contact(ctx: CompileContext) -> Term | None:
    if ctx.broadphase is not None:
        return None                     # diffpen.broadphase builds the pair term instead
    scene = ctx.scene
    spheres = [i for i in range(ctx.n)
               if ctx.collide[i] and ctx.radius[i] > 0.0 and scene.bodies[i].kind == "sphere"]
    rows = []
    for a_pos, i in enumerate(spheres):
        for j in spheres[a_pos + 1:]:
            if ctx.pinned[i] and ctx.pinned[j]:
                continue  # two fixed things never need evaluating
            mat = _pair_material(scene, scene.bodies[i].material, scene.bodies[j].material)
            rows.append((i, j, ctx.material_index[mat]))
    if not rows:
        return None
    ia, ib, mi = (np.array(col, dtype=np.int32) for col in zip(*rows))
    ra, rb = ctx.const(ctx.radius[ia]), ctx.const(ctx.radius[ib])
    n = ctx.n
    inv_m = _uniform(ctx, ctx.inv_mass(ia) + ctx.inv_mass(ib))
    g_side = ctx.const(_gravity_side(ctx.pinned[ia], ctx.pinned[ib]))
    g_vec = ctx.const(ctx.scene.gravity)
    site = ctx.factor_site(mi, inv_m)

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        x, v = state.position, state.velocity
        f = _sphere_pair_force(ctx, x[ia], ra, v[ia], x[ib], rb, v[ib], k, c, h, inv_m,
                               g_side, g_vec, ctx.step_factors(params, site, h))
        return scatter(f, ia, n) - scatter(f, ib, n), None
    return Term("contact_sphere_sphere", force, step_aware=True)


# --------------------------------------------------------------------------- materials
def _collider_materials(ctx: CompileContext, colliders: list) -> tuple:
    """The colliders' materials (in collider order) when some moving, colliding non-box body
    can touch them (boxes: :mod:`diffpen.terms.rigid`)."""
    if not any(ctx.collide[i] and not ctx.pinned[i] and ctx.scene.bodies[i].kind != "box"
               for i in range(ctx.n)):
        return ()
    return tuple(dict.fromkeys(col.material for col in colliders))


def sphere_pair_materials(ctx: CompileContext) -> tuple:
    """Materials of the sphere-sphere pairs that can act, in O(n): a pair (i, j) with a free
    end uses their shared material, or "default" when they differ. Order: each material some
    same-material pair uses, in order of its first sphere, then "default" for mixed pairs."""
    bodies, pinned = ctx.scene.bodies, ctx.pinned
    spheres = [i for i in range(ctx.n)
               if ctx.collide[i] and ctx.radius[i] > 0.0 and bodies[i].kind == "sphere"]
    by_mat: dict[str, list[int]] = {}
    for i in spheres:
        by_mat.setdefault(bodies[i].material, []).append(i)
    used = [m for m, members in by_mat.items()
            if len(members) >= 2 and any(not pinned[i] for i in members)]
    if len(by_mat) >= 2 and any(not pinned[i] for i in spheres):
        used.append(DEFAULT)
    return tuple(dict.fromkeys(used))


def _sphere_sphere_materials(ctx: CompileContext) -> tuple:
    return sphere_pair_materials(ctx) if ctx.broadphase is None else ()


def _broadphase_materials(ctx: CompileContext) -> tuple:
    """The sphere-sphere pair materials, then the sphere-box ones, of the pairs it finds."""
    if ctx.broadphase is None:
        return ()
    from .rigid import sphere_box_pairs
    has_ss, has_sb = _pair_kinds(ctx)
    return tuple(dict.fromkeys(
        (sphere_pair_materials(ctx) if has_ss else ())
        + (tuple(m for _, _, m in sphere_box_pairs(ctx.scene)) if has_sb else ())))


# --------------------------------------------------------------------------- stability bounds
_KISSING = 12  # most equal spheres that can touch one sphere at once


def _movers(ctx: CompileContext):
    return [i for i in range(ctx.n) if ctx.collide[i] and not ctx.pinned[i]]


def plane_crowding(normals) -> float:
    """How many plane contacts can push a body along one direction at once, as a stiffness
    factor: ``max_u sum_p max(n_p . u, 0)^2`` over unit vectors u, for the unit ``normals``
    (P, 3) of a scene's planes (1 for a floor, for a floor with walls or any set of mutually
    orthogonal planes, for opposite walls; about P for P planes of a shallow bowl, whose
    contacts all push up together). Planes facing each other (``n_p . u < 0``) are not
    counted: a body squeezed between them is not bounded either way. Maximised over the
    normals, their pairwise and total sums and 256 spread directions, each refined by the
    fixed point ``u <- sum_p max(n_p . u, 0) n_p`` (which never lowers the value)."""
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    if len(n) <= 1:
        return float(len(n))
    i = np.arange(256) + 0.5                        # a Fibonacci sphere
    z = 1.0 - 2.0 * i / 256
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    rad = np.sqrt(1.0 - z * z)
    cands = [n, np.stack([rad * np.cos(phi), rad * np.sin(phi), z], axis=1),
             n.sum(axis=0, keepdims=True)]
    if len(n) <= 64:
        a, b = np.triu_indices(len(n), 1)
        cands.append(n[a] + n[b])
    u = np.concatenate(cands)
    u = u[np.linalg.norm(u, axis=1) > 1e-9]
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    for _ in range(32):
        proj = np.maximum(u @ n.T, 0.0)
        nxt = proj @ n
        norm = np.linalg.norm(nxt, axis=1, keepdims=True)
        u = np.where(norm > 1e-12, nxt / np.where(norm > 1e-12, norm, 1.0), u)
    return max(1.0, float((np.maximum(u @ n.T, 0.0) ** 2).sum(axis=1).max()))


def _plane_bound(ctx: CompileContext):
    """One contact spring per (free, colliding body, plane), k / m, one contact at a time,
    times :func:`plane_crowding` of the scene's planes (the contacts of a bowl of planes
    push together)."""
    w = plane_crowding([pl.normal for pl in ctx.scene.planes])
    rows = [(i, pl.material, w, w, f"contact with plane {p} (material {pl.material!r})")
            for i in _movers(ctx) for p, pl in enumerate(ctx.scene.planes)]
    return (*_one(Bound.of(rows, "contact", combine="contact")),
            *_friction.contact_friction_bound(ctx, ctx.scene.planes))


def _fixed_sphere_bound(ctx: CompileContext):
    rows = [(i, fs.material, 1.0, 1.0,
             f"contact with fixed sphere {s} (material {fs.material!r})")
            for i in _movers(ctx) for s, fs in enumerate(ctx.scene.fixed_spheres)]
    return (*_one(Bound.of(rows, "contact", combine="contact")),
            *_friction.contact_friction_bound(ctx, ctx.scene.fixed_spheres))


def _sphere_sphere_bound(ctx: CompileContext):
    """In O(n): a sphere's candidate partners are the other colliding spheres; a pair uses
    their shared material, else "default"; 2 k / m when both are free (a two-sphere
    collision), counted once per material (one contact at a time), with the number of
    candidate neighbours (at most 12) for the packed bound."""
    scene, pinned = ctx.scene, ctx.pinned
    spheres = [i for i in range(ctx.n) if ctx.collide[i] and ctx.radius[i] > 0.0
               and scene.bodies[i].kind == "sphere"]
    count, free_count = {}, {}
    for i in spheres:
        m = scene.bodies[i].material
        count[m] = count.get(m, 0) + 1
        free_count[m] = free_count.get(m, 0) + (0 if pinned[i] else 1)
    total, total_free = len(spheres), sum(free_count.values())
    rows, mult = [], []
    for i in spheres:
        if pinned[i]:
            continue
        m = scene.bodies[i].material
        same, same_free = count[m] - 1, free_count[m] - 1
        other, other_free = total - count[m], total_free - free_count[m]
        n_same = min(same, _KISSING)
        if same > 0:
            f = 2.0 if same_free > 0 else 1.0
            rows.append((i, m, f, f,
                         f"contact between sphere {i} and another sphere (material {m!r})"))
            mult.append(n_same)
        if other > 0:
            f = 2.0 if other_free > 0 else 1.0
            rows.append((i, DEFAULT, f, f,
                         f"contact between sphere {i} and a sphere of another material"))
            mult.append(min(other, _KISSING - n_same))
    return _one(Bound.of(rows, "contact", combine="contact", packed=mult))


# --------------------------------------------------------------------------- broad-phase pairs
# --------------------------------------------------------------------------- the term
def _pair_material_table(ctx: CompileContext) -> tuple[np.ndarray, np.ndarray]:
    """Per-body scene-material index (n,) and table (s, s) -> params material index."""
    names = list(ctx.scene.materials)
    body_mat = np.array([names.index(b.material) for b in ctx.scene.bodies], dtype=np.int32)
    table = np.zeros((len(names), len(names)), dtype=np.int32)
    for a, na in enumerate(names):
        for b, nb in enumerate(names):
            table[a, b] = ctx.material_index.get(_pair_material(ctx.scene, na, nb), 0)
    return body_mat, table


def _kc(ctx: CompileContext, params, mi):
    """(k, c) per pair for traced material indices ``mi`` (scalars with one material)."""
    names = list(ctx.material_index)
    if len(names) == 1:
        p = params.contact[names[0]]
        return p.k, p.c
    ks = jnp.stack([jnp.asarray(params.contact[nm].k) for nm in names])
    cs = jnp.stack([jnp.asarray(params.contact[nm].c) for nm in names])
    return ks[mi], cs[mi]


def _pair_kinds(ctx: CompileContext) -> tuple[bool, bool]:
    """Whether any sphere-sphere / sphere-or-particle-box pair can act, in O(n) (no list of
    all pairs): a pair acts unless both ends are pinned."""
    cls, pinned = _bp._classes(ctx), ctx.pinned
    sph, box = cls == _bp._SPHERE, cls == _bp._BOX
    pt = sph | (cls == _bp._PARTICLE)
    has_ss = bool(sph.sum() >= 2 and (sph & ~pinned).any())
    has_sb = bool(box.any() and pt.any() and ((box & ~pinned).any() or (pt & ~pinned).any()))
    return has_ss, has_sb


def _broadphase_contact(ctx: CompileContext) -> Term | None:
    bp = ctx.broadphase
    if bp is None:
        return None
    has_ss, has_sb = _pair_kinds(ctx)
    if not (has_ss or has_sb):
        return None
    cls = _bp._classes(ctx)
    body_mat, table = _pair_material_table(ctx)
    body_mat, table = jnp.asarray(body_mat), jnp.asarray(table)
    is_box = jnp.asarray(cls == _bp._BOX)
    radius = ctx.const(ctx.radius)
    half_all = ctx.const([b.half_extents or (0.0, 0.0, 0.0) for b in ctx.scene.bodies])
    n = ctx.n

    init = jax.jit(lambda s: _bp.find_pairs(bp, ctx, s).overflow)(_initial_state(ctx))
    # per-body tables for the centred law, as the all-pairs sphere-sphere term has them
    inv_m_all = ctx.const(ctx.inv_mass(np.arange(n)))
    pinned_all = jnp.asarray(ctx.pinned)
    g_vec = ctx.const(ctx.scene.gravity)

    def search(params, state):
        return _bp.find_pairs(bp, ctx, state)

    def record(aux, pairs):
        old = aux[_bp.OVERFLOW]
        return {_bp.OVERFLOW: jnp.maximum(old, pairs.overflow.astype(old.dtype))}

    def force(params, state, pairs=None, *, h=None):
        if pairs is None:
            pairs = _bp.find_pairs(bp, ctx, state)
        i, j, valid = pairs.i, pairs.j, pairs.valid
        k, c = _kc(ctx, params, table[body_mat[i], body_mat[j]])
        f = jnp.zeros_like(state.position)
        tau = None
        if has_ss:
            ss = valid & ~is_box[i] & ~is_box[j]
            x, v = state.position, state.velocity
            fm = _sphere_pair_force(ctx, x[i], radius[i], v[i], x[j], radius[j], v[j], k, c,
                                    h, inv_m_all[i] + inv_m_all[j],
                                    _gravity_side(pinned_all[i], pinned_all[j], jnp), g_vec)
            fm = jnp.where(ss[:, None], fm, 0.0)
            f = f + jax.ops.segment_sum(fm, i, n) - jax.ops.segment_sum(fm, j, n)
        if has_sb:
            from .rigid import sphere_box_force
            box_j = is_box[j]
            sb = valid & (is_box[i] != box_j)
            s_idx, b_idx = jnp.where(box_j, i, j), jnp.where(box_j, j, i)
            fs, tau = sphere_box_force(ctx, k, c, state, s_idx, b_idx, half_all[b_idx], sb,
                                       h=h)
            f = f + fs
        return f, tau
    return Term("contact_broadphase", force, search=search, record=record, step_aware=True,
                aux={_bp.OVERFLOW: float(bool(init))}, report=_bp.warn_overflow)


def _initial_state(ctx: CompileContext):
    from ..state import State
    bodies = ctx.scene.bodies
    q = ctx.const([b.orientation for b in bodies]) if ctx.scene.has_rotation else None
    return State(time=ctx.const(0.0), position=ctx.const([b.position for b in bodies]),
                 velocity=ctx.const([b.velocity for b in bodies]), orientation=q)


def _broadphase_bound(ctx: CompileContext):
    """Stability rows of the broad-phase pair term: each sphere's contact with another
    sphere, one at a time per material (``2 / m``), and the stiffest candidate sphere-box
    contact per body (rotation included)."""
    from .. import rigid as _rigid
    from .rigid import _rows_bound, sphere_box_rows
    scene = ctx.scene
    bodies = scene.bodies
    zero = np.zeros(3)
    spheres = [i for i, b in enumerate(bodies)
               if b.collide and b.kind == "sphere" and b.radius > 0.0]
    # O(n): a free sphere's partners use its own material (another sphere of it exists) or
    # "default" (a sphere of another material exists); pairs with a free end all act
    count: dict = {}
    for i in spheres:
        count[bodies[i].material] = count.get(bodies[i].material, 0) + 1
    rows = []
    for i in spheres:
        if bodies[i].pinned:
            continue
        m = bodies[i].material
        mats = dict.fromkeys(([m] if count[m] > 1 else [])
                             + ([DEFAULT] if len(spheres) > count[m] else []))
        rows += [(i, mat, 2.0 * _rigid.mobility(scene, i, zero)) for mat in mats]
    rows += sphere_box_rows(scene)
    out = _rows_bound(rows, "contact")
    return () if out is None else (out,)


#: The contact term builders with their stability bounds and materials (see
#: :data:`diffpen.terms.BUILTIN`).
PLANE = with_bound(_plane_contact, _plane_bound,
                   materials=lambda ctx: _collider_materials(ctx, ctx.scene.planes))
FIXED_SPHERE = with_bound(_fixed_sphere_contact, _fixed_sphere_bound,
                          materials=lambda ctx: _collider_materials(ctx,
                                                                    ctx.scene.fixed_spheres))
SPHERE_SPHERE = with_bound(_sphere_sphere_contact, _sphere_sphere_bound,
                           materials=_sphere_sphere_materials)
BROADPHASE = with_bound(_broadphase_contact, _broadphase_bound,
                        materials=_broadphase_materials)
