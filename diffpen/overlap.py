"""Initial-overlap checks of a :class:`diffpen.Scene`: bodies must not start inside a plane, a
fixed sphere, a box or each other (a penalty contact that starts deep releases its stored
energy in one step, or never separates when the centres coincide).

The check is exact for every pair the compiled simulator would evaluate (sphere-sphere,
sphere/particle-box, body-plane, body-fixed-sphere, box corner-plane) and cheap for many
bodies: spheres and particles sit in a uniform hash grid, so adding a body looks only at its
neighbour cells (O(1) per body for spheres of similar size, no O(n^2) Python loop); planes
and fixed spheres are tested against all bodies at once with numpy.

An overlap deeper than ``OVERLAP_TOL`` (one half) times the smaller radius (or half extent) is
refused: the body starts inside the other one (a particle: any overlap); resting contact (a
penetration of ``m g / k``) and slightly compressed starts pass. ``allow_overlap=True`` (per body, or for the whole scene) starts
bodies compressed on purpose; two spheres at exactly one centre are refused even then (their
contact has no direction: nothing would ever push them apart).
"""
from __future__ import annotations

import numpy as np

from .errors import SceneError
from .geometry import box_corners as geometry_box_corners
from .geometry import quat_to_matrix

__all__ = ["OVERLAP_TOL", "OverlapIndex", "quat_matrix", "box_corners"]

#: deepest initial overlap accepted, as a fraction of the smaller radius / half extent: a
#: body overlapping by more than half its size starts INSIDE the other (for a particle, any
#: overlap); resting and slightly compressed starts pass
OVERLAP_TOL = 0.5
#: relative slack on the limit (a body placed exactly at it passes despite rounding)
_SLACK = 1e-9
#: more cells than this for one body: it goes to the short list checked against everything
_MAX_CELLS = 512


def quat_matrix(q) -> np.ndarray:
    """(3, 3) rotation of the unit quaternion ``q = (w, x, y, z)`` (body to world), on the
    host (:func:`diffpen.geometry.quat_to_matrix` with numpy)."""
    return quat_to_matrix(np.asarray(q, dtype=float), xp=np)


def box_corners(body) -> np.ndarray:
    """(8, 3) world corners of a box body at its initial pose, m."""
    return (np.asarray(body.position)
            + geometry_box_corners(body.half_extents) @ quat_matrix(body.orientation).T)


def _corner_depths(box, plane) -> tuple[np.ndarray, np.ndarray]:
    """``(depths (8,) m, corners (8, 3) m)`` of a box's corners below a plane at the box's
    pose (positive: under the surface)."""
    corners = box_corners(box)
    return plane.offset - corners @ np.asarray(plane.normal), corners


def _sphere_box_depth(xs, rs, box) -> np.ndarray:
    """Depths (m) of spheres ``xs`` (m, (m, 3)) with radii ``rs`` (m,) against one box."""
    rot = quat_matrix(box.orientation)
    half = np.asarray(box.half_extents)
    local = (np.asarray(xs) - np.asarray(box.position)) @ rot
    closest = np.clip(local, -half, half)
    dist = np.linalg.norm(local - closest, axis=-1)
    inside = dist <= 0.0
    return np.where(inside, rs + np.min(half - np.abs(local), axis=-1), rs - dist)


def _box_fixed_sphere(box, i: int, fs, j: int, started: bool = False) -> None:
    """Refuse box ``i`` (at its pose in ``box``) deep inside fixed sphere ``j`` (the pair the
    simulator evaluates as a sphere against the box), with the move that makes them touch."""
    center = np.asarray(fs.center, dtype=float)
    d = float(_sphere_box_depth(center[None], np.array([fs.radius]), box)[0])
    tol = OVERLAP_TOL * min(fs.radius, min(box.half_extents))
    if not _over(d, tol):
        return
    rot = quat_matrix(box.orientation)
    half = np.asarray(box.half_extents)
    local = (center - np.asarray(box.position)) @ rot
    delta = local - np.clip(local, -half, half)
    if np.linalg.norm(delta) > 0.0:             # centre outside the box: along the gap
        n = delta / np.linalg.norm(delta)
    else:                                       # inside: through the shallowest face
        a = int(np.argmin(half - np.abs(local)))
        n = np.zeros(3)
        n[a] = 1.0 if local[a] >= 0.0 else -1.0
    away = 0.0 - rot @ n                        # from the sphere's centre to the box
    where = "started at" if started else "at"
    _refuse(f"box {i} {where} {_fmt(box.position)} (half extents {_fmt(half)}) and fixed "
            f"sphere {j} (center {_fmt(center)}, radius {fs.radius:.4g} m)", d, tol,
            f"it starts inside fixed sphere {j}: move {'its start' if started else 'it'} "
            f"{d:.4g} m along {_fmt(away)} to touch the sphere's surface")


def _fmt(v) -> str:
    return "(" + ", ".join(f"{float(a):.4g}" for a in v) + ")"


def _over(depth, tol):
    """depth (m) beyond the limit tol (m), with a rounding slack."""
    return depth > tol * (1.0 + _SLACK) + 1e-15


def _refuse(what: str, depth: float, tol: float, fix: str, allow: bool = True) -> None:
    """Raise the overlap's SceneError; ``allow``: offer ``allow_overlap=True`` (not for
    coincident centres, which it refuses too: :meth:`OverlapIndex._coincident`)."""
    limit = (f"more than {tol:.3g} m, {OVERLAP_TOL:.0%} of the smaller size" if tol > 0.0 else
             "a particle has no size, so any overlap counts")
    offer = ("; or pass allow_overlap=True to start it compressed on purpose" if allow
             else "")
    raise SceneError(f"{what} overlap by {depth:.4g} m at the start ({limit}: it starts "
                     f"inside): {fix}{offer}.")


class OverlapIndex:
    """Spatial index of a scene's colliding bodies for the initial-overlap check."""

    def __init__(self):
        self.h = None                 # grid cell size, m (from the first sphere)
        self.cells: dict = {}         # cell -> [body index]
        self.big: list = []           # bodies spanning too many cells
        self.boxes: list = []         # box body indices
        self.allowed: set = set()     # bodies added with allow_overlap=True

    # ------------------------------------------------------------ grid
    def _range(self, x, r):
        # clipped to the integers' range: a body 1e39 m out made an invalid cast (its cell
        # then shares the clipped edge cell with any other that far, compared directly)
        def cell(v):
            with np.errstate(over="ignore", divide="ignore"):   # a tiny cell: clipped too
                return np.clip(np.floor(v / self.h), -2.0 ** 62, 2.0 ** 62).astype(np.int64)
        return cell(np.asarray(x) - r), cell(np.asarray(x) + r)

    def _ncells(self, lo, hi) -> int:
        return int(np.prod(hi - lo + 1))

    def _cells(self, lo, hi):
        for i in range(lo[0], hi[0] + 1):
            for j in range(lo[1], hi[1] + 1):
                for k in range(lo[2], hi[2] + 1):
                    yield (i, j, k)

    def _insert(self, idx: int, x, r: float) -> None:
        if self.h is None:
            self.h = 2.0 * r if r > 0.0 else 0.1
        lo, hi = self._range(x, r)
        if self._ncells(lo, hi) > _MAX_CELLS:
            self.big.append(idx)
            return
        for cell in self._cells(lo, hi):
            self.cells.setdefault(cell, []).append(idx)

    def _near(self, x, r, n_bodies: int) -> np.ndarray:
        """Indices of grid bodies whose cells meet the box ``x +- r`` (a superset)."""
        if self.h is None:
            return np.zeros(0, int)
        lo, hi = self._range(x, r)
        if self._ncells(lo, hi) > _MAX_CELLS:
            found = set(i for v in self.cells.values() for i in v)
        else:
            found = set()
            for cell in self._cells(lo, hi):
                found.update(self.cells.get(cell, ()))
        found.update(self.big)
        return np.array(sorted(found), int)

    def forget(self, idx: int) -> None:
        """Drop body ``idx`` from the index (a body removed again on bad input)."""
        for v in self.cells.values():
            if v and v[-1] == idx:
                v.pop()
        for lst in (self.big, self.boxes):
            if idx in lst:
                lst.remove(idx)
        self.allowed.discard(idx)

    def start_pair_depths(self, scene) -> np.ndarray:
        """(n,) m: each body's deepest start overlap with another colliding body, over the
        pairs with a body added with ``allow_overlap`` (every other pair is held to
        :data:`OVERLAP_TOL` of its smaller size); 0 where none."""
        bodies, out = scene.bodies, np.zeros(len(scene.bodies))

        def deepen(idx, depth):
            np.maximum.at(out, idx, np.maximum(np.asarray(depth, float), 0.0))
        for i in sorted(self.allowed):
            b = bodies[i]
            if b.kind == "box":
                near = [j for j in self._near(b.position, b.radius, len(bodies))
                        if j != i and bodies[j].kind != "box"]
                if near:
                    d = _sphere_box_depth(np.array([bodies[j].position for j in near]),
                                          np.array([bodies[j].radius for j in near]), b)
                    deepen(near, d), deepen([i] * len(near), d)
                continue
            x, r = np.asarray(b.position, float), float(b.radius)
            near = [j for j in self._near(x, r, len(bodies))
                    if j != i and bodies[j].kind != "box"]
            if near:
                xs = np.array([bodies[j].position for j in near], float)
                d = np.array([bodies[j].radius for j in near]) + r - np.linalg.norm(
                    xs - x, axis=1)
                deepen(near, d), deepen([i] * len(near), d)
            for j in self.boxes:
                d = _sphere_box_depth(x[None], np.array([r]), bodies[j])
                deepen([j], d), deepen([i], d)
        return out

    # ------------------------------------------------------------ checks
    def check_body(self, scene, body, idx: int, allow: bool = False) -> None:
        """Check a new body (not yet in ``scene.bodies``) against planes, fixed spheres,
        boxes and spheres (raises SceneError), then index it. ``allow``: index only."""
        if not body.collide:
            return
        if allow:
            self._coincident(scene, body, idx)
            self.allowed.add(idx)
            if body.kind == "box":
                self.boxes.append(idx)
            else:
                self._insert(idx, np.asarray(body.position), body.radius)
            return
        if body.kind == "box":
            self._check_box(scene, body, idx)
            return
        x, r = np.asarray(body.position), body.radius
        if not body.pinned:
            for j, pl in enumerate(scene.planes):
                self._plane(np.asarray(pl.normal), pl.offset, j, x[None], np.array([r]),
                            [idx], scene, body.kind)
            for j, fs in enumerate(scene.fixed_spheres):
                self._fixed(fs, j, x[None], np.array([r]), [idx], scene, body.kind)
        for j in self.boxes:
            box = scene.bodies[j]
            if body.pinned and box.pinned:
                continue
            d = float(_sphere_box_depth(x[None], np.array([r]), box)[0])
            tol = OVERLAP_TOL * min(r, min(box.half_extents))   # a particle: any overlap
            if _over(d, tol):
                _refuse(f"{body.kind} {idx} at {_fmt(x)} (radius {r:.4g} m) and box {j} at "
                        f"{_fmt(box.position)}", d, tol, "move it out of the box")
        if body.kind == "sphere" and r > 0.0:
            near = [i for i in self._near(x, r, len(scene.bodies))
                    if scene.bodies[i].kind == "sphere" and scene.bodies[i].radius > 0.0
                    and not (body.pinned and scene.bodies[i].pinned)]
            if near:
                xs = np.array([scene.bodies[i].position for i in near])
                rs = np.array([scene.bodies[i].radius for i in near])
                dist = np.linalg.norm(xs - x, axis=1)
                depth = rs + r - dist
                tol = OVERLAP_TOL * np.minimum(rs, r)
                bad = np.flatnonzero(_over(depth, tol))
                if bad.size:
                    b = int(bad[np.argmax(depth[bad] - tol[bad])])
                    i = near[b]
                    if dist[b] > 0.0:
                        fix = (f"move them at least {depth[b]:.4g} m further apart along "
                               f"{_fmt((x - xs[b]) / dist[b])}")
                    else:
                        fix = ("their centres coincide, so the contact has no direction and "
                               f"they never separate: move them {r + rs[b]:.4g} m apart")
                    _refuse(f"sphere {idx} at {_fmt(x)} (radius {r:.4g} m) and sphere {i} at "
                            f"{_fmt(xs[b])} (radius {rs[b]:.4g} m)", float(depth[b]),
                            float(tol[b]), fix, allow=bool(np.all(dist[bad] > 0.0)))
        self._insert(idx, x, r)

    def _coincident(self, scene, body, idx: int, dtype=float) -> None:
        """Refuse a sphere placed with ``allow_overlap`` at exactly the centre of another
        colliding sphere (the pairs with a sphere-sphere contact), its coordinates rounded to
        ``dtype``: their contact has no direction (:func:`diffpen.geometry.sphere_sphere`
        gives the normal 0), so no force ever pushes them apart and they stay overlapped,
        silently. ``allow_overlap`` lets bodies start compressed, which this cannot be."""
        def at(b):
            return np.asarray(np.asarray(b.position, dtype=float), dtype=dtype)
        x, r = at(body), body.radius
        if body.kind != "sphere" or r <= 0.0 or not body.collide:
            return
        for i in self._near(np.asarray(body.position, dtype=float), r, len(scene.bodies)):
            other = scene.bodies[i]
            if (i == idx or other.kind != "sphere" or other.radius <= 0.0
                    or not other.collide or (body.pinned and other.pinned)
                    or np.any(at(other) != x)):
                continue
            apart = float(np.linalg.norm(np.subtract(body.position, other.position)))
            same = ("start at the same centre" if apart == 0.0 else
                    f"start {apart:.3g} m apart, the same centre in {np.dtype(dtype).name}")
            raise SceneError(
                f"sphere {idx} at {_fmt(body.position)} and sphere {i} {same}: their "
                "contact has no direction, so no force would ever push them apart "
                "(allow_overlap starts bodies compressed, not coincident): move one of them "
                "by any distance" + ("." if apart == 0.0 else " that dtype resolves, or use "
                                     "float64."))

    def check_coincident(self, scene, dtype) -> None:
        """At compile: :meth:`_coincident` for every sphere added with ``allow_overlap``, in
        the simulator's ``dtype`` (two centres 1e-9 m apart are one in float32). Nothing to
        do in float64: adding each sphere checked it at float64's resolution."""
        if np.finfo(dtype).eps <= np.finfo(float).eps:
            return
        allowed = (range(len(scene.bodies)) if scene.allow_overlap else sorted(self.allowed))
        for i in allowed:
            self._coincident(scene, scene.bodies[i], i, dtype)

    def _check_box(self, scene, box, idx: int) -> None:
        half = min(box.half_extents)
        if not box.pinned:
            for j, pl in enumerate(scene.planes):
                d, corners = _corner_depths(box, pl)
                tol = OVERLAP_TOL * half
                if _over(d.max(), tol):
                    _refuse(f"box {idx} at {_fmt(box.position)} (corner "
                            f"{_fmt(corners[d.argmax()])}) and plane {j} (normal {_fmt(pl.normal)}, offset {pl.offset:.4g} m)",
                            float(d.max()), tol, f"raise it by {d.max():.4g} m along the "
                            "plane's normal")
            for j, fs in enumerate(scene.fixed_spheres):
                _box_fixed_sphere(box, idx, fs, j)
        near = self._near(box.position, box.radius, len(scene.bodies))
        near = [i for i in near if not (box.pinned and scene.bodies[i].pinned)]
        if near:
            xs = np.array([scene.bodies[i].position for i in near])
            rs = np.array([scene.bodies[i].radius for i in near])
            d = _sphere_box_depth(xs, rs, box)
            tol = OVERLAP_TOL * np.minimum(rs, half)          # a particle: any overlap
            bad = np.flatnonzero(_over(d, tol))
            if bad.size:
                b = int(bad[0])
                _refuse(f"box {idx} at {_fmt(box.position)} and "
                        f"{scene.bodies[near[b]].kind} {near[b]} at {_fmt(xs[b])}",
                        float(d[b]), float(tol[b]), "move it out of the box")
        self.boxes.append(idx)

    @staticmethod
    def _plane(n, offset, j, xs, rs, idx, scene, kind=None) -> None:
        d = rs - (xs @ n - offset)
        tol = OVERLAP_TOL * rs
        bad = np.flatnonzero(_over(d, tol))
        if bad.size:
            b = int(bad[np.argmax(d[bad])])
            i = idx[b]
            kind = kind or scene.bodies[i].kind
            _refuse(f"{kind} {i} at {_fmt(xs[b])} (radius {rs[b]:.4g} m) and plane {j} "
                    f"(normal {_fmt(n)}, offset {offset:.4g} m)", float(d[b]), float(tol[b]),
                    f"move it {d[b]:.4g} m along the plane's normal to touch the surface")

    @staticmethod
    def _fixed(fs, j, xs, rs, idx, scene, kind=None) -> None:
        dist = np.linalg.norm(xs - np.asarray(fs.center), axis=1)
        d = rs + fs.radius - dist
        tol = OVERLAP_TOL * np.minimum(np.where(rs > 0, rs, fs.radius), fs.radius)
        tol = np.where(rs > 0, tol, 0.0)
        bad = np.flatnonzero(_over(d, tol))
        if bad.size:
            b = int(bad[np.argmax(d[bad])])
            _refuse(f"{kind or scene.bodies[idx[b]].kind} {idx[b]} at {_fmt(xs[b])} (radius "
                    f"{rs[b]:.4g} m) and fixed sphere {j} (center {_fmt(fs.center)}, radius {fs.radius:.4g} m)", float(d[b]),
                    float(tol[b]), f"it starts inside fixed sphere {j}: move it out of the sphere")

    def check_collider(self, scene, kind: str, col, j: int) -> None:
        """Check a new plane or fixed sphere against every body already in the scene."""
        idx = [i for i, b in enumerate(scene.bodies) if b.collide and not b.pinned
               and i not in self.allowed]
        pts = [i for i in idx if scene.bodies[i].kind != "box"]
        if pts:
            xs = np.array([scene.bodies[i].position for i in pts])
            rs = np.array([scene.bodies[i].radius for i in pts])
            if kind == "plane":
                self._plane(np.asarray(col.normal), col.offset, j, xs, rs, pts, scene)
            else:
                self._fixed(col, j, xs, rs, pts, scene)
        if kind == "plane":
            for i in idx:
                b = scene.bodies[i]
                if b.kind != "box":
                    continue
                d, _ = _corner_depths(b, col)
                tol = OVERLAP_TOL * min(b.half_extents)
                if _over(d.max(), tol):
                    _refuse(f"box {i} at {_fmt(b.position)} and plane {j} (normal "
                            f"{_fmt(col.normal)}, offset {col.offset:.4g} m)", float(d.max()),
                            tol, f"raise it by {d.max():.4g} m along the plane's normal")
        else:
            for i in idx:
                if scene.bodies[i].kind == "box":
                    _box_fixed_sphere(scene.bodies[i], i, col, j)


def check_start_pose(scene, i: int, position, orientation=None) -> None:
    """Check body ``i`` of ``scene`` at a new start pose (``position`` (3,) m, ``orientation``
    (4,) unit quaternion or None for the scene's) against the scene's planes and fixed
    spheres, by the rule of the scene's own check (raises SceneError). Bodies placed with
    ``allow_overlap`` (or a scene built with it), pinned and non-colliding bodies pass."""
    import dataclasses
    body = scene.bodies[i]
    if (scene.allow_overlap or i in scene._overlap.allowed or body.pinned
            or not body.collide):
        return
    moved = dataclasses.replace(body, position=tuple(float(a) for a in position))
    if orientation is not None and body.kind == "box":
        moved = dataclasses.replace(moved, orientation=tuple(float(a) for a in orientation))
    if body.kind == "box":
        tol = OVERLAP_TOL * min(body.half_extents)
        for j, pl in enumerate(scene.planes):
            d, corners = _corner_depths(moved, pl)
            if _over(d.max(), tol):
                _refuse(f"box {i} started at {_fmt(moved.position)} (corner "
                        f"{_fmt(corners[d.argmax()])}) and plane {j} (normal {_fmt(pl.normal)}, "
                        f"offset {pl.offset:.4g} m)", float(d.max()), tol,
                        f"raise its start by {d.max():.4g} m along the plane's normal")
        for j, fs in enumerate(scene.fixed_spheres):
            _box_fixed_sphere(moved, i, fs, j, started=True)
        return
    x, r = np.asarray(moved.position)[None], np.array([body.radius])
    for j, pl in enumerate(scene.planes):
        OverlapIndex._plane(np.asarray(pl.normal), pl.offset, j, x, r, [i], scene, body.kind)
    for j, fs in enumerate(scene.fixed_spheres):
        OverlapIndex._fixed(fs, j, x, r, [i], scene, body.kind)
