"""Rigid-body terms, the ones that produce torque: box corners on planes and their friction,
boxes against fixed spheres, sphere-box contact and anchored springs (the dynamics,
quaternions, inertia, mobility and Euler's equations are :mod:`diffpen.rigid`; friction's
law and the friction of spheres and particles are :mod:`diffpen.terms.friction`). Nothing
of this module is traced for scenes without rigid bodies.

Terms (each written for ONE contact or ONE spring, lifted by ``vmap`` + segment sum):

* ``contact_box_plane``: each box corner below a plane is a penalty contact at that corner
  (the contact law of the simulator), with force ``f n`` at the corner and torque
  ``r x f n`` (``r`` corner lever arm), and its friction where the plane's material has some.
* ``contact_sphere_box``: spheres and particles against boxes (closest point on the box).
* ``contact_box_fixed_sphere``: boxes against fixed spheres.
* ``anchored_springs``: the paper's ``Spring_c`` (see :func:`anchored_spring_pair`).

Sphere-sphere and sphere-plane contacts of rigid spheres are the core's terms: without
friction their force passes through the centres and produces no torque (with it, those terms
apply its torque too, :func:`diffpen.terms.friction.contact_friction`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import geometry
from .. import rigid as _rigid
from ..geometry import rotate
from ..stability import Bound
from ..stability.depth import start_stretches
from .contact import plane_crowding
from .base import (CompileContext, Term, _pair_material, gather, merge_extra, plane_offset_extra,
                   plane_offsets, scatter, with_bound)
from .friction import (friction_bound, friction_extra, friction_row, rough_rows, row_mu,
                       smooth_coulomb, spring_stretch)
from .springs import _spring_axis, _spring_vector

__all__ = ["anchored_spring_pair", "sphere_box_pair", "corner_plane_pair", "smooth_coulomb",
           "sphere_box_pairs", "sphere_box_rows", "TERMS", "BOUND_LABEL"]


def sphere_box_pairs(scene) -> list[tuple[int, int, str]]:
    """Every (sphere or particle, box, material) pair of ``scene`` that can move."""
    bodies = scene.bodies
    boxes = [j for j, b in enumerate(bodies) if b.kind == "box" and b.collide]
    others = [i for i, b in enumerate(bodies) if b.kind != "box" and b.collide]
    return [(i, j, _pair_material(scene, bodies[i].material, bodies[j].material))
            for j in boxes for i in others if not (bodies[i].pinned and bodies[j].pinned)]


# --------------------------------------------------------------------------- one pair
def corner_plane_pair(x, v, w, rot, corner, normal, offset):
    """Geometry of ONE box corner against ONE plane.

    Args:
      x, v, w: (3,) box centre (m), velocity (m/s), angular velocity (rad/s, world).
      rot: (3, 3) box rotation.  corner: (3,) corner in the body frame, m.
      normal: (3,) unit plane normal.  offset: m.
    Returns:
      ``(d, vn, r)``: penetration of the corner (m), normal velocity of the corner point
      ``n . (v + w x r)`` (m/s), and its lever arm r = R corner (3,) m.
    """
    r = rotate(rot, corner)
    d, _ = geometry.sphere_plane(x + r, 0.0, normal, offset)
    vn = jnp.sum(normal * (v + jnp.cross(w, r)), axis=-1)
    return d, vn, r


def sphere_box_pair(xs, vs, ws, rs, xb, vb, wb, rot, half):
    """Geometry of ONE sphere ``s`` against ONE box ``b`` (see ``geometry.sphere_box``).

    Returns ``(d, vn, n, r_s, r_b)``: penetration (m), normal velocity of the contact point of
    s relative to b's (m/s, positive separating), the unit normal (3,) from b to s, and the
    lever arms (3,) m of the contact point from each centre.
    """
    d, n, p = geometry.sphere_box(xs, rs, xb, rot, half)
    r_s, r_b = p - xs, p - xb
    v_rel = vs + jnp.cross(ws, r_s) - vb - jnp.cross(wb, r_b)
    return d, jnp.sum(n * v_rel, axis=-1), n, r_s, r_b


def anchored_spring_pair(xa, va, wa, rot_a, anchor_a, xb, vb, wb, rot_b, anchor_b, rest):
    """Geometry of ONE anchored spring (the paper's ``Spring_c``).

    World anchors ``p = x + R anchor``; anchor velocities ``v + w x r``. Returns
    ``(stretch, stretch_rate, u, r_a, r_b)``: anchor distance - rest (m), its rate (m/s), the
    unit axis (3,) from b's anchor to a's, and the lever arms (3,) m.

    The force ``F = -k stretch - c stretch_rate`` along ``u`` acts on a at its anchor and
    ``-F`` on b at its own anchor. (The paper's listing applies both halves at ``p0`` and
    halves them, which neither conserves angular momentum nor gives b its torque; this is
    the physics it describes.)
    """
    r_a, r_b = rotate(rot_a, anchor_a), rotate(rot_b, anchor_b)
    delta = xa + r_a - xb - r_b
    dv = va + jnp.cross(wa, r_a) - vb - jnp.cross(wb, r_b)
    stretch, rate, u = _spring_axis(delta, dv, rest)
    return stretch, rate, u, r_a, r_b


# --------------------------------------------------------------------------- terms
def _box_rows(ctx: CompileContext):
    return [i for i, b in enumerate(ctx.scene.bodies)
            if b.kind == "box" and b.collide and not b.pinned]


def _box_plane_contact(ctx: CompileContext) -> Term | None:
    scene = ctx.scene
    rows = [(i, p, corner, ctx.material_index[pl.material])
            for i in _box_rows(ctx) for p, pl in enumerate(scene.planes)
            for corner in geometry.box_corners(scene.bodies[i].half_extents)]
    if not rows:
        return None
    bi = np.array([r[0] for r in rows], dtype=np.int32)
    mi = np.array([r[3] for r in rows], dtype=np.int32)
    corners = ctx.const([r[2] for r in rows])
    normals = ctx.const([scene.planes[r[1]].normal for r in rows])
    offsets = plane_offsets(ctx, [r[1] for r in rows])
    extra, checks = plane_offset_extra(ctx, [r[1] for r in rows])
    n = ctx.n
    # smooth Coulomb friction only when some material has it (static choice)
    rough = rough_rows(ctx, [scene.planes[r[1]].material for r in rows])
    merge_extra(extra, friction_extra(ctx, rough))

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        x, v = gather(state.position, bi, n), gather(state.velocity, bi, n)
        w = gather(state.angular_velocity, bi, n)
        rot = _rigid.quat_to_matrix(gather(state.orientation, bi, n))
        d, vn, r = jax.vmap(corner_plane_pair)(x, v, w, rot, corners, normals,
                                               offsets(params))
        fn = ctx.contact_force(d, vn, k, c, h)
        f = fn[:, None] * normals
        if rough is not None:
            with jax.named_scope("friction"):
                names, fi, slip = rough
                f = f + jax.vmap(smooth_coulomb)(v + jnp.cross(w, r), normals, fn,
                                                 row_mu(params, names, fi, fn[0]), slip)
        return scatter(f, bi, n), scatter(jnp.cross(r, f), bi, n)
    return Term("contact_box_plane", force, step_aware=True, extra=extra, checks=checks)


def _box_fixed_sphere_contact(ctx: CompileContext) -> Term | None:
    scene = ctx.scene
    rows = [(i, s, ctx.material_index[fs.material])
            for i in _box_rows(ctx) for s, fs in enumerate(scene.fixed_spheres)]
    if not rows:
        return None
    bi, si, mi = (np.array(col, dtype=np.int32) for col in zip(*rows))
    centers = ctx.const([scene.fixed_spheres[s].center for s in si])
    radii = ctx.const([scene.fixed_spheres[s].radius for s in si])
    half = ctx.const([scene.bodies[i].half_extents for i in bi])
    n = ctx.n

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        xb, vb = gather(state.position, bi, n), gather(state.velocity, bi, n)
        wb = gather(state.angular_velocity, bi, n)
        rot = _rigid.quat_to_matrix(gather(state.orientation, bi, n))
        zero = jnp.zeros_like(xb)
        d, vn, nrm, _, r_b = jax.vmap(sphere_box_pair)(centers, zero, zero, radii, xb, vb,
                                                        wb, rot, half)
        f = ctx.contact_force(d, vn, k, c, h)[:, None] * nrm    # on the fixed sphere
        return -scatter(f, bi, n), -scatter(jnp.cross(r_b, f), bi, n)
    return Term("contact_box_fixed_sphere", force, step_aware=True)


def sphere_box_force(ctx: CompileContext, k, c, state, si, bi, half, valid=None, h=None):
    """Forces and torques (n, 3) of sphere-box pairs ``(si, bi)`` (index arrays (m,), static
    or traced) with box half extents ``half`` (m, 3) m, contact stiffness ``k`` and damping
    ``c`` (scalars or (m,)); ``valid`` (m,) bool masks padded pairs of a broad phase; ``h``
    the inner step (s) for the step-averaged force, None for the pointwise one."""
    n = ctx.n
    radius = ctx.const(ctx.radius)
    xs, vs, ws = state.position[si], state.velocity[si], state.angular_velocity[si]
    xb, vb, wb = state.position[bi], state.velocity[bi], state.angular_velocity[bi]
    rot = _rigid.quat_to_matrix(state.orientation[bi])
    d, vn, nrm, r_s, r_b = jax.vmap(sphere_box_pair)(xs, vs, ws, radius[si], xb, vb, wb, rot,
                                                      half)
    fm = ctx.contact_force(d, vn, k, c, h)
    if valid is not None:
        fm = jnp.where(valid, fm, 0.0)
    f = fm[:, None] * nrm                                  # on the sphere
    # static pairs: static row picks, no XLA scatter (which would keep a rollout's loop
    # from compiling into one kernel, diffpen.terms.base.scatter); a broad phase's pairs
    # are traced: a segment sum
    add = ((lambda vals, idx: scatter(vals, idx, n)) if isinstance(si, np.ndarray)
           and isinstance(bi, np.ndarray) else
           (lambda vals, idx: jax.ops.segment_sum(vals, idx, n)))
    force = add(f, si) - add(f, bi)
    tau = add(jnp.cross(r_s, f), si) - add(jnp.cross(r_b, f), bi)
    return force, tau


def _sphere_box_contact(ctx: CompileContext) -> Term | None:
    if getattr(ctx, "broadphase", None) is not None:
        return None                     # the broad-phase pair term handles these pairs
    rows = [(i, j, ctx.material_index[m]) for i, j, m in sphere_box_pairs(ctx.scene)]
    if not rows:
        return None
    si, bi, mi = (np.array(col, dtype=np.int32) for col in zip(*rows))
    half = ctx.const([ctx.scene.bodies[j].half_extents for j in bi])

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        return sphere_box_force(ctx, k, c, state, si, bi, half, h=h)
    return Term("contact_sphere_box", force, step_aware=True)


def _anchored_springs(ctx: CompileContext) -> Term | None:
    springs = [s for s in ctx.scene.anchored_springs
               if not (ctx.pinned[s.a] and (s.b is None or ctx.pinned[s.b]))]
    if not springs:
        return None
    n = ctx.n
    ia = np.array([s.a for s in springs], dtype=np.int32)
    gi = np.array([ctx.group_index[s.group] for s in springs], dtype=np.int32)
    rest = ctx.const([s.rest_length for s in springs])
    zero = np.array([s.rest_length for s in springs], dtype=float) == 0.0
    anchor_a = ctx.const([s.anchor_a for s in springs])
    anchor_b = ctx.const([s.anchor_b if s.b is not None else (0.0, 0.0, 0.0)
                          for s in springs])
    world = np.array([s.b is None for s in springs])
    # a world end is a fixed point: its "body" is a zero-velocity frame at the anchor
    ib = np.array([0 if s.b is None else s.b for s in springs], dtype=np.int32)
    world_x = ctx.const([s.anchor_b if s.b is None else (0.0, 0.0, 0.0) for s in springs])
    has_world, all_world = bool(world.any()), bool(world.all())
    is_world = jnp.asarray(world)[:, None]

    def end_b(state, field):
        value = gather(field, ib, n)
        return jnp.where(is_world, 0.0, value) if has_world else value

    def force(params, state):
        k, c = ctx.spring_kc(params, gi)
        xa, va = gather(state.position, ia, n), gather(state.velocity, ia, n)
        # a scene without rotating bodies has no orientations: its springs have zero anchors
        # (Scene.add_anchored_spring), on bodies that neither turn nor take torque
        turning = state.orientation is not None
        eye = jnp.broadcast_to(jnp.eye(3, dtype=xa.dtype), xa.shape + (3,))
        wa = gather(state.angular_velocity, ia, n) if turning else jnp.zeros_like(xa)
        rot_a = _rigid.quat_to_matrix(gather(state.orientation, ia, n)) if turning else eye
        if all_world:
            xb = world_x
            vb = wb = jnp.zeros_like(xa)
            rot_b = eye
        else:
            xb = end_b(state, state.position) + (world_x if has_world else 0.0)
            vb = end_b(state, state.velocity)
            wb = end_b(state, state.angular_velocity) if turning else jnp.zeros_like(xa)
            rot_b = (_rigid.quat_to_matrix(gather(state.orientation, ib, n)) if turning
                     else eye)
        x, xd, u, r_a, r_b = jax.vmap(anchored_spring_pair)(xa, va, wa, rot_a, anchor_a, xb,
                                                             vb, wb, rot_b, anchor_b, rest)
        # on a, at its anchor (delta: from b's anchor to a's)
        f = _spring_vector(x, xd, u, xa + r_a - xb - r_b, k, c, zero)
        force, tau = scatter(f, ia, n), scatter(jnp.cross(r_a, f), ia, n)
        if not all_world:
            fb = jnp.where(is_world, 0.0, f) if has_world else f
            force = force - scatter(fb, ib, n)
            tau = tau - scatter(jnp.cross(r_b, fb), ib, n)
        return force, (tau if turning else None)
    return Term("anchored_springs", force)


# --------------------------------------------------------------------------- stability
#: Names the rigid terms' bounds in stability reports (their rows summed per body).
BOUND_LABEL = ("box contacts, sphere-box contacts, broad-phase pairs or anchored springs "
               "(rotation included)")


def _face_mobility(body) -> float:
    """Largest eigenvalue (1/kg) of ``M^-1 sum_c J_c^T J_c`` for a box resting on one face
    (its 4 corners in contact, normal = the face normal), the stiffest plane contact a box
    makes: ``J_c = [n, r_c x n]``, ``M = diag(m, m, m, I)``; the max over the 6 faces."""
    h = np.asarray(body.half_extents)
    inv_sqrt = 1.0 / np.sqrt(np.r_[np.full(3, body.mass), _rigid.inertia_diagonal(body)])
    best = 0.0
    for axis in range(3):
        n = np.eye(3)[axis]
        face = [c for c in geometry.box_corners(h) if c[axis] < 0.0]
        jac = np.array([np.r_[n, np.cross(r, n)] for r in face]) * inv_sqrt
        best = max(best, float(np.linalg.eigvalsh(jac.T @ jac)[-1]))
    return best


def _rows_bound(rows, param: str):
    """A mobility-weighted :class:`diffpen.stability.Bound` (the same weight on k and c) from
    rows ``(body, name, weight 1/kg)``."""
    return Bound.of([(b, key, w, w, BOUND_LABEL) for b, key, w in rows], param,
                    per_mass=False, label=BOUND_LABEL)


def _pair_rows(scene, i, j, key, lever_i, lever_j, count=1):
    """Rows of ONE contact or spring between bodies i and j (None: the world): its eigenvalue
    bound ``k (J_i M_i^-1 J_i^T + J_j M_j^-1 J_j^T)`` counted on both free ends."""
    w = count * (_rigid.mobility(scene, i, lever_i)
                 + (_rigid.mobility(scene, j, lever_j) if j is not None else 0.0))
    return [(b, key, w * (2.0 if j is not None else 1.0)) for b in (i, j)
            if b is not None and not scene.bodies[b].pinned]


def _box_plane_bound(ctx: CompileContext):
    """Up to the 4 corners of a face at once (:func:`_face_mobility`), and friction."""
    scene, contact, friction = ctx.scene, [], []
    crowd = plane_crowding([pl.normal for pl in scene.planes])
    loads = spring_stretch(scene)
    for i in _box_rows(ctx):
        b = scene.bodies[i]
        for pl in scene.planes:
            contact.append((i, pl.material, crowd * _face_mobility(b)))
            if scene.materials[pl.material].friction > 0.0:
                friction.append(friction_row(scene, i, pl.material,
                                              geometry.box_corners(b.half_extents), loads[i]))
    bound = _rows_bound(contact, "contact")
    return ((bound,) if bound is not None else ()) + friction_bound(scene, friction)


def _box_fixed_sphere_bound(ctx: CompileContext):
    scene, rows = ctx.scene, []
    for i in _box_rows(ctx):
        corners = geometry.box_corners(scene.bodies[i].half_extents)
        for fs in scene.fixed_spheres:
            rows += _pair_rows(scene, i, None, fs.material, corners, np.zeros(3))
    out = _rows_bound(rows, "contact")
    return () if out is None else (out,)


def sphere_box_rows(scene):
    """Candidate sphere-box contacts, one at a time: the stiffest per (body, material)
    (``_pair_rows`` of every pair, with each body's mobility computed once)."""
    best, mob = {}, {}
    zero = np.zeros(3)

    def mobility(i, box):
        if (i, box) not in mob:
            levers = geometry.box_corners(scene.bodies[i].half_extents) if box else zero
            mob[i, box] = _rigid.mobility(scene, i, levers)
        return mob[i, box]
    for i, j, mat in sphere_box_pairs(scene):
        w = 2.0 * (mobility(i, False) + mobility(j, True))
        for b in (i, j):
            if not scene.bodies[b].pinned:
                best[b, mat] = max(best.get((b, mat), 0.0), w)
    return [(b, key, w) for (b, key), w in best.items()]


def _sphere_box_bound(ctx: CompileContext):
    out = _rows_bound(sphere_box_rows(ctx.scene), "contact")
    return () if out is None else (out,)


def _tension_mobility(scene, i, lever, stretch: float) -> float:
    """Per unit k (1/kg): the rotational stiffness of a spring's tension ``T = k stretch``
    acting at body-frame lever ``lever`` of body i, ``T |r| / I_min``: turning the body by
    ``dtheta`` swings the force's point of action by ``|r| dtheta`` across it. It dominates
    ``k r^2 / I`` once the stretch exceeds the lever (a box held by long pre-stretched
    springs: 0 for pinned or non-rigid bodies)."""
    if i is None:
        return 0.0
    body = scene.bodies[i]
    if body.pinned or not body.rigid:
        return 0.0
    inv = 1.0 / _rigid.inertia_diagonal(body)
    return stretch * float(np.linalg.norm(lever)) * float(inv.max())


def _carried_weights(scene) -> dict:
    """Per free body, the weight (N) of the free bodies joined to it by springs of any kind
    (its connected component through free bodies) when that component hangs from the world
    (a spring to a world point or a pinned body), else 0: the most a spring of a hanging
    component can come to carry at rest under gravity, whatever its start stretch. A
    component that hangs from nothing rests on contacts, which carry its weight (a chain of
    100 light links lying on the ground was held to a 5x smaller step, needlessly); tension
    from weight carried over a contact (a chain draped over a fixed sphere) is not counted."""
    free = [i for i, b in enumerate(scene.bodies) if not b.pinned]
    parent = {i: i for i in free}

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i
    links = ([(sp.a, sp.b) for sp in scene.springs]
             + [(sp.a, sp.b) for sp in scene.anchored_springs]
             + [(sp.a, sp.b) for sp in scene.plastic_springs])
    for a, b in links:
        if a in parent and b in parent:
            parent[root(a)] = root(b)
    # a component hangs only from the world: a spring to a world point or a pinned body
    held = {root(a if a in parent else b) for a, b in links
            if (a in parent) != (b in parent)}
    g = float(np.linalg.norm(scene.gravity))
    total = {}
    for i in free:
        total[root(i)] = total.get(root(i), 0.0) + scene.bodies[i].mass * g
    return {i: (total[root(i)] if root(i) in held else 0.0) for i in free}


def _anchored_bound(ctx: CompileContext):
    """Each spring's ``k (J M^-1 J^T)`` on both ends (:func:`_pair_rows`) plus the
    rotational stiffness of its tension (:func:`_tension_mobility`): at the start poses
    (per unit k), and under the load gravity can hang on it (``"load"`` rows, 1/s^2: twice
    the weight of the bodies the spring's component joins, :func:`_carried_weights`, the
    peak of a load released from rest). A 1 g link holding a 10 kg weight on springs at
    rest length turns at ~7700 rad/s once loaded: counted at the start stretch (0) alone,
    the bound passed a step 3x past its limit. Tension beyond that (impacts, stretching
    by hand) is not bounded."""
    scene, rows, load = ctx.scene, [], []
    carried = _carried_weights(scene)
    stretch = np.abs(start_stretches(scene))[len(scene.springs):]   # anchored ones next
    for sp, s0 in zip(scene.anchored_springs, stretch):
        rows += _pair_rows(scene, sp.a, sp.b, sp.group, sp.anchor_a, sp.anchor_b)
        ends = [b for b in (sp.a, sp.b) if b is not None and not scene.bodies[b].pinned]
        t_load = 2.0 * max((carried[b] for b in ends), default=0.0)
        both = 2.0 if sp.b is not None else 1.0
        for tension, out, key in ((s0, rows, sp.group), (t_load, load, "gravity")):
            geo = (_tension_mobility(scene, sp.a, sp.anchor_a, tension)
                   + _tension_mobility(scene, sp.b, sp.anchor_b, tension))
            if geo > 0.0:
                out += [(b, key, geo * both) for b in ends]
    blocks = (_rows_bound(rows, "springs"), _rows_bound(load, "load"))
    return tuple(b for b in blocks if b is not None)


# --------------------------------------------------------------------------- params keys
def _box_collider_materials(ctx: CompileContext, colliders: list) -> tuple:
    """The colliders' materials, in collider order, when some free colliding box exists."""
    if not _box_rows(ctx):
        return ()
    return tuple(dict.fromkeys(col.material for col in colliders))


def _sphere_box_materials(ctx: CompileContext) -> tuple:
    if getattr(ctx, "broadphase", None) is not None:
        return ()                       # declared by the broad-phase pair term
    return tuple(dict.fromkeys(m for _, _, m in sphere_box_pairs(ctx.scene)))


def _anchored_groups(ctx: CompileContext) -> tuple:
    """The groups of every anchored spring (also of those between pinned ends)."""
    return tuple(dict.fromkeys(s.group for s in ctx.scene.anchored_springs))


#: The rigid-body term builders with their stability bounds and params keys, in force
#: summation order.
TERMS: tuple = (
    with_bound(_box_plane_contact, _box_plane_bound,
               materials=lambda ctx: _box_collider_materials(ctx, ctx.scene.planes)),
    with_bound(_box_fixed_sphere_contact, _box_fixed_sphere_bound,
               materials=lambda ctx: _box_collider_materials(ctx, ctx.scene.fixed_spheres)),
    with_bound(_sphere_box_contact, _sphere_box_bound, materials=_sphere_box_materials),
    with_bound(_anchored_springs, _anchored_bound, groups=_anchored_groups),
)
