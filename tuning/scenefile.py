"""TOML scene files: bodies, colliders, materials, springs, targets and what to fit, so that
``diffpen fit myscene.toml`` fits a user's own scene without Python.

Format (SI units; every table is optional except one body)::

    gravity = [0.0, 0.0, -9.81]     # m/s^2
    dt = 1e-3                       # s
    duration = 3.0                  # s, default rollout length
    law = "linear"                  # or "no_tension", "hunt_crossley"

    [materials.rubber]              # contact material: start/default k (N/m), c (N s/m)
    k = 1e4
    c = 20.0

    [[spheres]]                     # body 0
    radius = 0.1
    mass = 1.0
    position = [0.0, 0.0, 1.0]
    velocity = [0.0, 0.0, 0.0]      # optional
    material = "rubber"             # optional (default "default")

    [[particles]]                   # optional: mass, position, velocity, pinned
    [[planes]]                      # normal (default [0, 0, 1]), offset (0), material
    [[fixed_spheres]]               # center, radius, material
    [[springs]]                     # a, b (body index or [x, y, z]), k, c, rest_length, group

    [fit]
    body = 0                        # the bouncing body (default 0); plane = 0
    params = ["contact.rubber.k", "contact.rubber.c"]   # default: k and c of the plane's
    settle_tol = 1e-3               # material
    [fit.targets]                   # any of: apex_heights, settling_time,
    apex_heights = [0.4]            # contact_durations, restitution, max_penetration
    settling_time = 2.6
    # data = "record.csv"           # instead of targets: a measured t,z record (relative
                                    # to this file) of the body's centre height

Bodies are numbered in file order: spheres first, then particles. Every value is checked when
the file is read, with the file name and the entry in the message.
"""
from __future__ import annotations

import dataclasses
import math
import os
import tomllib

import diffpen as dp

from .fit import FitError
from .scenes import SceneSetup

__all__ = ["load_scene_file", "SceneFile", "fit_file", "SceneFileError"]

TOP = {"gravity", "dt", "duration", "law", "materials", "spheres", "particles", "planes",
       "fixed_spheres", "springs", "fit", "description", "k", "c"}
FIT = {"body", "plane", "params", "settle_tol", "targets", "data", "method", "maxiter",
       "weights"}


class SceneFileError(FitError):
    """A scene file that cannot be read or describes an invalid scene."""


@dataclasses.dataclass
class SceneFile:
    """A parsed scene file: ``setup`` (a :class:`tuning.scenes.SceneSetup`) and the ``fit``
    table (dict, or None), with ``path`` for relative file names."""
    path: str
    setup: SceneSetup
    fit: dict | None


def _check_keys(where: str, table: dict, allowed: set, path: str) -> None:
    bad = set(table) - allowed
    if bad:
        raise SceneFileError(f"{path}: unknown key(s) {sorted(bad)} in {where}; allowed: "
                             f"{sorted(allowed)}.")


def load_scene_file(path: str) -> SceneFile:
    """Read and validate a TOML scene file (nothing is compiled)."""
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except OSError as exc:
        raise SceneFileError(f"cannot read {path}: {exc.strerror}.") from None
    except tomllib.TOMLDecodeError as exc:
        raise SceneFileError(f"{path} is not valid TOML: {exc}.") from None
    _check_keys("the top level", doc, TOP, path)
    try:
        scene = dp.Scene(gravity=doc.get("gravity", (0.0, 0.0, -9.81)))
        for name, mat in doc.get("materials", {}).items():
            _check_keys(f"[materials.{name}]", mat, {"k", "c"}, path)
            scene.add_material(name, k=mat.get("k"), c=mat.get("c"))
        for i, s in enumerate(doc.get("spheres", [])):
            _check_keys(f"[[spheres]] #{i}", s, {"radius", "mass", "position", "velocity",
                                                 "material", "pinned"}, path)
            scene.add_sphere(radius=s["radius"], mass=s["mass"], position=s["position"],
                             velocity=s.get("velocity", (0.0, 0.0, 0.0)),
                             pinned=s.get("pinned", False),
                             material=s.get("material", "default"))
        for i, s in enumerate(doc.get("particles", [])):
            _check_keys(f"[[particles]] #{i}", s, {"mass", "position", "velocity", "pinned",
                                                   "material"}, path)
            scene.add_particle(mass=s["mass"], position=s["position"],
                               velocity=s.get("velocity", (0.0, 0.0, 0.0)),
                               pinned=s.get("pinned", False),
                               material=s.get("material", "default"))
        for i, s in enumerate(doc.get("planes", [])):
            _check_keys(f"[[planes]] #{i}", s, {"normal", "offset", "material"}, path)
            scene.add_plane(normal=s.get("normal", (0.0, 0.0, 1.0)), offset=s.get("offset", 0.0),
                            material=s.get("material", "default"))
        for i, s in enumerate(doc.get("fixed_spheres", [])):
            _check_keys(f"[[fixed_spheres]] #{i}", s, {"center", "radius", "material"}, path)
            scene.add_fixed_sphere(center=s["center"], radius=s["radius"],
                                   material=s.get("material", "default"))
        for i, s in enumerate(doc.get("springs", [])):
            _check_keys(f"[[springs]] #{i}", s, {"a", "b", "k", "c", "rest_length", "group"},
                        path)
            b = s["b"]
            scene.add_spring(s["a"], b if isinstance(b, int) else tuple(b), k=s.get("k"),
                             c=s.get("c"), rest_length=s.get("rest_length"),
                             group=s.get("group", "default"))
    except KeyError as exc:
        raise SceneFileError(f"{path}: missing required key {exc.args[0]!r}.") from None
    except dp.SceneError as exc:
        raise SceneFileError(f"{path}: {exc}") from None
    if not scene.bodies:
        raise SceneFileError(f"{path}: no bodies; add a [[spheres]] or [[particles]] entry.")
    dt = doc.get("dt", 1e-3)
    duration = doc.get("duration", 3.0)
    for name, v in (("dt", dt), ("duration", duration)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise SceneFileError(f"{path}: {name} must be a positive number of seconds, got "
                                 f"{v!r}.")
    law = doc.get("law", "linear")
    if law not in ("linear", "no_tension", "hunt_crossley"):
        raise SceneFileError(f"{path}: law must be linear, no_tension or hunt_crossley, got "
                             f"{law!r}.")
    fit = doc.get("fit")
    if fit is not None:
        _check_keys("[fit]", fit, FIT, path)
        if ("targets" in fit) == ("data" in fit):
            raise SceneFileError(f"{path}: [fit] needs either a [fit.targets] table or "
                                 "data = \"record.csv\" (not both).")
    mats = [m for m in scene.materials.values() if m.k is not None]
    k = doc.get("k", mats[0].k if mats else 1e4)
    c = doc.get("c", mats[0].c if mats and mats[0].c is not None else 10.0)
    setup = SceneSetup(scene=scene, dt=float(dt), steps=max(1, round(duration / dt)), k=k,
                       c=c, law=law, body=0 if scene.planes else None,
                       metrics=_metrics(fit) if scene.planes and scene.bodies[0].radius > 0
                       else None, description=doc.get("description", os.path.basename(path)))
    return SceneFile(path=path, setup=setup, fit=fit)


def _metrics(fit):
    body = (fit or {}).get("body", 0)
    plane = (fit or {}).get("plane", 0)
    tol = (fit or {}).get("settle_tol", 1e-3)

    def metrics(sim, traj, params):
        import jax

        from .metrics import ball_metrics
        f = jax.jit(lambda tr, p: ball_metrics(sim, tr, p, body=body, plane=plane, n_apex=3,
                                               settle_tol=tol))
        return f(traj, params).as_dict()
    return metrics


def fit_file(path: str, *, progress=None, method: str = "lm", lr: float = 0.05,
             maxiter: int | None = None):
    """Run the fit a scene file describes. Returns ``(summary dict, plot_fn or None)``.

    Targets are validated against the scene before anything is compiled; the start values
    are the materials' k and c from the file."""
    sf = load_scene_file(path)
    if sf.fit is None:
        raise SceneFileError(f"{path} has no [fit] table: add [fit.targets] (or data = ...) to "
                             "say what to fit.")
    from .cli._common import setup_jax
    setup_jax()
    fit = sf.fit
    scene = sf.setup.scene
    body, plane = fit.get("body", 0), fit.get("plane", 0)
    if not scene.planes or not 0 <= plane < len(scene.planes):
        raise SceneFileError(f"{path}: [fit] needs plane {plane} to bounce on.")
    if not 0 <= body < scene.n_bodies:
        raise SceneFileError(f"{path}: [fit] body {body} is not in the scene.")
    mat = scene.planes[plane].material
    m = scene.materials[mat]
    if "data" in fit:
        from .sysid import fit_trajectory, load_csv
        data = os.path.join(os.path.dirname(os.path.abspath(path)), fit["data"])
        t, z = load_csv(data)
        b = scene.bodies[body]
        res = fit_trajectory(t, z, radius=b.radius, mass=b.mass, law=sf.setup.law,
                             g=-scene.gravity[2], progress=progress,
                             maxiter=maxiter or 15)
        out = {"scene": f"{path}: body {body} fitted to {fit['data']}", "k": res.k, "c": res.c,
               "k_stderr": res.k_stderr, "c_stderr": res.c_stderr,
               "targets": {"data": fit["data"]}, "achieved": {"rms_residual": res.rms},
               "iterations": res.iterations, "seconds": res.seconds,
               "message": res.message, "notes": res.notes, "reached": True}
        return out, None
    import optax

    from .bounce import fit_bounce
    opt = None if method == "lm" else (optax.adam(lr) if method == "adam" else optax.sgd(lr))
    # with a settling-time target k is searched for; otherwise the file's k is the start
    searched = "settling_time" in fit["targets"]
    res = fit_bounce(scene, fit["targets"], dt=sf.setup.dt, law=sf.setup.law, body=body,
                     plane=plane, settle_tol=fit.get("settle_tol", 1e-3),
                     k0=None if searched else m.k, c0=None if searched else m.c,
                     free=fit.get("params"), method="lm" if opt is None else "optax",
                     optimizer=opt, maxiter=maxiter or fit.get("maxiter"),
                     weights=fit.get("weights"), progress=progress)
    cp = res.params.contact[mat]
    out = {"scene": f"{path} ({sf.setup.description})", "k": float(cp.k), "c": float(cp.c),
           "fitted": res.values, "targets": res.targets, "achieved": res.achieved,
           "rel_error": res.rel_error, "reached": res.reached, "iterations": res.iterations,
           "evaluations": res.evaluations, "seconds": res.seconds, "message": res.message,
           "notes": res.notes}
    return out, None

