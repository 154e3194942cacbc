"""Smooth Coulomb friction: the law of one contact and the terms that apply it.

* :func:`smooth_coulomb`: ``-mu max(fn, 0) v_t / sqrt(|v_t|^2 + s^2)`` of ONE contact
  (viscous below the slip speed ``s``, so it is differentiable, including at rest).
* The rough materials a term's rows read (:func:`rough_rows`, :func:`friction_extra`,
  :func:`row_mu`: ``mu`` is ``params.extra["friction"][material]``) and friction's rows of
  the stability bounds (:func:`friction_row`, :func:`friction_bound`: its viscous rate
  ``mu |g| / s``), shared with the box corners' friction (:mod:`diffpen.terms.rigid`).
* ``friction_sphere_plane`` and ``friction_fixed_sphere`` (:data:`TERMS`): spheres (rigid
  or not) and particles on planes and fixed spheres whose material has friction; rigid
  spheres also feel its torque. Nothing of it is traced without a rough material.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import geometry
from .. import rigid as _rigid
from ..stability import Bound
from .base import (CompileContext, Term, gather, merge_extra, plane_offset_extra, plane_offsets,
                   scatter, with_bound)

__all__ = ["smooth_coulomb", "rough_rows", "friction_extra", "row_mu", "friction_row",
           "friction_bound", "TERMS"]


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


def rough_rows(ctx: CompileContext, materials: list[str]):
    """Friction materials among ``materials`` (their mu is ``params.extra["friction"]``:
    :func:`friction_extra`), each row's index into them (``len`` for frictionless rows) and
    slip speeds (m/s); None when no row has friction."""
    scene = ctx.scene
    rough = list(dict.fromkeys(m for m in materials if scene.materials[m].friction > 0.0))
    if not rough:
        return None
    fi = np.array([rough.index(m) if m in rough else len(rough) for m in materials])
    return rough, fi, ctx.const([scene.materials[m].slip_speed for m in materials])


def friction_extra(ctx: CompileContext, rough) -> dict:
    """``{"friction": {material: mu}}``, the defaults of the friction coefficients read by
    rows ``rough`` (from :func:`rough_rows`; empty for None)."""
    if rough is None:
        return {}
    return {"friction": {m: ctx.scene.materials[m].friction for m in rough[0]}}


def row_mu(params, rough, fi, like):
    return jnp.stack([jnp.asarray(params.extra["friction"][m]) for m in rough]
                     + [jnp.zeros_like(like)])[fi]


def friction_row(scene, i: int, material: str, levers, spring_load: float = 0.0):
    """Friction below the slip speed is viscous: ``mu f / s`` per body, as a damping rate
    weight (1/s per unit mu), ``f`` its weight ``m |g|`` (at least 1 g) plus ``spring_load``
    (N, :func:`spring_loads`)."""
    b, mat = scene.bodies[i], scene.materials[material]
    load = b.mass * max(float(np.linalg.norm(scene.gravity)), 9.81) + spring_load
    return (i, material, load / mat.slip_speed * _rigid.mobility(scene, i, levers))


def spring_loads(scene) -> np.ndarray:
    """(n,) N: the tension of the springs and anchored springs joined to each body at the
    start pose (its group's scene stiffness times ``|length - rest|``): a load besides gravity
    that can press the body onto a rough contact for good (a ball held down by a 1000 N
    spring: counted at ``m g`` only, its friction chattered at +-0.1 m/s with the gate's
    "ok"). Counted in full, whatever its direction."""
    from ..overlap import quat_matrix
    bodies = scene.bodies
    out = np.zeros(len(bodies))
    pos = np.array([b.position for b in bodies], float).reshape(-1, 3)

    def add(a, b, xa, xb, rest, group):
        f = scene.spring_groups[group].k * abs(float(np.linalg.norm(xa - xb)) - rest)
        out[a] += f
        if b is not None:
            out[b] += f
    for sp in scene.springs:
        xb = pos[sp.b] if sp.b is not None else np.asarray(sp.anchor, float)
        add(sp.a, sp.b, pos[sp.a], xb, sp.rest_length, sp.group)
    for sp in scene.anchored_springs:
        def end(i, anchor):
            return pos[i] + quat_matrix(bodies[i].orientation) @ np.asarray(anchor, float)
        xb = end(sp.b, sp.anchor_b) if sp.b is not None else np.asarray(sp.anchor_b, float)
        add(sp.a, sp.b, end(sp.a, sp.anchor_a), xb, sp.rest_length, sp.group)
    return out


def friction_bound(scene, rows):
    """The :class:`diffpen.stability.Bound` of friction rows from :func:`friction_row`,
    each named by its material and slip speed (what to raise where it limits the step)."""
    return Bound.of([(b, name, w, w, f"friction of material {name!r} below its slip speed "
                     f"{scene.materials[name].slip_speed:g} m/s (a damper of rate mu f / "
                     "(m slip_speed), f the body's weight and spring tension)")
                     for b, name, w in rows], "friction",
                    per_mass=False)


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
    found = rough_rows(ctx, mats)
    rough, fi, slip = found
    contact, extra, checks = geometry_of(ctx, [r[1] for r in rows], bi)
    extra = merge_extra(friction_extra(ctx, found), extra)
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
        f = jax.vmap(smooth_coulomb)(v, nrm, fn, row_mu(params, rough, fi, fn[0]), slip)
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


def _slider_friction_bound(ctx: CompileContext, colliders):
    """Friction's viscous rows of every free, colliding sphere or particle against the rough
    ones of ``colliders`` (planes or fixed spheres)."""
    scene = ctx.scene
    loads = spring_loads(scene)
    rows = [friction_row(scene, i, col.material, (0.0, 0.0, scene.bodies[i].radius), loads[i])
            for i in _slider_rows(ctx)
            for col in colliders if scene.materials[col.material].friction > 0.0]
    out = friction_bound(scene, rows)
    return () if out is None else (out,)


def _rough_materials(ctx: CompileContext, colliders) -> tuple:
    """The rough materials of ``colliders`` (planes or fixed spheres: their k, c give the
    normal force) when some free colliding sphere or particle exists."""
    if not _slider_rows(ctx):
        return ()
    return tuple(dict.fromkeys(col.material for col in colliders
                               if ctx.scene.materials[col.material].friction > 0.0))


#: The friction terms of spheres and particles, planes first, with their stability bounds
#: and params keys (summed after the box corners, :data:`diffpen.terms.rigid.TERMS`).
TERMS: tuple = (
    with_bound(lambda ctx: _slider_friction(ctx, "friction_sphere_plane", ctx.scene.planes,
                                            _plane_geometry),
               lambda ctx: _slider_friction_bound(ctx, ctx.scene.planes),
               materials=lambda ctx: _rough_materials(ctx, ctx.scene.planes)),
    with_bound(lambda ctx: _slider_friction(ctx, "friction_fixed_sphere",
                                            ctx.scene.fixed_spheres, _fixed_sphere_geometry),
               lambda ctx: _slider_friction_bound(ctx, ctx.scene.fixed_spheres),
               materials=lambda ctx: _rough_materials(ctx, ctx.scene.fixed_spheres)),
)
