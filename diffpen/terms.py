"""Force terms: each one pair law of :mod:`diffpen.laws` / :mod:`diffpen.geometry` lifted to
the scene by ``jax.vmap`` over static index arrays plus a segment sum onto bodies.

A term builder ``build(ctx) -> Term | None`` returns None when the scene does not need the
term, so it is never traced. ``CORE`` lists the core builders with their stability bounds;
``diffpen.compile.BUILTIN_TERMS`` is the one fixed tuple of every built-in builder (core,
plastic, rigid, broad phase), in force summation order. Nothing registers itself on import.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import geometry, laws
from .scene import DEFAULT, Scene
from .stability import Bound
from .state import Params, State

__all__ = ["Term", "CompileContext", "CORE", "with_bound", "gather", "scatter", "static_dot",
           "static_scale", "spring_bands", "plane_offsets"]


# --------------------------------------------------------------------------- lifting helpers
def gather(x, idx: np.ndarray, n: int):
    """``x[idx]`` along axis 0, skipped when ``idx`` is ``arange(n)`` (decided at build time)."""
    if idx.shape[0] == n and np.array_equal(idx, np.arange(n)):
        return x
    if np.all(idx == idx[0]):
        return jnp.broadcast_to(x[int(idx[0])], (idx.shape[0],) + x.shape[1:])
    return x[idx]


def scatter(values, idx: np.ndarray, n: int):
    """Segment sum of per-pair ``values`` (m, ...) onto ``n`` bodies by static ``idx`` (m,)."""
    if idx.shape[0] == n and np.array_equal(idx, np.arange(n)):
        return values
    return jax.ops.segment_sum(values, jnp.asarray(idx), num_segments=n)


def static_dot(n: np.ndarray, v):
    """``dot(n, v)`` for a normal ``n`` (m, 3) known when the scene is compiled: components
    that are 0 for every row are left out, and +-1 columns need no product, so the ground
    plane's ``n . x`` is one slice of ``x``. ``v``: (m, 3) (or broadcastable)."""
    out = None
    for a in range(3):
        col = n[:, a]
        if not col.any():
            continue
        va = v[..., a]
        term = (va if (col == 1.0).all() else -va if (col == -1.0).all()
                else va * jnp.asarray(col, jnp.result_type(v)))
        out = term if out is None else out + term
    return jnp.zeros(jnp.shape(v)[:-1], jnp.result_type(v)) if out is None else out


def static_scale(f, n: np.ndarray):
    """``f[:, None] * n`` for a normal ``n`` (m, 3) known when the scene is compiled, built
    column by column so that XLA computes ``f`` once, not once per component, and writes
    zeros for components that are 0 in every row. ``f``: (m,). Returns (m, 3)."""
    cols = []
    for a in range(3):
        col = n[:, a]
        cols.append(jnp.zeros_like(f) if not col.any() else f if (col == 1.0).all()
                    else -f if (col == -1.0).all()
                    else f * jnp.asarray(col, jnp.result_type(f)))
    return jnp.stack(cols, axis=-1)


class Term(NamedTuple):
    """One force term of a compiled scene.

    name: used as ``jax.named_scope`` (visible in the jaxpr).
    force: ``force(params, state) -> (F, tau)``: F (n, 3) newtons on body centres, tau (n, 3)
      torques in N m about the centres, or None when the term produces no torque.
    search: optional ``search(params, state) -> found``, a search the force needs (the broad
      phase's candidate pairs). A step runs it once, at the state it starts from, and passes
      the result to the force evaluations at that state as ``force(params, state, found)``;
      called as ``force(params, state)`` the force searches itself.
    record: optional ``record(aux, found) -> {name: array}``: the ``State.aux`` entries a step
      updates from its search (``aux``: the step's current entries).
    step_aware: True when ``force`` takes the integrator's inner step as a keyword,
      ``force(..., h=h)`` (s): contact terms then apply their step-averaged force
      (``ContactLaw.step_force``); without it (or ``h=None``) the instantaneous force.
    bound: the term's rows of the stability bounds, a tuple of
      :class:`diffpen.stability.Bound` (empty: the term adds nothing to the step limit).
    """
    name: str
    force: Callable[..., tuple[Any, Any]]
    search: Callable[[Params, State], Any] | None = None
    record: Callable[[dict, Any], dict] | None = None
    step_aware: bool = False
    bound: tuple = ()


@dataclasses.dataclass
class CompileContext:
    """What a term builder sees: the scene and the static per-body arrays."""
    scene: Scene
    dtype: Any
    #: the contact law (``diffpen.laws.ContactLaw``; callable as its pointwise force)
    law: Callable
    width: float
    material_index: dict
    group_index: dict
    mass: np.ndarray        # (n,) kg
    radius: np.ndarray      # (n,) m
    pinned: np.ndarray      # (n,) bool
    collide: np.ndarray     # (n,) bool
    #: Filled by term builders of extensions: defaults of their ``Params.extra`` entries
    #: (``{name: pytree}``), initial ``State.aux`` entries (``{name: array}``), and
    #: ``aux_update(params, state) -> {name: array}`` functions applied after every step.
    extra_defaults: dict = dataclasses.field(default_factory=dict)
    aux_init: dict = dataclasses.field(default_factory=dict)
    aux_updates: list = dataclasses.field(default_factory=list)
    #: ``{extra name: check(label, value)}`` validating concrete values given to
    #: ``sim.params`` (default: finite and >= 0); raises SceneError.
    extra_checks: dict = dataclasses.field(default_factory=dict)
    #: Broad phase of dynamic pairs (``diffpen.broadphase``), or None: all pairs statically.
    broadphase: Any = None
    #: The simulator's step dt, s (the longest inner step): a step-averaged contact acts from
    #: a gap of ``|vn| h`` on, so searches for pairs reach that far.
    step: float | None = None
    #: How far the state's velocity lags the force evaluation's position, as a fraction of
    #: the inner step: 1/2 for semi-implicit Euler (its velocity is the mean over the step
    #: that ended), 0 for the others. Contacts that know their effective mass then apply
    #: their damping at the window centre's speed (``ContactLaw.centred_force``).
    velocity_lag: float = 0.0

    @property
    def n(self) -> int:
        return len(self.mass)

    def const(self, a):
        """A static numpy array as a constant of the simulator's float dtype."""
        return jnp.asarray(np.asarray(a, dtype=float), dtype=self.dtype)

    def contact_force(self, d, vn, k, c, h=None, inv_mass=None, accel=0.0):
        """Normal force (N) of contacts at depth ``d`` (m), separating speed ``vn`` (m/s):
        the law's step average over an inner step ``h`` (s), or its pointwise force for
        ``h=None`` (``diffpen.laws.ContactLaw.step_force``). With ``inv_mass`` (the
        contacts' effective inverse mass along the normal, 1/kg) and ``accel`` (their other
        separating acceleration, m/s^2: gravity) the step average takes its damping at the
        window centre's speed where the integrator's velocity lags (``velocity_lag``)."""
        if (h is None or inv_mass is None or self.velocity_lag == 0.0 or self.width != 0.0
                or getattr(self.law, "centred", None) is None):
            return self.law.step_force(d, vn, k, c, self.width, h)
        return self.law.centred_force(d, vn, k, c, h, self.velocity_lag * h, inv_mass, accel)

    def normal_gravity(self, normal: np.ndarray, bodies: np.ndarray):
        """Gravity's separating acceleration ``n . g`` (m/s^2) of contacts of free bodies
        ``bodies`` (m,) against fixed colliders with normals ``normal`` (m, 3) (0 for pinned
        bodies): a numpy constant."""
        g = np.asarray(self.scene.gravity, dtype=float)
        return np.where(self.pinned[bodies], 0.0, np.asarray(normal, float) @ g)

    def inv_mass(self, bodies: np.ndarray):
        """``1 / m`` (1/kg) of ``bodies`` (m,), 0 for pinned ones: a numpy array."""
        return np.where(self.pinned[bodies], 0.0, 1.0 / self.mass[bodies])

    def contact_kc(self, params: Params, mat: np.ndarray):
        """Per-pair (k, c) for material indices ``mat`` (m,), scalars when all pairs share one."""
        names = list(self.material_index)
        ks = [params.contact[name].k for name in names]
        cs = [params.contact[name].c for name in names]
        return _select(ks, mat), _select(cs, mat)

    def spring_kc(self, params: Params, grp: np.ndarray):
        names = list(self.group_index)
        ks = [params.springs[name].k for name in names]
        cs = [params.springs[name].c for name in names]
        return _select(ks, grp), _select(cs, grp)


def _select(values: list, idx: np.ndarray):
    first = int(idx[0])
    if np.all(idx == first):
        return values[first]
    return jnp.stack([jnp.asarray(v) for v in values])[jnp.asarray(idx)]


# --------------------------------------------------------------------------- core terms
def _uniform(ctx: CompileContext, a: np.ndarray):
    """A per-contact numpy constant as a scalar of the simulator's dtype when all rows share
    one value (fewer operands in the step), else an (m,) array."""
    a = np.asarray(a, dtype=float)
    return ctx.const(a[0] if np.all(a == a[0]) else a)


def _pair_material(scene: Scene, *names: str) -> str:
    return names[0] if len(set(names)) == 1 else DEFAULT


def plane_offsets(ctx: CompileContext, plane_ids):
    """``offsets(params) -> (m,)`` offsets (m) of the planes ``plane_ids`` (m,): constants,
    except for planes named in ``Scene.add_plane(name=...)``, whose offset is the leaf
    ``params.extra["plane_offset"][name]`` (registered here with the scene's value as
    default; any finite sign)."""
    planes = ctx.scene.planes
    const = ctx.const([planes[j].offset for j in plane_ids])
    names = list(dict.fromkeys(planes[j].name for j in plane_ids if planes[j].name))
    if not names:
        return lambda params: const
    ctx.extra_defaults.setdefault("plane_offset", {}).update(
        {pl.name: pl.offset for pl in planes if pl.name in names})
    ctx.extra_checks["plane_offset"] = _check_finite
    sel = np.array([names.index(planes[j].name) if planes[j].name else -1 for j in plane_ids])

    def offsets(params):
        vals = jnp.stack([jnp.asarray(params.extra["plane_offset"][g], ctx.dtype)
                          for g in names])
        return jnp.where(sel >= 0, vals[np.maximum(sel, 0)], const)
    return offsets


def _check_finite(label: str, v) -> None:
    if isinstance(v, jax.core.Tracer):
        return
    if not np.all(np.isfinite(np.asarray(v, dtype=float))):
        from .errors import SceneError
        raise SceneError(f"{label} must be a finite number of metres, got {v!r}.")


def _collider_contact(ctx: CompileContext, name: str, colliders: list, shape_args, *,
                      shape_fn=None, static_normal=None, offsets=None) -> Term | None:
    """Contacts of every moving, colliding non-box body with every fixed collider of one kind
    (boxes collide by their corners, diffpen.rigid). Give one of:

    * ``shape_fn``: ``shape_fn(x, r, *shape_args(collider))`` gives ``(d, n)`` for one pair;
    * ``static_normal(collider)`` (planes, ``shape_args = (offset,)``): the normal is a
      constant of the step (``static_dot`` / ``static_scale``) and
      ``d = r - (n . x - offset)``, geometry.sphere_plane with its zeros left out."""
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
    offset_fn = offsets(ctx, ci) if offsets is not None else None
    inv_m = _uniform(ctx, ctx.inv_mass(bi))
    g_plane = None if normal is None else _uniform(ctx, ctx.normal_gravity(normal, bi))
    g_vec = ctx.const(ctx.scene.gravity)

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        x, v = gather(state.position, bi, n), gather(state.velocity, bi, n)
        if normal is not None:          # the normal is a constant: leave out its zeros
            off = args[0] if offset_fn is None else offset_fn(params)
            d = radii - (static_dot(normal, x) - off)
            f = ctx.contact_force(d, static_dot(normal, v), k, c, h, inv_m, g_plane)
            return scatter(static_scale(f, normal), bi, n), None
        d, nrm = jax.vmap(shape_fn)(x, radii, *args)
        f = ctx.contact_force(d, geometry.dot(nrm, v), k, c, h, inv_m,
                              geometry.dot(nrm, g_vec))
        return scatter(f[:, None] * nrm, bi, n), None
    return Term(name, force, step_aware=True)


def _plane_contact(ctx: CompileContext) -> Term | None:
    return _collider_contact(ctx, "contact_plane", ctx.scene.planes,
                             lambda pl: (pl.offset,), static_normal=lambda pl: pl.normal,
                             offsets=plane_offsets)


def _fixed_sphere_contact(ctx: CompileContext) -> Term | None:
    return _collider_contact(ctx, "contact_fixed_sphere", ctx.scene.fixed_spheres,
                             lambda fs: (fs.center, fs.radius), shape_fn=geometry.sphere_sphere)


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
    # gravity moves both ends alike unless one is pinned: n . g (a - b) along the pair
    pin_a, pin_b = ctx.pinned[ia], ctx.pinned[ib]
    g_side = ctx.const(np.where(pin_b & ~pin_a, 1.0, np.where(pin_a & ~pin_b, -1.0, 0.0)))
    g_vec = ctx.const(ctx.scene.gravity)

    def force(params, state, *, h=None):
        k, c = ctx.contact_kc(params, mi)
        xa, xb = state.position[ia], state.position[ib]
        d, nrm = jax.vmap(geometry.sphere_sphere)(xa, ra, xb, rb)
        vn = geometry.dot(nrm, state.velocity[ia] - state.velocity[ib])
        f = ctx.contact_force(d, vn, k, c, h, inv_m,
                              g_side * geometry.dot(nrm, g_vec))[:, None] * nrm
        return scatter(f, ia, n) - scatter(f, ib, n), None
    return Term("contact_sphere_sphere", force, step_aware=True)


def _spring_axis(delta, rel_vel, rest):
    """Stretch (m), stretch rate (m/s) and unit axis for ONE spring."""
    length = geometry.safe_norm(delta)
    inv = jnp.where(length > 0.0, 1.0 / jnp.where(length > 0.0, length, 1.0), 0.0)
    u = delta * inv
    return length - rest, jnp.sum(u * rel_vel, axis=-1), u


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
        band_data.append((d, lo, hi, ctx.const(mask), ctx.const(rest_len), gidx))

    ia, ib, gi = ia_all[rest_ids], ib_all[rest_ids], gi_all[rest_ids]
    rest = ctx.const(rest_all[rest_ids])

    def force(params, state):
        x, v = state.position, state.velocity
        total = None
        for d, lo, hi, mask, rest_len, gidx in band_data:
            k, c = ctx.spring_kc(params, gidx)
            x, v = state.position, state.velocity
            delta = x[lo + d:hi + d] - x[lo:hi]       # from the low end to the high end
            dv = v[lo + d:hi + d] - v[lo:hi]
            ext, rate, u = jax.vmap(_spring_axis)(delta, dv, rest_len)
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
            f = laws.spring_force(ext, rate, k, c)[:, None] * u
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
    gi = np.array([r[3] for r in rows], dtype=np.int32)
    n = ctx.n

    def force(params, state):
        k, c = ctx.spring_kc(params, gi)
        delta = gather(state.position, ia, n) - anchors
        x, xd, u = jax.vmap(_spring_axis)(delta, gather(state.velocity, ia, n), rest)
        return scatter(laws.spring_force(x, xd, k, c)[:, None] * u, ia, n), None
    return Term("world_springs", force)


def _drag(ctx: CompileContext) -> Term | None:
    """Velocity drag ``F = -c v`` per body (``scene.add_drag``); ``c`` per drag group in
    ``params.extra["drag"][group]`` (N s/m). Absent (never traced) without drag."""
    rows = [(d.body, d.group) for d in ctx.scene.drags if not ctx.pinned[d.body]]
    if not rows:
        return None
    groups = list(dict.fromkeys(g for _, g in rows))
    ctx.extra_defaults["drag"] = {g: ctx.scene.drag_groups[g] for g in groups}
    bi = np.array([r[0] for r in rows], dtype=np.int32)
    gi = np.array([groups.index(r[1]) for r in rows], dtype=np.int32)
    n = ctx.n

    def force(params, state):
        c = _select([params.extra["drag"][g] for g in groups], gi)
        v = gather(state.velocity, bi, n)
        f = jax.vmap(laws.drag_force, in_axes=(0, None if jnp.ndim(c) == 0 else 0))(v, c)
        return scatter(f, bi, n), None
    return Term("drag", force)


# --------------------------------------------------------------------------- stability bounds
_KISSING = 12  # most equal spheres that can touch one sphere at once


def _movers(ctx: CompileContext):
    return [i for i in range(ctx.n) if ctx.collide[i] and not ctx.pinned[i]]


def _plane_bound(ctx: CompileContext):
    """One contact spring per (free, colliding body, plane), k / m (one contact at a time)."""
    rows = [(i, pl.material, 1.0, 1.0, f"contact with plane {p} (material {pl.material!r})")
            for i in _movers(ctx) for p, pl in enumerate(ctx.scene.planes)]
    return _one(Bound.of(rows, "contact", combine="contact"))


def _fixed_sphere_bound(ctx: CompileContext):
    rows = [(i, fs.material, 1.0, 1.0,
             f"contact with fixed sphere {s} (material {fs.material!r})")
            for i in _movers(ctx) for s, fs in enumerate(ctx.scene.fixed_spheres)]
    return _one(Bound.of(rows, "contact", combine="contact"))


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


def _one(bound):
    return () if bound is None else (bound,)


def with_bound(build: Callable[[CompileContext], Term | None],
               bound: Callable[[CompileContext], tuple] | None):
    """A term builder whose Term carries ``bound(ctx)`` (a tuple of
    :class:`diffpen.stability.Bound`): how a term and its stability bound are registered
    together (one line per term)."""
    if bound is None:
        return build

    def built(ctx: CompileContext) -> Term | None:
        term = build(ctx)
        return None if term is None else term._replace(bound=tuple(bound(ctx)))
    built.__name__ = getattr(build, "__name__", "term")
    return built


#: The core term builders with their stability bounds, in force summation order.
CORE: tuple = (
    with_bound(_plane_contact, _plane_bound),
    with_bound(_fixed_sphere_contact, _fixed_sphere_bound),
    with_bound(_sphere_sphere_contact, _sphere_sphere_bound),
    with_bound(_body_springs, _body_springs_bound),
    with_bound(_world_springs, _world_springs_bound),
    _drag,
)
