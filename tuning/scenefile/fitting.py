"""Running the bounce or ball-record fit a scene file describes (:func:`fit_file`)."""
from __future__ import annotations

import os

import diffpen as dp

from ..errors import FitError
from ..validate import SceneFileError, Where
from .loader import load_scene_file


# --------------------------------------------------------------------------- fitting
def fit_file(path: str, *, progress=False, method: str | None = None, lr: float | None = None,
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
        from ..sysid import fit_trajectory, load_csv
        t, z = load_csv(spec.data[0])
        law = dp.laws.get(sf.setup.law, sf.setup.compile_options.get("exponent", 1.0))
        try:
            res = fit_trajectory(t, z, radius=b.radius, mass=b.mass, law=law,
                                 g=-scene.gravity[2], progress=progress,
                                 maxiter=maxiter or spec.maxiter or 15)
        except FitError as exc:     # name the scene file and its record (the message did not)
            raise FitError(f"{path}: [fit] data {spec.data[0]}: {exc}") from None
        name = os.path.basename(spec.data[0])
        out = {"scene": f"{path}: body {spec.body} fitted to {name}", "k": res.k, "c": res.c,
               "k_stderr": res.k_stderr, "c_stderr": res.c_stderr,
               "targets": {"data": name}, "achieved": {"rms_residual": res.rms},
               "iterations": res.iterations, "seconds": res.seconds,
               "message": res.message, "notes": res.notes,
               "reached": getattr(res, "reached", True)}
        return out, None
    import optax

    from ..bounce import fit_bounce
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
