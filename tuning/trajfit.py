"""Fit any scene's parameters to measured motion: many records at once.

A *record* (:func:`tuning.records.read_record`) holds the times ``t`` (T,) s and, per observed
body, positions (T, 3) m with NaN for missing samples and optionally orientations (T, 4)
(w, x, y, z), world velocities (T, 3) m/s and BODY-frame angular velocities (T, 3) rad/s.

Pipeline (each step a public function, all importable from here):

1. :func:`prepare` (:mod:`tuning.record_batch`) turns records into one padded
   :class:`Batch`: each record's start state (:func:`first_state`,
   :mod:`tuning.first_state`: pose from row 0, velocities from the record's columns or
   estimated from the first frames), the frame times as indices into one rollout, and masks
   for missing samples and for records shorter than the longest.
2. :func:`simulate` (:mod:`tuning.record_batch`) rolls every record out from its own start
   state under ``jax.vmap`` (one compiled function for all) and samples positions and
   orientations at the frame times (linear interpolation when the frames do not fall on
   steps).
3. :func:`pose_residuals` (:mod:`tuning.pose`) compares them with the measurements: the
   pose loss, position errors in units of each body's size plus weighted rotation angles.
4. :func:`fit_records` (here) runs Levenberg-Marquardt on the chosen leaves of the params
   (signed leaves such as plane offsets in linear space, positive ones in log space) with a
   forward-mode Jacobian through the rollouts, optionally over a growing horizon, and
   reports standard errors, correlations and the parameter directions the records do not
   determine (:mod:`tuning.fit_errors`).

The params-leaf helpers (:func:`get_leaf`, :func:`with_leaves`), :class:`Free` and
:func:`free_from_spec` live in :mod:`tuning.free_leaves`, :func:`load_records` (records
matched to a scene file's bodies) in :mod:`tuning.records` (all importable from here). The
command's file-level workflow, ``diffpen fit SCENE.toml --data FILES``, is
:func:`tuning.scene_fit.fit_files`; records made by a simulator are
:func:`tuning.synthetic.synthetic_record` (both importable from here too).
The checkpoint of a resumable fit is :mod:`tuning.fit_checkpoint`.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .errors import FitError, check_starts_keep
from .progress import Progress
from .lm import levenberg_marquardt, warn_record_precision
from .first_state import first_state
from .free_leaves import Free, _normalise, free_from_spec, get_leaf, leaf_names, with_leaves
from .fit_errors import parameter_errors
from .pose import ROT_WEIGHT, body_size, pose_residuals, residual_records, rotation_angle
from .records import load_records
from .record_batch import Batch, layout_of, prepare, prepare_buckets, simulate, typed_params
from .record_programs import programs as _programs
from .start_refine import active_offsets
from .stable import params_unstable, solver_miss, unsafe_start

__all__ = ["Free", "Batch", "TrajFitResult", "leaf_names", "get_leaf", "with_leaves",
           "body_size", "first_state", "prepare", "prepare_buckets", "simulate", "pose_residuals",
           "fit_records", "ROT_WEIGHT", "rotation_angle", "LOG_SPAN", "AUTO_HORIZON",
           "free_from_spec", "load_records"]

#: a record fit whose scene file gives no ``[fit] horizon`` first fits these fractions of its
#: longest record, then the whole records (oscillating and tumbling records have local
#: minima that a fit of the whole records from a start a factor 2 off falls into)
AUTO_HORIZON = (0.125, 0.25, 0.5)

#: how far (a factor) a log-space leaf may move from its start value in a record fit where
#: its bounds allow more (``[fit.bounds]`` closer in win)
LOG_SPAN = 1e6

# --------------------------------------------------------------------------- fit
@dataclasses.dataclass
class TrajFitResult:
    """Outcome of :func:`fit_records`.

    params: fitted :class:`diffpen.Params`.  values: ``{name: value}`` of the fitted leaves.
    stderr: ``{name: standard error}``: the larger of Gauss-Newton's ``s^2 (J^T J)^-1`` and
      the records-as-clusters sandwich (:mod:`tuning.fit_errors`, which takes in what the
      residuals of one record share: the noise of its first frame, correlated frames; with
      few records it is itself uncertain); inf for a parameter the records do not depend
      on or that takes part in an undetermined direction (an entry above 0.1 in its unit
      vector: only a combination with the others is determined).
    correlation: (p, p) parameter correlation matrix (rows/columns in ``names`` order; NaN
      in the rows and columns of parameters whose standard error is inf).
    undetermined: directions of the fitted (log/linear) parameters the records leave
      undetermined: ``[{"eigenvalue_ratio": r, "direction": {name: coeff}}]`` for the
      eigenvectors of the scaled ``J^T J`` with eigenvalue below ``1e-8`` x the largest
      (a parameter whose Jacobian column is below 1e-8 of the largest counts
      as one the records do not depend on).
    cost_start, cost: pose loss (mean over records) at the start (the given ``params``, with
      multi-start too) and at the fitted values, both over the whole records (with a
      growing horizon too).
    horizons: the horizons (s) fitted in turn.  iterations: LM iterations in all.
    history: cost after each iteration.  seconds: wall time.  message: LM's last word;
      first, a contact k or c held by the safe step (:data:`SAFE_MARGIN`: the records favour
      a value the fit's dt does not allow; a smaller dt helps, wider bounds do not).
    unstable: records whose rollout at the fitted values ran past the safe step; when > 0
      ``cost`` is NaN and the message says so: the fit is not a result.
    starts: with multi-start, per start point ``{"values", "screen_cost", "cost" (None
      when LM did not run from it), "chosen"}``; else one entry for the given start.
    diverged: the rollouts' derivatives at the fitted values ran away (non-finite, or an
      entry of the Jacobian past :data:`JACOBIAN_LIMIT`) while their values stayed
      bounded: not a result (the message says so; standard errors and correlations NaN).
    cost_chosen_start: the pose loss over the whole records at the start point the kept fit
      ran from (with multi-start, the chosen one of ``starts``; else ``cost_start``).
    resumed: LM iterations taken from a checkpoint (``fit_records(checkpoint=...)``), 0 for
      a fit run whole; ``iterations`` and ``history`` count them too.
    residuals, jacobian: (m,) and (m, p) at the fitted values over the whole records (in
      fitting space; projected off the start offsets with ``refine_start``).
    """
    params: dp.Params
    names: list
    values: dict
    stderr: dict
    correlation: np.ndarray
    undetermined: list
    cost_start: float
    cost: float
    horizons: list
    iterations: int
    history: list
    seconds: float
    message: str
    unstable: int = 0
    starts: list = dataclasses.field(default_factory=list)
    diverged: bool = False
    cost_chosen_start: float | None = None
    resumed: int = 0
    residuals: np.ndarray | None = dataclasses.field(default=None, repr=False)
    jacobian: np.ndarray | None = dataclasses.field(default=None, repr=False)

    def as_dict(self) -> dict:
        return {"fitted": self.values, "stderr": self.stderr,
                "correlation": {a: {b: float(self.correlation[i, j])
                                    for j, b in enumerate(self.names)}
                                for i, a in enumerate(self.names)},
                "undetermined": self.undetermined, "cost_start": self.cost_start,
                "cost_chosen_start": self.cost_chosen_start, "cost": self.cost,
                "horizons": self.horizons, "iterations": self.iterations,
                "seconds": self.seconds, "message": self.message, "unstable": self.unstable,
                "diverged": self.diverged, "starts": self.starts, "resumed": self.resumed}


#: Largest |d residual / d parameter| a fit trusts. Residuals are pose errors of order 1
#: (positions in body sizes, angles in radians) and parameters are log values or metres, so a
#: derivative past this means the rollouts' tangents ran away (a sphere rolling without slip
#: through an impact, its viscous friction past the explicit step's limit: 1e64 and more).
JACOBIAN_LIMIT = 1e8

#: a fitted contact k or c within this fraction of its safe-step cap, or one the records push
#: up where this fraction more is past the scene's safe step, is held by the safe step
SAFE_MARGIN = 1e-3

def fit_records(sim: dp.Simulator, params, batch, free: Sequence[Free], *,
                rot_weight: float = ROT_WEIGHT, horizons: Sequence[float | None] = (None,),
                loss: str = "l2", maxiter: int = 30, starts: int | Sequence[dict] = 0,
                keep: int = 1, seed: int = 0, spread: float = 3.0,
                decay: float | None = None,
                progress: bool | None = False, checkpoint: str | None = None,
                fresh: bool = False, checkpoint_key: dict | None = None,
                refine_start: bool = False) -> TrajFitResult:
    """Fit the ``free`` leaves of ``params`` to all records of ``batch`` (a :class:`Batch`
    or the list :func:`prepare_buckets` makes) jointly.

    Levenberg-Marquardt on :func:`pose_residuals` with a forward-mode Jacobian
    (``jax.jacfwd``, one tangent per parameter) through the vmapped rollouts. ``horizons``
    (s; None = the whole records): fit the frames up to each horizon in turn, each start
    from the previous fit (a growing horizon for long, chaotic records); changing the
    horizon never recompiles. ``maxiter`` applies per horizon. ``decay`` (s): frames weigh
    ``exp(-t / decay)`` in the loss (:func:`pose_residuals`; None: all alike).

    Multi-start: ``starts`` adds start points to the one ``params`` holds -- an int N draws N
    points uniformly around it, seeded by ``seed``, inside the bounds: log-space leaves
    within a factor ``spread`` of the start value, linear ones within +-1/10 of their
    bounds' width (+-0.01 when unbounded); a list gives them as ``{leaf name: value}``
    (leaves not named keep ``params``' value). All are screened by one rollout each (the
    cost at the first horizon, or at the next ones in turn while all costs are equal, the
    message saying so; past the safe step: inf), LM runs from the ``keep``
    cheapest, and the result is the fit of lowest final cost;
    :attr:`TrajFitResult.starts` lists every start with its costs.

    ``checkpoint``: a JSON file the fit's progress is written to after every LM iteration
    (atomically; :mod:`tuning.fit_checkpoint`); a rerun of the same fit (same simulator,
    params, records, leaves, bounds and options) resumes from it and returns what an
    uninterrupted fit returns, bit for bit (:attr:`TrajFitResult.resumed`: the iterations
    taken from it). A checkpoint of another fit raises :class:`FitError` naming what
    differs, unless ``fresh``. The file is left in place: remove it once the result is kept.
    ``checkpoint_key``: fields the caller adds to the checkpoint's key, so that a refusal
    names what the caller changed (``diffpen fit``: the record files, the start-state
    estimate and its frame cap) and not only the records' arrays that follow from it.

    ``refine_start``: every record's start state (observed bodies' positions and velocities,
    with orientations their orientation and angular velocity) is fitted with the
    parameters, by variable projection (:mod:`tuning.start_refine`): for records without
    velocity columns, whose start velocities come from a few noisy frames; its uncertainty
    enters the standard errors.
    """
    if loss not in ("l2", "l1"):
        raise FitError(f"loss must be 'l2' or 'l1', got {loss!r}.")
    if not isinstance(starts, (int, np.integer)):
        starts = list(starts)           # a generator is read once
    check_starts_keep(starts, keep)
    warn_record_precision(sim.dtype)
    free = [f.resolved() for f in free]
    if not free:
        raise FitError("nothing to fit: name at least one params leaf in [fit].")
    names = [f.name for f in free]
    if len(set(names)) != len(names):
        raise FitError(f"a parameter is named twice in {names}.")
    x0 = []
    for f in free:
        v = float(np.asarray(get_leaf(params, f.name)))
        if not f.lo <= v <= f.hi:
            raise FitError(f"{f.name} = {v} is outside its bounds [{f.lo}, {f.hi}]: change "
                           "the start value or the bounds.")
        if f.log and v <= 0:
            raise FitError(f"{f.name} = {v}: a log-space parameter must start > 0.")
        x0.append(f.to_x(v))
    lo = np.array([f.x_bounds()[0] for f in free], dtype=float)
    hi = np.array([f.x_bounds()[1] for f in free], dtype=float)
    # a log-space leaf stays within LOG_SPAN of its start value where no bound is nearer: one
    # the records barely see could otherwise walk off to 0 (or overflow) in a rugged landscape
    for i, f in enumerate(free):
        if f.log:
            lo[i] = max(lo[i], x0[i] - math.log(LOG_SPAN))
            hi[i] = min(hi[i], x0[i] + math.log(LOG_SPAN))
    # the optimiser stays inside the stable region: contact k and c capped at the safe step
    # of one contact on the lightest body (tuning.stable); the flag still judges the result
    from .stable import safe_contact_bounds
    batches = list(batch) if isinstance(batch, (list, tuple)) else [batch]
    k_max, c_max = safe_contact_bounds(sim, **_depth_reference(sim, params, free, lo, batches))
    caps = []                       # each leaf's safe-step cap (inf: none)
    for i, f in enumerate(free):
        parts = f.name.split(".")
        cap = (k_max if parts[-1] == "k" else c_max) if (
            parts[0] == "contact" and parts[-1] in ("k", "c")) else math.inf
        caps.append(cap)
        if cap < math.inf:
            if x0[i] > f.to_x(cap):
                raise FitError(f"{f.name} starts at {f.from_x(x0[i]):.6g}, past the largest "
                               f"safe value {cap:.6g} for dt = {sim.dt:g} s: start lower, or "
                               "use a smaller dt or more substeps.")
            hi[i] = min(hi[i], float(f.to_x(cap)))

    # the compiled residuals take the params and the records' arrays as arguments: a later
    # fit of the same layout (simulator, leaves, loss, batch shapes) compiles nothing
    programs, arrays = _programs(sim, free, batches, rot_weight, loss, decay,
                                 bool(refine_start))
    params_in = typed_params(params, sim.dtype)
    ck = None
    if checkpoint is not None:
        from .fit_checkpoint import FitCheckpoint, fit_key
        ck = FitCheckpoint(checkpoint, fit_key(
            sim, params_in, free, arrays, [layout_of(b)[0] for b in batches],
            rot_weight=rot_weight, horizons=list(horizons), loss=loss, maxiter=maxiter,
            starts=starts if isinstance(starts, (int, np.integer)) else
            [dict(v) for v in starts], keep=keep, seed=seed, spread=spread, decay=decay,
            **({"refine_start": True} if refine_start else {}), **(checkpoint_key or {})),
            fresh=fresh)
    saved = ck.state if ck is not None else {}
    resumed = ck.resumed_iterations if ck is not None else 0

    def res_jac_flag(x, horizon):
        return programs[0](params_in, arrays, x, horizon)

    def cost_flag(x, horizon):
        return programs[1](params_in, arrays, x, horizon)

    def res_jac(x, horizon):
        # a point past the safe step is no fit: its residuals are nan, so LM rejects the
        # trial step (tuning.lm) instead of walking out of the stable region
        r, J, bad = res_jac_flag(x, horizon)
        return jnp.where(bad > 0, jnp.nan, r), J

    t0 = time.perf_counter()
    cands = [np.asarray(x0, dtype=float)] + _start_points(free, x0, lo, hi, starts, seed,
                                                          spread)
    keep = max(1, min(int(keep), len(cands)))
    screened = []

    def whole_cost(x):
        if len(cands) > 1:          # the screen compiled the cost alone
            c, bad = cost_flag(jnp.asarray(x), jnp.asarray(np.inf))
        else:                       # one start: no second program for one or two costs
            r, _, bad = res_jac_flag(jnp.asarray(x), jnp.asarray(np.inf))
            c = jnp.sum(r * r)
        return math.inf if int(bad) or not np.isfinite(float(c)) else float(c)
    screen_note = ""
    if "screen" in saved:
        screened, order, screen_note = (saved["screen"]["costs"], saved["screen"]["order"],
                                        saved["screen"]["note"])
        screened = [float(c) for c in screened]
    elif len(cands) > 1:
        # the first horizon's costs rank the starts; where they do not tell them apart (a
        # horizon that ends before the first contact), the next horizons in turn, up to the
        # whole records
        stages = [np.inf if h is None else float(h) for h in horizons]
        stages = [h for j, h in enumerate(stages) if h not in stages[:j]]
        if np.inf not in stages:
            stages.append(np.inf)
        for hz in stages:
            screened = []
            for xc in cands:
                c, bad = cost_flag(jnp.asarray(xc), jnp.asarray(hz))
                screened.append(math.inf if int(bad) or not np.isfinite(float(c))
                                else float(c))
            if not _screen_tied(screened):
                break
        if hz != stages[0]:
            screen_note = ("; the starts' costs at the first horizon were equal: screened "
                           + ("on the whole records" if hz == np.inf else f"up to {hz:g} s"))
        if _screen_tied(screened) and keep < len(cands):
            screen_note = ("; the starts' screen costs are equal up to the whole records: LM "
                           f"ran from the first {keep} in order, not from the cheapest")
        order = [int(i) for i in np.argsort(screened, kind="stable")[:keep]]
    else:
        order = [0]
    if ck is not None and "screen" not in saved:
        ck.state = {"screen": {"costs": screened, "order": order, "note": screen_note},
                    "runs": []}
        ck.save()
    ended = {int(u["ci"]): u for u in (ck.state["runs"] if ck is not None else [])}
    current = ck.state.get("current") if ck is not None else None
    bar = Progress(maxiter * len(horizons) * len(order), label="fit", enabled=progress)
    runs, it_all = [], 0
    for ci in order:
        x = cands[ci]
        if bool(params_unstable(sim, with_leaves(params, {
                f.name: f.from_x(x[i]) for i, f in enumerate(free)}))):
            continue                    # past the safe step: no LM from here
        if ci in ended:                 # a run the checkpoint holds whole
            u = ended[ci]
            x = np.asarray(u["x"], dtype=float)
            hist, message, cost_start = list(u["history"]), u["message"], u["cost_start"]
            it_all += int(u["iterations"])
        else:
            x, hist, message, cost_start, it_all = _run_stages(
                ci, cands, horizons, lo, hi, maxiter, res_jac, whole_cost, bar, it_all,
                current if current is not None and current["ci"] == ci else None, ck)
        r, J, n_bad = (np.asarray(a) for a in res_jac_flag(jnp.asarray(x),
                                                           jnp.asarray(np.inf)))
        runs.append((ci, x, r, J, int(n_bad), hist, message, cost_start))
    bar.close()
    if not runs:
        raise unsafe_start({f.name: float(f.from_x(cands[order[0]][i]))
                            for i, f in enumerate(free)}, sim.dt, sim)
    # lowest final cost among the stable fits (an unstable one only when all are)
    best = min(runs, key=lambda u: (u[4] > 0, float(u[2] @ u[2])))
    _, x, r, J, n_bad, hist, message, cost_chosen_start = best
    # cost_start is at the given values (cands[0]), whichever start the fit kept
    cost_start = cost_chosen_start if best[0] == 0 else whole_cost(cands[0])
    cost = float(r @ r)
    start_info = [{"values": {f.name: float(f.from_x(xc[i])) for i, f in enumerate(free)},
                   "screen_cost": screened[j] if screened else None,
                   "cost": next((float(u[2] @ u[2]) for u in runs if u[0] == j), None),
                   "chosen": j == best[0]}
                  for j, xc in enumerate(cands)]
    if n_bad:   # past the safe step: never a result (tuning.stable)
        cost = math.nan
        message = (f"NOT a result: {n_bad} of {sum(len(b.paths) for b in batches)} records "
                   f"ran past the safe step at the fitted values{solver_miss(sim)} "
                   "(State.aux['unstable']); lower dt or tighten the [fit.bounds] of k / c "
                   f"({message})")
    jmax = float(np.max(np.abs(J))) if J.size and np.all(np.isfinite(J)) else math.inf
    diverged = not jmax <= JACOBIAN_LIMIT
    if diverged:
        # the rollouts' derivatives ran away while their values stayed bounded (a tangent
        # mode the step cannot hold, e.g. stiff viscous friction under an impact's load):
        # the Gauss-Newton steps, errors and correlations mean nothing
        message = (f"NOT a result: the rollouts' derivatives blew up (largest |d residual / "
                   f"d parameter| = {jmax:.3g}, past {JACOBIAN_LIMIT:g}); the step is too "
                   "long for their tangent dynamics: lower dt or raise the slip_speed of "
                   f"friction materials ({message})")
    values = {f.name: float(f.from_x(x[i])) for i, f in enumerate(free)}
    # held by the safe step: a contact k / c within SAFE_MARGIN of its cap, or one the records
    # push up (cost falls as it grows) where a step of SAFE_MARGIN up is past the scene's
    # safe step (trial points there are rejected, so LM only creeps towards it)
    g = J.T @ r if np.all(np.isfinite(J)) and np.all(np.isfinite(r)) else np.zeros(len(free))
    held = []
    if not (n_bad or diverged):
        for i, f in enumerate(free):
            if caps[i] == math.inf:
                continue
            v = values[f.name]
            if v >= caps[i] * (1.0 - SAFE_MARGIN):
                held.append(i)
            elif g[i] < 0.0:
                up = np.asarray(x, float).copy()
                up[i] = f.to_x(v * (1.0 + SAFE_MARGIN))
                if int(cost_flag(jnp.asarray(up), jnp.asarray(np.inf))[1]):
                    held.append(i)
    if held:
        message = ("held by the safe step (the records favour a larger value than dt = "
                   f"{sim.dt:g} s allows; the other fitted values are biased with it): "
                   + ", ".join(f"{free[i].name} = {values[free[i].name]:.6g}" for i in held)
                   + "; use a smaller dt (halving it allows 4x the contact k, 2x the c) or "
                   f"more substeps in the scene file, not wider [fit.bounds] ({message})")
    near = 1e-9 * (1.0 + np.abs(np.asarray(x, float)))
    ends = [f"{f.name} = {values[f.name]:.6g} "
            f"({'lower' if abs(x[i] - lo[i]) <= near[i] else 'upper'})"
            for i, f in enumerate(free)
            if min(abs(x[i] - lo[i]), abs(x[i] - hi[i])) <= near[i] and i not in held]
    if ends:
        message += ("; at a bound (the records favour a value beyond it: widen [fit.bounds], "
                    f"or take the bound as the answer; a log-space leaf without bounds moves at "
                    f"most a factor {LOG_SPAN:g} from its start, the safe step caps contact k "
                    f"and c): {', '.join(ends)}")
    message += screen_note
    rows, first = [], 0                     # each residual's record over all batches
    for b in batches:
        rows.append(residual_records(b, loss, sim.scene.has_rotation) + first)
        first += b.pos.shape[0]
    rows = np.concatenate(rows)
    stderr, corr, undetermined = parameter_errors(
        J, r, cost, free, values, rows if len(rows) == len(r) else None,
        sum(active_offsets(sim, b) for b in batches) if refine_start else 0)
    if diverged:
        stderr = {name: math.nan for name in stderr}
        corr = np.full_like(corr, np.nan)
        undetermined = []
    # a positive leaf whose standard error exceeds its value: the records barely see it (a
    # cloth's structural k fitted 2.7 +- 11.8 from 120, truth 200, was not said; audit13)
    loose = [f"{f.name} = {values[f.name]:.3g} +- {stderr[f.name]:.2g}" for f in free
             if f.log and math.isfinite(stderr[f.name]) and stderr[f.name] > values[f.name]]
    if loose:
        message += ("; barely determined by the records (a standard error above the value; "
                    "hold it, or record motion that moves it): " + ", ".join(loose))
    fitted = with_leaves(params, {n: jnp.asarray(v, sim.dtype) for n, v in values.items()})
    return TrajFitResult(fitted, names, values, stderr, corr, undetermined, cost_start, cost,
                         [None if h is None else float(h) for h in horizons], it_all, hist,
                         time.perf_counter() - t0, message, unstable=n_bad,
                         starts=start_info, diverged=diverged,
                         cost_chosen_start=cost_chosen_start, resumed=resumed,
                         residuals=r, jacobian=J)


def _run_stages(ci, cands, horizons, lo, hi, maxiter, res_jac, whole_cost, bar, it_all,
                current, ck):
    """One LM run of :func:`fit_records` from start ``cands[ci]`` through every horizon in
    turn: ``(x, history, message, cost_start, it_all)``. ``current``: the checkpoint's run
    in progress from this start (resumed at its stage), or None; ``ck``: the
    :class:`tuning.fit_checkpoint.FitCheckpoint` told of every iteration, or None."""
    x, hist, message, it_start = cands[ci], [], "", it_all
    stage, lm_state = -1, None
    if current is not None:
        x = np.asarray(current["lm"]["x"], dtype=float)
        hist, cost_start = list(current["history"]), current["cost_start"]
        it_all, it_start = int(current["it_all"]), int(current["it_start"])
        stage, lm_state = int(current["stage"]), current["lm"]
    else:
        # the start's cost on the whole records, the scale of the final cost (the first
        # stage of a growing horizon sees only the first seconds of every record)
        cost_start = whole_cost(cands[ci])
    for j, hz in enumerate(horizons):
        if j < stage:
            continue
        resume = lm_state if j == stage else None
        if resume is None and hz is None and j > 0 and cost_start < whole_cost(x):
            # the shorter horizons led somewhere the whole records like less than the
            # start (parameters the early frames do not determine can drift): the
            # whole-record stage starts from the start point instead
            x = cands[ci]
        h = jnp.asarray(np.inf if hz is None else float(hz))

        def note(lm, j=j, before=list(hist), it_before=it_all):
            ck.state["current"] = {"ci": ci, "stage": j, "history": before,
                                   "cost_start": cost_start, "it_all": it_before,
                                   "it_start": it_start, "lm": lm}
            ck.save()
        res = levenberg_marquardt(lambda xx: res_jac(xx, h), x, lo, hi, maxiter=maxiter,
                                  progress=bar, offset=it_all, resume=resume,
                                  on_iteration=None if ck is None else note)
        x = res.x
        it_all += res.iterations
        hist += [float(c) for c in res.cost_history]
        message = res.message
    if ck is not None:
        ck.state["runs"].append({"ci": ci, "x": [float(v) for v in x], "history": hist,
                                 "message": message, "cost_start": cost_start,
                                 "iterations": it_all - it_start})
        ck.state.pop("current", None)
        ck.save()
    return x, hist, message, cost_start, it_all


def _depth_reference(sim, params, free, lo, batches) -> dict:
    """What :func:`tuning.stable.safe_contact_bounds` needs for a contact law that stiffens
    with depth to count the records' own start energy (:mod:`diffpen.stability.depth`) instead
    of the bodies' radii: the records' start states, ``params`` (a named plane's offset) and
    the softest contact stiffness the fit may reach (the lower bound of a fitted contact k,
    else its value), whose contact sinks deepest; empty for the other laws."""
    if sim.analysis.depth_exponent is None:
        return {}
    fitted = {f.name: float(f.from_x(lo[i])) for i, f in enumerate(free)}
    ks = [fitted.get(f"contact.{name}.k", float(np.min(np.asarray(cp.k))))
          for name, cp in params.contact.items()]
    return dict(state=[b.start for b in batches], params=params,
                k_min=min(ks) if ks else None)


def _screen_tied(costs) -> bool:
    """The screen's finite costs are all equal to rounding (they rank nothing)."""
    c = np.asarray([v for v in costs if np.isfinite(v)], float)
    return c.size > 1 and float(c.max() - c.min()) <= 1e-12 * float(np.abs(c).max())


def _start_points(free, x0, lo, hi, starts, seed, spread) -> list:
    """Extra start points of :func:`fit_records` in fitting space (see its ``starts``)."""
    if isinstance(starts, (int, np.integer)):          # >= 0: fit_records checked it
        rng = np.random.default_rng(seed)
        half = np.array([math.log(spread) if f.log else (
            0.1 * (hi[i] - lo[i]) if np.isfinite(hi[i] - lo[i]) else 0.01)
            for i, f in enumerate(free)])
        x0 = np.asarray(x0, dtype=float)
        a, b = np.maximum(x0 - half, lo), np.minimum(x0 + half, hi)
        return [rng.uniform(a, b) for _ in range(int(starts))]
    out = []
    names = {f.name: i for i, f in enumerate(free)}
    for k, values in enumerate(starts):
        x = np.asarray(x0, dtype=float).copy()
        for name, v in dict(values).items():
            key = _normalise(name)
            if key not in names:
                raise FitError(f"start {k}: {name!r} is not a fitted parameter "
                               f"({sorted(names)}).")
            f = free[names[key]]
            if f.log and v <= 0:
                raise FitError(f"start {k}: {name} = {v} must be > 0 (fitted in log space).")
            x[names[key]] = float(f.to_x(v))
        out.append(np.clip(x, lo, hi))
    return out


# --------------------------------------------------------------------------- scene files
def check_stable(sim: dp.Simulator, params, path: str | None = None) -> None:
    """Raise :class:`diffpen.StabilityError` (with the safe step) before any rollout when
    ``sim``'s explicit integrator is past its limit at ``params`` -- the batched rollouts
    run with concrete checks off. ``path``: the scene file, named in the message."""
    if not sim.analysis.integrator.explicit:     # implicit_euler_with(...) records too
        return
    rep = sim.stability(params)
    if not rep.stable:
        raise dp.StabilityError(
            (f"{path}: " if path else "")
            + f"the scene's integrator {sim.integrator!r} is unstable at dt = {sim.dt:g} s for "
            f"its start parameters (stable step {rep.stable_dt:.3g} s, set by "
            f"{rep.limiting or 'the springs and contacts'}): lower dt in the scene file or "
            "start from softer k / smaller c.", stable_dt=rep.safe_dt,
            substeps=rep.substeps_needed)


def __getattr__(name):
    # the file-level workflow builds on this module: imported when first asked for
    if name == "fit_files":
        from .scene_fit import fit_files
        return fit_files
    if name == "synthetic_record":
        from .synthetic import synthetic_record
        return synthetic_record
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
