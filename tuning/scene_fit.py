"""``diffpen fit SCENE.toml --data FILES...``: a scene file's ``[fit]`` parameters fitted
to record files (:func:`fit_files`), on top of :mod:`tuning.trajfit`'s
:func:`~tuning.trajfit.fit_records`: the output path checked before anything is compiled,
the records loaded and batched, the fit, the accuracy before and after (as ``diffpen
evaluate`` measures it) and the fitted scene written (:mod:`tuning.fitted_scene`).
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import time
import warnings
from typing import Sequence

import jax.numpy as jnp
import numpy as np

from .errors import FitError
from .first_state import FLIGHT_FRAMES
from .record_batch import prepare, prepare_buckets
from .trajfit import (AUTO_HORIZON, check_stable, fit_records, free_from_spec,
                      load_records)

__all__ = ["fit_files"]


#: Fewest rows a fitted record has (the start-state estimate takes up to 5 frames)
MIN_FIT_ROWS = 6
#: Whether :func:`fit_files` measures the time step's error by default (``step_check=None``;
#: ``--no-step-check``): the tests turn it off but where they test it (tests/conftest.py),
#: as it compiles the residuals once more at dt / 2 for every fit
STEP_CHECK = True


def fit_files(scene_path: str, data: Sequence[str], *, out: str | None = None,
              estimate: str | None = None, loss: str = "l2", horizons=None,
              maxiter: int | None = None, starts: int = 0, keep: int = 1,
              max_frames: int | None = None, progress: bool | None = False,
              fresh: bool = False, keep_progress: bool = False,
              step_check: bool | None = None) -> dict:
    """``diffpen fit SCENE.toml --data FILES...``: fit the scene file's ``[fit] params`` to
    all records jointly (:func:`fit_records`; ``starts`` / ``keep``: its multi-start), write
    the fitted scene to ``out`` (with ``estimate`` / ``max_frames`` in its ``[fit]`` table
    where they differ from the scene file's). ``max_frames``: the first-state estimate's frame cap
    (:func:`first_state`). ``estimate``, ``horizons`` and ``max_frames`` left None take
    the scene file's ``[fit] first_state``, ``horizon`` (+ the whole records; ``horizon =
    []``: the whole records only) and ``flight_frames``, else ``"record"``,
    :data:`AUTO_HORIZON` of the longest record (+ the whole records) and ``FLIGHT_FRAMES``
    (20).

    With ``out`` the fit is resumable: it holds ``out``'s lock (:class:`tuning.io.OutputLock`;
    a second fit into the same file is refused) and writes its progress to
    ``out`` + ``.fit-progress.json`` after every LM iteration
    (:mod:`tuning.fit_checkpoint`); the same call again resumes an interrupted fit from
    there (``fresh``: start afresh, overwriting the progress of another fit), and the file
    is removed once ``out`` is written (``keep_progress``: left for the caller to remove;
    the command removes it once it has printed the summary, so that a Ctrl-C before then
    still resumes). A symbolic link ``out`` is followed: its target is written, and the
    progress kept beside the target. ``step_check`` (default :data:`STEP_CHECK`): report the
    time step's own error (``step_shift``, in ``stderr``; ``stderr_noise`` without it).

    Returns a JSON-ready summary: ``fitted``, ``stderr``, ``correlation``,
    ``undetermined``, ``cost_start``/``cost`` (at the scene file's and the fitted values;
    ``cost_chosen_start`` at the multi-start point the fit kept), the accuracy before and after
    (:mod:`tuning.evaluate` summaries), ``records``, ``seconds``, ``out``.
    """
    from .scenefile import load_scene_file
    sf = load_scene_file(scene_path)
    if sf.spec is None or not sf.spec.free:
        raise FitError(f"{scene_path}: say what to fit in a [fit] table, e.g. [fit] params = "
                       "[\"contact.default.k\", \"contact.default.c\"] (the params leaves to "
                       "fit, with optional [fit.bounds]).")
    if sf.spec.method != "lm":
        raise FitError(f"{scene_path}: [fit] method = {sf.spec.method!r}, but fits to records "
                       "use Levenberg-Marquardt (method and lr choose the optimiser of "
                       "bounce-target fits): drop method, or set it to \"lm\".")
    free = free_from_spec(sf.spec)
    file_estimate = sf.spec.first_state or "record"
    file_frames = sf.spec.flight_frames or FLIGHT_FRAMES
    estimate = estimate or file_estimate
    max_frames = max_frames or file_frames
    # command-line start-state overrides go into the fitted scene's [fit] table, so that
    # diffpen evaluate of the written file measures what this fit reports
    overrides = {k: v for k, v, f in (("first_state", estimate, file_estimate),
                                      ("flight_frames", max_frames, file_frames)) if v != f}
    data = list(data) if data else list(sf.spec.data or [])
    records, bodies = load_records(sf, data)
    short = [f"{r.path} ({len(r.t)} rows)" for r in records if len(r.t) < MIN_FIT_ROWS]
    if short:       # 2 rows fitted k 65% off, reported determined; nothing compiled yet
        raise FitError(f"records too short to fit: {', '.join(short)}. A fitted record needs "
                       f"at least {MIN_FIT_ROWS} rows: its start velocity comes from its first "
                       "5 frames, and the rows after them are what the parameters are fitted "
                       "to. Use longer records, or leave these out (diffpen evaluate takes "
                       "them).")
    if horizons is None:
        if sf.spec.horizon is not None:
            horizons = tuple(sf.spec.horizon) + (None,)
        else:
            longest = max(r.duration for r in records)
            horizons = tuple(f * longest for f in AUTO_HORIZON) + (None,)
    run = dict(sf=sf, scene_path=scene_path, free=free, records=records, bodies=bodies,
               data=data,
               out=out, estimate=estimate, loss=loss, horizons=horizons, maxiter=maxiter,
               starts=starts, keep=keep, max_frames=max_frames, overrides=overrides,
               progress=progress, step_check=STEP_CHECK if step_check is None else step_check)
    if out is None:
        return _fit(**run)
    _check_out(out, scene_path, data)
    from .fit_checkpoint import checkpoint_path
    from .io import OutputError, OutputLock, check_output, clean_orphans
    progress = checkpoint_path(out)
    try:
        check_output(progress, what="the fit's progress file", derived_from="--out")
        lock = OutputLock(out, what="--out").acquire()
    except OutputError as exc:
        raise FitError(str(exc)) from None
    try:
        clean_orphans(out)
        clean_orphans(progress)
        summary = _fit(**run, fresh=fresh, checkpoint=progress)
        if not keep_progress and summary["out"] is not None:
            os.unlink(progress)         # the fitted scene holds the result now
        return summary
    finally:
        lock.release()


def _fit(sf, scene_path, free, records, bodies, data, *, out, estimate, loss, horizons,
         maxiter, starts, keep, max_frames, overrides, progress, step_check, fresh=False,
         checkpoint=None) -> dict:
    """:func:`fit_files` once its inputs are read and its output checked and locked."""
    from .evaluate import collapse_message, evaluate_batch, evaluator
    t0 = time.perf_counter()
    sim = sf.compile()
    params = sf.params(sim)
    check_stable(sim, params, sf.path)
    first_states = {}                   # shared by the evaluation batch and the fit's buckets
    batch = prepare(sim, records, bodies=bodies, estimate=estimate, max_frames=max_frames,
                    cache=first_states)
    ev_fn = evaluator(sim, batch)
    before = evaluate_batch(sim, params, batch, fn=ev_fn)
    with warnings.catch_warnings():     # the same records: the batch above said it all
        warnings.simplefilter("ignore")
        buckets = prepare_buckets(sim, records, bodies=bodies, estimate=estimate,
                                  max_frames=max_frames, cache=first_states)
    res = fit_records(sim, params, buckets, free, loss=loss, horizons=horizons,
                      maxiter=maxiter or sf.spec.maxiter or 30, starts=starts, keep=keep,
                      progress=progress, checkpoint=checkpoint, fresh=fresh,
                      checkpoint_key=None if checkpoint is None else _progress_key(
                          data, estimate, max_frames), refine_start=estimate == "refine")
    moved = {name.split(".", 2)[2]: v for name, v in res.values.items()
             if name.startswith("extra.plane_offset.")}
    if moved:
        # the first-state estimate counts flight frames against the planes (and with
        # "record" takes the lag from free flight's gravity or from the frames' slope by
        # them): evaluated as the fitted scene file is (diffpen evaluate), with its fitted
        # plane offsets
        scene = copy.copy(sim.scene)
        scene.planes = [dataclasses.replace(pl, offset=moved[pl.name]) if pl.name in moved
                        else pl for pl in sim.scene.planes]
        batch = prepare(sim, records, bodies=bodies, estimate=estimate,
                        max_frames=max_frames, scene=scene)
        ev_fn = evaluator(sim, batch)
    after = evaluate_batch(sim, res.params, batch, fn=ev_fn)
    out_error = None
    if out is not None:
        from .fitted_scene import write_fitted
        try:
            write_fitted(scene_path, res.values, out, fit=overrides)
        except (ValueError, OSError) as exc:     # the fit is kept: its values are reported
            out_error = f"could not write --out {out}: {exc}"
    summary = res.as_dict()
    shift = (_step_shift(sf, sim, res, free, records, bodies, estimate, max_frames, loss)
             if step_check else None)
    if shift is not None:
        summary["stderr_noise"] = dict(res.stderr)
        summary["step_shift"] = shift
        summary["stderr"] = {n: math.hypot(e, shift[n]) if math.isfinite(e) else e
                             for n, e in res.stderr.items()}
        over = [n for n, e in res.stderr.items() if abs(shift[n]) > max(e, 0.0)]
        if over:
            summary["message"] += (
                "; the time step moves " + ", ".join(
                    f"{n} by {shift[n]:+.3g}" for n in over) + " (towards dt -> 0, more "
                "than its noise error; in the standard errors): refit with a smaller dt "
                "for values that do not depend on it")
    summary.update({
        "scene": scene_path, "records": len(records), "bodies": bodies, "estimate": estimate,
        "flight_frames": max_frames,
        "loss": loss, "before": {"position_error_pct": before.position_error_pct,
                                 "rotation_error_deg": before.rotation_error_deg},
        "after": {"position_error_pct": after.position_error_pct,
                  "rotation_error_deg": after.rotation_error_deg},
        "out": None if out_error else out, "seconds": time.perf_counter() - t0,
        "fit_seconds": res.seconds,
        "reached": not (res.unstable or after.unstable or res.diverged)})
    crushed = collapse_message(after.records)
    if crushed:     # a plastic member crushed below 5% of its length at the fitted values
        summary["collapsed_records"] = [r["path"] for r in after.records if r["collapsed"]]
        summary["message"] += "; " + crushed
    if out_error:
        summary["out_error"] = out_error
    return summary


def _step_shift(sf, sim, res, free, records, bodies, estimate, max_frames, loss):
    """How far the fitted values move towards the continuous model (dt -> 0), ``{leaf:
    shift}`` in the leaves' units: one Gauss-Newton step on the change of the residuals at
    the fitted values when the step is halved, twice it (Richardson: the integrators' error
    is first order in dt through contacts), ``-J^+ 2 (r_{dt/2} - r_dt)``; None where a
    rollout at either step is past its safe step or the residuals are not finite. Without
    it the standard errors covered only the records' noise: noise-free records of a chain
    fitted its damping 9.6% off at dt = 1 ms, 9 errors away."""
    from .pose import ROT_WEIGHT
    from .record_batch import typed_params
    from .record_programs import programs
    r1, J1 = res.residuals, res.jacobian        # the fit's own, at dt
    if res.unstable or not (np.all(np.isfinite(r1)) and np.all(np.isfinite(J1))):
        return None
    x = np.array([f.to_x(res.values[f.name]) for f in free], float)
    half = sf.compile(dt=sim.dt / 2)
    with warnings.catch_warnings():     # the fit's own batches warned already
        warnings.simplefilter("ignore")
        buckets = prepare_buckets(half, records, bodies=bodies, estimate=estimate,
                                  max_frames=max_frames)
    (rj, _), arrays = programs(half, free, buckets, ROT_WEIGHT, loss, None,
                               estimate == "refine")
    r2, _, bad = (np.asarray(a) for a in rj(typed_params(res.params, half.dtype), arrays,
                                             jnp.asarray(x), jnp.asarray(np.inf)))
    if int(bad) or not np.all(np.isfinite(r2)):
        return None
    step = -np.linalg.lstsq(J1, 2.0 * (r2 - r1), rcond=None)[0]
    return {f.name: float(f.from_x(x[i] + step[i]) - res.values[f.name])
            for i, f in enumerate(free)}


def _progress_key(data, estimate, max_frames) -> dict:
    """What ``diffpen fit`` adds to its progress key: the record files in order by name and
    contents (a changed file is named, ``data.3:toss_026.csv``; not by folder, so a fit whose
    records moved, or that resumes from another working folder, still resumes), the
    start-state estimate and its frame cap."""
    from .io import file_digest
    return {"data": {f"{i + 1}:{os.path.basename(p)}": file_digest(p)
                     for i, p in enumerate(data)},
            "first_state": estimate, "flight_frames": max_frames}


def _check_out(out: str, scene_path: str, data) -> None:
    """``--out``: a writable ``.toml`` file that is not one of the inputs, checked before
    anything is compiled (a typo must not cost a fit, nor overwrite a record)."""
    from .io import OutputError, check_output
    try:
        p = check_output(out, what="--out", ext=".toml")
    except OutputError as exc:
        raise FitError(str(exc)) from None
    if not p.lower().endswith(".toml"):
        raise FitError(f"--out {out}: the fitted scene is a TOML file; give a name ending in "
                       ".toml.")
    inputs = [scene_path, *(data or [])]
    if any(os.path.exists(f) and os.path.samefile(p, f) if os.path.exists(p) else False
           for f in inputs):
        raise FitError(f"--out {out} is one of the inputs (the scene file or a record): "
                       "write the fitted scene to a new file.")
    from .fitted_scene import FITTED_MARK, is_fitted_scene
    if os.path.exists(p) and not is_fitted_scene(p):
        raise FitError(f"--out {out} exists and is not a scene diffpen fit wrote (its first "
                       f"line is not \"{FITTED_MARK} ...\"; fits before that line was added "
                       "wrote none): the fit would replace it. Move or remove it, or choose "
                       "another --out.")
