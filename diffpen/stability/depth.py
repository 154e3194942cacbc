"""The reference depth of a contact law whose stiffness grows with depth, from the energy a
rollout starts with.

Hunt-Crossley's contact stiffens with depth, ``dF/dd = n k d^(n-1)``, so the safe step takes
it at a reference depth: each body's radius (:class:`~.bounds.Analysis` ``d_ref``), the
deepest a penetration can meaningfully go. A ball dropped from 1 m onto a Hertz contact (1 kg,
k 1e6 N/m^1.5) sinks 1.4 cm, not 10, and its stiffness there is 2.7x smaller: the radius
refuses a step of 1 ms that this ball takes safely.

Energy bounds the depth instead, where the scene lets it: no force besides gravity, the
contacts, springs, friction and drag can give energy back (no custom terms but those
declared passive, :class:`diffpen.terms.TermBuilder`; a plastic spring's rest length only
follows its compressed length, which lowers what it stores), gravity's potential is bounded
below (no gravity, or planes that hold the bodies up, :func:`_floors`: a horizontal floor,
or tilted planes whose normals add up to the up direction, as a trough, a funnel or a ramp
sloping into a wall; a named plane at the offset its params give; with springs, every free
body collides, so that none can sink below the floor and pull another body in through a
spring), the springs' stored energy ``k x^2 / 2`` at the start is counted (with their
groups' stiffness from the params; without them, every spring must start at its rest length,
within :data:`REST_TOLERANCE`), and no body starts in contact (a box: none of its corners on
or below a plane). A damped linear spring stores ``k x^2 / 2 >= 0`` and gives back no more
than it stored, so then no contact ever stores more than the start's kinetic energy
(rotation included), potential energy and springs' energy ``E0`` of the bodies that collide
(a body that collides with nothing keeps its energy to itself: it could only reach a contact
through a spring), and a contact of stiffness ``k`` holds it at ``k d^(n+1) / (n+1) = E0``.
The potential is counted from where a body's centre could get at the deepest penetration
counted (its reference size ``d_ref`` below its support): for a sphere that is the floor
(its support is its radius, its reference size too), for a box ``d_ref - min(half extents)``
below it (a box face down and sunk by its half-diagonal). The bound takes twice ``E0``
(:data:`ENERGY_MARGIN`: room for the explicit step's own energy error, held to several % per
contact event by the safe step), and never more than the radius. Where any condition fails
the radius stays.

:func:`start_energy` computes ``E0`` on the host from a concrete start state (None where the
scene or the state does not qualify); ``Simulator.rollout`` hands it to the up-front gate and,
as a traced argument, to the traced flag, so both count the same depth. Where the start state
or a named plane's offset is traced (under jit, vmap or grad) the up-front gate keeps the
radius (it cannot read them), and the traced flag counts the same energy from the traced
values (:func:`energy_bound`: ``inf``, the radius, where a body starts in contact, and for
a traced start of more than 512 colliding bodies, whose every pair it would compare; the host
sweeps along x instead).
"""
from __future__ import annotations

import functools
import itertools

import numpy as np

from ..geometry import box_corners, quat_to_matrix

__all__ = ["ENERGY_MARGIN", "REST_TOLERANCE", "qualifies", "start_energy", "energy_bound",
           "energy_depth", "start_depths", "start_stretches"]

#: the energy a contact may store, in units of the start's kinetic and potential energy
ENERGY_MARGIN = 2.0


def qualifies(scene, law, passive_terms: bool) -> bool:
    """Whether ``scene`` compiled with ``law`` (a ``diffpen.laws.ContactLaw``) lets the start
    energy bound its contacts' depth (module docstring); static, at compile time.
    ``passive_terms``: every term of the simulator is built in or declared passive
    (:class:`diffpen.terms.TermBuilder`)."""
    if float(law.exponent) == 1.0 and float(law.damping_exponent) == 0.0:
        return False                    # the stiffness does not depend on depth
    if not passive_terms:
        return False
    g = np.asarray(scene.gravity, float)
    gn = float(np.linalg.norm(g))
    if gn == 0.0:
        return True
    if (scene.springs or scene.anchored_springs or scene.plastic_springs) and not all(
            b.collide or b.pinned for b in scene.bodies):
        return False                    # a body no plane holds up could pull one in deeper
    return bool(_floors(scene))


def _floors(scene) -> list[tuple[tuple[int, ...], np.ndarray]]:
    """What holds the colliding bodies up against gravity: each ``(planes, weights)`` a set of
    up to three planes whose normals, weighted by ``weights >= 0``, sum to the up direction.
    Every colliding body stays above every plane (``n_p . x >= offset_p`` less what it
    reaches and sinks), so ``up . x = sum_p w_p n_p . x >= sum_p w_p offset_p``: a horizontal
    floor (one plane, weight 1), a trough of two tilted planes or a funnel of three bound
    gravity's potential below (the weak dual of the lowest point above every plane); a ramp
    alone does not (empty: the radius). Scenes of more than 12 planes look for floors only.
    Depends on the gravity and the planes' normals only (cached: a rollout asks each time)."""
    return _floor_sets(tuple(float(v) for v in scene.gravity),
                       tuple(tuple(float(v) for v in p.normal) for p in scene.planes))


@functools.lru_cache(maxsize=256)
def _floor_sets(gravity: tuple, normals: tuple) -> list:
    """:func:`_floors` of the gravity and the planes' normals."""
    g = np.asarray(gravity, float)
    up = -g / float(np.linalg.norm(g))
    normals = [np.asarray(n, float) / np.linalg.norm(n) for n in normals]
    sizes = (1, 2, 3) if len(normals) <= 12 else (1,)
    found = []
    for size in sizes:
        for planes in itertools.combinations(range(len(normals)), size):
            basis = np.stack([normals[i] for i in planes], axis=1)          # (3, size)
            w, _, rank, _ = np.linalg.lstsq(basis, up, rcond=None)
            if (rank == size and np.all(w >= 0.0)
                    and np.linalg.norm(basis @ w - up) <= 1e-12):
                found.append((planes, w))
    return found


#: how far (relative to its rest length, floored at 1 mm) a spring may be stretched or
#: compressed at the start for its energy to count as none (float32 positions round to ~1e-7)
REST_TOLERANCE = 1e-6


def _spring_stretches(scene, x, rot, xp=np, plastic_rest=None):
    """``(stretch, rest, groups)``: every spring's, anchored spring's and plastic spring's
    length less its rest length (m; an array), the rest lengths (m) and the group names, ``x``
    (n, 3) the centres, ``rot`` (n, 3, 3) the rotations (None: an anchored spring cannot be
    measured: stretch None), ``plastic_rest`` the plastic springs' current rest lengths
    (``State.aux["plastic_rest"]``; None: their initial ones)."""
    def far(ends, anchors, moved):
        """the second ends: a body's point or a world point"""
        ib = np.array([-1 if b is None else b for b in ends], dtype=int)
        world = np.asarray(anchors, float).reshape(-1, 3)
        return xp.where((ib >= 0)[:, None], moved(np.maximum(ib, 0)), world)
    springs, anchored, plastic = scene.springs, scene.anchored_springs, scene.plastic_springs
    rest = np.array([sp.rest_length for sp in springs] + [sp.rest_length for sp in anchored]
                    + [sp.rest_length for sp in plastic])
    if plastic and plastic_rest is not None:
        rest = xp.concatenate([rest[:len(rest) - len(plastic)],
                               xp.asarray(plastic_rest, x.dtype).reshape(-1)])
    groups = [sp.group for sp in springs + anchored + plastic]
    parts = []
    if springs:
        pa = x[np.array([sp.a for sp in springs], dtype=int)]
        pb = far([sp.b for sp in springs],
                 [sp.anchor if sp.b is None else (0.0, 0.0, 0.0) for sp in springs],
                 lambda i: x[i])
        parts.append(xp.linalg.norm(pa - pb, axis=1))
    if anchored:
        if rot is None:
            return None, rest, groups
        ia = np.array([sp.a for sp in anchored], dtype=int)
        local_a = np.array([sp.anchor_a for sp in anchored], float)
        local_b = np.array([sp.anchor_b for sp in anchored], float)
        pa = x[ia] + xp.einsum("nij,nj->ni", rot[ia], local_a)
        pb = far([sp.b for sp in anchored], local_b,
                 lambda i: x[i] + xp.einsum("nij,nj->ni", rot[i], local_b))
        parts.append(xp.linalg.norm(pa - pb, axis=1))
    if plastic:
        ends = np.array([(sp.a, sp.b) for sp in plastic], dtype=int)
        parts.append(xp.linalg.norm(x[ends[:, 0]] - x[ends[:, 1]], axis=1))
    if not parts:
        return xp.zeros(0), rest, groups
    return xp.concatenate(parts) - rest, rest, groups


def start_stretches(scene) -> np.ndarray:
    """(springs + anchored springs + plastic springs,) m, in that order: each spring's length
    less its rest length at the scene's start poses (:func:`_spring_stretches` on the
    host), what the springs' start tension is counted from (the friction and anchored-spring
    stability bounds, :mod:`diffpen.terms`)."""
    bodies = scene.bodies
    x = np.array([b.position for b in bodies], float).reshape(-1, 3)
    rot = np.array([quat_to_matrix(np.asarray(b.orientation, float), xp=np) if b.rigid
                    else np.eye(3) for b in bodies]).reshape(-1, 3, 3)
    return _spring_stretches(scene, x, rot)[0]


def _spring_energy(scene, x, rot, xp=np, spring_k=None, plastic_rest=None):
    """``(ok, energy)``: the springs' stored energy ``k x^2 / 2`` (J) at the start, with the
    groups' stiffness ``spring_k`` (``{group: k}`` N/m); without it, whether every spring
    starts at its rest length (within :data:`REST_TOLERANCE`), which stores none."""
    if not (scene.springs or scene.anchored_springs or scene.plastic_springs):
        return xp.asarray(True), 0.0
    stretch, rest, groups = _spring_stretches(scene, x, rot, xp, plastic_rest)
    if stretch is None:
        return xp.asarray(False), 0.0
    if spring_k is not None:
        names = sorted(set(groups))
        table = xp.stack([xp.asarray(spring_k[g], stretch.dtype) for g in names])
        k = table[np.array([names.index(g) for g in groups], dtype=int)]
        return xp.all(table >= 0.0), 0.5 * xp.sum(k * stretch * stretch)
    return xp.all(xp.abs(stretch) <= REST_TOLERANCE * xp.maximum(rest, 1e-3)), 0.0


def start_energy(scene, mass, radius, pinned, collide, position, velocity, *,
                 orientation=None, angular_velocity=None, inertia=None,
                 offsets=None, spring_k=None, plastic_rest=None) -> float | None:
    """Kinetic (rotation included) and potential energy (J) of a concrete start state
    (``position``, ``velocity`` (n, 3)), potential counted as the module docstring says;
    None when a colliding body (``collide`` (n,) bool, fixed per simulator) starts in contact
    (with a plane: a box by its corners, other bodies by their ``radius``; with a fixed sphere
    or another colliding body: by ``radius``, a box's bounding sphere), a value is not
    finite, or, without ``spring_k`` (``{spring group: k}`` N/m, as ``params.springs``
    gives them), a spring starts stretched or compressed (with it, the springs' stored
    energy counts); ``plastic_rest``: the plastic springs' rest lengths (m, the state's
    ``aux["plastic_rest"]``; default their initial ones). Rotating scenes also give
    ``orientation`` (n, 4) (w, x, y, z), ``angular_velocity`` (n, 3) world frame, rad/s, and
    ``inertia`` (n, 3) body-frame principal moments, kg m^2 (0 for bodies that do not
    rotate). ``offsets``: the planes' offsets (m, one per plane; default the scene's), as a
    named plane's ``params.extra["plane_offset"]`` sets them. Assumes :func:`qualifies`;
    :func:`energy_bound` is the same, traceable."""
    e = float(energy_bound(scene, mass, radius, pinned, collide, position, velocity,
                           orientation=orientation, angular_velocity=angular_velocity,
                           inertia=inertia, offsets=offsets, spring_k=spring_k,
                           plastic_rest=plastic_rest, xp=np))
    return e if np.isfinite(e) else None


#: colliding bodies up to which every pair is compared at once (a traced start state with
#: more keeps the radius); the host sweeps along x beyond it
_DENSE_PAIRS = 512
#: the most pairs the host's sweep compares (beyond it: the radius)
_SWEEP_PAIRS = 20_000_000


def _can_touch(a, b):
    """Whether bodies of kinds ``a`` and ``b`` (arrays of :func:`_kinds`) have a contact:
    sphere-sphere, and a sphere or particle with a box (boxes do not touch boxes, particles
    touch only colliders and boxes)."""
    return ((a == 1) & (b == 1)) | ((a == 2) != (b == 2))


def _kinds(scene, idx):
    """The kinds of bodies ``idx``: 0 particle, 1 sphere, 2 box."""
    return np.array([{"particle": 0, "sphere": 1, "box": 2}[scene.bodies[i].kind]
                     for i in idx], dtype=int)


def _touching(x, r, kind) -> bool | None:
    """Whether two of the bodies (centres ``x`` (n, 3) m, radii ``r`` (n,) m, ``kind`` (n,)
    as :func:`_kinds`) that have a contact touch (centre distance <= the sum of their radii),
    on the host: the bodies sorted along x, each compared with those ahead of it within its
    radius plus the largest one. None (unknown) where that would compare more than
    :data:`_SWEEP_PAIRS` pairs."""
    order = np.argsort(x[:, 0], kind="stable")
    xs, rs, ks = x[order], r[order], kind[order]
    ahead = (np.searchsorted(xs[:, 0], xs[:, 0] + rs + rs.max(), side="right")
             - np.arange(len(xs)) - 1)
    if ahead.sum() > _SWEEP_PAIRS:
        return None
    for k in range(1, int(ahead.max(initial=0)) + 1):
        i = np.flatnonzero(ahead >= k)
        i = i[_can_touch(ks[i], ks[i + k])]
        if np.any(np.sum((xs[i] - xs[i + k]) ** 2, axis=1) <= (rs[i] + rs[i + k]) ** 2):
            return True
    return False


def _scatter(xp, a, idx, vals):
    """``a`` with ``a[idx] = vals`` (numpy or jax.numpy)."""
    if xp is np:
        a = a.copy()
        a[idx] = vals
        return a
    return a.at[idx].set(vals)


def energy_bound(scene, mass, radius, pinned, collide, position, velocity, *,
                 orientation=None, angular_velocity=None, inertia=None, offsets=None,
                 spring_k=None, plastic_rest=None, xp=np):
    """:func:`start_energy` as an array, ``inf`` where it is None: with ``xp=jax.numpy`` the
    start state and the offsets may be traced (a rollout's traced flag counts a traced start
    state, or a named plane's traced offset, this way: :meth:`diffpen.Simulator.rollout`)."""
    if np.count_nonzero(np.asarray(collide, bool)) > _DENSE_PAIRS and xp is not np:
        return xp.asarray(np.inf)       # a traced pair check of every pair: the radius
    fl = xp.float64 if xp is np else None
    x = xp.asarray(position, fl)
    v = xp.asarray(velocity, x.dtype)
    # only bodies that can touch a collider count: one that collides with nothing (and,
    # in scenes that qualify, is tied to no spring) keeps its own energy to itself, and
    # one below the floor would count a negative potential
    idle = np.asarray(pinned, bool) | ~np.asarray(collide, bool)
    m = np.where(idle, 0.0, np.asarray(mass, float))
    r = np.asarray(radius, float)
    ok = xp.all(xp.isfinite(x)) & xp.all(xp.isfinite(v))
    rot = None
    if orientation is not None:
        q = xp.asarray(orientation, x.dtype)
        w = xp.asarray(angular_velocity, x.dtype)
        ok = ok & xp.all(xp.isfinite(q)) & xp.all(xp.isfinite(w))
        rot = quat_to_matrix(q / xp.linalg.norm(q, axis=1, keepdims=True), xp=xp)
    ok_springs, energy = _spring_energy(scene, x, rot, xp, spring_k, plastic_rest)
    ok = ok & ok_springs
    if offsets is None:
        offsets = [float(p.offset) for p in scene.planes]
    collide = np.asarray(collide, bool)
    boxes = np.array([i for i, b in enumerate(scene.bodies)
                      if b.half_extents is not None and rot is not None], dtype=int)
    # (boxes, 8, 3) corners from the centres, world frame
    corners = (xp.einsum("bij,bkj->bki", rot[boxes], np.stack(
        [box_corners(scene.bodies[i].half_extents) for i in boxes]))
        if boxes.size else None)
    # how far below its centre a body reaches towards a plane: a box by its lowest corner
    for p, off in zip(scene.planes, offsets):
        nrm = np.asarray(p.normal, float)
        reach = r if corners is None else _scatter(xp, xp.asarray(r, x.dtype), boxes,
                                                   xp.max(-(corners @ nrm), axis=1))
        gap = x @ nrm - off - reach
        ok = ok & ~xp.any(collide & (gap <= 0.0))
    for fs in scene.fixed_spheres:
        dist = xp.linalg.norm(x - np.asarray(fs.center, float), axis=1)
        ok = ok & ~xp.any(collide & (dist <= r + float(fs.radius)))
    idx = np.flatnonzero(collide)
    kind = _kinds(scene, idx)
    if idx.size > _DENSE_PAIRS:         # on the host: a sweep along x
        ok = ok & (_touching(x[idx], r[idx], kind) is False)
    elif idx.size > 1:
        xc, rc = x[idx], r[idx]
        dist = xp.sqrt(xp.sum((xc[:, None, :] - xc[None, :, :]) ** 2, axis=-1))
        pairs = _can_touch(kind[:, None], kind[None, :]) & ~np.eye(idx.size, dtype=bool)
        ok = ok & ~xp.any(pairs & (dist <= rc[:, None] + rc[None, :]))
    energy = energy + 0.5 * xp.sum(m * xp.sum(v * v, axis=1))
    if rot is not None:
        spin = xp.einsum("nji,nj->ni", rot, w)                          # body frame
        moments = np.where(idle[:, None], 0.0, np.asarray(inertia, float))
        energy = energy + 0.5 * xp.sum(moments * spin * spin)
    g = np.asarray(scene.gravity, float)
    gn = float(np.linalg.norm(g))
    if gn > 0.0:
        floors = _floors(scene)
        if not floors:                  # (a scene that does not qualify: the radius)
            return xp.asarray(np.inf)
        # a box can sink its centre into a plane by its half-diagonal less its support
        sink = np.zeros(len(r))
        sink[boxes] = r[boxes] - np.array([min(scene.bodies[i].half_extents) for i in boxes])
        # the lowest each body's centre can get: the best of the floors' bounds
        low = None
        for planes, w in floors:
            bound = sum(float(wi) * offsets[i] for i, wi in zip(planes, w)) - sink * float(
                np.sum(w))
            low = bound if low is None else xp.maximum(low, bound)
        energy = energy + gn * xp.sum(m * (x @ (-g / gn) - low))
    ok = ok & xp.isfinite(energy)
    return xp.where(ok, energy, xp.inf)


def energy_depth(exponent: float, k, energy, xp=np):
    """Depth (m) at which a contact of stiffness ``k`` (N/m^n; an array) stores
    ``ENERGY_MARGIN x energy`` J: ``((n + 1) E / k)^(1 / (n + 1))`` (inf where ``k`` is 0)."""
    n1 = float(exponent) + 1.0
    pos = k > 0.0
    return xp.where(pos, (n1 * ENERGY_MARGIN * energy / xp.where(pos, k, 1.0)) ** (1.0 / n1),
                    xp.inf)


def start_depths(scene) -> np.ndarray:
    """(n,) m: each body's deepest penetration into a plane, fixed sphere or another body at
    its start pose (a sphere's or particle's centre, a box's corners; 0 where none). A body
    started deeper than its radius (``allow_overlap=True``) takes this as its reference
    depth: at the radius the safe step counted a Hertz ball started 0.6 m deep 2.4x softer
    than it was, and its launch gained 19% of its energy."""
    from ..overlap import box_corners
    bodies = scene.bodies
    out = np.zeros(len(bodies))
    if not bodies:
        return out
    x = np.array([b.position for b in bodies], float)
    r = np.array([0.0 if b.half_extents else b.radius for b in bodies], float)
    for pl in scene.planes:             # centres (spheres, particles), one array per plane
        out = np.maximum(out, r + pl.offset - x @ np.asarray(pl.normal, float))
    for fs in scene.fixed_spheres:
        out = np.maximum(out, r + fs.radius - np.linalg.norm(x - np.asarray(fs.center, float),
                                                                 axis=1))
    for i, b in enumerate(bodies):      # a box's corners
        if b.half_extents:
            c = box_corners(b)
            depth = [pl.offset - c @ np.asarray(pl.normal, float) for pl in scene.planes]
            depth += [fs.radius - np.linalg.norm(c - np.asarray(fs.center, float), axis=-1)
                      for fs in scene.fixed_spheres]
            out[i] = max([0.0] + [float(np.max(d)) for d in depth])
    out = np.maximum(out, 0.0)
    index = getattr(scene, "_overlap", None)        # pairs of bodies started inside each other
    return out if index is None else np.maximum(out, index.start_pair_depths(scene))
