"""Accuracy against run time (work-precision) of every integrator: error against an independent
reference (:mod:`tuning.reports.reference`) on a ladder of dt, for a ball drop, a damped spring
and a hanging chain, with the median wall time of each run; the cheapest integrator and dt that
meet a tolerance; the log-log diagram.

Everything here computes and returns plain data (dicts, lists), except
:func:`plot_accuracy`, which writes a figure; ``tuning.cli.report`` prints. Times are medians
of several runs after compilation, measured with ``jax.block_until_ready``.

Units: SI throughout (m, kg, s, N/m, N s/m).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax.numpy as jnp
import numpy as np

import diffpen as dp

from ..io import save_figure_file
from ..scenes import ball_scene
from .extreme import INTEGRATORS
from .reference import (G, BallReference, apex_heights, ball_reference, chain_reference,
                        settling_time, spring_closed_form)
from .timing import median_time

__all__ = ["BallSpec", "horizon", "accuracy", "recommend", "plot_accuracy"]


# --------------------------------------------------------------------------- accuracy
@dataclasses.dataclass
class BallSpec:
    """The ball problem: k (N/m), c (N s/m), mass (kg), radius (m), drop height of the centre
    (m), simulated time T (s), apexes compared, settling energy fraction."""
    k: float = 1e4
    c: float = 20.0
    mass: float = 1.0
    radius: float = 0.1
    height: float = 1.0
    T: float = 3.0
    n_apex: int = 3
    settle_frac: float = 0.01


def _landing_time(ref: BallReference, n: int) -> float:
    """Time (s) the ball lands after its ``n``-th apex (the start of contact ``n + 1``; inf if
    the reference has no such contact): an apex counts once its flight has ended."""
    return ref.contacts[n][0] if len(ref.contacts) > n else math.inf


def _too_few_bounces(spec: BallSpec) -> str:
    """What to change when the reference ball bounces too few times: the damping when it is
    damped (damping ratio > 0.1), else k: a ball damped a little (restitution ~ exp(-pi zeta)
    > 0.7) bounces often, and its reference fails because the integration cannot resolve a
    contact that short (k 1e18 N/m on 1 kg: 3e-9 s)."""
    zeta = spec.c / (2.0 * math.sqrt(spec.k * spec.mass))
    if zeta > 0.1:
        return f"lower the damping c (damping ratio {zeta:.3g})"
    return (f"its contact lasts only {math.pi * math.sqrt(spec.mass / spec.k):.3g} s (damping "
            f"ratio {zeta:.3g}), too short for the reference integration to resolve: lower k")


def horizon(spec: BallSpec, longest: float = 60.0) -> float:
    """The simulated time (s) the ball's report needs: past the landing after its
    ``n_apex``-th apex (an apex counts once its flight has ended) and 10% past its settling
    time when it settles, 3 s at least (the default ``BallSpec.T``). Raises ValueError when
    the ball does not bounce that often within ``longest`` s."""
    ref = ball_reference(k=spec.k, c=spec.c, m=spec.mass, r=spec.radius, z0=spec.height,
                         T=longest)
    landing = _landing_time(ref, spec.n_apex)
    if len(ref.apexes) < spec.n_apex or not landing < longest:
        raise ValueError(f"the ball (k {spec.k:g} N/m, c {spec.c:g} N s/m, {spec.mass:g} kg, "
                         f"dropped from {spec.height:g} m) does not bounce {spec.n_apex} "
                         f"times within {longest:g} s: {_too_few_bounces(spec)}")
    need = [3.0, landing + 0.05]
    ts = ref.settling_time(spec.settle_frac)
    if math.isfinite(ts) and ts < longest:
        need.append(1.1 * ts)
    return max(need)


def _ball_errors(spec: BallSpec, ref: BallReference, t, z, v):
    ap = apex_heights(t, z, spec.radius, spec.n_apex)
    ap_ref = np.array(ref.apexes[:spec.n_apex])
    rel = np.abs(ap - ap_ref) / (ap_ref - spec.radius)
    d = np.maximum(spec.radius - z, 0.0)
    e = (0.5 * spec.mass * v * v + spec.mass * G * (z - spec.radius)
         + 0.5 * spec.k * d * d)
    e_all = np.concatenate([[spec.mass * G * (spec.height - spec.radius)], e])
    t_all = np.concatenate([[0.0], t])
    ts = settling_time(t_all, e_all, spec.settle_frac)
    ts_ref = ref.settling_time(spec.settle_frac)
    return {"apex_rel_error": float(np.max(rel)) if np.all(np.isfinite(rel)) else math.inf,
            "apexes": ap.tolist(), "settling_time": ts,
            "settling_error": abs(ts - ts_ref) if math.isfinite(ts) else math.inf}


def _dts(coarse: float, n: int):
    return [coarse / 2 ** i for i in range(n)]


def accuracy(*, ball: BallSpec | None = None, integrators=INTEGRATORS, n_dt: int = 6,
             coarse_dt: float = 4e-3, widths=(0.0, 1e-5, 1e-4, 1e-3, 1e-2),
             width_dt: float = 1.25e-4, repeats: int = 5, problems=("ball", "spring", "chain"),
             default_dtypes=("float32", "float64"), progress: Callable | None = None,
             dts=None) -> dict:
    """Error against run time for each integrator and a ladder of dt (halving from
    ``coarse_dt``), on three problems, against independent references:

    * ``ball``: drop onto the plane (linear law, smoothing 0): max relative error of the first
      apex heights (above the plane) against the DOP853 reference with located contact
      events; settling time (energy to 1%) error in s.
    * ``spring``: particle on a damped world spring (k = 100 N/m, m = 1 kg, zeta = 0.1,
      x0 = 0.1 m, 2 s): max |x - x_exact| / x0 against the closed form.
    * ``chain``: 6 particles hanging from a pinned one (k = 200 N/m, c = 0.5 N s/m, 0.1 kg),
      released sideways, 1.5 s: max tip position error / chain length against DOP853.

    Plus the ball's smoothing-width ladder (semi-implicit Euler at ``width_dt``) and the
    default configuration (semi-implicit Euler, dt = 1e-3 s, default smoothing) in each of
    ``default_dtypes``. A rollout the simulator refuses (``StabilityError``) or that blows up
    (``NonFiniteError``) is a point of infinite error with the error's name as ``"note"``.
    Times: median of ``repeats`` rollouts of the whole problem after compilation. ``dts``
    (s), when given, replaces the halving ladder for every problem.
    Returns a JSON-able dict: ``{"problems": {name: {integrator: [points]}}, "widths":
    [...], "default": [...], "ball": spec}``; a point is ``{"dt", "error", "time", ...}``.
    """
    spec = ball or BallSpec()
    say = progress or (lambda *_: None)
    out = {"ball": dataclasses.asdict(spec), "problems": {}, "widths": [], "default": []}
    ref = ball_reference(k=spec.k, c=spec.c, m=spec.mass, r=spec.radius, z0=spec.height,
                         T=spec.T)
    if "ball" in problems and not (len(ref.apexes) >= spec.n_apex
                                   and _landing_time(ref, spec.n_apex) < spec.T):
        raise ValueError(f"the ball's apex {spec.n_apex} comes after T = {spec.T:g} s: give a "
                         f"longer BallSpec.T (tuning.reports.accuracy.horizon picks one)")
    if "ball" in problems:
        scene = ball_scene(mass=spec.mass, radius=spec.radius, height=spec.height)
        res = {}
        for integ in integrators:
            pts = []
            for dt in dts or _dts(coarse_dt, n_dt):
                sim = dp.compile(scene, dt, integrator=integ, smoothing=0.0,
                                 dtype=jnp.float64, substeps="auto")
                params = sim.params(k=spec.k, c=spec.c)
                steps = int(round(spec.T / dt))
                try:
                    traj = sim.rollout(params, steps)
                except (dp.StabilityError, dp.NonFiniteError) as e:
                    pts.append({"dt": dt, "error": math.inf, "time": math.nan,
                                "note": type(e).__name__})
                    continue
                t = np.asarray(traj.time)
                z, v = (np.asarray(traj.position)[:, 0, 2], np.asarray(traj.velocity)[:, 0, 2])
                errs = _ball_errors(spec, ref, t, z, v)
                wall = median_time(lambda: sim.rollout(params, steps).position, repeats=repeats)
                pts.append({"dt": dt, "error": errs["apex_rel_error"], "time": wall,
                            "settling_error": errs["settling_error"],
                            "substeps": sim.stability(params).substeps_needed})
                say("ball", integ, pts[-1])
            res[integ] = pts
        out["problems"]["ball"] = res
        out["reference"] = {"apexes": ref.apexes[:spec.n_apex],
                            "settling_time": ref.settling_time(spec.settle_frac)}
        # smoothing width ladder and the default configuration
        for w in widths:
            sim = dp.compile(scene, width_dt, smoothing=w, dtype=jnp.float64)
            steps = int(round(spec.T / width_dt))
            try:
                traj = sim.rollout(sim.params(k=spec.k, c=spec.c), steps)
            except (dp.StabilityError, dp.NonFiniteError) as e:    # refused, as in the ladder
                out["widths"].append({"width": w, "dt": width_dt, "error": math.inf,
                                      "settling_error": math.inf, "note": type(e).__name__})
                say("width", w, out["widths"][-1])
                continue
            errs = _ball_errors(spec, ref, np.asarray(traj.time),
                                np.asarray(traj.position)[:, 0, 2],
                                np.asarray(traj.velocity)[:, 0, 2])
            out["widths"].append({"width": w, "dt": width_dt, "error": errs["apex_rel_error"],
                                  "settling_error": errs["settling_error"]})
            say("width", w, out["widths"][-1])
        for dtype in default_dtypes:
            sim = dp.compile(scene, 1e-3, dtype=jnp.dtype(dtype))
            params = sim.params(k=spec.k, c=spec.c)
            steps = int(round(spec.T / 1e-3))
            try:
                traj = sim.rollout(params, steps)
            except (dp.StabilityError, dp.NonFiniteError) as e:    # refused, as in the ladder
                out["default"].append({"dtype": dtype, "dt": 1e-3, "smoothing": sim.smoothing,
                                       "steps": steps, "error": math.inf,
                                       "settling_error": math.inf, "time": math.nan,
                                       "time_per_step": math.nan, "note": type(e).__name__})
                say("default", dtype, out["default"][-1])
                continue
            errs = _ball_errors(spec, ref, np.asarray(traj.time, float),
                                np.asarray(traj.position, float)[:, 0, 2],
                                np.asarray(traj.velocity, float)[:, 0, 2])
            wall = median_time(lambda: sim.rollout(params, steps).position, repeats=repeats)
            out["default"].append({"dtype": dtype, "dt": 1e-3, "smoothing": sim.smoothing,
                                   "steps": steps, "error": errs["apex_rel_error"],
                                   "settling_error": errs["settling_error"], "time": wall,
                                   "time_per_step": wall / steps})
            say("default", dtype, out["default"][-1])
    if "spring" in problems:
        k, c, m, x0, T = 100.0, 2.0, 1.0, 0.1, 2.0
        scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
        p = scene.add_particle(mass=m, position=(0.0, 0.0, 1.0 + x0))
        scene.add_spring(p, (0.0, 0.0, 0.0), k=k, c=c, rest_length=1.0)
        res = {}
        for integ in integrators:
            pts = []
            for dt in dts or _dts(coarse_dt * 2.5, n_dt):
                sim = dp.compile(scene, dt, integrator=integ, dtype=jnp.float64)
                params = sim.params()
                steps = int(round(T / dt))
                traj = sim.rollout(params, steps)
                x = np.asarray(traj.position)[:, 0, 2] - 1.0
                err = float(np.max(np.abs(x - spring_closed_form(np.asarray(traj.time), k=k,
                                                                 c=c, m=m, x0=x0)))) / x0
                wall = median_time(lambda: sim.rollout(params, steps).position, repeats=repeats)
                pts.append({"dt": dt, "error": err, "time": wall})
                say("spring", integ, pts[-1])
            res[integ] = pts
        out["problems"]["spring"] = res
    if "chain" in problems:
        n, k, c, m, L, T = 6, 200.0, 0.5, 0.1, 0.2, 1.5
        scene = dp.Scene(gravity=(0.0, 0.0, -G))
        prev = scene.add_particle(mass=m, position=(0.0, 0.0, 0.0), pinned=True)
        for i in range(1, n + 1):
            b = scene.add_particle(mass=m, position=(L * i, 0.0, 0.0))
            scene.add_spring(prev, b, k=k, c=c, rest_length=L, group="chain")
            prev = b
        x0 = np.array([[L * i, 0.0, 0.0] for i in range(n + 1)])
        res = {}
        refs = {}
        for integ in integrators:
            pts = []
            for dt in dts or _dts(coarse_dt, n_dt):
                sim = dp.compile(scene, dt, integrator=integ, dtype=jnp.float64)
                params = sim.params()
                steps = int(round(T / dt))
                traj = sim.rollout(params, steps)
                tt = np.asarray(traj.time)
                if dt not in refs:
                    refs[dt] = chain_reference(tt, x0=x0, m=m, k=k, c=c, rest=L)
                tip = np.asarray(traj.position)[:, -1]
                err = float(np.max(np.linalg.norm(tip - refs[dt][:, -1], axis=-1))) / (n * L)
                wall = median_time(lambda: sim.rollout(params, steps).position, repeats=repeats)
                pts.append({"dt": dt, "error": err, "time": wall})
                say("chain", integ, pts[-1])
            res[integ] = pts
        out["problems"]["chain"] = res
    return out


def recommend(result: dict, tol: float, problem: str = "ball"):
    """Cheapest (integrator, dt) of ``result["problems"][problem]`` whose error <= tol, as a
    point dict with its integrator, or None when none meets it."""
    best = None
    for integ, pts in result["problems"].get(problem, {}).items():
        for p in pts:
            if p["error"] <= tol and math.isfinite(p["time"]):
                if best is None or p["time"] < best["time"]:
                    best = dict(p, integrator=integ)
    return best


# --------------------------------------------------------------------------- plot
def plot_accuracy(result: dict, path: str) -> None:
    """Log-log work-precision diagram: x = error, y = wall time, one curve per integrator,
    one panel per problem; the default configuration is starred. matplotlib is imported here
    (the ``plot`` extra)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError("--plot needs matplotlib: pip install 'diffpen[plot]' (or pip "
                          "install matplotlib).") from None
    names = list(result["problems"])
    titles = {"ball": "ball drop: apex heights (rel.)", "spring": "damped spring (rel.)",
              "chain": "hanging chain: tip (rel. to length)"}
    fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 4.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        for i, (integ, pts) in enumerate(result["problems"][name].items()):
            pts = [p for p in pts if math.isfinite(p["error"]) and math.isfinite(p["time"])
                   and p["error"] > 0]
            if not pts:
                continue
            x = [p["error"] for p in pts]
            y = [p["time"] for p in pts]
            ax.loglog(x, y, "o-", color=f"C{i}", label=integ, ms=4)
            ax.annotate(f"{pts[0]['dt']:.0e}", (x[0], y[0]), fontsize=7, color=f"C{i}",
                        xytext=(3, 3), textcoords="offset points")
        if name == "ball":
            for d in result.get("default", []):
                if not math.isfinite(d["error"]):
                    continue
                ax.loglog([d["error"]], [d["time"]], "*", ms=12,
                          color="k" if d["dtype"] == "float64" else "0.5",
                          label=f"default ({d['dtype']}, dt 1e-3)")
        ax.set_xlabel("error against reference")
        ax.set_ylabel("wall time of the rollout (s)")
        ax.set_title(titles.get(name, name), fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("diffpen work-precision (lower left is better; label = coarsest dt)",
                 fontsize=11)
    fig.tight_layout()
    save_figure_file(fig, path, dpi=110)
    plt.close(fig)
