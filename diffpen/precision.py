"""What a simulator's float dtype can hold and resolve, checked when a scene is compiled.

* :func:`check_dtype_range`: every number of the scene fits the dtype (float32: a value past
  3.4e38 would become inf).
* :func:`check_coordinates`: the dtype resolves the scene's motion where it is (float32 at
  1e4 m from the origin rounds a step's displacement away).
* :func:`min_resolved_step` / :func:`warn_step`: the inner step is long enough for the dtype
  to resolve a step's displacement (float32 at dt = 1e-7 s: a dropped ball stood still for
  0.06 s, and fell 1.9% short in 0.2 s); a :class:`PrecisionWarning` otherwise.

Both raise :class:`diffpen.SceneError` saying what to change (rescale, move the scene near
the origin, or float64).
"""
from __future__ import annotations

import numpy as np

from .errors import SceneError, warn

__all__ = ["check_dtype_range", "check_coordinates", "min_resolved_step", "warn_step",
           "PrecisionWarning", "FAR_COARSER", "FREEZE_FRACTION", "EVENTS_FORCE_ERROR",
           "events_min_step", "warn_events"]


#: how much coarser than at the scene's own scale (1 m or its largest body) the dtype's
#: resolution at the scene's farthest coordinate may be before it counts as far out
FAR_COARSER = 16.0


def check_dtype_range(scene, dtype) -> None:
    """Refuse a scene number that ``dtype`` cannot hold: past its largest finite value it
    becomes inf when the simulator is built (float32: a sphere at x = 1e39 m compiled and its
    rollout stopped on NaN blaming the time step). Every number of every element (bodies,
    planes, fixed spheres, springs, materials, spring and drag groups, gravity), one array
    per field (10,000 bodies: 0.13 s, against 2.5 s for their compile); nothing to check in
    float64; and bodies' sizes, rigid bodies' moments of inertia and rough materials' slip
    speeds against its smallest normal number (:func:`_check_inertia`, also in float64).
    Raises SceneError naming the element and the value."""
    import dataclasses
    _check_inertia(scene, dtype)
    top = float(np.finfo(dtype).max)
    if top >= float(np.finfo(np.float64).max):
        return                  # float64: every finite number fits (inf is refused on input)

    def refuse(what, value):
        raise SceneError(f"{what} = {float(value):.4g} is past {np.dtype(dtype).name}'s "
                         f"largest number ({top:.4g}): it would become inf. Rescale the "
                         "units, or compile with dtype=jnp.float64.")

    def check(kind, names, elems):
        """``elems``: dataclasses of one type (or plain numbers) named ``kind[name]``."""
        if not elems:
            return
        fields = ([f.name for f in dataclasses.fields(elems[0])]
                  if dataclasses.is_dataclass(elems[0]) else [None])
        for field in fields:
            values = [e if field is None else getattr(e, field) for e in elems]
            kept = [i for i, v in enumerate(values) if v is not None
                    and not isinstance(v, (str, bytes, bool, np.bool_))]
            if not kept:
                continue
            try:
                try:            # one array for the field (equal shapes: the common case)
                    arr = np.asarray([values[i] for i in kept], dtype=float)
                    big = np.max(np.abs(arr.reshape(len(kept), -1)), axis=1, initial=0.0)
                except ValueError:          # ragged: element by element
                    big = np.array([np.max(np.abs(np.asarray(values[i], dtype=float)),
                                           initial=0.0) for i in kept])
            except (TypeError, ValueError):
                continue                # not numbers (names, groups)
            rows = [(names[i], values[i]) for i in kept]
            over = np.nonzero(np.asarray(big) > top)[0]
            if over.size:
                n, v = rows[int(over[0])]
                worst = np.asarray(v, dtype=float).reshape(-1)
                refuse(f"{kind}[{n!r}]" + (f".{field}" if field else ""),
                       worst[np.argmax(np.abs(worst))])
    g = np.asarray(scene.gravity, dtype=float)
    if np.max(np.abs(g)) > top:
        refuse("gravity", g[np.argmax(np.abs(g))])
    for kind in ("bodies", "planes", "fixed_spheres", "springs", "anchored_springs",
                 "plastic_springs", "drags"):
        elems = getattr(scene, kind)
        check(kind, list(range(len(elems))), elems)
    for kind in ("materials", "spring_groups", "drag_groups"):
        table = getattr(scene, kind)
        check(kind, list(table), list(table.values()))


def _check_inertia(scene, dtype) -> None:
    """Refuse a rigid body whose moments of inertia (given, or derived from its size) are
    below ``dtype``'s smallest normal number, where their inverse overflows: a box of half
    extent 1e-20 m in float32 (1e-40 kg m^2) ran to NaN at its first step and the rollout
    blamed the time step; at 1e-170 m in float64 numpy's eigenvalue solver failed."""
    from .rigid import inertia_diagonal
    tiny = float(np.finfo(dtype).tiny)

    def refuse(what: str, why: str, fix: str):
        """A value below the square root of ``tiny``, where its square rounds to 0."""
        raise SceneError(f"{what} is below the square root of {np.dtype(dtype).name}'s "
                         f"smallest normal number ({tiny ** 0.5:.3g}): {why}. {fix}"
                         + (", or use dtype=float64." if np.dtype(dtype).itemsize < 8
                            else "."))
    for name, mat in scene.materials.items():
        if mat.friction > 0.0 and mat.slip_speed < tiny ** 0.5:     # s^2 underflows to 0
            refuse(f"material {name!r}'s slip_speed ({mat.slip_speed:.3g} m/s)",
                   "friction's |v_t|^2 + slip_speed^2 rounds to 0 for a body at rest (0 / 0)",
                   "Raise it (it is the speed below which friction is viscous)")
    for i, b in enumerate(scene.bodies):
        size = min(b.half_extents) if b.half_extents else b.radius
        if 0.0 < size < tiny ** 0.5:   # audit17: 5e-324 m divided by 0 in the step checks
            refuse(f"body {i}'s size ({size:.3g} m)",
                   "its areas and the checks' times round to 0",
                   "Rescale the scene (metres to a unit where the body is not this small)")
        if not b.rigid or b.pinned:
            continue
        moments = inertia_diagonal(b)
        if np.min(moments) < tiny:
            raise SceneError(
                f"body {i}'s moments of inertia reach {np.min(moments):.3g} kg m^2, below "
                f"{np.dtype(dtype).name}'s smallest normal number ({tiny:.3g}): their inverse "
                "overflows. Rescale the scene (metres and kilograms to a unit where the body "
                "is not this small), or use dtype=float64.")


def check_coordinates(scene, dtype) -> None:
    """Refuse a scene placed so far from the origin that ``dtype`` cannot resolve its motion
    there: the spacing of representable numbers at its farthest coordinate (body positions,
    plane offsets, fixed spheres) above 1e-4 of its smallest body or of its shortest spring
    (its rest length, or its start length if that is 0: a particle rope far out ran 2% off,
    unwarned), or 1% of the static
    deflection ``m g / k`` of its declared contact materials, where that is more than
    :data:`FAR_COARSER` times the spacing at the scene's own scale. There a step's
    displacement ``|v| dt`` rounds away (float32: a box sliding at x = 1e4 m never moved while
    friction stopped its velocity; a ball resting on a plane at z = 1e4 m froze, reading
    -0.3 m/s). Raises SceneError: move the scene near the origin, or use float64. Also
    refuses spheres placed with ``allow_overlap`` whose centres are one in ``dtype``
    (:meth:`diffpen.overlap.OverlapIndex.check_coincident`)."""
    bodies = scene.bodies
    if not bodies:
        return
    scene._overlap.check_coincident(scene, dtype)
    far, sizes = _extent(scene)
    scale = max([1.0] + sizes)
    dt = np.dtype(dtype).type
    res_far = float(np.spacing(dt(far)))
    if not np.isfinite(far) or res_far <= FAR_COARSER * float(np.spacing(dt(scale))):
        return
    limits = []
    if sizes:
        limits.append((1e-4 * min(sizes), f"1e-4 of its smallest body ({min(sizes):.3g} m)"))
    rests = [_spring_length(scene, sp) for group in (scene.springs, scene.anchored_springs,
                                                     scene.plastic_springs) for sp in group]
    rests = [r for r in rests if r > 0.0]
    if rests:       # a rope, cloth or jelly of particles has no body size: its springs' does
        limits.append((1e-4 * min(rests), f"1e-4 of its shortest spring ({min(rests):.3g} m)"))
    g = float(np.linalg.norm(scene.gravity))
    ks = [m.k for m in scene.materials.values() if m.k]
    free = [b.mass for b in bodies if not b.pinned]
    if g > 0.0 and ks and free:
        depth = min(free) * g / max(ks)
        limits.append((0.01 * depth, f"1% of a body's resting depth m g / k ({depth:.3g} m)"))
    if not limits:
        return
    limit, what = min(limits)
    if res_far > limit:
        raise SceneError(
            f"the scene reaches {far:.4g} m from the origin, where {np.dtype(dtype).name} "
            f"resolves positions only to {res_far:.2g} m, more than {what}: a step's "
            "displacement |v| dt would round away there (bodies freeze while their velocity "
            "changes). Move the scene near the origin (only positions relative to each other "
            "and to the planes matter), or compile with dtype=float64.")


def _spring_length(scene, sp) -> float:
    """A spring's length scale, m: its rest length, else (a zero-length spring) the distance
    between its ends at the start (0 for an anchored spring between body-frame points)."""
    from .elements import Spring
    if sp.rest_length > 0.0 or not isinstance(sp, Spring):
        return float(sp.rest_length)
    end = scene.bodies[sp.b].position if sp.b is not None else sp.anchor
    return float(np.linalg.norm(np.subtract(scene.bodies[sp.a].position, end)))


def _extent(scene, free: bool = False) -> tuple:
    """``(far, sizes)``: the scene's farthest coordinate from the origin (m: body positions,
    plane offsets, fixed spheres) and its bodies' positive sizes (radius or smallest half
    extent, m; ``free``: of the bodies that are not pinned)."""
    bodies = scene.bodies
    far = float(np.abs(np.array([b.position for b in bodies], dtype=float)).max())
    for pl in scene.planes:
        far = max(far, abs(float(pl.offset)))
    for fs in scene.fixed_spheres:
        far = max(far, float(np.max(np.abs(fs.center))) + float(fs.radius))
    sizes = [min(b.half_extents) if b.half_extents else b.radius for b in bodies
             if not (free and b.pinned)]
    return far, [s for s in sizes if s > 0.0]


class PrecisionWarning(UserWarning):
    """A step too short for the simulator's float dtype to resolve its displacements: the
    run works, with rounding errors past the integrator's; the message says what to change."""


#: the longest a body at rest under gravity may stand still, as a fraction of the scene's
#: fall time ``sqrt(L / g)`` (L its smallest body, else 1 m), before :func:`warn_step` warns:
#: its first steps move it by ``g t h^2 < spacing / 2``, which rounds away, until
#: ``t = spacing / (2 g h)``
FREEZE_FRACTION = 0.1


def min_resolved_step(scene, dtype) -> float:
    """The shortest inner step (s) at which ``dtype`` resolves the motion of the scene's
    bodies under gravity where they are (:data:`FREEZE_FRACTION`): ``spacing / (2 g
    FREEZE_FRACTION sqrt(L / g))``, ``spacing`` the dtype's spacing of numbers at the scene's
    farthest coordinate plus its largest body. 0 without gravity or free bodies. Float32, a
    ball dropped from 1 m: 6.0e-7 s for a 10 cm ball, 1.9e-6 s for a 1 cm one; a 1 mm ball
    dropped from 5 mm: 2.4e-8 s; float64: ~1e-15 s."""
    g = float(np.linalg.norm(np.asarray(scene.gravity, float)))
    if g == 0.0 or not any(not b.pinned for b in scene.bodies):
        return 0.0
    far, sizes = _extent(scene, free=True)    # sizes of free bodies: a pinned one never falls
    reach = far + max(sizes, default=0.0)   # where the bodies' surfaces are (mm scenes: mm)
    spacing = float(np.spacing(np.dtype(dtype).type(reach)))
    fall = float(np.sqrt((min(sizes) if sizes else 1.0) / g))
    return spacing / (2.0 * g * FREEZE_FRACTION * fall)


def warn_step(min_step: float, h: float, dtype) -> None:
    """Warn (:class:`PrecisionWarning`) when the inner step ``h`` (s) is below ``min_step``
    (:func:`min_resolved_step`)."""
    if h >= min_step:
        return
    name = np.dtype(dtype).name
    warn(
        f"an inner step of {h:.3g} s is too short for {name} at this scene's scale: the first "
        f"steps of a body at rest under gravity move it by less than half the spacing of "
        f"{name} numbers, so it stands still while its velocity grows, and rounding errors "
        "past the integrator's follow (a 10 cm ball in float32 at dt = 1e-7 s fell 1.9% short "
        f"in 0.2 s). Use dtype=float64, or an inner step of at least {min_step:.2g} s.",
        PrecisionWarning)


#: the largest rounding error, as a fraction of g, of the force an event-exact contact
#: record rebuilds each step before :func:`warn_events` warns
EVENTS_FORCE_ERROR = 1e-3


def events_min_step(scene, dtype) -> float:
    """The shortest inner step (s) at which the event-exact contact records
    (``diffpen.laws.linear(events=True)`` ...) rebuild their force to
    :data:`EVENTS_FORCE_ERROR` of g in ``dtype``: each step's force is a second difference of
    positions over ``h^2`` (``diffpen.event_step``), whose rounding, the dtype's spacing at
    the scene's farthest coordinate plus its largest body, grows as ``spacing / h^2``:
    ``sqrt(spacing / (EVENTS_FORCE_ERROR g))`` (g at least 9.81 m/s^2). A 10 cm ball dropped
    from 0.3 m: 1.7e-3 s in float32 (at 1e-4 s its derivatives were off by up to 64%,
    13x at 5e-5 s), 2.4e-8 s in float64."""
    g = max(float(np.linalg.norm(np.asarray(scene.gravity, float))), 9.81)
    far, sizes = _extent(scene)
    spacing = float(np.spacing(np.dtype(dtype).type(far + max(sizes, default=0.0))))
    return float(np.sqrt(spacing / (EVENTS_FORCE_ERROR * g)))


def warn_events(least: float, h: float, dtype) -> None:
    """Warn (:class:`PrecisionWarning`) when an event-exact record's inner step ``h`` (s) is
    below ``least`` (:func:`events_min_step`; the rollout's gate calls it with the step it
    takes, substeps included): its force's rounding error then passes
    :data:`EVENTS_FORCE_ERROR` of g, and its derivatives, which it exists to give exactly,
    are off by more."""
    if h >= least:
        return
    name = np.dtype(dtype).name
    warn(f"an event-exact contact record at an inner step of {h:.3g} s in {name}: it rebuilds "
         "each step's force from a second difference of positions over h^2, whose rounding "
         f"here is about {least * least / (h * h) * EVENTS_FORCE_ERROR:.2g} g (a 10 cm ball "
         "in float32 at dt 1e-4 s: derivatives up to 64% off). Use dtype=float64 (what these "
         f"records are for), an inner step of at least {least:.2g} s, or the law's default "
         "record.", PrecisionWarning)
