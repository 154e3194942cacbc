"""TOML scene files: every element of a :class:`diffpen.Scene`, the run settings, and what to
fit, so that ``diffpen fit myscene.toml`` / ``diffpen simulate myscene.toml`` need no Python.

The schema (SI units; every table is optional except one body; unknown keys are errors)::

    description = "..."             # one line for printouts
    gravity = [0.0, 0.0, -9.81]     # m/s^2
    dt = 1e-3                       # s
    duration = 3.0                  # s, default rollout length
    law = "linear"                  # "linear", "no_tension", "hunt_crossley"
    exponent = 1.5                  # Hunt-Crossley exponent (>= 1)
    integrator = "semi_implicit_euler"   # any of diffpen.integrators.INTEGRATORS
    smoothing = "auto"              # contact smoothing width, m (>= 0) or "auto"
    substeps = 1                    # int >= 1 or "auto"
    plastic_smoothing = 1e-3        # strain width of the plastic yield onset
    broadphase = { kind = "grid" }  # or { kind = "aabb", max_pairs = 4096 }; also margin,
                                    # cell_size, max_per_cell, bounds = [[x0,y0,z0],[x1,y1,z1]]
    k = 1e4                         # default contact k (N/m) and c (N s/m) of materials
    c = 10.0                        # that do not give their own
    allow_overlap = false           # bodies may start overlapping (also per body, plane and
                                    #   fixed sphere), where the library checks overlaps

    [materials.rubber]              # contact material ("default" exists already)
    k = 1e4                         # N/m
    c = 20.0                        # N s/m
    friction = 0.3                  # Coulomb mu >= 0 (box corners, rigid spheres)
    slip_speed = 0.01               # m/s > 0

    [[spheres]]                     # radius, mass, position; optional name, velocity,
    [[particles]]                   #   material, pinned, collide (particles: no radius)
    [[boxes]]                       # half_extents, mass, position; optional name, velocity,
    [[rigid_spheres]]               #   orientation [w,x,y,z], angular_velocity (world frame)
                                    #   OR body_angular_velocity (body frame), inertia [3]
                                    #   (kg m^2), material, pinned, collide
    [[planes]]                      # normal [0,0,1], offset 0, material, name (a named plane's
                                    #   offset is the param extra.plane_offset.NAME when the
                                    #   library supports it)
    [[fixed_spheres]]               # center, radius, material
    [spring_groups.NAME]            # k, c: declare a spring group
    [[springs]]                     # a, b (body index or name; b may be a world point
                                    #   [x,y,z]), k, c, rest_length, group
    [[anchored_springs]]            # a, b (omit b for a world point), anchor_a, anchor_b
                                    #   (body frame, m), k, c, rest_length, group
    [[plastic_springs]]             # a, b, k, c, yield_strain in (0, 1), rest_length, group
    [[drag]]                        # bodies (a ref or array of refs; a builder's name means
                                    #   all its nodes), c (N s/m), group
    [[ropes]]                       # n, start, end, mass, k, c; name ("rope"), pinned [0],
                                    #   bend (k | [k, c] | false), drag, velocity, collide
    [[cloths]]                      # nx, ny, spacing, mass; name ("cloth"), origin, axes,
                                    #   structural, shear, bend, pinned [[i,j],...], drag, ...
    [[jellies]]                     # nx, ny, nz, spacing, mass; name ("jelly"), origin, edge,
                                    #   face, body, pinned [[i,j,l],...], drag, velocity, ...
    [[crumple_bars]]                # n, start, end, mass, k, c, yield_strain; name ("bar"),
                                    #   width, pinned, drag, velocity, collide

    [fit]
    params = ["contact.rubber.k", "contact.rubber.c"]   # leaf paths of sim.params()
    body = 0                        # index or name (bounce fits: the bouncing body)
    plane = 0                       # index or name
    settle_tol = 1e-3               # m
    method = "lm"                   # "lm", "adam", "sgd";  maxiter = 40;  lr = 0.05
    observe = ["cube"]              # bodies the records observe (default: the named bodies)
    [fit.bounds]                    # "path" = [lo, hi]
    [fit.space]                     # "path" = "log" | "linear" (default: linear for offsets
                                    #   and other signed leaves, log for positive ones)
    [fit.weights]                   # target or loss-term name = weight >= 0
    [fit.targets]                   # apex_heights, settling_time, contact_durations,
                                    #   restitution, max_penetration
    # data = "record.csv"           # or an array of records, instead of targets

Bodies are numbered: spheres, particles, boxes, rigid_spheres, then the nodes of ropes,
cloths, jellies and crumple_bars, each in file order. A body is referred to by its index, by
its ``name``, or, for a builder's node, as ``NAME[i]`` / ``NAME[i,j]`` / ``NAME[i,j,l]``
(negative indices count from the end). Parameter paths are the ``jax.tree_util`` key paths of
``sim.params()`` written with dots (``contact.rubber.k``, ``springs.rope.stretch.c``,
``extra.friction.rubber``, ``extra.drag.rope.drag``, ``extra.plastic.bar``) or as
``jax.tree_util.keystr`` gives them (``.contact['rubber'].k``).

Every value is checked when the file is read -- types without coercion (``radius = "0.1"``
and ``mass = true`` are errors), ranges, references, sizes (steps, bodies, contact pairs:
estimated and refused above limits the caller can raise) -- with the file name, the key and
the fix in the message, before anything is compiled.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import os
import re
import tomllib

import numpy as np

import diffpen as dp
from diffpen import builders
from diffpen.checks import human_bytes, human_time

from . import validate as V
from .params import key_name
from .scenes import SceneSetup
from .validate import SceneFileError, Where

__all__ = ["load_scene_file", "SceneFile", "FitSpec", "fit_file", "SceneFileError",
           "is_scene_path", "param_leaves", "leaf_space", "MAX_STEPS", "MAX_BODIES",
           "MAX_DENSE_PAIRS", "MAX_TRAJECTORY_BYTES"]

#: size guards (raise them by argument of :func:`load_scene_file`)
MAX_STEPS = 10_000_000
MAX_BODIES = 200_000
MAX_DENSE_PAIRS = 500_000          # contact pairs evaluated every step without a broad phase
MAX_TRAJECTORY_BYTES = 8 * 2**30   # a rollout saving every step
#: positions, centres and anchor points must lie within this distance of the origin, m
MAX_COORD = 1e6

BODY_TABLES = ("spheres", "particles", "boxes", "rigid_spheres")
BUILDER_TABLES = ("ropes", "cloths", "jellies", "crumple_bars")
TOP = {"description", "gravity", "dt", "duration", "law", "exponent", "integrator",
       "allow_overlap",
       "smoothing", "substeps", "plastic_smoothing", "broadphase", "k", "c", "materials",
       *BODY_TABLES, "planes", "fixed_spheres", "spring_groups", "springs",
       "anchored_springs", "plastic_springs", "drag", *BUILDER_TABLES, "fit"}
#: [fit] keys; extended by fits that need more
FIT = {"body", "plane", "params", "bounds", "space", "settle_tol", "targets", "data", "method",
       "maxiter", "lr", "weights", "observe"}
TARGETS = {"apex_heights", "settling_time", "contact_durations", "restitution",
           "max_penetration"}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
_NODE = re.compile(r"^([A-Za-z_][A-Za-z0-9_\-]*)\[\s*(-?\d+(?:\s*,\s*-?\d+)*)\s*\]$")


def is_scene_path(arg: str) -> bool:
    """Whether a command-line SCENE argument names a scene file rather than a built-in scene:
    a ``.toml`` suffix in any case (``ball.TOML`` is a file, never the built-in ``ball``)."""
    return isinstance(arg, str) and arg.lower().endswith(".toml")


# --------------------------------------------------------------------------- results
@dataclasses.dataclass
class FitSpec:
    """The validated ``[fit]`` table.

    free: parameter leaf paths to fit (dotted, see the module docstring); empty means the
      fitting code's default.  bounds: ``{path: (lo, hi)}``.  space: ``{path: "log" |
      "linear"}`` for every free path.  targets: bounce targets or None.  data: absolute
      record paths or None.  body, plane: indices.  observe: body names the records observe.
    """
    free: list
    bounds: dict
    space: dict
    targets: dict | None
    data: list | None
    body: int
    plane: int
    observe: list
    method: str = "lm"
    maxiter: int | None = None
    lr: float = 0.05
    weights: dict | None = None
    settle_tol: float = 1e-3


@dataclasses.dataclass
class SceneFile:
    """A parsed scene file (nothing compiled).

    path: the file.  setup: :class:`tuning.scenes.SceneSetup` (scene, dt, steps, k, c, law,
    metrics).  fit: the raw ``[fit]`` dict (validated) or None; spec: its :class:`FitSpec`.
    names: ``{name: body index}`` of named bodies and builder groups' nodes (``rope[3]``).
    planes: ``{name: plane index}``.  nodes: ``{builder name: index array}``.
    compile_options: keyword arguments for :func:`diffpen.compile` (integrator, law, ...).
    """
    path: str
    setup: SceneSetup
    fit: dict | None
    spec: FitSpec | None = None
    names: dict = dataclasses.field(default_factory=dict)
    planes: dict = dataclasses.field(default_factory=dict)
    nodes: dict = dataclasses.field(default_factory=dict)
    compile_options: dict = dataclasses.field(default_factory=dict)
    _sim: tuple | None = dataclasses.field(default=None, repr=False)

    @property
    def scene(self) -> dp.Scene:
        return self.setup.scene

    def body_index(self, ref) -> int:
        """Body index of ``ref`` (an index, a name or ``NAME[i,...]``); SceneFileError if none."""
        return _Refs(self).body(Where(self.path, "body"), ref)

    def compile(self, **overrides) -> dp.Simulator:
        """``diffpen.compile`` with the file's dt and options (``overrides`` win). Lazy: JAX
        compiles on the first rollout. Without overrides, the simulator built while checking
        ``[fit] params`` is reused (same scene, dt, options and dtype)."""
        if not overrides and self._sim is not None and self._sim[0] == _x64():
            return self._sim[1]
        kw = dict(self.compile_options)
        kw.update(overrides)
        dt = kw.pop("dt", self.setup.dt)
        return dp.compile(self.scene, dt, **kw)

    def params(self, sim: dp.Simulator) -> dp.Params:
        """``sim.params`` with the file's materials, falling back to the top-level k and c."""
        return _default_params(sim, self.setup.k, self.setup.c)


# --------------------------------------------------------------------------- params
def param_leaves(params) -> dict:
    """``{dotted path: leaf}`` of a params pytree, from ``jax.tree_util`` key paths
    (``contact.rubber.k``, ``extra.friction.rubber``, ...)."""
    import jax
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    return {".".join(key_name(k) for k in path): leaf for path, leaf in leaves}


def _keystr_paths(params) -> dict:
    import jax
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    return {jax.tree_util.keystr(path): ".".join(key_name(k) for k in path)
            for path, _ in leaves}


#: leaves that may take any sign (fitted in linear space)
SIGNED = ("offset",)


def leaf_space(path: str, value) -> str:
    """``"linear"`` for signed leaves (a path with a part naming an offset, or a value <= 0),
    ``"log"`` for the positive ones (stiffness, damping, friction, slip speed, drag, yield
    strain)."""
    parts = path.split(".")
    kind = parts[1] if parts[0] == "extra" and len(parts) > 1 else parts[-1]
    if any(s in kind for s in SIGNED):
        return "linear"
    try:
        v = float(np.asarray(value))
    except (TypeError, ValueError):
        return "linear"
    return "log" if v > 0.0 else "linear"


def _default_params(sim, k, c):
    contact = {}
    for name in sim.materials:
        m = sim.scene.materials[name]
        contact[name] = (m.k if m.k is not None else k, m.c if m.c is not None else c)
    return sim.params(contact=contact)


# --------------------------------------------------------------------------- references
class _Refs:
    def __init__(self, sf_or_names, nodes=None, n_bodies=None):
        if isinstance(sf_or_names, SceneFile):
            self.names, self.nodes = sf_or_names.names, sf_or_names.nodes
            self.n = sf_or_names.scene.n_bodies
        else:
            self.names, self.nodes, self.n = sf_or_names, nodes, n_bodies

    def body(self, w: Where, ref) -> int:
        if isinstance(ref, bool) or not isinstance(ref, (int, str)):
            raise w.error(f"must be a body index or name, got {V._kind(ref)} {V._show(ref)}.")
        if isinstance(ref, int):
            if not 0 <= ref < self.n:
                raise w.error(f"is body {ref}, but the scene has {self.n} bodies (0.."
                              f"{self.n - 1}) at this point; bodies are numbered spheres, "
                              "particles, boxes, rigid_spheres, then builder nodes.")
            return ref
        if ref in self.names:
            return self.names[ref]
        m = _NODE.match(ref.strip())
        if m and m.group(1) in self.nodes:
            idx = self.nodes[m.group(1)]
            ij = tuple(int(s) for s in m.group(2).split(","))
            if len(ij) != idx.ndim or not all(-s <= v < s for v, s in zip(ij, idx.shape)):
                raise w.error(f"{V._show(ref)} is outside {m.group(1)!r}, whose nodes have shape "
                              f"{idx.shape}: write {m.group(1)}[" + ",".join(
                                  f"0..{s - 1}" for s in idx.shape) + "].")
            return int(idx[ij])
        known = [n for n in self.names if "[" not in n][:8] + [f"{g}[...]" for g in self.nodes]
        raise w.error(f"names body {V._show(ref)}, which the scene does not have; known: "
                      f"{', '.join(known) or 'no named bodies'} (or an index 0.."
                      f"{self.n - 1}). Give the body a name = \"...\" first.")


# --------------------------------------------------------------------------- loading
def load_scene_file(path, *, max_steps: int = MAX_STEPS, max_bodies: int = MAX_BODIES,
                    max_dense_pairs: int = MAX_DENSE_PAIRS,
                    max_trajectory_bytes: int = MAX_TRAJECTORY_BYTES) -> SceneFile:
    """Read and validate a TOML scene file (schema in the module docstring). Nothing is
    compiled; the size guards (steps, bodies, contact pairs without a broad phase, trajectory
    memory) are checked from estimates before the scene is built.
    Raises :class:`SceneFileError` with the file, the key and the fix."""
    path = os.fspath(path)
    text = V.read_text_file(path, "TOML scene")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneFileError(f"{path} is not valid TOML: {exc}.", path=path) from None
    return _Loader(path, doc, max_steps=max_steps, max_bodies=max_bodies,
                   max_dense_pairs=max_dense_pairs,
                   max_trajectory_bytes=max_trajectory_bytes).load()


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


def _int_grid(w: Where, v, dims: int) -> list:
    if not isinstance(v, list):
        raise w.error(f"must be an array of node indices, got {V._kind(v)} {V._show(v)}.")
    out = []
    for i, p in enumerate(v):
        if dims == 1:
            out.append(V.integer(w / i, p))
        else:
            if not isinstance(p, list) or len(p) != dims:
                raise (w / i).error(f"must be {dims} integer grid indices, got {V._show(p)}.")
            out.append(tuple(V.integer(w / i / j, x) for j, x in enumerate(p)))
    return out


def _quat_rotate(q, v) -> tuple:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return tuple(float(a) for a in r @ np.asarray(v, float))


class _Loader:
    def __init__(self, path, doc, **limits):
        self.path, self.doc, self.limits = path, doc, limits
        self.root = Where(path)
        self.names: dict = {}
        self.nodes: dict = {}
        self.plane_names: dict = {}

    # ---------------------------------------------------------------- helpers
    def w(self, *parts) -> Where:
        w = self.root
        for p in parts:
            w = w / p
        return w

    def entries(self, key: str) -> list:
        if key not in self.doc:
            return []
        return V.tables(self.w(key), self.doc[key], header=key)

    def call(self, w: Where, fn, *args, **kw):
        try:
            return fn(*args, **kw)
        except dp.SceneError as exc:
            if isinstance(exc, SceneFileError):
                raise
            raise w.error(str(exc)) from None

    def name(self, w: Where, v, taken: dict) -> str:
        V.string(w, v)
        if not _NAME.match(v):
            raise w.error(f"{v!r} is not a valid name: use letters, digits, '_' or '-', "
                          "starting with a letter or '_'.")
        if v in taken or v in self.nodes:
            raise w.error(f"{v!r} is used twice: names must differ.")
        return v

    @staticmethod
    def point(w: Where, v, unit: str = "m") -> tuple:
        """A position (m) within MAX_COORD of the origin."""
        return V.vector(w, v, unit=unit, limit=MAX_COORD)

    def require(self, w: Where, e: dict, key: str):
        if key not in e:
            raise w.error(f"is missing required key {key!r}.")
        return e[key]

    # ---------------------------------------------------------------- top level
    def load(self) -> SceneFile:
        doc, root = self.doc, self.root
        V.check_keys(root, doc, TOP)
        dt = V.number(self.w("dt"), doc.get("dt", 1e-3), low=0.0, low_open=True, unit="s")
        duration = V.number(self.w("duration"), doc.get("duration", 3.0), low=0.0,
                            low_open=True, unit="s")
        gravity = V.vector(self.w("gravity"), doc.get("gravity", [0.0, 0.0, -9.81]),
                           unit="m/s^2")
        law = V.choice(self.w("law"), doc.get("law", "linear"), sorted(dp.laws.CONTACT_LAWS))
        opts = {"law": law}
        if "exponent" in doc:
            opts["exponent"] = V.number(self.w("exponent"), doc["exponent"], low=1.0)
        if "integrator" in doc:
            opts["integrator"] = V.choice(self.w("integrator"), doc["integrator"],
                                          sorted(dp.integrators.INTEGRATORS))
        if "smoothing" in doc:
            s = doc["smoothing"]
            opts["smoothing"] = ("auto" if s == "auto" else
                                 V.number(self.w("smoothing"), s, low=0.0,
                                          unit='m (or "auto")'))
        if "substeps" in doc:
            s = doc["substeps"]
            opts["substeps"] = "auto" if s == "auto" else V.integer(self.w("substeps"), s,
                                                                     low=1)
        bp = self.broadphase()
        if bp is not None:
            opts["broadphase"] = bp
        k = V.number(self.w("k"), doc["k"], low=0.0, unit="N/m") if "k" in doc else None
        c = V.number(self.w("c"), doc["c"], low=0.0, unit="N s/m") if "c" in doc else None
        self.check_sizes(dt, duration, bp is not None)
        self.dt = dt

        overlap = V.boolean(self.w("allow_overlap"), doc.get("allow_overlap", False))
        scene = (dp.Scene(gravity=gravity, allow_overlap=True)
                 if overlap and _takes(dp.Scene, "allow_overlap") else dp.Scene(gravity=gravity))
        self.scene = scene
        if "plastic_smoothing" in doc:
            scene.plastic_smoothing = V.number(self.w("plastic_smoothing"),
                                               doc["plastic_smoothing"], low=0.0)
        self.materials()
        self.spring_groups()
        self.bodies()
        self.builders()
        if not scene.bodies:
            raise root.error("has no bodies; add a [[spheres]], [[particles]], [[boxes]], "
                             "[[rigid_spheres]] entry or a builder ([[ropes]], [[cloths]], "
                             "[[jellies]], [[crumple_bars]]).")
        self.colliders()
        self.springs()
        self.drag()
        mats = [m for m in scene.materials.values() if m.k is not None]
        k = k if k is not None else (mats[0].k if mats else 1e4)
        cs = [m.c for m in scene.materials.values() if m.c is not None]
        c = c if c is not None else (cs[0] if cs else 10.0)
        desc = doc.get("description", os.path.basename(self.path))
        V.string(self.w("description"), desc)
        fit_raw = doc.get("fit")
        sf = SceneFile(path=self.path, setup=None, fit=fit_raw, names=self.names,
                       planes=self.plane_names, nodes=self.nodes, compile_options=opts)
        spec = None
        if fit_raw is not None:
            spec = self.fit(sf, k, c)
        body = spec.body if spec else 0
        plane = spec.plane if spec else 0
        ball_like = (scene.planes and scene.bodies[body].radius > 0
                     and scene.bodies[body].kind == "sphere" and not scene.bodies[body].rigid)
        sf.setup = SceneSetup(
            scene=scene, dt=dt, steps=max(1, round(duration / dt)), k=k, c=c, law=law,
            body=body if scene.planes else None,
            metrics=_metrics(body, plane, spec.settle_tol if spec else 1e-3)
            if ball_like else None, description=desc,
            compile_options={key: v for key, v in opts.items() if key != "law"})
        sf.spec = spec
        return sf

    def broadphase(self):
        if "broadphase" not in self.doc:
            return None
        w = self.w("broadphase")
        t = self.doc["broadphase"]
        if isinstance(t, str):
            t = {"kind": t}
        V.table(w, t, example='broadphase = { kind = "grid" }')
        kind = V.choice(w / "kind", self.require(w, t, "kind"), ["aabb", "grid"])
        keys = ({"kind", "max_pairs", "margin"} if kind == "aabb" else
                {"kind", "max_pairs", "margin", "cell_size", "max_per_cell", "bounds"})
        V.check_keys(w, t, keys)
        kw = {}
        if "max_pairs" in t:
            kw["max_pairs"] = V.integer(w / "max_pairs", t["max_pairs"], low=1)
        if "margin" in t:
            kw["margin"] = V.number(w / "margin", t["margin"], low=0.0, unit="m")
        if kind == "aabb":
            return dp.broadphase.AABB(**kw)
        if "cell_size" in t:
            kw["cell_size"] = V.number(w / "cell_size", t["cell_size"], low=0.0,
                                       low_open=True, unit="m")
        if "max_per_cell" in t:
            kw["max_per_cell"] = V.integer(w / "max_per_cell", t["max_per_cell"], low=1)
        if "bounds" in t:
            b = t["bounds"]
            if not isinstance(b, list) or len(b) != 2:
                raise (w / "bounds").error("must be [[x0, y0, z0], [x1, y1, z1]] (m).")
            kw["bounds"] = tuple(V.vector(w / "bounds" / i, x, unit="m")
                                 for i, x in enumerate(b))
        return dp.broadphase.Grid(**kw)

    # ---------------------------------------------------------------- sizes
    def _count(self, w, e, key, default=None):
        v = e.get(key, default)
        return v if isinstance(v, int) and not isinstance(v, bool) and v > 0 else 0

    def check_sizes(self, dt, duration, has_broadphase):
        """Refuse, from estimates and before building, scenes too large to run."""
        lim = self.limits
        n_direct = {k: len(self.doc[k]) if isinstance(self.doc.get(k), list) else 0
                    for k in BODY_TABLES}
        n_nodes = 0
        for key in BUILDER_TABLES:
            for e in (self.doc.get(key) if isinstance(self.doc.get(key), list) else []):
                if not isinstance(e, dict):
                    continue
                if key in ("ropes", "crumple_bars"):
                    n = self._count(None, e, "n")
                    n_nodes += n * (2 if key == "crumple_bars" and "width" in e else 1)
                else:
                    dims = ("nx", "ny") if key == "cloths" else ("nx", "ny", "nz")
                    n_nodes += math.prod(self._count(None, e, d) for d in dims)
        n_bodies = sum(n_direct.values()) + n_nodes
        if n_bodies > lim["max_bodies"]:
            raise self.root.error(
                f"describes {n_bodies:,} bodies ({n_nodes:,} of them builder nodes); the limit "
                f"is {lim['max_bodies']:,} (building and compiling such a scene takes minutes "
                "and GiB). Make it smaller, or pass max_bodies= to load_scene_file.")
        spheres = [e for k in ("spheres", "rigid_spheres") for e in
                   (self.doc.get(k) if isinstance(self.doc.get(k), list) else [])
                   if isinstance(e, dict) and e.get("collide", True) is not False]
        boxes = [e for e in (self.doc.get("boxes") if isinstance(self.doc.get("boxes"), list)
                             else []) if isinstance(e, dict) and e.get("collide", True)
                 is not False]
        ns, nb = len(spheres), len(boxes)
        pairs = ns * (ns - 1) // 2 + ns * nb
        if not has_broadphase and pairs > lim["max_dense_pairs"]:
            mem = pairs * (3 * 4 + 12 * 8) / 2**30
            build = pairs * 1e-6
            raise self.root.error(
                f"has {ns:,} colliding spheres and {nb:,} boxes: {pairs:,} contact pairs "
                f"evaluated every step without a broad phase (about {mem:.1f} GiB of pair "
                f"arrays per step and {build / 60:.0f} min to list them before compiling); the "
                f"limit is {lim['max_dense_pairs']:,}. Add broadphase = {{ kind = \"grid\" }} "
                "(or { kind = \"aabb\", max_pairs = ... }) at the top level, or pass "
                "max_dense_pairs= to load_scene_file.")
        steps = duration / dt
        per_body = 13 if (n_direct["boxes"] or n_direct["rigid_spheres"]) else 6
        traj = steps * max(n_bodies, 1) * per_body * 8
        seconds = steps * max(1e-6, 2e-8 * (n_bodies + (pairs if not has_broadphase else
                                                         8 * n_bodies)))
        if steps > lim["max_steps"] or traj > lim["max_trajectory_bytes"]:
            raise self.w("duration").error(
                f"= {duration:g} s at dt = {dt:g} s is {steps:.3g} steps: a rollout saving "
                f"every step would hold about {human_bytes(traj)} and run for roughly "
                f"{human_time(seconds)}. The limits are {lim['max_steps']:,} steps and "
                f"{human_bytes(lim['max_trajectory_bytes'])}; shorten duration, raise dt, or pass "
                "max_steps= / max_trajectory_bytes= to load_scene_file.")

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
                    mass=V.number(w / "mass", self.require(w, e, "mass"), low=0.0,
                                  low_open=True, unit="kg"),
                    position=self.point(w / "position", self.require(w, e, "position")),
                    velocity=V.vector(w / "velocity", e.get("velocity", [0.0, 0.0, 0.0]),
                                      unit="m/s"),
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
            wb = V.vector(w / "body_angular_velocity", e["body_angular_velocity"],
                          unit="rad/s")
            kw["angular_velocity"] = _quat_rotate(q, wb)
        else:
            kw["angular_velocity"] = V.vector(w / "angular_velocity",
                                              e.get("angular_velocity", [0.0, 0.0, 0.0]),
                                              unit="rad/s")
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
                      "mass": V.number(w / "mass", self.require(w, e, "mass"), low=0.0,
                                       low_open=True, unit="kg"),
                      "velocity": V.vector(w / "velocity", e.get("velocity", [0.0, 0.0, 0.0]),
                                           unit="m/s"),
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

    # ---------------------------------------------------------------- [fit]
    def fit(self, sf: SceneFile, k, c) -> FitSpec:
        w = self.w("fit")
        fit = V.table(w, self.doc["fit"], example='[fit] params = ["contact.default.k"]')
        V.check_keys(w, fit, FIT)
        refs = self.refs()
        body = refs.body(w / "body", fit.get("body", 0))
        plane = 0
        if "plane" in fit:
            p = fit["plane"]
            if isinstance(p, str) and p in self.plane_names:
                plane = self.plane_names[p]
            else:
                plane = V.integer(w / "plane", p, low=0)
                if plane >= len(self.scene.planes):
                    raise (w / "plane").error(f"is plane {plane}, but the scene has "
                                              f"{len(self.scene.planes)} plane(s).")
        has_t, has_d = "targets" in fit, "data" in fit
        if has_t and has_d:
            raise w.error("has both [fit.targets] and data: give either targets (a bounce fit) "
                          "or data = \"record.csv\" (an array for several records), not both.")
        if not (has_t or has_d or fit.get("params")):
            raise w.error("says nothing to fit: add a [fit.targets] table, data = "
                          "\"record.csv\", or params = [...] (with records given on the "
                          "command line, diffpen fit SCENE.toml --data FILE.csv ...).")
        targets = None
        if has_t:
            targets = self.targets(w / "targets", fit["targets"])
        data = V.path_list(w / "data", fit["data"], suffix=".csv") if has_d else None
        observe = [n for n in self.names if "[" not in n]      # the named bodies
        if "observe" in fit:
            o = fit["observe"]
            items = o if isinstance(o, list) else [o]
            if not items:
                raise (w / "observe").error("is empty: name the observed bodies.")
            observe = []
            for j, x in enumerate(items):
                wj = w / "observe" / j if isinstance(o, list) else w / "observe"
                V.string(wj, x)
                refs.body(wj, x)
                observe.append(x)
        method = V.choice(w / "method", fit.get("method", "lm"), ["lm", "adam", "sgd"])
        maxiter = (V.integer(w / "maxiter", fit["maxiter"], low=1) if "maxiter" in fit
                   else None)
        lr = V.number(w / "lr", fit.get("lr", 0.05), low=0.0, low_open=True)
        settle = V.number(w / "settle_tol", fit.get("settle_tol", 1e-3), low=0.0,
                          low_open=True, unit="m")
        weights = None
        if "weights" in fit:
            ww = w / "weights"
            weights = {kk: V.number(ww / kk, v, low=0.0)
                       for kk, v in V.table(ww, fit["weights"],
                                            example="[fit.weights] settling_time = 2").items()}
            if targets is not None:
                bad = [kk for kk in weights if kk not in targets]
                if bad:
                    raise (ww / bad[0]).error(f"weights a target that is not given; targets: "
                                              f"{', '.join(targets)}.")
        free, bounds, space = self.fit_params(w, fit, sf, k, c)
        return FitSpec(free=free, bounds=bounds, space=space, targets=targets, data=data,
                       body=body, plane=plane, observe=observe, method=method,
                       maxiter=maxiter, lr=lr, weights=weights, settle_tol=settle)

    def targets(self, w, t):
        V.table(w, t, example="[fit.targets] apex_heights = [0.4]")
        if not t:
            raise w.error(f"is empty: give at least one of {', '.join(sorted(TARGETS))}.")
        V.check_keys(w, t, TARGETS)
        out = {}
        for key, v in t.items():
            if key in ("apex_heights", "contact_durations"):
                out[key] = V.number_list(w / key, v, low=0.0, low_open=True,
                                         unit="m" if key == "apex_heights" else "s")
            elif key == "restitution":
                out[key] = V.number_list(w / key, v, low=0.0, low_open=True, high=1.0)
            else:
                out[key] = V.number(w / key, v, low=0.0, low_open=True,
                                    unit="s" if key == "settling_time" else "m")
        return out

    def fit_params(self, w, fit, sf, k, c):
        """Free leaf paths, checked against the key paths of the compiled params pytree."""
        names = fit.get("params", [])
        if isinstance(names, str):
            names = [names]
        if not isinstance(names, list) or not all(isinstance(p, str) and p for p in names):
            raise (w / "params").error(f"must be an array of parameter paths (strings such as "
                                       f"\"contact.default.k\"), got {V._show(fit.get('params'))}.")
        for key in ("bounds", "space"):
            if key in fit:
                V.table(w / key, fit[key], example=f'[fit.{key}] "contact.default.k" = ...')
        if not names and not fit.get("bounds") and not fit.get("space"):
            return [], {}, {}
        # everything that needs no parameter structure is checked before the simulator is built
        given_space = {p: V.choice(w / "space" / p, s, ["log", "linear"])
                       for p, s in fit.get("space", {}).items()}
        given_bounds = {}
        for p, b in fit.get("bounds", {}).items():
            wp = w / "bounds" / p
            if not isinstance(b, list) or len(b) != 2:
                raise wp.error(f"must be [lo, hi], got {V._kind(b)} {V._show(b)}.")
            lo, hi = (V.number(wp / j, x) for j, x in enumerate(b))
            if not lo < hi:
                raise wp.error(f"needs lo < hi, got [{lo:g}, {hi:g}].")
            given_bounds[p] = (lo, hi)
        try:
            with np.errstate(over="ignore"):      # only the structure is needed here
                sim = dp.compile(self.scene, self.dt, **sf.compile_options)
                params = _default_params(sim, k, c)
            sf._sim = (_x64(), sim)
        except dp.SceneError as exc:
            raise w.error(f"cannot build the parameters: {exc}") from None
        leaves = param_leaves(params)
        alias = _keystr_paths(params)

        def resolve(wp, p):
            p = p.strip()
            if p in leaves:
                return p
            if p in alias:
                return alias[p]
            raise wp.error(f"{p!r} is not a parameter of this scene; its parameters are: "
                           f"{', '.join(leaves) or 'none'}.")
        free = []
        for i, p in enumerate(names):
            q = resolve(w / "params" / i, p)
            if q in free:
                raise (w / "params" / i).error(f"names {q!r} twice.")
            free.append(q)
        space = {p: leaf_space(p, leaves[p]) for p in free}
        for p, s in given_space.items():
            q = resolve(w / "space" / p, p)
            if q not in free:
                raise (w / "space" / p).error(f"sets the space of {q!r}, which is not in [fit] "
                                              "params; add it there.")
            space[q] = s
        bounds = {}
        for p, (lo, hi) in given_bounds.items():
            wp = w / "bounds" / p
            q = resolve(wp, p)
            if q not in free:
                raise wp.error(f"bounds {q!r}, which is not in [fit] params; add it there.")
            v = float(np.asarray(leaves[q]))
            if space.get(q) == "log" and lo <= 0.0:
                raise wp.error(f"has lo = {lo:g} <= 0 for a leaf fitted in log space; give lo "
                               "> 0, or set [fit.space] to \"linear\" for it.")
            if not lo <= v <= hi:
                raise wp.error(f"[{lo:g}, {hi:g}] does not contain the start value {v:g} from "
                               "the scene; widen the bounds or change the start value.")
            bounds[q] = (lo, hi)
        for q, s in space.items():
            if s == "log" and float(np.asarray(leaves[q])) <= 0.0:
                raise (w / "params").error(f"{q!r} starts at {float(np.asarray(leaves[q])):g}, "
                                           "which log space cannot hold; give it a positive "
                                           "start value or fit it in linear space.")
        return free, bounds, space


def _x64() -> bool:
    import jax
    return bool(jax.config.jax_enable_x64)


def _takes(fn, name: str) -> bool:
    """Whether ``fn`` accepts keyword ``name`` (options newer than some library builds)."""
    try:
        return name in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def _metrics(body, plane, tol):
    def metrics(sim, traj, params):
        import jax

        from .metrics import ball_metrics
        f = jax.jit(lambda tr, p: ball_metrics(sim, tr, p, body=body, plane=plane, n_apex=3,
                                               settle_tol=tol))
        return f(traj, params).as_dict()
    return metrics


# --------------------------------------------------------------------------- fitting
def fit_file(path: str, *, progress=None, method: str | None = None, lr: float | None = None,
             maxiter: int | None = None):
    """Run the bounce or ball-record fit a scene file describes. Returns ``(summary dict,
    plot_fn or None)``. Everything in the file is validated before anything is compiled; JAX
    settings (float64, caches) are the caller's (the command line sets them)."""
    sf = load_scene_file(path)
    if sf.spec is None:
        raise SceneFileError(f"{path} has no [fit] table: add [fit.targets] (or data = ...) to "
                             "say what to fit.", path=path, key="fit")
    spec, scene = sf.spec, sf.scene
    w = Where(path, "fit")
    if spec.targets is None and spec.data is None:
        raise w.error("has no targets or data: add [fit.targets], data = \"record.csv\", or "
                      "give the records on the command line (--data FILE.csv ...).")
    method = method or spec.method
    lr = spec.lr if lr is None else lr
    if not scene.planes:
        raise (w / "plane").error("needs a plane to bounce on: add a [[planes]] entry.")
    b = scene.bodies[spec.body]
    if b.kind != "sphere" or b.rigid:
        raise (w / "body").error(f"is a {'rigid ' if b.rigid else ''}{b.kind}: this fit needs "
                                 "a (non-rotating) sphere bouncing on a plane; fits of other "
                                 "bodies to records are run by the record fit.")
    if spec.bounds:
        raise (w / "bounds").error("applies to record fits of several parameters; a bounce "
                                   "fit keeps k within its accuracy limit by itself: remove "
                                   "[fit.bounds].")
    mat = scene.planes[spec.plane].material
    if spec.data is not None:
        if len(spec.data) != 1:
            raise (w / "data").error("names several records: a ball fit reads one t,z record.")
        from .sysid import fit_trajectory, load_csv
        t, z = load_csv(spec.data[0])
        law = dp.laws.get(sf.setup.law, sf.setup.compile_options.get("exponent", 1.0))
        res = fit_trajectory(t, z, radius=b.radius, mass=b.mass, law=law,
                             g=-scene.gravity[2], progress=progress,
                             maxiter=maxiter or spec.maxiter or 15)
        name = os.path.basename(spec.data[0])
        out = {"scene": f"{path}: body {spec.body} fitted to {name}", "k": res.k, "c": res.c,
               "k_stderr": res.k_stderr, "c_stderr": res.c_stderr,
               "targets": {"data": name}, "achieved": {"rms_residual": res.rms},
               "iterations": res.iterations, "seconds": res.seconds,
               "message": res.message, "notes": res.notes,
               "reached": getattr(res, "reached", True)}
        return out, None
    import optax

    from .bounce import fit_bounce
    opt = None if method == "lm" else (optax.adam(lr) if method == "adam" else optax.sgd(lr))
    m = scene.materials[mat]
    # with a settling-time target k is searched for; otherwise the file's k is the start
    searched = "settling_time" in spec.targets
    res = fit_bounce(scene, spec.targets, dt=sf.setup.dt, law=sf.setup.law, body=spec.body,
                     plane=spec.plane, settle_tol=spec.settle_tol,
                     k0=None if searched else (m.k if m.k is not None else sf.setup.k),
                     c0=None if searched else (m.c if m.c is not None else sf.setup.c),
                     free=spec.free or None, method="lm" if opt is None else "optax",
                     optimizer=opt, maxiter=maxiter or spec.maxiter, weights=spec.weights,
                     progress=progress, **sf.setup.compile_options)
    cp = res.params.contact[mat]
    out = {"scene": f"{path} ({sf.setup.description})", "k": float(cp.k), "c": float(cp.c),
           "fitted": res.values, "targets": res.targets, "achieved": res.achieved,
           "rel_error": res.rel_error, "reached": res.reached, "iterations": res.iterations,
           "evaluations": res.evaluations, "seconds": res.seconds, "message": res.message,
           "notes": res.notes}
    return out, None
