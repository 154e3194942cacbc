"""Smooth Coulomb friction: the law of one contact and the terms that apply it.

* :func:`smooth_coulomb`: ``-mu max(fn, 0) v_t / sqrt(|v_t|^2 + s^2)`` of ONE contact
  (viscous below the slip speed ``s``, so it is differentiable, including at rest).
* The rough materials a term's rows read (:func:`rough_rows`, :func:`friction_extra`,
  :func:`row_mu`: ``mu`` is ``params.extra["friction"][material]``) and friction's rows of
  the stability bounds (:func:`friction_row`, :func:`friction_bound`: its viscous rate
  ``mu |g| / s``), shared with the box corners' friction (:mod:`diffpen.terms.rigid`).
* :func:`contact_friction` and :func:`contact_friction_bound`: friction of spheres (rigid or
  not) and particles on planes and fixed spheres whose material has some, applied by their
  contact terms (``contact_plane``, ``contact_fixed_sphere``) from the normal force they
  compute, as the box corners apply theirs; rigid spheres also feel its torque. Nothing of
  it is traced without a rough material.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import rigid as _rigid
from ..stability import Bound
from ..stability.depth import start_stretches
from .base import CompileContext, gather, scatter

__all__ = ["smooth_coulomb", "rough_rows", "friction_extra", "row_mu", "friction_row",
           "friction_bound", "contact_friction", "contact_friction_bound", "spring_stretch"]


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


def friction_row(scene, i: int, material: str, levers, stretch: dict | None = None):
    """Friction below the slip speed is viscous: ``mu f / s`` per body, as damping rate
    weights (1/s per unit mu). ``f`` is its weight ``m |g|`` (at least 1 g) plus the tension
    of the springs joined to it: ``stretch`` ``{group: m}`` (:func:`spring_stretch`), each
    counted at the group's stiffness of the parameters the rollout is given. Returns
    ``(i, material, weight row, {group: stretch row})``."""
    b, mat = scene.bodies[i], scene.materials[material]
    per_newton = _rigid.mobility(scene, i, levers) / mat.slip_speed
    weight = b.mass * max(float(np.linalg.norm(scene.gravity)), 9.81)
    return (i, material, weight * per_newton,
            {g: x * per_newton for g, x in (stretch or {}).items() if x > 0.0})


def spring_stretch(scene) -> list:
    """Per body ``{group: m}``: the summed ``|length - rest|`` at the start pose of the
    springs and anchored springs of each group joined to it. Times the group's stiffness,
    a load besides gravity that can press the body onto a rough contact for good (a ball
    held down by a 1000 N spring: counted at ``m g`` only, its friction chattered at
    +-0.1 m/s with the gate's "ok"; counted at the scene's stiffness, a stiffer one given
    to the rollout chattered the same). Counted in full, whatever its direction."""
    out = [dict() for _ in scene.bodies]
    stretch = np.abs(start_stretches(scene))
    for x, sp in zip(stretch, scene.springs + scene.anchored_springs):  # (plastic ones last)
        for b in (sp.a, sp.b):
            if b is not None:
                out[b][sp.group] = out[b].get(sp.group, 0.0) + float(x)
    return out


def friction_bound(scene, rows) -> tuple:
    """The :class:`diffpen.stability.Bound` blocks of friction rows from
    :func:`friction_row`, each named by its material and slip speed (what to raise where it
    limits the step): the weight's rows, and the springs' rows scaled by their group's
    stiffness (``Bound.scale``). ``()`` for no rows."""
    def label(name):
        return (f"friction of material {name!r} below its slip speed "
                f"{scene.materials[name].slip_speed:g} m/s (a damper of rate mu f / "
                "(m slip_speed), f the body's weight and spring tension, counted for "
                "every body that can touch the material, whether or not it reaches it: "
                "one that never does can take collide = false)")
    weight = Bound.of([(b, name, w, w, label(name)) for b, name, w, _ in rows], "friction",
                      per_mass=False)
    loads = [(b, name, w, w, label(name), g) for b, name, _, by in rows
             for g, w in sorted(by.items())]
    groups = tuple(dict.fromkeys(r[5] for r in loads))
    springs = Bound.of([r[:5] for r in loads], "friction", per_mass=False,
                       scale=groups, scale_key=np.array([groups.index(r[5]) for r in loads],
                                                        dtype=int)) if loads else None
    return tuple(x for x in (weight, springs) if x is not None)


def _slider_rows(ctx: CompileContext) -> list[int]:
    """The bodies friction on a plane acts on apart from boxes: free, colliding spheres
    (rigid or not) and particles."""
    return [i for i, b in enumerate(ctx.scene.bodies)
            if b.kind in ("sphere", "particle") and b.collide and not b.pinned]


def contact_friction(ctx: CompileContext, bi, materials):
    """Smooth Coulomb friction of the contact rows of a sphere or particle term (bodies
    ``bi`` (m,) against colliders of ``materials`` (m,)) whose material is rough, from the
    normal force that term applies (``contact_plane``, ``contact_fixed_sphere``: computed
    once per step, not again here). A rigid sphere's contact point is ``-radius n`` from
    its centre: friction there turns it; a sphere that does not rotate (``add_sphere``) or a
    particle slides, its contact point moving with its centre, and the force goes through
    the centre.

    Returns None when no row is rough, else ``(extra, friction)``: the term's
    ``Params.extra`` defaults (:func:`friction_extra`) and ``friction(params, state, nrm,
    fn) -> (force (n, 3), torque (n, 3) or None)`` on the bodies, N and N m, from the rows'
    unit normals ``nrm`` (m, 3) and normal forces ``fn`` (m,) N."""
    scene = ctx.scene
    sel = np.array([r for r, (i, m) in enumerate(zip(bi, materials))
                    if scene.materials[m].friction > 0.0
                    and scene.bodies[int(i)].kind in ("sphere", "particle")], dtype=np.int32)
    if not sel.size:
        return None
    b = np.asarray(bi, dtype=np.int32)[sel]
    found = rough_rows(ctx, [materials[r] for r in sel])
    rough, fi, slip = found
    turning = np.array([scene.bodies[i].rigid for i in b])
    arm = ctx.const(ctx.radius[b] * turning) if turning.any() else None   # None: none turns
    n = ctx.n

    def friction(params, state, nrm, fn):
        with jax.named_scope("friction"):
            nrm, fn = nrm[sel], fn[sel]
            v = gather(state.velocity, b, n)
            lever = None if arm is None else -arm[:, None] * nrm  # centre to contact point
            if lever is not None:
                v = v + jnp.cross(gather(state.angular_velocity, b, n), lever)
            f = jax.vmap(smooth_coulomb)(v, nrm, fn, row_mu(params, rough, fi, fn[0]), slip)
            tau = None if lever is None else scatter(jnp.cross(lever, f), b, n)
            return scatter(f, b, n), tau
    return friction_extra(ctx, found), friction


def contact_friction_bound(ctx: CompileContext, colliders) -> tuple:
    """Friction's viscous rows of every free, colliding sphere or particle against the rough
    ones of ``colliders`` (planes or fixed spheres), for the stability bound of the contact
    term that applies it (:func:`contact_friction`): ``()`` or ``(Bound,)``."""
    scene = ctx.scene
    loads = spring_stretch(scene)
    rows = [friction_row(scene, i, col.material, (0.0, 0.0, scene.bodies[i].radius), loads[i])
            for i in _slider_rows(ctx)
            for col in colliders if scene.materials[col.material].friction > 0.0]
    return friction_bound(scene, rows)
