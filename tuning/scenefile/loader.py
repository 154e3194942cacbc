"""Reading a TOML scene file: :func:`load_scene_file` and the loader's top level (run
settings, broad phase), which calls the element, size and ``[fit]`` readers."""
from __future__ import annotations

import os
import re
import tomllib

import diffpen as dp

from .. import validate as V
from ..metrics import ball_model_gaps
from ..scenes import SceneSetup
from ..validate import SceneFileError, Where
from .advice import file_advice
from .elements import _ElementTables
from .fitspec import _FitTable
from .record import SceneFile
from .schema import (DEFAULT_C, DEFAULT_K, MAX_BODIES, MAX_COORD, MAX_DENSE_PAIRS, MAX_MASS,
                     MAX_SPEED, MAX_STEPS, MAX_TRAJECTORY_BYTES, TOP, _NAME, _takes)
from .sizes import _SizeGuards


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


class _Loader(_ElementTables, _SizeGuards, _FitTable):
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
            table = re.split(r"[.\[]", w.key, maxsplit=1)[0]
            raise w.error(file_advice(str(exc), table, self.doc)) from None

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

    @staticmethod
    def speed(w: Where, v, unit: str = "m/s") -> tuple:
        """A start velocity (m/s) or angular velocity (rad/s), each component within
        MAX_SPEED."""
        return V.vector(w, v, unit=unit, limit=MAX_SPEED, beyond=(
            f"give a start speed in {unit} below that (a faster one is a unit slip or not a "
            "motion this simulator steps)."))

    @staticmethod
    def mass(w: Where, v) -> float:
        """A body's mass, kg, in (0, MAX_MASS]."""
        return V.number(w, v, low=0.0, low_open=True, high=MAX_MASS, unit="kg")

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
        if duration < dt * (1.0 - 1e-9):
            raise self.w("duration").error(
                f"= {duration:g} s is shorter than one step (dt = {dt:g} s): the rollout "
                f"runs round(duration / dt) steps; give duration >= {dt:g} s or a smaller dt.")
        law = V.choice(self.w("law"), doc.get("law", "linear"), sorted(dp.laws.CONTACT_LAWS))
        opts = {"law": law}
        takes = [n for n, rec in sorted(dp.laws.CONTACT_LAWS.items()) if rec.takes_exponent]
        if "exponent" in doc and law not in takes:
            names = " or ".join(f'"{n}"' for n in takes)
            raise self.w("exponent").error(
                f"applies only to law = {names}, but law = {law!r}: remove exponent, or set "
                f"law = {names}.")
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
        # a material without its own k / c takes the top-level k / c, else the documented
        # defaults (never another material's)
        k = DEFAULT_K if k is None else k
        c = DEFAULT_C if c is None else c
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
                     and scene.bodies[body].kind == "sphere" and not scene.bodies[body].rigid
                     and not ball_model_gaps(scene, body))     # springs, drag: not a ball
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
            kw["bounds"] = lo, hi = tuple(V.vector(w / "bounds" / i, x, unit="m")
                                          for i, x in enumerate(b))
            bad = [a for a, x0, x1 in zip("xyz", lo, hi) if not x0 < x1]
            if bad:
                raise (w / "bounds").error(
                    f"= {V._show(b, 60)} has lo >= hi on {', '.join(bad)}: give "
                    "[[x0, y0, z0], [x1, y1, z1]] (m) with x0 < x1, y0 < y1 and z0 < z1.")
        return dp.broadphase.Grid(**kw)


def _metrics(body, plane, tol):
    def metrics(sim, traj, params):
        from ..metrics import ball_metrics_dict
        return ball_metrics_dict(sim, traj, params, body=body, plane=plane, n_apex=3,
                                 settle_tol=tol)
    return metrics
