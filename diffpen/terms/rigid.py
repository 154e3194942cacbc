"""Rigid-body terms, the ones that produce torque: box corners on planes, their friction,
boxes against fixed spheres, sphere-box contact and anchored springs (the dynamics,
quaternions, inertia and Euler's equations are :mod:`diffpen.rigid`), and the friction of
spheres and particles on rough planes and fixed spheres (torque on rigid spheres). Nothing
of this module is traced for scenes without rigid bodies or rough colliders.

Terms (each written for ONE contact or ONE spring, lifted by ``vmap`` + segment sum):

* ``contact_box_plane``: each box corner below a plane is a penalty contact at that corner
  (the contact law of the simulator), with force ``f n`` at the corner and torque
  ``r x f n`` (``r`` corner lever arm).
* ``contact_sphere_box``: spheres and particles against boxes (closest point on the box).
* ``contact_box_fixed_sphere``: boxes against fixed spheres.
* ``anchored_springs``: the paper's ``Spring_c`` (see :func:`anchored_spring_pair`).
* ``friction_sphere_plane``: smooth Coulomb friction (:func:`smooth_coulomb`) of spheres and
  particles on planes whose material has friction; rigid spheres also feel its torque.
* ``friction_fixed_sphere``: the same on fixed spheres whose material has friction.

Sphere-sphere and sphere-plane contacts of rigid spheres are the core's terms: without
friction their force passes through the centres and produces no torque.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import geometry
from .. import rigid as _rigid
from ..geometry import rotate
from ..stability import Bound
from .contact import plane_crowding
from .base import (CompileContext, Term, _pair_material, gather, merge_extra, plane_offset_extra,
                   plane_offsets, scatter, with_bound)
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


def smooth_coulomb(v, normal, fn, mu, slip_speed):
    """Smooth Coulomb friction of ONE contact: ``-mu max(fn, 0) v_t / sqrt(|v_t|^2 + s^2)``.

    Args:
      v: (3,) velocity of the contact point relative to the other surface, m/s.
      normal: (3,) unit contact normal.  fn: normal force, N (only pushing counts).
      mu: friction coefficient.  slip_speed: s, m/s > 0: below it friction grows linearly
        with the sliding speed (a viscous law of coefficient ``mu fn / s``), so the force is
        smooth in v (differentiable, including at rest) and tends to ``mu fn`` when sliding.
    Returns:
      (3,) tangential force, N.
    """
    v_t = v - jnp.sum(v * normal, axis=-1) * normal
    speed = jnp.sqrt(jnp.sum(v_t * v_t, axis=-1) + slip_speed * slip_speed)
    # a tie (fn = 0: a body starting exactly on the surface) takes the pushing side, as the
    # contact window does (jnp.maximum splits its derivative 0.5 / 0.5 there: d loss / d
    # plane offset of a box resting on a rough plane came out 13x too large)
    return -mu * jnp.where(fn >= 0.0, fn, 0.0) * v_t / speed


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
    rough = _rough(ctx, [scene.planes[r[1]].material for r in rows])
    merge_extra(extra, _friction_extra(ctx, rough))

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
                                                 _row_mu(params, names, fi, fn[0]), slip)
        return scatter(f, bi, n), scatter(jnp.cross(r, f), bi, n)
    return Term("contact_box_plane", force, step_aware=True, extra=extra, checks=checks)


def _rough(ctx: CompileContext, materials: list[str]):
    """Friction materials among ``materials`` (their mu is ``params.extra["friction"]``:
    :func:`_friction_extra`), each row's index into them (``len`` for frictionless rows) and
    slip speeds (m/s); None when no row has friction."""
    scene = ctx.scene
    rough = list(dict.fromkeys(m for m in materials if scene.materials[m].friction > 0.0))
    if not rough:
        return None
    fi = np.array([rough.index(m) if m in rough else len(rough) for m in materials])
    return rough, fi, ctx.const([scene.materials[m].slip_speed for m in materials])


def _friction_extra(ctx: CompileContext, rough) -> dict:
    """``{"friction": {material: mu}}``, the defaults of the friction coefficients read by
    rows ``rough`` (from :func:`_rough`; empty for None)."""
    if rough is None:
        return {}
    return {"friction": {m: ctx.scene.materials[m].friction for m in rough[0]}}


def _row_mu(params, rough, fi, like):
    return jnp.stack([jnp.asarray(params.extra["friction"][m]) for m in rough]
                     + [jnp.zeros_like(like)])[fi]


def _slider_rows(ctx: CompileContext) -> list[int]:
    """The bodies friction on a plane acts on apart from boxes: free, colliding spheres
    (rigid or not) and particles."""
    return [i for i, b in enumerate(ctx.scene.bodies)
            if b.kind in ("sphere", "particle") and b.collide and not b.pinned]


def _slider_friction(ctx: CompileContext, name: str, colliders, geometry_of) -> Term | None:
    """Smooth Coulomb friction of spheres and particles on the rough ones of ``colliders``
    (planes or fixed spheres). The normal force is the core contact's law (``contact_plane``,
    ``contact_fixed_sphere``), recomputed for these rows, centred damping included (a
    sphere's contact point lies on the normal through its centre: effective inverse mass
    1 / m). A rigid sphere's contact point is ``-radius n`` from its centre: friction there
    turns it; a sphere that does not rotate (``add_sphere``) or a particle slides, its
    contact point moving with its centre, and the force goes through the centre.

    ``geometry_of(ctx, cols, bi) -> (contact, extra, checks)``: for the rows' colliders
    ``cols`` and bodies ``bi``, ``contact(params, x) -> (d (m,), n (m, 3), g_n (m,))`` (depth,
    unit normal, gravity's separating acceleration) and the term's extra params."""
    scene = ctx.scene
    rows = [(i, j) for i in _slider_rows(ctx) for j, col in enumerate(colliders)
            if scene.materials[col.material].friction > 0]
    if not rows:
        return None
    bi = np.array([r[0] for r in rows], dtype=np.int32)
    mats = [colliders[r[1]].material for r in rows]
    mi = np.array([ctx.material_index[m] for m in mats], dtype=np.int32)
    found = _rough(ctx, mats)
    rough, fi, slip = found
    contact, extra, checks = geometry_of(ctx, [r[1] for r in rows], bi)
    extra = merge_extra(_friction_extra(ctx, found), extra)
    inv_m = ctx.const(ctx.inv_mass(bi))
    site = ctx.factor_site(mi, inv_m)       # a law's per-contact step constants, if any
    turning = np.array([scene.bodies[i].rigid for i in bi])
    arm = ctx.const(ctx.radius[bi] * turning) if turning.any() else None   # None: none turns
    n = ctx.n

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        x, v = gather(state.position, bi, n), gather(state.velocity, bi, n)
        d, nrm, g_n = contact(params, x)
        fn = ctx.contact_force(d, geometry.dot(nrm, v), k, c, h, inv_m, g_n,
                               ctx.step_factors(params, site, h))
        lever = None if arm is None else -arm[:, None] * nrm     # centre to contact point
        if lever is not None:
            v = v + jnp.cross(gather(state.angular_velocity, bi, n), lever)
        f = jax.vmap(smooth_coulomb)(v, nrm, fn, _row_mu(params, rough, fi, fn[0]), slip)
        tau = None if lever is None else scatter(jnp.cross(lever, f), bi, n)
        return scatter(f, bi, n), tau
    return Term(name, force, step_aware=True, extra=extra, checks=checks)


def _plane_geometry(ctx: CompileContext, planes, bi):
    """:func:`_slider_friction`'s geometry of planes (offsets of named planes are params)."""
    normals_np = np.array([ctx.scene.planes[p].normal for p in planes], dtype=float)
    normals, radii = ctx.const(normals_np), ctx.const(ctx.radius[bi])
    offsets = plane_offsets(ctx, planes)
    g_n = ctx.const(ctx.normal_gravity(normals_np, bi))
    extra, checks = plane_offset_extra(ctx, planes)

    def contact(params, x):
        d, _ = jax.vmap(geometry.sphere_plane)(x, radii, normals, offsets(params))
        return d, normals, g_n
    return contact, extra, checks


def _fixed_sphere_geometry(ctx: CompileContext, spheres, bi):
    """:func:`_slider_friction`'s geometry of fixed spheres (normals from their centres)."""
    fixed = [ctx.scene.fixed_spheres[s] for s in spheres]
    centers, big = ctx.const([f.center for f in fixed]), ctx.const([f.radius for f in fixed])
    radii, g_vec = ctx.const(ctx.radius[bi]), ctx.const(ctx.scene.gravity)

    def contact(params, x):
        d, nrm = jax.vmap(geometry.sphere_sphere)(x, radii, centers, big)
        return d, nrm, geometry.dot(nrm, g_vec)
    return contact, {}, {}


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
    force = jax.ops.segment_sum(f, si, n) - jax.ops.segment_sum(f, bi, n)
    tau = (jax.ops.segment_sum(jnp.cross(r_s, f), si, n)
           - jax.ops.segment_sum(jnp.cross(r_b, f), bi, n))
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


def _mobility(scene, i: int, levers) -> float:
    """Bound on ``J M^-1 J^T`` (1/kg) of a unit force of any direction n at body-frame
    point(s) ``levers`` (k, 3) m of body i: ``1/m + max (r x n)^T I^-1 (r x n)``, the largest
    eigenvalue of ``[r]x^T diag(1/I) [r]x`` over the given points (0 for pinned bodies; no
    rotation term for bodies that do not rotate or forces through the centre)."""
    body = scene.bodies[i]
    if body.pinned:
        return 0.0
    rot = 0.0
    if body.rigid:
        inv = 1.0 / _rigid.inertia_diagonal(body)
        for r in np.atleast_2d(np.asarray(levers, dtype=float)):
            skew = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
            rot = max(rot, float(np.linalg.eigvalsh(skew.T @ (inv[:, None] * skew))[-1]))
    return 1.0 / body.mass + rot


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
    w = count * (_mobility(scene, i, lever_i)
                 + (_mobility(scene, j, lever_j) if j is not None else 0.0))
    return [(b, key, w * (2.0 if j is not None else 1.0)) for b in (i, j)
            if b is not None and not scene.bodies[b].pinned]


def _friction_row(scene, i: int, material: str, levers):
    """Friction below the slip speed is viscous: ``mu m |g| / s`` (at least 1 g) per body,
    as a damping rate weight (1/s per unit mu)."""
    b, mat = scene.bodies[i], scene.materials[material]
    load = b.mass * max(float(np.linalg.norm(scene.gravity)), 9.81)
    return (i, material, load / mat.slip_speed * _mobility(scene, i, levers))


def _friction_bound(scene, rows):
    """The :class:`diffpen.stability.Bound` of friction rows from :func:`_friction_row`,
    each named by its material and slip speed (what to raise where it limits the step)."""
    return Bound.of([(b, name, w, w, f"friction of material {name!r} below its slip speed "
                     f"{scene.materials[name].slip_speed:g} m/s (a damper of rate "
                     "mu |g| / slip_speed)") for b, name, w in rows], "friction",
                    per_mass=False)


def _box_plane_bound(ctx: CompileContext):
    """Up to the 4 corners of a face at once (:func:`_face_mobility`), and friction."""
    scene, contact, friction = ctx.scene, [], []
    crowd = plane_crowding([pl.normal for pl in scene.planes])
    for i in _box_rows(ctx):
        b = scene.bodies[i]
        for pl in scene.planes:
            contact.append((i, pl.material, crowd * _face_mobility(b)))
            if scene.materials[pl.material].friction > 0.0:
                friction.append(_friction_row(scene, i, pl.material,
                                              geometry.box_corners(b.half_extents)))
    return tuple(x for x in (_rows_bound(contact, "contact"),
                             _friction_bound(scene, friction)) if x is not None)


def _slider_friction_bound(ctx: CompileContext, colliders):
    """Friction's viscous rows of every free, colliding sphere or particle against the rough
    ones of ``colliders`` (planes or fixed spheres)."""
    scene = ctx.scene
    rows = [_friction_row(scene, i, col.material, (0.0, 0.0, scene.bodies[i].radius))
            for i in _slider_rows(ctx)
            for col in colliders if scene.materials[col.material].friction > 0.0]
    out = _friction_bound(scene, rows)
    return () if out is None else (out,)


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
            mob[i, box] = _mobility(scene, i, levers)
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


def _start_stretch(scene, sp) -> float:
    """``| |p_b - p_a| - rest |`` (m) of an anchored spring at the scene's start poses."""
    def end(i, anchor):
        if i is None:
            return np.asarray(anchor, dtype=float)
        body = scene.bodies[i]
        rot = (np.asarray(_rigid.quat_to_matrix(np.asarray(body.orientation, float), xp=np))
               if body.rigid else np.eye(3))
        return np.asarray(body.position, float) + rot @ np.asarray(anchor, float)
    return abs(float(np.linalg.norm(end(sp.b, sp.anchor_b) - end(sp.a, sp.anchor_a)))
               - sp.rest_length)


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
    for sp in scene.anchored_springs:
        rows += _pair_rows(scene, sp.a, sp.b, sp.group, sp.anchor_a, sp.anchor_b)
        ends = [b for b in (sp.a, sp.b) if b is not None and not scene.bodies[b].pinned]
        s0 = _start_stretch(scene, sp)
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


def _rough_materials(ctx: CompileContext, colliders) -> tuple:
    """The rough materials of ``colliders`` (planes or fixed spheres: their k, c give the
    normal force) when some free colliding sphere or particle exists."""
    if not _slider_rows(ctx):
        return ()
    return tuple(dict.fromkeys(col.material for col in colliders
                               if ctx.scene.materials[col.material].friction > 0.0))


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
    with_bound(lambda ctx: _slider_friction(ctx, "friction_sphere_plane", ctx.scene.planes,
                                            _plane_geometry),
               lambda ctx: _slider_friction_bound(ctx, ctx.scene.planes),
               materials=lambda ctx: _rough_materials(ctx, ctx.scene.planes)),
    with_bound(lambda ctx: _slider_friction(ctx, "friction_fixed_sphere",
                                            ctx.scene.fixed_spheres, _fixed_sphere_geometry),
               lambda ctx: _slider_friction_bound(ctx, ctx.scene.fixed_spheres),
               materials=lambda ctx: _rough_materials(ctx, ctx.scene.fixed_spheres)),
    with_bound(_box_fixed_sphere_contact, _box_fixed_sphere_bound,
               materials=lambda ctx: _box_collider_materials(ctx, ctx.scene.fixed_spheres)),
    with_bound(_sphere_box_contact, _sphere_box_bound, materials=_sphere_box_materials),
    with_bound(_anchored_springs, _anchored_bound, groups=_anchored_groups),
)
