"""Sweeps of a scene file's parameters: ``diffpen sweep SCENE.toml``.

A grid over any leaves of the scene's parameters (``[fit] params`` over ``[fit.bounds]`` by
default, or ``axes`` given explicitly; log-spaced for positive leaves, linear for signed ones
such as plane offsets), evaluated with :func:`tuning.sweep.sweep` (chunks of one vmapped
call, written atomically as they finish, resumable, split over devices and processes; sizes
that cannot fit refused first, :func:`check_size`):

* with records (``data``, or the file's ``[fit] data``): every point rolls every record out
  open loop from its first state (:mod:`tuning.evaluate`) and keeps the mean and the median
  over records of the position error (% of the body's size) and of the rotation error
  (degrees): the landscape a record fit (``diffpen fit SCENE.toml --data``) descends;
* without records: the bounce metrics of the ``[fit] body`` (a sphere) on the ``[fit]
  plane`` (:func:`tuning.metrics.ball_metrics`: apex heights, settling time, contact
  durations, maximum penetration, restitution) over the file's duration.

Records are scored as ``diffpen evaluate`` scores them: a record whose rollout goes past the
scene's safe step has no errors at that point and is left out of its mean and median, and
counted (metric ``unstable_records``); a point where no record has a result is NaN and
counted (metric ``unstable``), as every point of a bounce sweep past the safe step.
Sweeping a plane offset (``extra.plane_offset.NAME``), each record's start state is
estimated against the swept offset, as ``diffpen evaluate`` of the scene file with that
offset estimates it (whether the body is in free flight depends on its distance to the
planes): one batch of start states per distinct row of the swept offsets, prepared on the
host before the sweep (G first-state estimates of every record for G distinct rows).
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import math
import os
import warnings
from typing import Sequence

import numpy as np

from .errors import FitError
from .first_state import FLIGHT_FRAMES

__all__ = ["sweep_scene_file", "sweep_axes", "RECORD_METRICS", "BOUNCE_METRICS"]

#: what a sweep over records keeps per point
RECORD_METRICS = ("position_error_pct", "position_error_median", "rotation_error_deg",
                  "rotation_error_median")
#: per point, the records past the scene's safe step, left out of its means and medians
UNSTABLE_RECORDS = "unstable_records"
#: per point, how many records' rollouts had a plastic spring collapse (crushed below 5% of
#: its length, :mod:`diffpen.terms.plastic`: past what the model describes); scenes with
#: plastic springs only. Their errors are kept, and the command counts these points.
COLLAPSED_RECORDS = "collapsed_records"
#: what a sweep without records keeps per point (the bounce of the [fit] body)
BOUNCE_METRICS = ("apex_heights", "settling_time", "max_penetration", "contact_durations",
                  "restitution")


#: float columns a point keeps beyond its swept values (metrics, flags), in memory, the .npz
#: and the .csv table
METRIC_COLUMNS = 8


def check_size(sim, points: int, steps: int, records: int, chunk: int, swept: int) -> None:
    """Refuse a sweep that cannot fit, before its points are made or anything is compiled
    (:class:`tuning.sweep.SweepError`, saying what to lower): the results (``points`` x the
    swept and metric columns, held in memory, the .npz and the .csv) or one chunk's rollouts
    (``chunk`` points x ``records`` (at least 1) rollouts of ``steps`` steps, each counted as
    :func:`diffpen.checks.estimate` counts a saved trajectory) past half this machine's
    memory; the results' message gives the compute at :data:`diffpen.checks.STEP_RATE` too
    (a CPU's rate: no sweep is refused for its time, which a GPU may cut many times)."""
    from diffpen.checks import STEP_RATE, estimate, human_time

    from .sweep_files import refuse_oversized
    runs = max(records, 1)
    rollout, seconds = estimate(sim, steps)
    seconds *= float(points) * runs
    work = (f"about {human_time(seconds)} of compute ({points:.0f} points x {runs} "
            f"rollout{'s' if runs > 1 else ''} of {steps} steps of {sim.n_bodies} bodies at "
            f"~{STEP_RATE:.0e} body-steps/s)")
    refuse_oversized(points, float(points) * (swept + METRIC_COLUMNS) * 8 * 3,
                     f"a chunk of {min(chunk, points):.0f} points x {runs} rollouts of "
                     f"{steps} steps", min(chunk, points) * runs * rollout, work,
                     "lower n (diffpen sweep --n).", "lower chunk (diffpen sweep --chunk).")


def sweep_axes(sf, params, axes: Sequence | None, n: Sequence[int]) -> dict:
    """``{leaf path: (n_i,) values}`` of the grid: ``axes`` = ``[(path, lo, hi), ...]`` or
    None for the scene file's ``[fit] params`` over ``[fit.bounds]``; ``n``: points per
    axis (one value for all). Log-spaced for leaves in log space (``[fit.space]`` or
    :func:`tuning.scenefile.leaves.leaf_space`), linear for signed ones."""
    from .scenefile.leaves import _keystr_paths, leaf_space, param_leaves
    leaves, alias = param_leaves(params), _keystr_paths(params)
    spec = sf.spec
    if not axes:
        if spec is None or not spec.free:
            raise FitError(f"{sf.path}: say what to sweep: --param PATH LO HI (repeat it for "
                           "more axes), or [fit] params with [fit.bounds] in the file.")
        missing = [p for p in spec.free if p not in spec.bounds]
        if missing:
            raise FitError(f"{sf.path}: [fit] params {missing} have no [fit.bounds]: give "
                           "their ranges there or as --param PATH LO HI.")
        axes = [(p, *spec.bounds[p]) for p in spec.free]
    if len(n) not in (1, len(axes)):
        raise FitError(f"--n takes one count or one per axis ({len(axes)}), got {list(n)}.")
    counts = list(n) * len(axes) if len(n) == 1 else list(n)
    out = {}
    for (path, lo, hi), m in zip(axes, counts):
        p = alias.get(path, path.strip())
        if p not in leaves:
            raise FitError(f"{p!r} is not a parameter of {sf.path}; its parameters are: "
                           f"{', '.join(leaves)}.")
        if p in out:
            raise FitError(f"{p!r} is swept twice.")
        lo, hi = float(lo), float(hi)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise FitError(f"{p}: the range must be finite with LO < HI, got {lo:g} {hi:g}.")
        if int(m) < 2:
            raise FitError(f"{p}: at least 2 points per axis, got {m}.")
        # the kind of leaf decides (log for the positive ones), not its start value: a
        # damping declared 0 was swept linearly while its k beside it went in log steps
        space = (spec.space.get(p) if spec is not None and p in spec.space else None) or \
            leaf_space(p, 1.0)
        if space == "log" and lo <= 0.0:
            if leaf_space(p, 1.0) == "log":
                raise FitError(f"{p}: a positive parameter is swept in log steps and needs "
                               f"LO > 0, got {lo:g} (to include {lo:g}, set [fit.space] "
                               f"\"{p}\" = \"linear\" in the scene file).")
            space = "linear"
        out[p] = (np.geomspace(lo, hi, int(m)) if space == "log"
                  else np.linspace(lo, hi, int(m)))
    return out


def _digest(path: str) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()[:16]


def _record_batches(sim, records, bodies, estimate, max_frames, names, points):
    """``(batch, offsets)``: the records' :class:`~tuning.record_batch.Batch` and, when plane
    offsets are swept, ``(plane names, (G, K) table of the distinct rows of the points'
    offsets, start states with a leading axis G)``: each record's start state estimated
    against the scene with that row's offsets, as ``diffpen evaluate`` of a scene file with
    those offsets does (G first-state estimates of every record, on the host); else None."""
    import jax
    import jax.numpy as jnp

    from .trajfit import prepare
    cols = [j for j, p in enumerate(names) if p.startswith("extra.plane_offset.")]
    kw = dict(bodies=bodies, estimate=estimate, max_frames=max_frames)
    if not cols:
        return prepare(sim, records, **kw), None
    planes = [names[j].split(".", 2)[2] for j in cols]
    table = np.unique(np.asarray(points, float)[:, cols], axis=0)
    batches = []
    for row in table:
        # one scene per row, and no first-state cache shared between them: its key does
        # not hold the planes
        moved = dict(zip(planes, (float(v) for v in row)))
        scene = copy.copy(sim.scene)
        scene.planes = [dataclasses.replace(pl, offset=moved[pl.name]) if pl.name in moved
                        else pl for pl in sim.scene.planes]
        with warnings.catch_warnings():         # said once, by the first row's batch
            if batches:
                warnings.simplefilter("ignore")
            batches.append(prepare(sim, records, scene=scene, **kw))
    first = batches[0]
    for b in batches[1:]:       # only the start states depend on the planes
        if (b.lagged is None) != (first.lagged is None) or (
                b.lagged is not None and not np.array_equal(b.lagged, first.lagged)):
            raise FitError("the records' batches differ between the swept plane offsets "
                           "(their unobserved bodies' lag): sweep one offset at a time.")
    starts = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *(b.start for b in batches))
    return first, (planes, table, starts)


def sweep_scene_file(scene_path: str, data: Sequence[str] = (), axes: Sequence | None = None,
                     *, n: Sequence[int] = (16,), out: str | None = None, resume: bool = True,
                     chunk: int = 64, estimate: str | None = None,
                     max_frames: int | None = None, progress: bool | None = False,
                     check=None):
    """Sweep the scene file's parameters (see the module docstring).

    Args:
      scene_path: a ``.toml`` scene file.  data: record files (default the file's ``[fit]
        data``; none: bounce metrics).  axes: ``[(leaf path, lo, hi), ...]`` or None (the
        ``[fit] params`` over ``[fit.bounds]``).  n: grid points per axis (one for all).
      out: ``.npz`` (and a ``.csv`` beside it), written atomically as the chunks finish
        (:mod:`tuning.sweep_files`); a rerun
        with the same scene file, records, axes and settings resumes it, another sweep's
        file is refused.  chunk: points per vmapped call (bounds memory).
      estimate, max_frames: the records' first-state estimate and its cap on flight frames
        (None: the file's ``[fit]`` values, else ``"record"`` / ``FLIGHT_FRAMES``).
      progress: see :func:`tuning.sweep.sweep`.
      check: ``check(info)`` called with the ``axes`` and ``metrics`` of ``info`` and the
        record files read (``data``) once they are known, before any point is computed or
        written (e.g. the CLI's ``--metric``, ``--plot`` and that no output is a record);
        it raises to stop the sweep.
    Returns:
      ``(SweepResult, info)``: ``info`` holds ``axes`` ({path: values}), ``metrics`` (the
      names kept), ``records`` (count) and ``simulator`` (the compiled
      :class:`diffpen.Simulator`).
    """
    import jax
    import jax.numpy as jnp

    from .io import describe_simulator
    from .scenefile import load_scene_file
    from .sweep import grid_points, sweep
    from .trajfit import load_records
    sf = load_scene_file(scene_path)
    spec = sf.spec
    data = list(data) if data else list((spec.data if spec is not None else None) or [])
    sim = sf.compile()
    params0 = sf.params(sim)
    grid_axes = sweep_axes(sf, params0, axes, n)
    names = list(grid_axes)
    n_points = int(np.prod([len(v) for v in grid_axes.values()], dtype=float))
    records = load_records(sf, data) if data else None
    steps = (max(int(np.ceil(r.duration / sim.dt)) + 1 for r in records[0]) if data
             else sf.setup.steps)
    check_size(sim, n_points, steps, len(data), chunk, len(names))
    points, shape = grid_points(grid_axes)
    key = dict(describe_simulator(sim), scene_file=_digest(scene_path))
    plastic = bool(sim.scene.plastic_springs)      # the collapse flag (COLLAPSED_RECORDS)
    if data:
        from .evaluate import _errors
        from .record_batch import simulate
        records, bodies = records
        estimate = estimate or (spec.first_state if spec is not None else None) or "record"
        max_frames = max_frames or (spec.flight_frames if spec is not None else None) or \
            FLIGHT_FRAMES
        batch, offsets = _record_batches(sim, records, bodies, estimate, max_frames, names,
                                         points)
        key.update(records=[[os.path.basename(r.path), _digest(r.path)] for r in records],
                   estimate=estimate, flight_frames=max_frames)
        kept = list(RECORD_METRICS)

        def summary(v):
            """Mean and median over the records with a result, NaN when none has one (as
            tuning.evaluate._summary)."""
            v = jnp.where(jnp.isfinite(v), v, jnp.nan)
            return jnp.nanmean(v), jnp.nanmedian(v)

        def metrics_fn(params):
            b = batch
            if offsets is not None:     # the start states estimated at these plane offsets
                planes, table, starts = offsets
                row = jnp.stack([params.extra["plane_offset"][pl] for pl in planes])
                g = jnp.argmin(jnp.sum(jnp.abs(jnp.asarray(table, row.dtype) - row), axis=1))
                b = dataclasses.replace(batch, start=jax.tree_util.tree_map(
                    lambda a: a[g], starts))
            pos, quat, bad, *crushed = simulate(sim, params, b, with_flag=True,
                                                with_collapse=plastic)
            pe, re = _errors(pos, quat, b)
            nan = jnp.asarray(jnp.nan, pe.dtype)
            pe = jnp.where(bad, nan, pe)        # past the safe step: no result (as evaluate)
            m = dict(zip(("position_error_pct", "position_error_median"), summary(pe)))
            if re is not None:
                m.update(zip(("rotation_error_deg", "rotation_error_median"),
                             summary(jnp.where(bad, nan, re))))
            m[UNSTABLE_RECORDS] = jnp.sum(jnp.isnan(pe))
            if plastic:
                m[COLLAPSED_RECORDS] = jnp.sum(crushed[0])
            m["unstable"] = ~jnp.any(jnp.isfinite(pe))      # no record has a result
            return m
        if not batch.has_rotation:
            kept = kept[:2]
    else:
        from .bounce import bounce_metrics_fn
        body = spec.body if spec is not None else 0
        plane = spec.plane if spec is not None else 0
        tol = spec.settle_tol if spec is not None else 1e-3
        b = sf.scene.bodies[body] if body < len(sf.scene.bodies) else None
        if b is None or b.kind != "sphere" or not sf.scene.planes:
            raise FitError(f"{scene_path}: without records (--data FILE.csv ...) a sweep "
                           "measures the bounce of a sphere on a plane ([fit] body, plane); "
                           "this scene has none: give records to sweep against.")
        steps = sf.setup.steps
        key.update(body=body, plane=plane, settle_tol=tol, steps=steps, n_apex=3)
        kept = list(BOUNCE_METRICS) + ["settled"]
        metrics_fn = bounce_metrics_fn(sim, steps, body=body, plane=plane, n_apex=3,
                                       settle_tol=tol)

    if check is not None:
        check({"axes": grid_axes, "metrics": kept, "data": list(data)})

    def finalize(m, pts):
        if "settled" in m:      # not settled within the rollout: NaN, not its end
            m["settling_time"] = np.where(m["settled"], m["settling_time"], np.nan)
        return m
    res = sweep(metrics_fn, params0, points, names, chunk=chunk, out=out, resume=resume,
                key=key, keys=kept + ["unstable"] + ([UNSTABLE_RECORDS] if data else [])
                + ([COLLAPSED_RECORDS] if data and plastic else []),
                shape=shape, axes=grid_axes,
                progress=progress, finalize=finalize)
    info = {"axes": grid_axes, "metrics": kept, "records": len(data), "simulator": sim}
    return res, info
