"""Element tables of a scene file into a :class:`diffpen.Scene`: materials, bodies,
builders (ropes, cloths, jellies, crumple bars), colliders, springs and drag."""
from __future__ import annotations

import math

import numpy as np

import diffpen as dp
from diffpen import builders
from diffpen.elements import unit_vector

from .. import validate as V
from ..validate import Where
from .record import _Refs
from .schema import BODY_TABLES, BUILDER_TABLES, MAX_COORD, _takes


def _kc_opt(w: Where, v):
    """A builder spring group: k, [k, c], or false (left out)."""
    if v is False:
        return None
    if isinstance(v, list):
        if len(v) != 2:
            raise w.error(f"must be k, [k, c] or false, got {V._show(v)}.")
        return (V.number(w / 0, v[0], low=0.0, unit="N/m"),
                V.number(w / 1, v[1], low=0.0, unit="N s/m"))
    return V.number(w, v, low=0.0, unit="N/m (or [k, c], or false to leave the springs out)")


_GRID_EXAMPLE = {1: "[0, -1]", 2: "[[0, 0], [-1, 0]]", 3: "[[0, 0, 0], [-1, 0, 0]]"}


def _int_grid(w: Where, v, dims: int) -> list:
    """Node indices of a builder's ``pinned``: integers (dims 1) or ``dims``-integer arrays."""
    example = f"{V._leaf(w)} = {_GRID_EXAMPLE[dims]}"
    if not isinstance(v, list):
        raise w.error(f"must be an array of node indices, got {V._kind(v)} {V._show(v)}; "
                      f"e.g. {example}.")

    def index(wi, x):
        if isinstance(x, bool) or not isinstance(x, int):
            what = "a node index" if dims == 1 else "a grid index"
            raise wi.error(f"must be {what} (a whole number), got {V._kind(x)} {V._show(x)}; "
                           f"e.g. {example}.")
        return x

    out = []
    for i, p in enumerate(v):
        if dims == 1:
            out.append(index(w / i, p))
        else:
            if not isinstance(p, list) or len(p) != dims:
                raise (w / i).error(f"must be {dims} integer grid indices, got {V._show(p)}; "
                                    f"e.g. {example}.")
            out.append(tuple(index(w / i / j, x) for j, x in enumerate(p)))
    return out


def _quat_rotate(q, v) -> tuple:
    w, x, y, z = unit_vector(np.asarray(q, float))[0]
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return tuple(float(a) for a in r @ np.asarray(v, float))


class _ElementTables:
    """Mixin of :class:`_Loader`: one method per element table."""

    # ---------------------------------------------------------------- materials
    def materials(self):
        if "materials" not in self.doc:
            return
        w = self.w("materials")
        mats = V.table(w, self.doc["materials"], example="[materials.rubber] k = 1e4")
        for name, m in mats.items():
            wm = w / name
            V.table(wm, m, example=f"[materials.{name}] k = 1e4")
            V.check_keys(wm, m, {"k", "c", "friction", "slip_speed"})
            kw = {}
            for key, unit in (("k", "N/m"), ("c", "N s/m"), ("friction", "")):
                if key in m:
                    kw[key] = V.number(wm / key, m[key], low=0.0, unit=unit)
            if "slip_speed" in m:
                kw["slip_speed"] = V.number(wm / "slip_speed", m["slip_speed"], low=0.0,
                                            low_open=True, unit="m/s")
            self.call(wm, self.scene.add_material, name, **kw)

    def spring_groups(self):
        if "spring_groups" not in self.doc:
            return
        w = self.w("spring_groups")
        for name, g in V.table(w, self.doc["spring_groups"],
                               example="[spring_groups.tether] k = 100").items():
            wg = w / name
            V.table(wg, g)
            V.check_keys(wg, g, {"k", "c"})
            k = V.number(wg / "k", self.require(wg, g, "k"), low=0.0, unit="N/m")
            c = V.number(wg / "c", g.get("c", 0.0), low=0.0, unit="N s/m")
            self.call(wg, self.scene.add_spring_group, name, k, c)

    def material_of(self, w, e):
        m = e.get("material", dp.scene.DEFAULT)
        V.string(w / "material", m)
        if m not in self.scene.materials:
            raise (w / "material").error(
                f"names material {m!r}, which is not declared; add a [materials.{m}] table "
                f"(known: {', '.join(sorted(self.scene.materials))}).")
        return m

    # ---------------------------------------------------------------- bodies
    def bodies(self):
        common = {"name", "mass", "position", "velocity", "pinned", "material", "collide",
                  "allow_overlap"}
        rigid = common | {"orientation", "angular_velocity", "body_angular_velocity", "inertia"}
        allowed = {"spheres": common | {"radius"}, "particles": common,
                   "boxes": rigid | {"half_extents"}, "rigid_spheres": rigid | {"radius"}}
        for key in BODY_TABLES:
            for i, e in enumerate(self.entries(key)):
                w = self.w(key, i)
                V.check_keys(w, e, allowed[key])
                kw = dict(
                    mass=self.mass(w / "mass", self.require(w, e, "mass")),
                    position=self.point(w / "position", self.require(w, e, "position")),
                    velocity=self.speed(w / "velocity", e.get("velocity", [0.0, 0.0, 0.0])),
                    pinned=V.boolean(w / "pinned", e.get("pinned", False)),
                    material=self.material_of(w, e),
                    collide=V.boolean(w / "collide", e.get("collide", True)))
                if key in ("spheres", "rigid_spheres"):
                    kw["radius"] = V.number(w / "radius", self.require(w, e, "radius"),
                                            low=0.0, low_open=True, high=MAX_COORD, unit="m")
                if key == "boxes":
                    kw["half_extents"] = self.point(w / "half_extents",
                                                    self.require(w, e, "half_extents"))
                if key in ("boxes", "rigid_spheres"):
                    self.rigid_kw(w, e, kw)
                name = self.name(w / "name", e["name"], self.names) if "name" in e else None
                fn = {"spheres": self.scene.add_sphere, "particles": self.scene.add_particle,
                      "boxes": self.scene.add_box,
                      "rigid_spheres": self.scene.add_rigid_sphere}[key]
                self.overlap(w, e, fn, kw)
                idx = self.call(w, fn, **kw)
                if name is not None:
                    self.names[name] = idx

    def overlap(self, w, e, fn, kw):
        """``allow_overlap = true``: start overlapping a collider or body on purpose (passed
        on where the library checks initial overlaps; without that check it is the default)."""
        if "allow_overlap" in e and V.boolean(w / "allow_overlap", e["allow_overlap"]):
            if _takes(fn, "allow_overlap"):
                kw["allow_overlap"] = True

    def rigid_kw(self, w, e, kw):
        q = V.vector(w / "orientation", e.get("orientation", [1.0, 0.0, 0.0, 0.0]), 4,
                     what="w, x, y, z")
        if math.sqrt(sum(x * x for x in q)) < 1e-12:
            raise (w / "orientation").error("is the zero quaternion: give a rotation as [w, x, "
                                            "y, z], e.g. [1, 0, 0, 0] for none.")
        kw["orientation"] = q
        if "angular_velocity" in e and "body_angular_velocity" in e:
            raise w.error("gives both angular_velocity (world frame) and body_angular_velocity "
                          "(body frame): keep one.")
        if "body_angular_velocity" in e:
            wb = self.speed(w / "body_angular_velocity", e["body_angular_velocity"], "rad/s")
            kw["angular_velocity"] = _quat_rotate(q, wb)
        else:
            kw["angular_velocity"] = self.speed(w / "angular_velocity",
                                                e.get("angular_velocity", [0.0, 0.0, 0.0]),
                                                "rad/s")
        if "inertia" in e:
            kw["inertia"] = V.vector(w / "inertia", e["inertia"], unit="kg m^2")
            for j, v in enumerate(kw["inertia"]):
                V.number(w / "inertia" / j, v, low=0.0, low_open=True, unit="kg m^2")

    # ---------------------------------------------------------------- builders
    def builders(self):
        common = {"name", "mass", "pinned", "drag", "velocity", "collide"}
        allowed = {
            "ropes": common | {"n", "start", "end", "k", "c", "bend"},
            "cloths": common | {"nx", "ny", "spacing", "origin", "axes", "structural",
                                "shear", "bend"},
            "jellies": common | {"nx", "ny", "nz", "spacing", "origin", "edge", "face",
                                 "body"},
            "crumple_bars": common | {"n", "start", "end", "k", "c", "yield_strain", "width"},
        }
        default_name = {"ropes": "rope", "cloths": "cloth", "jellies": "jelly",
                        "crumple_bars": "bar"}
        for key in BUILDER_TABLES:
            for i, e in enumerate(self.entries(key)):
                w = self.w(key, i)
                V.check_keys(w, e, allowed[key])
                name = self.name(w / "name", e.get("name", default_name[key]), self.names)
                kw = {"group": name,
                      "mass": self.mass(w / "mass", self.require(w, e, "mass")),
                      "velocity": self.speed(w / "velocity",
                                             e.get("velocity", [0.0, 0.0, 0.0])),
                      "collide": V.boolean(w / "collide", e.get("collide", True))}
                if "drag" in e:
                    kw["drag"] = (None if e["drag"] is False else
                                  V.number(w / "drag", e["drag"], low=0.0, unit="N s/m"))
                if key in ("ropes", "crumple_bars"):
                    kw["n"] = V.integer(w / "n", self.require(w, e, "n"), low=2)
                    kw["start"] = self.point(w / "start", self.require(w, e, "start"))
                    kw["end"] = self.point(w / "end", self.require(w, e, "end"))
                    kw["k"] = V.number(w / "k", self.require(w, e, "k"), low=0.0, unit="N/m")
                    kw["c"] = V.number(w / "c", e.get("c", 0.0), low=0.0, unit="N s/m")
                    if "pinned" in e:
                        kw["pinned"] = _int_grid(w / "pinned", e["pinned"], 1)
                else:
                    dims = 2 if key == "cloths" else 3
                    for d in ("nx", "ny", "nz")[:dims]:
                        kw[d] = V.integer(w / d, self.require(w, e, d), low=2)
                    kw["spacing"] = V.number(w / "spacing", self.require(w, e, "spacing"),
                                             low=0.0, low_open=True, high=MAX_COORD, unit="m")
                    if "origin" in e:
                        kw["origin"] = self.point(w / "origin", e["origin"])
                    if "pinned" in e:
                        kw["pinned"] = _int_grid(w / "pinned", e["pinned"], dims)
                if key == "ropes":
                    if "bend" in e:
                        kw["bend"] = _kc_opt(w / "bend", e["bend"])
                    fn = builders.add_rope
                elif key == "crumple_bars":
                    if "yield_strain" in e:
                        kw["yield_strain"] = V.number(w / "yield_strain", e["yield_strain"],
                                                      low=0.0, low_open=True, high=1.0,
                                                      high_open=True)
                    if "width" in e:
                        kw["width"] = V.number(w / "width", e["width"], low=0.0,
                                               low_open=True, unit="m")
                    fn = builders.add_crumple_bar
                elif key == "cloths":
                    if "axes" in e:
                        a = e["axes"]
                        if not isinstance(a, list) or len(a) != 2:
                            raise (w / "axes").error("must be two directions [[x,y,z], "
                                                     "[x,y,z]].")
                        kw["axes"] = tuple(V.vector(w / "axes" / j, x) for j, x in
                                           enumerate(a))
                    for g in ("structural", "shear", "bend"):
                        if g in e:
                            kw[g] = _kc_opt(w / g, e[g])
                    fn = builders.add_cloth
                else:
                    for g in ("edge", "face", "body"):
                        if g in e:
                            kw[g] = _kc_opt(w / g, e[g])
                    fn = builders.add_jelly
                idx = self.call(w, fn, self.scene, **kw)
                self.nodes[name] = np.asarray(idx)
                for ij in np.ndindex(*np.shape(idx)):
                    self.names[f"{name}[{','.join(map(str, ij))}]"] = int(idx[ij])

    # ---------------------------------------------------------------- colliders
    def colliders(self):
        plane_kw = _takes(self.scene.add_plane, "name")
        for i, e in enumerate(self.entries("planes")):
            w = self.w("planes", i)
            V.check_keys(w, e, {"normal", "offset", "material", "name", "allow_overlap"})
            kw = dict(normal=V.vector(w / "normal", e.get("normal", [0.0, 0.0, 1.0])),
                      offset=V.number(w / "offset", e.get("offset", 0.0), low=-MAX_COORD,
                                      high=MAX_COORD, unit="m"),
                      material=self.material_of(w, e))
            self.overlap(w, e, self.scene.add_plane, kw)
            name = None
            if "name" in e:
                name = self.name(w / "name", e["name"], self.plane_names)
                if plane_kw:
                    kw["name"] = name
            idx = self.call(w, self.scene.add_plane, **kw)
            if name is not None:
                self.plane_names[name] = idx
        for i, e in enumerate(self.entries("fixed_spheres")):
            w = self.w("fixed_spheres", i)
            V.check_keys(w, e, {"center", "radius", "material", "allow_overlap"})
            kw = dict(center=self.point(w / "center", self.require(w, e, "center")),
                      radius=V.number(w / "radius", self.require(w, e, "radius"), low=0.0,
                                      low_open=True, high=MAX_COORD, unit="m"),
                      material=self.material_of(w, e))
            self.overlap(w, e, self.scene.add_fixed_sphere, kw)
            self.call(w, self.scene.add_fixed_sphere, **kw)

    # ---------------------------------------------------------------- springs
    def refs(self) -> _Refs:
        return _Refs(self.names, self.nodes, self.scene.n_bodies)

    def spring_common(self, w, e, kw, *, default_group):
        for key, unit in (("k", "N/m"), ("c", "N s/m"), ("rest_length", "m")):
            if key in e:
                kw[key] = V.number(w / key, e[key], low=0.0, unit=unit)
        kw["group"] = V.string(w / "group", e.get("group", default_group))

    def springs(self):
        refs = self.refs()
        for i, e in enumerate(self.entries("springs")):
            w = self.w("springs", i)
            V.check_keys(w, e, {"a", "b", "k", "c", "rest_length", "group"})
            a = refs.body(w / "a", self.require(w, e, "a"))
            b = self.require(w, e, "b")
            b = (self.point(w / "b", b, "m (a world point)") if isinstance(b, list)
                 else refs.body(w / "b", b))
            kw = {}
            self.spring_common(w, e, kw, default_group=dp.scene.DEFAULT)
            self.call(w, self.scene.add_spring, a, b, **kw)
        for i, e in enumerate(self.entries("anchored_springs")):
            w = self.w("anchored_springs", i)
            V.check_keys(w, e, {"a", "b", "anchor_a", "anchor_b", "k", "c", "rest_length",
                                "group"})
            a = refs.body(w / "a", self.require(w, e, "a"))
            b = refs.body(w / "b", e["b"]) if "b" in e else None
            kw = {"anchor_a": self.point(w / "anchor_a", e.get("anchor_a", [0.0, 0.0, 0.0])),
                  "anchor_b": self.point(w / "anchor_b", e.get("anchor_b", [0.0, 0.0, 0.0]))}
            self.spring_common(w, e, kw, default_group=dp.scene.DEFAULT)
            self.call(w, self.scene.add_anchored_spring, a, b, **kw)
        for i, e in enumerate(self.entries("plastic_springs")):
            w = self.w("plastic_springs", i)
            V.check_keys(w, e, {"a", "b", "k", "c", "yield_strain", "rest_length", "group"})
            a = refs.body(w / "a", self.require(w, e, "a"))
            b = refs.body(w / "b", self.require(w, e, "b"))
            kw = {}
            self.spring_common(w, e, kw, default_group="plastic")
            if "yield_strain" in e:
                kw["yield_strain"] = V.number(w / "yield_strain", e["yield_strain"], low=0.0,
                                              low_open=True, high=1.0, high_open=True)
            self.call(w, self.scene.add_plastic_spring, a, b, **kw)

    def drag(self):
        refs = self.refs()
        for i, e in enumerate(self.entries("drag")):
            w = self.w("drag", i)
            V.check_keys(w, e, {"bodies", "c", "group"})
            b = self.require(w, e, "bodies")
            items = b if isinstance(b, list) else [b]
            if not items:
                raise (w / "bodies").error("is empty: give a body or an array of bodies.")
            idx = []
            for j, x in enumerate(items):
                wj = w / "bodies" / j if isinstance(b, list) else w / "bodies"
                if isinstance(x, str) and x in self.nodes:      # every node of a builder
                    idx += [int(i) for i in self.nodes[x].ravel()]
                else:
                    idx.append(refs.body(wj, x))
            kw = {"group": V.string(w / "group", e.get("group", "drag"))}
            if "c" in e:
                kw["c"] = V.number(w / "c", e["c"], low=0.0, unit="N s/m")
            self.call(w, self.scene.add_drag, idx, **kw)
