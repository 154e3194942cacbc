"""Soft-body builders: helpers that add ropes, cloths, jelly lattices, crumple bars and the
workshop paper's ball-spring chain to a :class:`diffpen.Scene`.

Every node is a particle (a point mass, radius 0) that collides with the scene's planes and
fixed spheres (``collide=True``); there is no self-collision. Springs are ordinary scene
springs (or plastic springs for :func:`add_crumple_bar`) in named spring groups, so their
stiffness ``k`` (N/m) and damping ``c`` (N s/m) are entries of the params pytree::

    nodes = add_cloth(scene, 10, 10, spacing=0.05, mass=0.2, structural=(200.0, 0.1))
    sim = dp.compile(scene, dt=1e-3)
    params = sim.params(k=1e4, c=10.0, springs={"cloth.structural": (400.0, 0.1)})

Springs whose two ends are both pinned are left out (they could never act). Rest lengths are
the initial distances. Each builder validates its input before adding anything and raises
:class:`diffpen.SceneError` saying what to change. Units: SI.
"""
from __future__ import annotations

import itertools
import math
from typing import Iterable, Sequence

import numpy as np

from .elements import finite_vec
from .errors import SceneError
from .scene import Scene, _all_or_nothing

__all__ = [
    "add_rope", "add_cloth", "add_jelly", "add_crumple_bar", "paper_chain",
    "paper_chain_equilibrium", "PAPER_CHAIN",
]

#: The workshop paper's chain constants (the demo's ``MASS``, ``KS``, ``KD``, gravity and
#: ``DT``), its end points in metres (screen x -> x, screen y -> -z) and the ball count.
PAPER_CHAIN = dict(n_balls=7, mass=10.0, ks=50.0, kd=1.0, g=9.8, dt=0.1,
                   first=(100.0, 0.0, 100.0), last=(500.0, 0.0, 100.0))


# --------------------------------------------------------------------------- validation
def _count(name: str, value, minimum: int = 2) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise SceneError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    return int(value)


def _pos(name: str, value) -> float:
    if isinstance(value, (str, bytes, bool, np.bool_)):     # numbers only, never coerced
        raise SceneError(f"{name} must be a number, got {value!r}"
                         + (": write it without quotes." if isinstance(value, str) else "."))
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{name} must be a number, got {value!r}.") from None
    if not (math.isfinite(v) and v > 0.0):
        raise SceneError(f"{name} must be a positive, finite number, got {value!r}.")
    return v


def _nonneg(name: str, value) -> float:
    """A finite number >= 0 (0 allowed, e.g. no drag or no gravity)."""
    if isinstance(value, (int, float, np.integer, np.floating)) and value == 0 \
            and not isinstance(value, (bool, np.bool_)):
        return 0.0
    return _pos(name, value)


def _vec(name: str, value) -> np.ndarray:
    return finite_vec(name, value, 3, "3 numbers (x, y, z)")


def _kc(name: str, value) -> tuple[float, float] | None:
    """A spring group's ``(k, c)``: a pair, a bare k (c = 0) or None (group left out)."""
    if value is None:
        return None
    if isinstance(value, (int, float, np.floating, np.integer)):
        value = (value, 0.0)
    try:
        if isinstance(value, (str, bytes)) or any(
                isinstance(v, (str, bytes, bool, np.bool_)) for v in value):
            raise ValueError                        # numbers only, never coerced
        k, c = (float(v) for v in value)
    except (TypeError, ValueError):
        raise SceneError(f"{name} must be (k, c) in (N/m, N s/m), a bare k, or None to leave "
                         f"the springs out; got {value!r}.") from None
    if not (math.isfinite(k) and k >= 0.0 and math.isfinite(c) and c >= 0.0):
        raise SceneError(f"{name} = (k, c) must be finite and >= 0, got {value!r}.")
    return k, c


def _pins(name: str, pinned, shape: tuple[int, ...]) -> set[tuple[int, ...]]:
    """Grid coordinates of pinned nodes; negative indices count from the end. ``pinned``: a
    collection of node indices (integers for a 1-D builder, index tuples for a grid), one
    integer for a 1-D builder's single node, or None for none."""
    if pinned is None:
        pinned = ()
    elif isinstance(pinned, (int, np.integer)) and not isinstance(pinned, (bool, np.bool_)) \
            and len(shape) == 1:
        pinned = (pinned,)          # pinned=0 pinned no node at all ("0 or ()" is ())
    try:
        items = list(pinned)
    except TypeError:
        raise SceneError(f"{name}: pinned must be a list of node indices (e.g. [0] or [] for "
                         f"none), got {pinned!r}.") from None
    out = set()
    for p in items:
        try:
            q = (p,) if np.ndim(p) == 0 else tuple(p)
        except TypeError:
            q = (p,)
        if len(q) != len(shape) or not all(isinstance(v, (int, np.integer))
                                           and not isinstance(v, (bool, np.bool_)) for v in q):
            raise SceneError(f"{name}: each pinned node must be {len(shape)} integer grid "
                             f"index(es) for a grid of shape {shape}, got {p!r}.")
        if not all(-s <= v < s for v, s in zip(q, shape)):
            raise SceneError(f"{name}: pinned node {p!r} is outside the grid of shape {shape}; "
                             f"indices run from 0 to {tuple(s - 1 for s in shape)} (or "
                             "negative, from the end).")
        out.add(tuple(int(v) % s for v, s in zip(q, shape)))
    return out


def _check_new_groups(scene: Scene, names: Iterable[str], group) -> None:
    """Refuse ``group`` (the builder's prefix) unless a non-empty string (None made groups
    named "None.stretch"), and any of ``names`` the scene already has."""
    if not (isinstance(group, str) and group):
        raise SceneError(f"group must be a non-empty string (the prefix of the builder's "
                         f"spring groups), got {group!r}.")
    for g in names:
        if g in scene.spring_groups or g in scene.drag_groups:
            raise SceneError(f"group {g!r} already exists in this scene: pass another "
                             "group= prefix to the builder.")


# --------------------------------------------------------------------------- assembly
def _lattice(scene: Scene, positions: np.ndarray, node_mass: float, pins: set, velocity,
             collide: bool) -> np.ndarray:
    """Add one particle per grid point of ``positions`` (*shape, 3); returns indices (*shape)."""
    shape = positions.shape[:-1]
    idx = np.empty(shape, dtype=np.int64)
    for p in itertools.product(*(range(s) for s in shape)):
        pinned = p in pins
        idx[p] = scene.add_particle(node_mass, positions[p],
                                    (0.0, 0.0, 0.0) if pinned else velocity,
                                    pinned=pinned, collide=collide)
    return idx


def _pairs(idx: np.ndarray, offsets: Sequence[tuple[int, ...]]) -> list[tuple[int, int]]:
    """Index pairs (p, p + offset) of a grid of node indices, for every offset that fits."""
    shape = idx.shape
    out = []
    for off in offsets:
        for p in itertools.product(*(range(s) for s in shape)):
            q = tuple(a + o for a, o in zip(p, off))
            if all(0 <= v < s for v, s in zip(q, shape)):
                out.append((int(idx[p]), int(idx[q])))
    return out


def _connect(scene: Scene, pairs, group: str, kc) -> int:
    """Add springs for ``pairs`` in a new group ``(k, c)``, skipping pinned-pinned pairs."""
    live = [(a, b) for a, b in pairs
            if not (scene.bodies[a].pinned and scene.bodies[b].pinned)]
    if not live:
        return 0
    scene.add_spring_group(group, *kc)
    for a, b in live:
        scene.add_spring(a, b, group=group)
    return len(live)


def _drag(scene: Scene, idx: np.ndarray, group: str, c) -> None:
    if c is None:
        return
    free = [int(i) for i in idx.ravel() if not scene.bodies[int(i)].pinned]
    if free:
        scene.add_drag(free, c=c, group=group)


# --------------------------------------------------------------------------- rope
@_all_or_nothing
def add_rope(scene: Scene, n: int, start: Sequence[float], end: Sequence[float], mass: float,
             k: float, c: float = 0.0, *, pinned: Iterable[int] = (0,),
             bend: tuple[float, float] | float | None = None, drag: float | None = None,
             velocity: Sequence[float] = (0.0, 0.0, 0.0), collide: bool = True,
             group: str = "rope") -> np.ndarray:
    """Add a rope (or chain) of ``n`` nodes evenly spaced on the segment ``start`` -> ``end``.

    Neighbours are joined by springs of group ``f"{group}.stretch"`` (``k`` N/m, ``c`` N s/m);
    with ``bend=(k, c)`` also every second node (group ``f"{group}.bend"``).

    Args:
      scene: the scene to add to.  n: number of nodes, >= 2.
      start, end: (3,) end points, m (distinct).  mass: total mass, kg (split equally).
      k: stretch stiffness, N/m.  c: stretch damping, N s/m.
      pinned: node indices (0..n-1, negative from the end) fixed in space; default the first.
      bend: ``(k, c)`` of the bend springs, or None.  drag: velocity drag c (N s/m) on each
        free node (group ``f"{group}.drag"``), or None.
      velocity: (3,) initial velocity of the free nodes, m/s.  collide: nodes touch planes and
        fixed spheres.  group: prefix of the spring/drag group names.
    Returns:
      (n,) int array of body indices, from ``start`` to ``end``.
    """
    n = _count("rope node count n", n)
    p0, p1 = _vec("rope start (m)", start), _vec("rope end (m)", end)
    if np.linalg.norm(p1 - p0) == 0.0:
        raise SceneError("rope start and end coincide: give two different points.")
    mass = _pos("rope mass (kg)", mass)
    stretch = _kc("rope (k, c)", (k, c))
    bend = _kc("rope bend", bend)
    if bend is not None and n < 3:      # it was left out without a word
        raise SceneError(f"rope bend springs join every second node, and a rope of {n} nodes "
                         "has none: leave bend out, or give n >= 3.")
    pins = _pins("rope pinned", pinned, (n,))
    velocity = _vec("rope velocity (m/s)", velocity)
    _check_new_groups(scene, [f"{group}.stretch", f"{group}.bend", f"{group}.drag"], group)
    t = np.linspace(0.0, 1.0, n)[:, None]
    idx = _lattice(scene, p0 + t * (p1 - p0), mass / n, pins, velocity, collide)
    _connect(scene, _pairs(idx, [(1,)]), f"{group}.stretch", stretch)
    if bend is not None:
        _connect(scene, _pairs(idx, [(2,)]), f"{group}.bend", bend)
    _drag(scene, idx, f"{group}.drag", drag)
    return idx


# --------------------------------------------------------------------------- cloth
@_all_or_nothing
def add_cloth(scene: Scene, nx: int, ny: int, spacing: float, mass: float, *,
              origin: Sequence[float] = (0.0, 0.0, 0.0),
              axes: tuple[Sequence[float], Sequence[float]] = ((1.0, 0.0, 0.0),
                                                                (0.0, 1.0, 0.0)),
              structural: tuple[float, float] | float = (100.0, 0.1),
              shear: tuple[float, float] | float | None = (50.0, 0.05),
              bend: tuple[float, float] | float | None = (10.0, 0.01),
              pinned: Iterable[tuple[int, int]] = (), drag: float | None = None,
              velocity: Sequence[float] = (0.0, 0.0, 0.0), collide: bool = True,
              group: str = "cloth") -> np.ndarray:
    """Add a rectangular cloth: an ``nx`` x ``ny`` grid of particles.

    Node ``(i, j)`` starts at ``origin + spacing * (i * axes[0] + j * axes[1])`` (axes are
    normalised; default: the cloth lies flat in a horizontal plane). Three spring groups, each
    one entry ``(k, c)`` of ``params.springs``:

    * ``f"{group}.structural"``: (i, j)-(i+1, j) and (i, j)-(i, j+1)  (rest ``spacing``);
    * ``f"{group}.shear"``: both diagonals of every cell  (rest ``sqrt(2) spacing``);
    * ``f"{group}.bend"``: (i, j)-(i+2, j) and (i, j)-(i, j+2)  (rest ``2 spacing``; a
      cloth of 2 x 2 nodes has none, and then no bend group in ``params.springs``).

    Args:
      nx, ny: nodes along ``axes[0]`` and ``axes[1]``, each >= 2.  spacing: m, > 0.
      mass: total mass, kg (split equally over the nodes).
      origin: (3,) position of node (0, 0), m.  axes: two orthogonal (3,) directions.
      structural, shear, bend: ``(k, c)`` in (N/m, N s/m), a bare k, or None (group left out;
        structural is required).
      pinned: grid coordinates ``(i, j)`` of nodes fixed in space (negative from the end).
      drag: velocity drag c (N s/m) on each free node (group ``f"{group}.drag"``), or None.
      velocity: (3,) initial velocity of the free nodes, m/s.
      collide: nodes touch planes and fixed spheres.  group: prefix of the group names.
    Returns:
      (nx, ny) int array of body indices; ``nodes[i, j]`` is node (i, j).
    """
    nx, ny = _count("cloth nx", nx), _count("cloth ny", ny)
    spacing = _pos("cloth spacing (m)", spacing)
    mass = _pos("cloth mass (kg)", mass)
    o = _vec("cloth origin (m)", origin)
    try:
        u, v = (_vec("cloth axis", a) for a in axes)
    except ValueError:
        raise SceneError("cloth axes must be two (3,) directions.") from None
    nu, nv = np.linalg.norm(u), np.linalg.norm(v)
    if nu == 0.0 or nv == 0.0 or abs(np.dot(u, v)) > 1e-9 * nu * nv:
        raise SceneError(f"cloth axes must be two non-zero orthogonal directions, got {axes!r}.")
    u, v = u / nu, v / nv
    kcs = {"structural": _kc("cloth structural", structural),
           "shear": _kc("cloth shear", shear), "bend": _kc("cloth bend", bend)}
    if kcs["structural"] is None:
        raise SceneError("cloth structural springs are required: give structural=(k, c).")
    pins = _pins("cloth pinned", pinned, (nx, ny))
    velocity = _vec("cloth velocity (m/s)", velocity)
    _check_new_groups(scene, [f"{group}.{g}" for g in (*kcs, "drag")], group)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    pos = o + spacing * (i[..., None] * u + j[..., None] * v)
    idx = _lattice(scene, pos, mass / (nx * ny), pins, velocity, collide)
    offsets = {"structural": [(1, 0), (0, 1)], "shear": [(1, 1), (1, -1)],
               "bend": [(2, 0), (0, 2)]}
    for name, kc in kcs.items():
        if kc is not None:
            _connect(scene, _pairs(idx, offsets[name]), f"{group}.{name}", kc)
    _drag(scene, idx, f"{group}.drag", drag)
    return idx


# --------------------------------------------------------------------------- jelly
@_all_or_nothing
def add_jelly(scene: Scene, nx: int, ny: int, nz: int, spacing: float, mass: float, *,
              origin: Sequence[float] = (0.0, 0.0, 0.0),
              edge: tuple[float, float] | float = (500.0, 0.5),
              face: tuple[float, float] | float | None = (300.0, 0.3),
              body: tuple[float, float] | float | None = (200.0, 0.2),
              pinned: Iterable[tuple[int, int, int]] = (), drag: float | None = None,
              velocity: Sequence[float] = (0.0, 0.0, 0.0), collide: bool = True,
              group: str = "jelly") -> np.ndarray:
    """Add a jelly block: an ``nx`` x ``ny`` x ``nz`` lattice of particles, axis-aligned.

    Node ``(i, j, l)`` starts at ``origin + spacing * (i, j, l)``. Spring groups (each one
    ``(k, c)`` entry of ``params.springs``):

    * ``f"{group}.edge"``: lattice edges along x, y, z  (rest ``spacing``);
    * ``f"{group}.face"``: both diagonals of every cell face  (rest ``sqrt(2) spacing``);
    * ``f"{group}.body"``: the four body diagonals of every cell  (rest ``sqrt(3) spacing``).

    Args:
      nx, ny, nz: nodes along x, y, z, each >= 2.  spacing: m, > 0.
      mass: total mass, kg (split equally).  origin: (3,) node (0, 0, 0), m.
      edge, face, body: ``(k, c)`` in (N/m, N s/m), a bare k, or None (left out; edge is
        required).
      pinned: lattice coordinates ``(i, j, l)`` fixed in space.
      drag: velocity drag c (N s/m) on each free node, or None.
      velocity: (3,) initial velocity of the free nodes, m/s.
      collide: nodes touch planes and fixed spheres.  group: prefix of the group names.
    Returns:
      (nx, ny, nz) int array of body indices; ``nodes[i, j, l]`` is node (i, j, l).
    """
    nx, ny, nz = (_count(f"jelly {a}", v) for a, v in (("nx", nx), ("ny", ny), ("nz", nz)))
    spacing = _pos("jelly spacing (m)", spacing)
    mass = _pos("jelly mass (kg)", mass)
    o = _vec("jelly origin (m)", origin)
    kcs = {"edge": _kc("jelly edge", edge), "face": _kc("jelly face", face),
           "body": _kc("jelly body", body)}
    if kcs["edge"] is None:
        raise SceneError("jelly edge springs are required: give edge=(k, c).")
    pins = _pins("jelly pinned", pinned, (nx, ny, nz))
    velocity = _vec("jelly velocity (m/s)", velocity)
    _check_new_groups(scene, [f"{group}.{g}" for g in (*kcs, "drag")], group)
    grid = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"),
                    axis=-1)
    idx = _lattice(scene, o + spacing * grid, mass / (nx * ny * nz), pins, velocity, collide)
    offsets = {"edge": [(1, 0, 0), (0, 1, 0), (0, 0, 1)],
               "face": [(1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1)],
               "body": [(1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1)]}
    for name, kc in kcs.items():
        if kc is not None:
            _connect(scene, _pairs(idx, offsets[name]), f"{group}.{name}", kc)
    _drag(scene, idx, f"{group}.drag", drag)
    return idx


# --------------------------------------------------------------------------- crumple bar
@_all_or_nothing
def add_crumple_bar(scene: Scene, n: int, start: Sequence[float], end: Sequence[float],
                    mass: float, k: float, c: float = 0.0, *, yield_strain: float = 0.05,
                    width: float | None = None, pinned: Iterable[int] = (),
                    drag: float | None = None, velocity: Sequence[float] = (0.0, 0.0, 0.0),
                    collide: bool = True, group: str = "bar") -> np.ndarray:
    """Add a crumple bar: ``n`` stations from ``start`` to ``end`` joined by plastic springs.

    With ``width=None`` it is a 1D bar (n nodes, n - 1 plastic springs along it). With a
    ``width`` (m) it is a planar truss "ladder": two rails offset by +-width/2 along the
    direction ``(0, 0, 1) x axis`` (or ``(0, 1, 0) x axis`` for a vertical bar), rungs and both
    diagonals of every cell, every member plastic; nodes[:, 0] and nodes[:, 1] are the rails.

    All members are in group ``group`` (``params.springs[group]`` = (k, c); yield strain
    ``params.extra["plastic"][group]``, in (0, 1)): a member compressed by more than
    ``yield_strain`` times its initial length shortens for good (see :mod:`diffpen.terms.plastic`).

    Args:
      n: stations, >= 2.  start, end: (3,) m.  mass: total kg.  k: N/m.  c: N s/m.
      yield_strain: in (0, 1).  width: truss width, m (> 0), or None for a 1D bar.
      pinned: station indices fixed in space (both rails of a truss).
      drag: velocity drag c (N s/m) on each free node, or None.  velocity: (3,) m/s.
    Returns:
      (n,) body indices for a bar, (n, 2) for a truss.
    """
    n = _count("crumple bar station count n", n)
    p0, p1 = _vec("bar start (m)", start), _vec("bar end (m)", end)
    axis = p1 - p0
    if np.linalg.norm(axis) == 0.0:
        raise SceneError("bar start and end coincide: give two different points.")
    mass = _pos("bar mass (kg)", mass)
    k, c = _kc("bar (k, c)", (k, c))
    try:
        if isinstance(yield_strain, (str, bytes, bool, np.bool_)):
            raise ValueError                        # numbers only, never coerced
        ys = float(yield_strain)
    except (TypeError, ValueError):
        ys = float("nan")
    if not (0.0 < ys < 1.0):
        raise SceneError(f"bar yield_strain must be in (0, 1) (compression at which members "
                         f"start to crumple, as a fraction of their length), got "
                         f"{yield_strain!r}.")
    pin_st = {p[0] for p in _pins("bar pinned", pinned, (n,))}
    velocity = _vec("bar velocity (m/s)", velocity)
    _check_new_groups(scene, [group, f"{group}.drag"], group)
    if group in scene.plastic_groups:
        raise SceneError(f"plastic group {group!r} already exists: pass another group=.")
    t = np.linspace(0.0, 1.0, n)[:, None]
    line = p0 + t * axis
    if width is None:
        idx = _lattice(scene, line, mass / n, {(s,) for s in pin_st}, velocity, collide)
        pairs = _pairs(idx, [(1,)])
    else:
        width = _pos("bar width (m)", width)
        a = axis / np.linalg.norm(axis)
        side = np.cross((0.0, 0.0, 1.0), a)
        if np.linalg.norm(side) < 1e-9:
            side = np.cross((0.0, 1.0, 0.0), a)
        side = side / np.linalg.norm(side)
        pos = np.stack([line - 0.5 * width * side, line + 0.5 * width * side], axis=1)
        pins = {(s, r) for s in pin_st for r in (0, 1)}
        idx = _lattice(scene, pos, mass / (2 * n), pins, velocity, collide)
        pairs = _pairs(idx, [(1, 0), (0, 1), (1, 1), (1, -1)])
    live = [(a, b) for a, b in pairs if not (scene.bodies[a].pinned and scene.bodies[b].pinned)]
    for a, b in live:
        scene.add_plastic_spring(a, b, k=k, c=c, yield_strain=ys, group=group)
    _drag(scene, idx, f"{group}.drag", drag)
    return idx


# --------------------------------------------------------------------------- paper chain
def paper_chain(*, seed: int = 0, spread: float = 80.0, n_balls: int = 7, mass: float = 10.0,
                ks: float = 50.0, kd: float = 1.0, g: float = 9.8,
                first: Sequence[float] = (100.0, 0.0, 100.0),
                last: Sequence[float] = (500.0, 0.0, 100.0)) -> tuple[Scene, np.ndarray]:
    """The workshop paper's ball-spring chain demo, with its constants and correct signs.

    ``n_balls`` balls of ``mass`` (paper: 7 x MASS=10); the first is fixed at ``first`` and
    the last at ``last`` (paper's screen (x, y) -> (x, -z): (100, 0, 100) and (500, 0, 100));
    neighbours are joined by zero-rest-length springs ``F = -KS (x_i - x_j)`` (KS=50) pulling
    each ball TOWARDS its neighbours (the paper's listing has the sign reversed); each free
    ball feels a drag ``F = -KD v`` (KD=1) on its own velocity, as in the listing (scene drag
    group ``"chain.drag"``); gravity ``g = 9.8`` along -z. The free balls start at seeded
    scattered positions: x uniform on the span, z = first z + uniform(-spread, spread), y = 0.
    Units are the paper's (screen units as metres).

    Time step: the paper's DT = 0.1 s (``PAPER_CHAIN["dt"]``) with semi-implicit Euler is
    stable. One spring on one ball gives w = sqrt(KS / m) = sqrt(5) = 2.24 rad/s, w h = 0.22;
    the chain's stiffest mode (free balls, stiffness KS tridiag(-1, 2, -1)) has
    w_max = sqrt(KS (2 + sqrt 3) / m) = 4.32 rad/s (Gershgorin bound sqrt(2 * 2 KS / m) = 4.47),
    w_max h = 0.43 < 2, and with the drag k h^2 + 2 c h = 1.87 + 0.2 = 2.07 < 4 m = 40. Every
    mode decays like exp(-KD t / (2 m)) (time constant 20 s), so after 2000 steps (200 s) the
    start transient has shrunk by exp(-10) ~ 4.5e-5 and the balls sit at the static
    equilibrium (:func:`paper_chain_equilibrium`), which semi-implicit Euler keeps exactly.

    Args:
      seed: seed of the scattered start positions (numpy default_rng).  spread: z scatter, m.
      n_balls: >= 3.  mass: kg per ball.  ks: N/m.  kd: drag, N s/m.  g: m/s^2.
      first, last: (3,) fixed end balls, m.
    Returns:
      ``(scene, balls)``: the scene and the (n_balls,) body indices, first to last.
    """
    n_balls = _count("paper chain n_balls", n_balls, 3)
    mass, ks = _pos("chain mass (kg)", mass), _pos("chain KS (N/m)", ks)
    kd = _nonneg("chain KD (N s/m)", kd)
    g = _nonneg("chain g (m/s^2, along -z)", g)
    p0, p1 = _vec("chain first (m)", first), _vec("chain last (m)", last)
    if seed is not None and (isinstance(seed, (bool, np.bool_))
                             or not isinstance(seed, (int, np.integer))):
        raise SceneError(f"paper chain seed must be an integer (or None), got {seed!r}.")
    spread = 0.0 if spread == 0 and not isinstance(spread, (str, bytes, bool)) else _pos(
        "paper chain spread (m, the z scatter of the start positions; 0 for none)", spread)
    rng = np.random.default_rng(seed)
    scene = Scene(gravity=(0.0, 0.0, -g))
    balls = [scene.add_particle(mass, p0, pinned=True, collide=False)]
    for _ in range(n_balls - 2):
        x = rng.uniform(min(p0[0], p1[0]), max(p0[0], p1[0]))
        z = p0[2] + rng.uniform(-spread, spread)
        balls.append(scene.add_particle(mass, (x, 0.0, z), collide=False))
    balls.append(scene.add_particle(mass, p1, pinned=True, collide=False))
    scene.add_spring_group("chain.spring", ks, 0.0)
    for a, b in zip(balls[:-1], balls[1:]):
        scene.add_spring(a, b, rest_length=0.0, group="chain.spring")
    scene.add_drag(balls[1:-1], c=kd, group="chain.drag")
    return scene, np.array(balls)


def paper_chain_equilibrium(*, n_balls: int = 7, mass: float = 10.0, ks: float = 50.0,
                            g: float = 9.8, first: Sequence[float] = (100.0, 0.0, 100.0),
                            last: Sequence[float] = (500.0, 0.0, 100.0)) -> np.ndarray:
    """Static equilibrium of :func:`paper_chain`, solved directly as a linear system.

    Free ball i (1..n-2) balances ``KS (x_{i-1} - 2 x_i + x_{i+1}) + m g = 0`` (zero rest
    length makes it linear); ``K x = b`` is solved with ``numpy.linalg.solve``.

    Returns: (n_balls, 3) positions, m, including the two fixed ends.
    """
    n = _count("paper chain n_balls", n_balls, 3)
    mass, ks = _pos("chain mass (kg)", mass), _pos("chain KS (N/m)", ks)
    g = _nonneg("chain g (m/s^2, along -z)", g)
    p0, p1 = _vec("chain first (m)", first), _vec("chain last (m)", last)
    m = n - 2
    K = ks * (2.0 * np.eye(m) - np.eye(m, k=1) - np.eye(m, k=-1))
    b = np.tile(np.array([0.0, 0.0, -mass * g]), (m, 1))
    b[0] += ks * p0
    b[-1] += ks * p1
    return np.vstack([p0, np.linalg.solve(K, b), p1])
