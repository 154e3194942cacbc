"""Many independent fits at once: one jitted optimisation loop, vmapped over a batch of rows
and sharded over every device.

A row is one fit: its own targets (N target sets, e.g. a table of apex heights) or its own
start point (N starts for the same targets: a multi-start fit), or both. Every row runs the
optax loop of :func:`tuning.fit.fit` with ``method="optax"`` (:class:`tuning.optimise.OptaxLoop`,
the same iteration and stopping rule): the free leaves of the :class:`diffpen.Params` are
optimised in log space by an optax transformation, projected onto box bounds after every
step, the loss is ``sum_j w_j ((m_j - t_j) / |t_j|)^2``, a row stops when all its targets
are within tolerance at a point inside the safe step that, for a settling-time target, has
settled (or its loss is not finite), and the row reports its best point (the lowest loss among
stable points). So row ``i`` of :func:`fit_batch` is :func:`tuning.fit.fit` run alone on row
``i``'s targets and start, with the same optimiser and ``maxiter`` (same ``reached``,
``converged`` and message).

The whole loop (:meth:`tuning.optimise.OptaxLoop.run`, a ``lax.while_loop`` over iterations;
rows that have stopped keep their state) is one per-row function lifted to the batch by :func:`tuning.shard.sharded_map`: the
batch axis is split over a 1-D device ``Mesh`` with ``NamedSharding(mesh, P("batch"))``, and
the results equal the single-device run. A batch that is not a multiple of the device count is
padded by repeating its last row; the padding never reaches the result. Over several processes
(:mod:`tuning.distributed`) every process calls with the same rows and gets every row back;
processes given different targets, starts or settings, or a different metrics function or
optimiser (compared by the jaxpr of one row's fit), stop at once with the same error.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

import diffpen as dp

from . import distributed
from . import params as P
from .compiled import ProgramCache, frozen_key
from .errors import FitError, positive_int
from .fit import at_bounds, result_message
from .optimise import (LIMIT, MESSAGES, NON_FINITE, REACHED, RUNNING, OptaxLoop,
                       default_optimizer, settling)
from .problem import (FreeLeaves, achieved, normalise_targets, residuals, target_spec,
                      tolerances, with_flag)
from .shard import batch_mesh, sharded_map

__all__ = ["fit_batch", "BatchFitter", "BatchFitResult", "RUNNING", "REACHED", "NON_FINITE",
           "LIMIT", "MESSAGES"]


@dataclasses.dataclass
class BatchFitResult:
    """Outcome of :func:`fit_batch` for N rows and P fitted leaves.

    free: (P,) fitted leaf paths.  values: (N, P) fitted values (SI units: N/m, N s/m, ...),
      the lowest-loss point of each row.  start: (N, P) start values (after clipping to the
      bounds).
    targets: ``{metric: (N, n) array}``.  achieved: ``{metric: (N, n) array}`` measured on
      each row's fitted trajectory (nan for an absent event).
    rel_error: ``{metric: (N,) max |achieved - target| / |target|}``.
    loss: (N,) loss at the fitted values (inf if the first evaluation already failed).
    loss_history: (N, maxiter) loss per iteration (nan after the row stopped).
    converged: (N,) bool, the stopping rule fired (every target within its tolerance).
    reached: (N,) bool, every target of the reported point is within its tolerance (and
      it is not past its safe step; with a settling-time target, it settled: as in
      :func:`tuning.problem.achieved`).
    iterations: (N,) iterations run.  status: (N,) int code, see :data:`MESSAGES`.
    messages: (N,) what happened to each row, in words (the ``message`` that
      :func:`tuning.fit.fit` gives for that row).
    devices: devices the batch axis was split over.  seconds: wall time of the call,
      compilation included (a later call with the same layout reuses the program).
    unstable: (N,) bool, the row's reported point is past its safe step (its metrics are not
      a result, whatever its loss).
    """
    free: list
    values: np.ndarray
    start: np.ndarray
    targets: dict
    achieved: dict
    rel_error: dict
    loss: np.ndarray
    loss_history: np.ndarray
    converged: np.ndarray
    reached: np.ndarray
    iterations: np.ndarray
    status: np.ndarray
    messages: list
    devices: int
    seconds: float
    params0: dp.Params = dataclasses.field(repr=False, default=None)
    unstable: np.ndarray = None

    def __len__(self) -> int:
        return self.values.shape[0]

    def params(self, row: int) -> dp.Params:
        """The fitted :class:`diffpen.Params` of ``row``."""
        flat = dict(P.flatten(self.params0))
        flat.update({p: float(v) for p, v in zip(self.free, self.values[row])})
        return P.unflatten(self.params0, flat)

    def best(self) -> int:
        """Index of the row with the lowest loss among the rows not past their safe step (the
        answer of a multi-start fit; a row past it kept an ordinary loss and was picked over
        a stable row whose apex was missing). Raises :class:`FitError` when every row is
        past its safe step: none is a result."""
        ok = np.isfinite(self.loss)
        if self.unstable is not None:
            ok &= ~np.asarray(self.unstable, bool)
            if not ok.any() and np.asarray(self.unstable, bool).all():
                raise FitError("every row of the batch is past its safe step: none is a result; "
                               "lower the stiffness bounds or the time step.")
        return int(np.argmin(np.where(ok, self.loss, np.inf)))


def _rows(targets, starts) -> tuple[list, list | None]:
    """Targets and starts as equal-length lists of rows (a single dict is shared)."""
    if not isinstance(targets, dict) and (
            isinstance(targets, (str, bytes)) or not isinstance(targets, Sequence)
            or not all(isinstance(row, dict) for row in targets)):
        raise FitError(f"targets must be a dict {{metric: value or list}} shared by every row, "
                       f"or a list of such dicts, one per row; got {targets!r:.80}.")
    n_t = None if isinstance(targets, dict) else len(targets)
    n_s = None if starts is None else len(starts)
    if n_t == 0 or n_s == 0:
        raise FitError("empty batch: give at least one row of targets (a list of dicts) or of "
                       "starts.")
    if n_t is not None and n_s is not None and n_t != n_s:
        raise FitError(f"mismatched batch lengths: {n_t} rows of targets but {n_s} starts; "
                       "give one start per row, or a single targets dict shared by all starts.")
    n = n_t or n_s or 1
    rows = [targets] * n if n_t is None else list(targets)
    return rows, None if starts is None else list(starts)


class BatchFitter:
    """A reusable batched fit of the ``free`` leaves of ``params0``; call it with targets.

    The compiled program depends on the layout of the targets (metric names, entry counts),
    not on their values, so calling the same fitter again with new targets or starts of the
    same layout and batch size does not recompile.

    Args:
      metrics_fn: traceable ``params -> {metric: scalar or (n,) array}`` (e.g.
        :func:`tuning.bounce.bounce_metrics_fn`).
      params0: :class:`diffpen.Params` giving the default start and the frozen leaves.
      free: leaf paths to fit (default every contact k and c).
      bounds: ``{path: (lo, hi)}`` in SI units; default :func:`tuning.fit.default_bounds` of
        ``params0``'s value. Shared by every row.
      weights: ``{metric: weight}`` (default 1).  rtol: relative tolerance per metric (float
        or dict); a row stops when all its targets are within it.
      optimizer: optax transformation acting on the log-parameters (default
        :func:`tuning.fit.default_optimizer` with ``learning_rate``).
      learning_rate: step of the default optimiser (relative change, 0.05 = 5 %); > 0.
      maxiter: iteration limit per row; >= 1.
      mesh: 1-D device mesh with axis ``"batch"`` (default :func:`tuning.shard.batch_mesh`:
        all devices).
      sim: the simulator behind ``metrics_fn`` (optional): contact k and c bounded inside its
        safe step and the stability flag added, as in :func:`tuning.fit.fit`.
      state: with ``sim``, the concrete start state of every row's rollouts, as in
        :func:`tuning.fit.fit` (a Hunt-Crossley contact's safe step at the depth its energy
        allows; default None: the bodies' radii).
    """

    def __init__(self, metrics_fn: Callable, params0: dp.Params, *, free=None,
                 bounds: dict | None = None, weights: dict | None = None, rtol=1e-3,
                 optimizer: optax.GradientTransformation | None = None,
                 learning_rate: float = 0.05, maxiter: int = 200, mesh=None, sim=None,
                 state=None):
        lr = float(learning_rate)
        if not (math.isfinite(lr) and lr > 0.0):
            raise FitError(f"learning_rate must be a positive number (a relative step, e.g. "
                           f"0.05), got {learning_rate!r}.")
        positive_int("maxiter", maxiter, "iterations per row")
        leaves = FreeLeaves.build(params0, free, bounds, sim, state=state)
        # a point past the safe step is never reached (tuning.stable)
        self.metrics_fn = with_flag(metrics_fn, sim, state)
        self.params0, self.free = params0, list(leaves.free)
        self.x0, self.lo, self.hi = leaves.x0, leaves.lo, leaves.hi
        self.weights, self.rtol = weights, rtol
        self.optimizer = default_optimizer(lr) if optimizer is None else optimizer
        self._learning_rate = None if optimizer is not None else lr
        self.maxiter = int(maxiter)
        self.mesh = batch_mesh() if mesh is None else mesh
        self._leaves = leaves
        self._programs: dict = {}

    # ------------------------------------------------------------------ inputs
    def _starts(self, starts: list | None, n: int) -> np.ndarray:
        """(n, P) start values, clipped to the bounds."""
        return self._leaves.start_values([{}] * n if starts is None else starts)

    def _targets(self, rows: list) -> tuple[dict, tuple]:
        """``({metric: (N, n)}, spec)``; every row must have the same metrics and lengths."""
        norm = []
        for i, row in enumerate(rows):
            try:
                norm.append(normalise_targets(dict(row)))
            except FitError as err:
                raise FitError(f"targets row {i}: {err}") from None
        layout = {k: v.size for k, v in norm[0].items()}
        for i, row in enumerate(norm[1:], start=1):
            got = {k: v.size for k, v in row.items()}
            if got != layout:
                raise FitError(f"targets row {i} has the layout {got} but row 0 has {layout}: "
                               "every row needs the same metrics with the same number of "
                               "entries (one compiled program serves the batch).")
        stacked = {k: np.stack([row[k] for row in norm]) for k in layout}
        return stacked, target_spec(norm[0], self.weights, self.rtol)

    def _work(self, tg: dict, spec: tuple, x0: np.ndarray) -> bytes:
        """A digest of one call's work: the targets, starts, target settings, fitted leaves
        and their bounds, the frozen leaves, the iteration limit, the default optimiser's step
        and the devices (several processes must all pass the same). What the fit computes
        (the metrics function, the optimiser, the loss and the loop) is compared by the batch
        program before it first runs: the digest of its jaxpr (:func:`tuning.shard.sharded_map`)."""
        frozen = sorted(P.flatten(self.params0).items())
        h = hashlib.sha256(repr((spec, self.free, self.maxiter, self._learning_rate,
                                 [d.id for d in self.mesh.devices.flat],
                                 [n for n, _ in frozen])).encode())
        arrays = [x0, self.lo, self.hi, *(tg[k] for k in sorted(tg))]
        arrays += [v for _, v in frozen]
        for a in arrays:
            a = np.ascontiguousarray(np.asarray(a, np.float64))
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())
        return h.digest()

    # ------------------------------------------------------------------ program
    def _program(self, spec: tuple) -> Callable:
        """The sharded batch program for one target layout (built once per layout)."""
        if spec in self._programs:
            return self._programs[spec]
        log_lo, log_hi = self._leaves.log_lo, self._leaves.log_hi

        def loss_fn(theta, tgt):
            m = self.metrics_fn(self._leaves.params_of(theta))
            r = residuals(m, tgt, spec)
            return jnp.sum(r * r), (r, m)

        loop = OptaxLoop(loss_fn, self.optimizer, lambda th: jnp.clip(th, log_lo, log_hi),
                         tolerances(spec), self.maxiter, settling=settling(spec))

        def one(theta0, tgt):
            """One row: theta0 (P,) log start, tgt {metric: (n,)} -> fitted row."""
            c = loop.run(theta0, tgt)
            return {"theta": c["best_theta"], "loss": c["best_loss"], "metrics": c["best_m"],
                    "history": c["history"], "status": c["status"],
                    "iterations": loop.iterations(c)}

        run = sharded_map(one, self.mesh, what="batched fit program (the metrics function, "
                          "the optimiser and the fit loop, compared by their jaxpr)")
        self._programs[spec] = run
        return run

    def program(self, targets) -> Callable:
        """The sharded batch program for the layout of ``targets`` (as in :meth:`__call__`):
        the :func:`tuning.shard.sharded_map` runner, with ``.mesh`` and ``.jitted`` (lower it to
        inspect how the batch axis is split). Built once per layout."""
        return self._program(self._targets(_rows(targets, None)[0])[1])

    # ------------------------------------------------------------------ call
    def __call__(self, targets, starts: Sequence[dict] | None = None) -> BatchFitResult:
        """Run every row's fit.

        Args:
          targets: ``{metric: value or list}`` shared by every row (a multi-start fit), or a
            list of N such dicts, one per row (e.g. ``[{"apex_heights": [0.2]},
            {"apex_heights": [0.1]}]``, heights in m). Every row needs the same metrics with
            the same number of entries.
          starts: None (every row starts at ``params0``) or a list of N ``{path: value}``
            dicts (SI units; paths left out start at ``params0``'s value).
        Returns: :class:`BatchFitResult` with N rows.
        """
        rows, starts = _rows(targets, starts)
        tg, spec = self._targets(rows)
        x0 = self._starts(starts, len(rows))
        # several processes: each fills its devices' rows from its own batch, so all must pass
        # the same (else rows of other fits would be returned as this one's)
        distributed.check_same("batched fit (targets, starts and settings)",
                               self._work(tg, spec, x0))
        t0 = time.perf_counter()
        run = self._program(spec)
        out = jax.device_get(jax.block_until_ready(
            run(jnp.asarray(np.log(x0)), {k: jnp.asarray(v) for k, v in tg.items()})))
        seconds = time.perf_counter() - t0
        n = len(rows)
        if out["loss"].shape != (n,):     # sharded_map drops the padding rows
            raise RuntimeError(f"batch program returned {out['loss'].shape[0]} rows for {n}.")
        ach = {k: np.asarray(out["metrics"][k], float).reshape(n, -1)[:, :v.shape[1]]
               for k, v in tg.items()}
        rel = {k: np.empty(n) for k in tg}
        reached = np.zeros(n, bool)
        unstable = (np.asarray(out["metrics"]["unstable"]).reshape(n, -1).any(axis=1)
                    if "unstable" in out["metrics"] else np.zeros(n, bool))
        status = np.asarray(out["status"], int)
        theta, loss = np.asarray(out["theta"], float), np.asarray(out["loss"], float)
        messages = []
        for i in range(n):
            # every metric of the row: achieved checks "settled" and "unstable" too
            m_i = {k: np.asarray(v)[i] for k, v in out["metrics"].items()}
            _, rel_i, reached[i] = achieved(m_i, {k: v[i] for k, v in tg.items()}, spec)
            for k in tg:
                rel[k][i] = rel_i[k]
            said = MESSAGES.get(int(status[i]), "not run")
            messages.append(result_message(said, reached[i], m_i, spec,
                                           at_bounds(self.free, theta[i], self._leaves))
                            if np.isfinite(loss[i]) else
                            f"the first iteration already failed: {said}")
        return BatchFitResult(
            free=list(self.free), values=np.exp(theta), start=x0,
            targets=tg, achieved=ach, rel_error=rel, loss=loss,
            loss_history=np.asarray(out["history"], float), converged=status == REACHED,
            reached=reached, iterations=np.asarray(out["iterations"], int), status=status,
            messages=messages, devices=int(run.mesh.devices.size), seconds=seconds,
            params0=self.params0, unstable=unstable)


def fit_batch(metrics_fn: Callable, params0: dp.Params, targets,
              starts: Sequence[dict] | None = None, **options) -> BatchFitResult:
    """Run N independent fits at once, the batch axis sharded over every device.

    ``fit_batch(metrics_fn, params0, targets, starts, **options)`` is
    ``BatchFitter(metrics_fn, params0, **options)(targets, starts)``; see :class:`BatchFitter`
    for the options (``free``, ``bounds``, ``weights``, ``rtol``, ``optimizer``,
    ``learning_rate``, ``maxiter``, ``mesh``, ``sim``, ``state``). A later call with equal
    arguments (the same metrics function, equal ``params0`` and options) reuses the fitter
    built first: new targets or starts of the same layout compile nothing.

    Args:
      metrics_fn: traceable ``params -> {metric: scalar or (n,) array}``.
      params0: start :class:`diffpen.Params` (also supplies the frozen leaves).
      targets: one ``{metric: value or list}`` for every row, or a list of N of them.
      starts: None or a list of N ``{path: value}`` start points (SI units).
    Returns: :class:`BatchFitResult`; row i equals :func:`tuning.fit.fit` with
      ``method="optax"`` on row i alone.
    Raises: :class:`tuning.fit.FitError` (a ``ValueError``) for an empty batch, rows of
      different layouts or counts, non-finite or zero targets, unknown parameters, a
      non-positive learning rate or iteration limit: before anything is compiled.
    """
    fitter = BatchFitter(metrics_fn, params0, **options)    # the options checked, then
    rows, first = _rows(targets, starts)                   # the batch: before any trace
    fitter._targets(rows)
    fitter._starts(first, len(rows))
    # one fitter for equal arguments and for what metrics_fn computes now (its jaxpr: a
    # function whose globals changed is another program): a later call compiles nothing
    try:
        now = distributed.jaxpr_digest(jax.make_jaxpr(lambda p: metrics_fn(p))(params0))
    except Exception:       # noqa: BLE001 - not traceable here: the fit says why
        now = None
    key = None if now is None else frozen_key(metrics_fn, now, params0, options)
    return (fitter if key is None else _FITTERS.get(key, lambda: fitter))(targets, starts)


#: fitters :func:`fit_batch` built, by their arguments (values), the last 8
_FITTERS = ProgramCache()
