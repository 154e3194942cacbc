"""Scene: what exists (bodies, springs, colliders, materials). Plain Python, no JAX tracing.

A :class:`Scene` is built by ``add_*`` calls, each of which validates its input at once and
raises :class:`diffpen.SceneError` with a message saying what to change; the records it holds
and the checks live in :mod:`diffpen.elements`. ``diffpen.compile``
turns a scene into a simulator; the scene itself holds no arrays of JAX.

Units: SI (metres, kilograms, seconds, newtons).
"""
from __future__ import annotations

import copy
import dataclasses
import math
from typing import Sequence

import numpy as np

from .elements import (DEFAULT, AnchoredSpring, Body, Drag, FixedSphere, Material,
                       PlasticSpring, Plane, Spring, SpringGroup, finite_vec, number,
                       positive, unit_vector, vec3)
from .errors import SceneError
from .overlap import OverlapIndex


def _flag(name: str, value) -> bool:
    """A True/False argument: a bool (or numpy bool), not a string or number."""
    if not isinstance(value, (bool, np.bool_)):
        raise SceneError(f"{name} must be True or False, got {value!r}.")
    return bool(value)


#: what a refused add_* call could have changed before it was refused (restored on failure):
#: the group tables (small: copied) and the element lists (append-only: truncated)
_GROUPS = ("spring_groups", "plastic_groups", "drag_groups")
_LISTS = ("springs", "plastic_springs", "anchored_springs", "drags")


def _all_or_nothing(method):
    """Run an add_* method (or a builder, ``method(scene, ...)``) so that a refused call
    (SceneError) leaves the scene as it was: a group it declared before the refusal would
    make the corrected retry fail, and a builder refused halfway (a node inside a fixed
    sphere, a negative drag) left the nodes added so far. O(groups) per call (copying the
    element lists made building a 64 x 64 cloth 4x slower)."""
    import functools

    @functools.wraps(method)
    def run(*args, **kwargs):
        # the scene: the method's self, or a builder's first argument, by position or by
        # name (add_rope(scene=...) must keep working)
        self = args[0] if args else kwargs.get("scene", kwargs.get("self"))
        if not isinstance(self, Scene):
            return method(*args, **kwargs)      # let the call itself say what is wrong
        groups = {name: dict(getattr(self, name)) for name in _GROUPS}
        sizes = {name: len(getattr(self, name)) for name in _LISTS}
        n_bodies = len(self.bodies)
        try:
            return method(*args, **kwargs)
        except SceneError:
            for name, value in groups.items():
                setattr(self, name, value)
            for name, n in sizes.items():
                del getattr(self, name)[n:]
            for idx in range(len(self.bodies) - 1, n_bodies - 1, -1):
                self._overlap.forget(idx)           # last added first: popped from its cells
            del self.bodies[n_bodies:]
            raise
    return run

__all__ = ["Scene", "DEFAULT"]

class Scene:
    """Builder for a simulation scene.

    Args:
      gravity: (3,) gravitational acceleration, m/s^2. ``(0, 0, 0)`` leaves gravity out of
        the compiled step entirely.

    Example::

        scene = Scene(gravity=(0.0, 0.0, -9.81))
        ball = scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0))
        scene.add_plane()
    """

    def __init__(self, gravity: Sequence[float] = (0.0, 0.0, -9.81), *,
                 allow_overlap: bool = False):
        self.gravity = vec3("gravity", gravity)
        #: start bodies overlapped on purpose (no initial-overlap check; see diffpen.overlap)
        self.allow_overlap = _flag("allow_overlap", allow_overlap)
        self._overlap = OverlapIndex()
        self.bodies: list[Body] = []
        self.springs: list[Spring] = []
        self.anchored_springs: list[AnchoredSpring] = []
        self.planes: list[Plane] = []
        self.fixed_spheres: list[FixedSphere] = []
        self.materials: dict[str, Material] = {DEFAULT: Material()}
        self.spring_groups: dict[str, SpringGroup] = {}
        self.drags: list[Drag] = []
        self.drag_groups: dict[str, float] = {}          # group -> default c, N s/m
        self.plastic_springs: list[PlasticSpring] = []
        self.plastic_groups: dict[str, float] = {}       # group -> default yield strain
        #: width, in strain, of the smooth onset of plastic flow (static; 0 = hard yield)
        self.plastic_smoothing: float = 1e-3

    def snapshot(self) -> "Scene":
        """A copy of this scene that later edits of it do not reach: what
        :func:`diffpen.compile` keeps as ``Simulator.scene``, so that a body, spring or
        material added or changed after compiling cannot give ``sim.init_state()`` (or
        anything else read from the scene) a shape or value the compiled step was not built
        for. Its containers are new; the frozen elements in them are shared, the mutable
        ones (materials, spring groups, the overlap index) copied."""
        new = copy.copy(self)
        for name, value in vars(self).items():
            if isinstance(value, list):
                setattr(new, name, list(value))
            elif isinstance(value, dict):
                setattr(new, name, {k: copy.copy(v) for k, v in value.items()})
        ov = new._overlap = copy.copy(self._overlap)
        ov.cells = {cell: list(ids) for cell, ids in self._overlap.cells.items()}
        ov.big, ov.boxes = list(ov.big), list(ov.boxes)
        ov.allowed = set(ov.allowed)
        return new

    # ----------------------------------------------------------------- bodies
    def _add_body(self, kind, mass, radius, position, velocity, pinned, material, collide,
                  allow_overlap=False) -> int:
        mass = positive("mass (kg)", mass)
        radius = positive("radius (m)", radius, allow_zero=(kind == "particle"))
        position = vec3("position (m)", position)
        velocity = vec3("velocity (m/s)", velocity)
        if pinned and any(v != 0.0 for v in velocity):
            raise SceneError("a pinned body cannot have an initial velocity: drop velocity= "
                             "or pinned=True.")
        self._check_material(material)
        body = Body(kind, mass, radius, position, velocity, _flag("pinned", pinned), material,
                    _flag("collide", collide))
        if kind != "box":      # boxes are checked with their orientation (_make_rigid)
            self._overlap.check_body(self, body, len(self.bodies),
                                     allow=self._allowed(allow_overlap))
        self.bodies.append(body)
        return len(self.bodies) - 1

    def _allowed(self, allow_overlap) -> bool:
        if not isinstance(allow_overlap, (bool, np.bool_)):
            raise SceneError(f"allow_overlap must be True or False, got {allow_overlap!r}.")
        return bool(allow_overlap) or self.allow_overlap

    def add_particle(self, mass: float, position: Sequence[float],
                     velocity: Sequence[float] = (0.0, 0.0, 0.0), *, pinned: bool = False,
                     material: str = DEFAULT, collide: bool = True,
                     allow_overlap: bool = False) -> int:
        """Add a point mass. Returns its body index.

        Args:
          mass: kg, > 0.  position: (3,) m.  velocity: (3,) m/s.
          pinned: fixed in space (takes no force, never moves).
          material: contact material name (see :meth:`add_material`).
          collide: whether it touches planes and fixed spheres.
          allow_overlap: start it inside a collider or another body on purpose (otherwise an
            initial overlap deeper than 50% of the smaller size raises SceneError; see
            :mod:`diffpen.overlap`).
        """
        return self._add_body("particle", mass, 0.0, position, velocity, pinned, material,
                              collide, allow_overlap)

    def add_sphere(self, radius: float, mass: float, position: Sequence[float],
                   velocity: Sequence[float] = (0.0, 0.0, 0.0), *, pinned: bool = False,
                   material: str = DEFAULT, collide: bool = True,
                   allow_overlap: bool = False) -> int:
        """Add a sphere (translating point mass with a contact radius). Returns its index.

        Args:
          radius: m, > 0.  mass: kg, > 0.  position: (3,) centre, m.  velocity: (3,) m/s.
          pinned: fixed in space.  material: contact material name.
          collide: whether it touches planes, fixed spheres and other spheres.
          allow_overlap: start it overlapping a collider or another body on purpose.
        """
        return self._add_body("sphere", mass, radius, position, velocity, pinned, material,
                              collide, allow_overlap)

    # ----------------------------------------------------------------- colliders
    def add_plane(self, normal: Sequence[float] = (0.0, 0.0, 1.0), offset: float = 0.0, *,
                  material: str = DEFAULT, name: str | None = None,
                  allow_overlap: bool = False) -> int:
        """Add a fixed plane ``normal . p = offset``; the solid is on the side ``-normal``.

        Args:
          normal: (3,) outward normal (normalised here; must be non-zero).
          offset: m, signed distance of the plane from the origin along ``normal``.
          name: opt-in: a named plane's offset is a differentiable parameter,
            ``params.extra["plane_offset"][name]`` (m, any sign; default ``offset``), e.g. to
            fit where a measured ground really is. Unnamed planes keep a constant offset.
        Returns: the plane's index.
        """
        n, norm = unit_vector(vec3("plane normal", normal))
        if norm == 0.0:
            raise SceneError("plane normal must be non-zero, e.g. (0, 0, 1) for the ground.")
        offset = number("plane offset (m)", offset)
        self._check_material(material)
        if name is not None:
            if not isinstance(name, str) or not name:
                raise SceneError(f"plane name must be a non-empty string, got {name!r}.")
            if any(pl.name == name for pl in self.planes):
                raise SceneError(f"a plane named {name!r} exists already: names must differ.")
        plane = Plane(tuple(float(a) for a in n), offset, material, name)
        if not self._allowed(allow_overlap):
            self._overlap.check_collider(self, "plane", plane, len(self.planes))
        self.planes.append(plane)
        return len(self.planes) - 1

    def add_fixed_sphere(self, center: Sequence[float], radius: float, *,
                         material: str = DEFAULT, allow_overlap: bool = False) -> int:
        """Add a fixed spherical obstacle of ``radius`` (m) at ``center`` (m). Returns index."""
        center = vec3("fixed sphere center (m)", center)
        radius = positive("fixed sphere radius (m)", radius)
        self._check_material(material)
        fs = FixedSphere(center, radius, material)
        if not self._allowed(allow_overlap):
            self._overlap.check_collider(self, "fixed sphere", fs, len(self.fixed_spheres))
        self.fixed_spheres.append(fs)
        return len(self.fixed_spheres) - 1

    # ----------------------------------------------------------------- materials
    def add_material(self, name: str, k: float | None = None, c: float | None = None, *,
                     friction: float = 0.0, slip_speed: float = 0.01) -> str:
        """Declare a contact material with default stiffness ``k`` (N/m), damping ``c`` (N s/m).

        Contact parameters live per material in the params pytree. A body-collider contact
        uses the collider's material; a sphere-sphere contact uses the bodies' material when
        both share one, else ``"default"``.

        ``friction`` (Coulomb coefficient mu >= 0) > 0 adds smooth Coulomb friction to the
        contacts of box corners, spheres (rigid or not) and particles with planes of this
        material, and of spheres and particles with fixed spheres of it,
        ``-mu f_n v_t / sqrt(|v_t|^2 + slip_speed^2)`` (``slip_speed`` m/s > 0, static); mu is
        then ``params.extra["friction"][name]``. Contacts between spheres, with boxes and of
        box corners with fixed spheres stay frictionless.
        """
        if not isinstance(name, str) or not name:
            raise SceneError(f"material name must be a non-empty string, got {name!r}.")
        if k is not None:
            k = positive(f"material {name!r} k (N/m)", k, allow_zero=True)
        if c is not None:
            c = positive(f"material {name!r} c (N s/m)", c, allow_zero=True)
        friction = positive(f"material {name!r} friction", friction, allow_zero=True)
        slip_speed = positive(f"material {name!r} slip_speed (m/s)", slip_speed)
        new = Material(k, c, friction, slip_speed)
        old = self.materials.get(name)
        if old is not None and old != Material() and old != new:
            raise SceneError(f"material {name!r} is already declared as {old}: a second "
                             f"declaration ({new}) would change it for everything that uses "
                             "it. Declare each material once, or give this one another name.")
        self.materials[name] = new
        return name

    def _check_material(self, material: str) -> None:
        if material not in self.materials:
            raise SceneError(f"unknown material {material!r}: declare it first with "
                             f"scene.add_material({material!r}, k=..., c=...). Known: "
                             f"{sorted(self.materials)}.")

    # ----------------------------------------------------------------- springs
    def add_spring_group(self, name: str, k: float, c: float = 0.0) -> str:
        """Declare a spring group with stiffness ``k`` (N/m) and damping ``c`` (N s/m)."""
        if not isinstance(name, str) or not name:
            raise SceneError(f"spring group name must be a non-empty string, got {name!r}.")
        k = positive(f"spring group {name!r} k (N/m)", k, allow_zero=True)
        c = positive(f"spring group {name!r} c (N s/m)", c, allow_zero=True)
        new, old = SpringGroup(k, c), self.spring_groups.get(name)
        if old is not None and old != new:
            raise SceneError(f"spring group {name!r} is already declared with k = {old.k} N/m, "
                             f"c = {old.c} N s/m: a second declaration (k = {new.k}, c = "
                             f"{new.c}) would change every spring in it. Declare each group "
                             "once, or give this one another name.")
        self.spring_groups[name] = new
        return name

    @_all_or_nothing
    def add_spring(self, a: int, b, *, k: float | None = None, c: float | None = None,
                   rest_length: float | None = None, group: str = DEFAULT) -> int:
        """Join body ``a`` to body ``b`` (an index) or to a fixed world point (a 3-tuple).

        Force ``F = -k x - c v`` along the axis (``x = length - rest_length``), equal and
        opposite on the two ends. Stiffness and damping are per ``group``; giving ``k``/``c``
        for a new group declares it.

        Args:
          a: body index.  b: body index, or (3,) world anchor point in metres.
          k: N/m.  c: N s/m.
          rest_length: m, >= 0; default is the initial distance.
          group: spring group name (its k and c are one entry in the params pytree).
        Returns: the spring's index.
        """
        self._check_body_index(a, "spring end a")
        if isinstance(b, (int, np.integer)) and not isinstance(b, bool):
            self._check_body_index(b, "spring end b")
            if int(b) == int(a):
                raise SceneError(f"spring joins body {a} to itself: give two different bodies.")
            b_idx, anchor = int(b), None
            pb = self.bodies[b_idx].position
        else:
            b_idx, anchor = None, vec3("spring anchor point (m)", b)
            pb = anchor
        pa = self.bodies[int(a)].position
        if b_idx is not None and self.bodies[int(a)].pinned and self.bodies[b_idx].pinned:
            raise SceneError(f"spring joins two pinned bodies ({a}, {b}): it can never act; "
                             "remove it or unpin one end.")
        self._use_spring_group(group, k, c)
        if rest_length is None:
            rest_length = math.dist(pa, pb)
        rest_length = positive("spring rest_length (m)", rest_length, allow_zero=True)
        if (b_idx is not None and rest_length > 0.0 and tuple(pa) == tuple(pb)
                and tuple(self.bodies[int(a)].velocity) == tuple(self.bodies[b_idx].velocity)):
            # no refusal: another force (a contact, another spring) may part them first
            from .errors import warn
            warn(f"spring {len(self.springs)} joins bodies {a} and {b_idx}, which start at one "
                 "point with one velocity: it has no direction there, so it pushes them "
                 f"apart (to its rest length {rest_length:.4g} m) only once something else "
                 "moves one of them; start them apart if it should act from the start.",
                 UserWarning)
        self.springs.append(Spring(int(a), b_idx, anchor, rest_length, group))
        return len(self.springs) - 1

    # ----------------------------------------------------------------- drag
    @_all_or_nothing
    def add_drag(self, bodies, c: float | None = None, *, group: str = "drag") -> str:
        """Add a velocity drag ``F = -c v`` (v in m/s, world frame) on each of ``bodies``.

        The coefficient ``c`` (N s/m, >= 0) is one entry of the params pytree per ``group``:
        ``sim.params(extra={"drag": {group: c}})``; giving ``c`` for a new group declares its
        default. Scenes without drag trace no drag code. Pinned bodies are skipped.

        Args:
          bodies: a body index or a sequence of body indices.
          c: N s/m; required for a new group; must match the group's default otherwise.
          group: drag group name.
        Returns: the group name.
        """
        if not isinstance(group, str) or not group:
            raise SceneError(f"drag group name must be a non-empty string, got {group!r}.")
        idx = [bodies] if isinstance(bodies, (int, np.integer)) else list(np.ravel(bodies))
        if not idx:
            raise SceneError("add_drag got no bodies: give a body index or a list of them.")
        for i in idx:
            self._check_body_index(i, "drag body")
        if group not in self.drag_groups:
            if c is None:
                raise SceneError(f"drag group {group!r} is new: give c= (N s/m).")
            self.drag_groups[group] = positive(f"drag group {group!r} c (N s/m)", c,
                                                allow_zero=True)
        elif c is not None and positive("drag c (N s/m)", c,
                                        allow_zero=True) != self.drag_groups[group]:
            raise SceneError(f"drag group {group!r} already has c={self.drag_groups[group]}; "
                             f"got c={c}. Use another group name.")
        have = {(d.body, d.group) for d in self.drags}
        for i in idx:
            if (int(i), group) in have:
                raise SceneError(f"body {int(i)} already has drag of group {group!r}.")
            self.drags.append(Drag(int(i), group))
            have.add((int(i), group))
        return group

    # ----------------------------------------------------------------- plastic springs
    @_all_or_nothing
    def add_plastic_spring(self, a: int, b: int, *, k: float | None = None,
                           c: float | None = None, yield_strain: float | None = None,
                           rest_length: float | None = None, group: str = "plastic") -> int:
        """Join bodies ``a`` and ``b`` by a plastic (crumple) spring.

        It acts as a damped spring ``F = -k (l - L) - c dl/dt`` whose rest length ``L`` (m,
        kept in ``State.aux``) shortens irreversibly whenever the compression ``L - l`` exceeds
        ``yield_strain * L0`` (``L0`` the initial rest length); see :mod:`diffpen.terms.plastic`.
        ``k`` (N/m) and ``c`` (N s/m) are the spring group's (``params.springs[group]``), the
        yield strain is ``params.extra["plastic"][group]`` (dimensionless, in (0, 1)).

        Returns: the plastic spring's index.
        """
        self._check_body_index(a, "plastic spring end a")
        self._check_body_index(b, "plastic spring end b")
        a, b = int(a), int(b)
        if a == b:
            raise SceneError(f"plastic spring joins body {a} to itself: give two bodies.")
        if self.bodies[a].pinned and self.bodies[b].pinned:
            raise SceneError(f"plastic spring joins two pinned bodies ({a}, {b}): it can never "
                             "act; remove it or unpin one end.")
        if group not in self.plastic_groups:
            if yield_strain is None:
                raise SceneError(f"plastic group {group!r} is new: give yield_strain= (a "
                                 "fraction in (0, 1), e.g. 0.05).")
            ys = positive("yield_strain", yield_strain)
            if not (0.0 < ys < 1.0):
                raise SceneError(f"yield_strain must be in (0, 1) (compression at which the "
                                 f"spring starts to crumple, as a fraction of its rest length), "
                                 f"got {yield_strain!r}.")
            self.plastic_groups[group] = ys
        elif yield_strain is not None and positive(
                "yield_strain", yield_strain) != self.plastic_groups[group]:
            raise SceneError(f"plastic group {group!r} already has yield_strain="
                             f"{self.plastic_groups[group]}; got {yield_strain}. Use another "
                             "group name.")
        self._use_spring_group(group, k, c)
        if rest_length is None:
            rest_length = math.dist(self.bodies[a].position, self.bodies[b].position)
            if not rest_length > 0.0:   # it said "rest_length must be positive", not given
                raise SceneError(f"plastic spring {a}-{b}: bodies {a} and {b} start at the same "
                                 "point, so its rest length (their distance) would be 0 and "
                                 "its strain undefined: move them apart or give rest_length.")
        rest_length = positive("plastic spring rest_length (m)", rest_length)
        self.plastic_springs.append(PlasticSpring(a, b, rest_length, group))
        return len(self.plastic_springs) - 1

    # ----------------------------------------------------------------- rigid bodies
    def _make_rigid(self, i: int, orientation, angular_velocity, inertia, half_extents,
                    allow_overlap: bool = False) -> int:
        """Turn the just-added body ``i`` into a rigid body (removed again on bad input)."""
        body = self.bodies[i]
        try:
            q, norm = unit_vector(finite_vec("orientation (w, x, y, z)", orientation, 4))
            if norm == 0.0:         # any other finite one is normalised (1e-13 was "zero")
                raise SceneError("orientation quaternion is zero: give a rotation as "
                                 "(w, x, y, z), e.g. (1, 0, 0, 0) for none.")
            w = vec3("angular_velocity (rad/s)", angular_velocity)
            if body.pinned and any(v != 0.0 for v in w):
                raise SceneError("a pinned body cannot have an initial angular velocity: drop "
                                 "angular_velocity= or pinned=True.")
            if inertia is not None:
                inertia = tuple(positive("inertia (kg m^2)", v)
                                for v in finite_vec("inertia (kg m^2)", inertia, 3))
                big = max(inertia)
                if big > (sum(inertia) - big) * (1.0 + 1e-9):
                    raise SceneError(
                        f"inertia {inertia} kg m^2 cannot be a rigid body's principal "
                        "moments: each must be at most the sum of the other two (a thin "
                        "plate reaches equality). Check the values and their order (body "
                        "x, y, z axes).")
            rigid = dataclasses.replace(
                body, rigid=True, orientation=tuple(float(v) for v in q),
                angular_velocity=w, inertia=inertia, half_extents=half_extents)
            if body.kind == "box":
                self._overlap.check_body(self, rigid, i, allow=self._allowed(allow_overlap))
        except SceneError:
            self.bodies.pop()
            self._overlap.forget(i)
            raise
        self.bodies[i] = rigid
        return i

    def add_box(self, half_extents: Sequence[float], mass: float, position: Sequence[float],
                velocity: Sequence[float] = (0.0, 0.0, 0.0), *,
                orientation: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
                angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
                inertia: Sequence[float] | None = None, pinned: bool = False,
                material: str = DEFAULT, collide: bool = True,
                allow_overlap: bool = False) -> int:
        """Add a rigid box. Returns its body index.

        Args:
          half_extents: (3,) half side lengths along the body axes, m, each > 0.
          mass: kg, > 0.  position: (3,) centre, m.  velocity: (3,) m/s.
          orientation: quaternion (w, x, y, z), body to world; normalised here (a zero
            quaternion is rejected).
          angular_velocity: (3,) world frame, rad/s.
          inertia: (3,) body-frame principal moments, kg m^2; default the solid box's
            ``(m / 3) (hy^2 + hz^2)``, ... .
          pinned: fixed in space.  material: contact material name.
          collide: whether it touches planes, fixed spheres and spheres.
        Contacts: each corner against planes, spheres against the box (see
        :mod:`diffpen.rigid`); boxes do not collide with other boxes.
        """
        h = tuple(positive("box half_extents (m)", v)
                  for v in finite_vec("box half_extents (m)", half_extents, 3))
        i = self._add_body("box", mass, math.hypot(*h), position, velocity, pinned, material,
                           collide)
        return self._make_rigid(i, orientation, angular_velocity, inertia, h, allow_overlap)

    def add_rigid_sphere(self, radius: float, mass: float, position: Sequence[float],
                         velocity: Sequence[float] = (0.0, 0.0, 0.0), *,
                         orientation: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
                         angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
                         inertia: Sequence[float] | None = None, pinned: bool = False,
                         material: str = DEFAULT, collide: bool = True,
                         allow_overlap: bool = False) -> int:
        """Add a sphere that also rotates (orientation, angular velocity, inertia).

        Same arguments as :meth:`add_box`, with ``radius`` (m, > 0) for the half extents;
        default inertia ``(2/5) m r^2`` (solid sphere). It collides like :meth:`add_sphere`.
        """
        i = self._add_body("sphere", mass, radius, position, velocity, pinned, material,
                           collide, allow_overlap)
        return self._make_rigid(i, orientation, angular_velocity, inertia, None)

    @_all_or_nothing
    def add_anchored_spring(self, a: int, b, anchor_a: Sequence[float] = (0.0, 0.0, 0.0),
                            anchor_b: Sequence[float] = (0.0, 0.0, 0.0), *,
                            k: float | None = None, c: float | None = None,
                            rest_length: float | None = None, group: str = DEFAULT) -> int:
        """Join a point fixed in body ``a`` to a point fixed in body ``b`` (the paper's
        ``Spring_c``), or to a world point.

        The force ``F = -k x - c v`` acts along the anchor-to-anchor axis (``x`` = anchor
        distance - rest length, ``v`` its rate, including angular velocity x lever arm), at
        each body's own anchor, equal and opposite, so it also produces torques.

        Args:
          a: body index.  b: body index, or None to fix the second end at the world point
            ``anchor_b``.
          anchor_a: (3,) anchor in the body frame of ``a``, m (from its centre).
          anchor_b: (3,) anchor in the body frame of ``b``, m; the world point, m, if ``b``
            is None.
          k: N/m.  c: N s/m.  rest_length: m, >= 0; default the initial anchor distance.
          group: spring group name (groups are shared with :meth:`add_spring`).
        A non-zero anchor needs a rigid body (:meth:`add_box`, :meth:`add_rigid_sphere`).
        Returns: the anchored spring's index.
        """
        self._check_body_index(a, "anchored spring end a")
        anchor_a = vec3("anchor_a (m)", anchor_a)
        anchor_b = vec3("anchor_b (m)", anchor_b)
        ends = [(int(a), anchor_a, "a")]
        if b is not None:
            self._check_body_index(b, "anchored spring end b")
            if int(b) == int(a):
                raise SceneError(f"anchored spring joins body {a} to itself: give two "
                                 "different bodies.")
            if self.bodies[int(a)].pinned and self.bodies[int(b)].pinned:
                raise SceneError(f"anchored spring joins two pinned bodies ({a}, {b}): it "
                                 "can never act; remove it or unpin one end.")
            ends.append((int(b), anchor_b, "b"))
        for i, anchor, name in ends:
            body = self.bodies[i]
            if not body.rigid and any(v != 0.0 for v in anchor):
                raise SceneError(
                    f"anchor_{name}={anchor} is off the centre of body {i}, a {body.kind} "
                    "that does not rotate: off-centre anchors need a rigid body "
                    "(scene.add_box or scene.add_rigid_sphere), or use anchor (0, 0, 0).")
        self._use_spring_group(group, k, c)
        world = [self._anchor_world(i, anc) for i, anc, _ in ends]
        if b is None:
            world.append(np.asarray(anchor_b))
        if rest_length is None:
            rest_length = float(np.linalg.norm(world[0] - world[1]))
        rest_length = positive("spring rest_length (m)", rest_length, allow_zero=True)
        self.anchored_springs.append(AnchoredSpring(
            int(a), None if b is None else int(b), anchor_a, anchor_b, rest_length, group))
        return len(self.anchored_springs) - 1

    def _use_spring_group(self, group: str, k, c) -> None:
        """Declare spring ``group`` from ``k``/``c`` if new, else check they agree with it."""
        if group not in self.spring_groups:
            if k is None:
                raise SceneError(f"spring group {group!r} is new: give k= (N/m), or declare "
                                 f"it with scene.add_spring_group({group!r}, k=..., c=...).")
            self.add_spring_group(group, k, 0.0 if c is None else c)
            return
        g = self.spring_groups[group]
        for name, given, have in (("k", k, g.k), ("c", c, g.c)):
            if given is not None and positive(f"spring {name}", given, allow_zero=True) != have:
                raise SceneError(
                    f"spring group {group!r} already has {name}={have}; got {name}={given}. "
                    "Stiffness and damping are per group: use another group name.")

    def _anchor_world(self, i: int, anchor) -> np.ndarray:
        """World position (m) of body ``i``'s body-frame ``anchor`` at its initial pose."""
        body = self.bodies[i]
        w, x, y, z = body.orientation
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        return np.asarray(body.position) + r @ np.asarray(anchor)

    @property
    def has_rotation(self) -> bool:
        """True when some body is rigid (the compiled state then carries orientations)."""
        return any(b.rigid for b in self.bodies)

    def _check_body_index(self, i, what: str) -> None:
        if not isinstance(i, (int, np.integer)) or isinstance(i, bool):
            raise SceneError(f"{what} must be a body index (int), got {i!r}.")
        if not 0 <= int(i) < len(self.bodies):
            raise SceneError(f"{what} names body {i}, but the scene has {len(self.bodies)} "
                             f"bodies (indices 0..{len(self.bodies) - 1}). Add the body first.")

    # ----------------------------------------------------------------- queries
    @property
    def n_bodies(self) -> int:
        return len(self.bodies)

    def __repr__(self) -> str:
        return (f"Scene(bodies={len(self.bodies)}, springs={len(self.springs)}, "
                f"planes={len(self.planes)}, fixed_spheres={len(self.fixed_spheres)}, "
                f"gravity={self.gravity})")
