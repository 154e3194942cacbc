"""The optax loop: first-order fitting of log-parameters with any
``optax.GradientTransformation``, projected onto box bounds after every step.

:class:`OptaxLoop` is ONE iteration (:meth:`OptaxLoop.step`) on a carry that holds the
iterate, the optimiser state, the best point so far and the loss history; it is pure and
traceable, so it runs either

* from the host, one jitted call per iteration (:func:`fit_optax`, behind
  ``tuning.fit.fit(method="optax")``: a progress bar, the loop compiles once), or
* inside a ``lax.while_loop`` (:meth:`OptaxLoop.run`, behind :mod:`tuning.batch_fit`, vmapped
  over rows and sharded over devices),

with the same rule either way. Per iteration: the loss ``sum_j r_j^2`` of the weighted
relative residuals (:func:`tuning.problem.residuals`) and its gradient (forward mode for a
handful of parameters, :func:`diffpen.value_and_grad`), one optax update, the projection.
The loop stops when every residual is within its tolerance at a point that is not past its
safe step (``"unstable"`` false) and, with a ``settling_time`` target, that has settled
(``"settled"`` true: else the time is only the rollout's end), when the loss is not finite, or
at ``maxiter``. The best point is the lowest-loss one among stable points (an unstable point
only while none is stable).
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

import diffpen as dp

from .errors import FitError
from .problem import Problem, Solution, tolerances
from .stable import FLAG

__all__ = ["default_optimizer", "settling", "OptaxLoop", "fit_optax", "RUNNING", "REACHED",
           "NON_FINITE", "LIMIT", "MESSAGES"]

#: Status codes of the loop (``OptaxLoop`` carry ``"status"``).
RUNNING, REACHED, NON_FINITE, LIMIT = 0, 1, 2, 3
MESSAGES = {REACHED: "targets reached", LIMIT: "iteration limit reached",
            NON_FINITE: "loss became non-finite; stopped (try a smaller learning rate or dt)"}


def default_optimizer(learning_rate: float = 0.05) -> optax.GradientTransformation:
    """Adam on log-parameters with global-norm clipping and a decaying step: steps are
    relative changes (0.05 = 5 %), halved every 60 iterations so the fit settles to ~1e-4."""
    schedule = optax.exponential_decay(learning_rate, transition_steps=60, decay_rate=0.5)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adam(schedule))


def settling(spec: tuple) -> bool:
    """Whether the target spec has a ``settling_time`` target (``OptaxLoop(settling=...)``)."""
    return any(s.name == "settling_time" for s in spec)


class OptaxLoop:
    """One optax loop on log-parameters ``theta`` (any pytree of float arrays).

    Args:
      loss_fn: traceable ``loss_fn(theta, *args) -> (loss, (r (m,), metrics))``: the sum of
        squared residuals, the residuals and the metrics dict (``"unstable"`` in it, when
        present, blocks reaching and ranks the point after the stable ones).
      tx: the optax transformation (it sees ``theta``).
      project: ``theta -> theta`` onto the box (log bounds), applied after every update.
      tols: (m,) residual thresholds (:func:`tuning.problem.tolerances`).
      maxiter: iteration limit (>= 1).
      settling: a ``settling_time`` target is among the residuals: a point whose metrics'
        ``"settled"`` entry is false does not meet it (its time is only the rollout's end;
        as in :func:`tuning.problem.achieved`). :func:`settling` of the target spec.
      history: keep the loss of every iteration in the carry (``c["history"]``, (maxiter,)),
        for :meth:`run`; a host driver that records the losses itself passes False, so that
        a new ``maxiter`` changes no array shape (and compiles nothing new).
    """

    def __init__(self, loss_fn: Callable, tx: optax.GradientTransformation,
                 project: Callable, tols, maxiter: int, *, settling: bool = False,
                 history: bool = True):
        self.tx, self.tols, self.maxiter = tx, np.asarray(tols), int(maxiter)
        self.settling, self.history = bool(settling), bool(history)
        value_and_grad = dp.value_and_grad(loss_fn, has_aux=True)

        def update(theta, state, *args):
            (loss, (r, m)), g = value_and_grad(theta, *args)
            upd, state = tx.update(g, state, theta)
            new = project(optax.apply_updates(theta, upd))
            return new, state, loss, r, {k: jnp.asarray(v) for k, v in m.items()}
        # jitted so that init's eval_shape and every step share ONE trace of loss_fn
        self.update = jax.jit(update)

    def init(self, theta0, *args) -> dict:
        """The carry before the first iteration, from the log start ``theta0`` (traceable)."""
        state = self.tx.init(theta0)
        shapes = jax.eval_shape(self.update, theta0, state, *args)
        loss_s, m_s = shapes[2], shapes[4]
        c = {"it": jnp.asarray(0), "theta": theta0, "state": state,
                "loss": jnp.asarray(jnp.nan, loss_s.dtype),
                "best_loss": jnp.asarray(jnp.inf, loss_s.dtype), "best_theta": theta0,
                "best_m": jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), m_s),
                "best_bad": jnp.asarray(True), "best_met": jnp.asarray(False),
                "has_best": jnp.asarray(False),
                "status": jnp.asarray(RUNNING)}
        if self.history:
            c["history"] = jnp.full((self.maxiter,), jnp.nan, loss_s.dtype)
        return c

    def step(self, c: dict, *args) -> dict:
        """One iteration: evaluate at ``c["theta"]``, keep it if it is the best point, stop or
        move to the projected update (pure; ``args`` go to ``loss_fn``)."""
        new, state, loss, r, m = self.update(c["theta"], c["state"], *args)
        finite = jnp.isfinite(loss)
        bad = jnp.any(m[FLAG]) if FLAG in m else jnp.asarray(False)
        met = finite & jnp.all(jnp.abs(r) <= self.tols) & ~bad
        if self.settling and "settled" in m:     # never settled: not a settling time
            met = met & jnp.all(m["settled"])
        status = jnp.where(~finite, NON_FINITE, jnp.where(
            met, REACHED, jnp.where(c["it"] + 1 >= self.maxiter, LIMIT, RUNNING)))
        lower = loss < c["best_loss"]
        # stable points first, then points that meet every target (the loss weighs the
        # targets together: a lower one can miss a tolerance), then the lowest loss
        bb, bm = c["best_bad"], c["best_met"]
        better = finite & (~c["has_best"] | (bb & ~bad) | ((bb == bad) & (
            (met & ~bm) | ((met == bm) & lower))))
        go = status == RUNNING

        def pick(flag, a, b):
            return jax.tree_util.tree_map(lambda x, y: jnp.where(flag, x, y), a, b)
        out = {"it": jnp.where(go, c["it"] + 1, c["it"]),
                "theta": pick(go, new, c["theta"]),
                "state": pick(go, state, c["state"]),
                "loss": loss,
                "best_loss": jnp.where(better, loss, c["best_loss"]),
                "best_theta": pick(better, c["theta"], c["best_theta"]),
                "best_m": pick(better, m, c["best_m"]),
                "best_bad": jnp.where(better, bad, c["best_bad"]),
                "best_met": jnp.where(better, met, c["best_met"]),
                "has_best": c["has_best"] | better,
                "status": status}
        if "history" in c:
            out["history"] = c["history"].at[c["it"]].set(jnp.where(finite, loss, jnp.nan))
        return out

    def run(self, theta0, *args) -> dict:
        """The whole loop as one ``lax.while_loop`` (traceable: jit, vmap over rows). Returns
        the final carry; see :meth:`iterations`."""
        return jax.lax.while_loop(lambda c: c["status"] == RUNNING,
                                  lambda c: self.step(c, *args), self.init(theta0, *args))

    def iterations(self, c: dict):
        """Iterations run by a finished carry (traceable): the loop's steps, ``c["it"] + 1``
        when it reached the targets or its limit (``maxiter``), ``c["it"]`` when the loss
        became non-finite (that step is not counted); the loss history holds one entry per
        iteration, the loss at the point it started from."""
        return jnp.where(c["status"] == LIMIT, self.maxiter,
                         jnp.where(c["status"] == REACHED, c["it"] + 1, c["it"]))


def fit_optax(problem: Problem, optimizer: optax.GradientTransformation | None = None, *,
              maxiter: int = 300, progress=None) -> Solution:
    """Run the optax loop on ``problem`` from the host, one jitted iteration per call.

    The optimiser sees the free leaves only, as a dict of their log values keyed by leaf
    path: the frozen leaves are constants of the loss, neither differentiated nor moved
    (they had been carried through the optimiser with ``optax.set_to_zero``, and each was
    one more forward-mode tangent: 7 for a fit of 1 leaf among 7). ``optimizer`` acts on
    log-parameters (default :func:`default_optimizer`). ``progress``: a :class:`tuning.progress.Progress` or None.
    Returns a :class:`tuning.problem.Solution` at the best point (see the module docstring);
    each iteration evaluates the loss at its point (the first at the start) and then steps, so
    the history has one entry per iteration (:meth:`OptaxLoop.iterations`).
    """
    opt = optimizer if optimizer is not None else default_optimizer()
    leaves, free = problem.leaves, problem.free
    idx = {p: i for i, p in enumerate(free)}
    log_lo, log_hi = leaves.log_lo, leaves.log_hi
    traces = [0]

    def loss_fn(theta_d, targets):
        traces[0] += 1
        theta = jnp.stack([theta_d[p] for p in free])
        r, m = problem.evaluate(theta, targets)
        return jnp.sum(r * r), (r, m)

    def project(theta_d):
        return {p: jnp.clip(v, log_lo[idx[p]], log_hi[idx[p]]) for p, v in theta_d.items()}

    def build():
        loop = OptaxLoop(loss_fn, opt, project, tolerances(problem.spec), maxiter,
                         settling=settling(problem.spec), history=False)
        return loop, jax.jit(loop.step)
    # the same optimiser (the default one, or the same object), bounds and maxiter
    loop, step = problem.program(("optax", "default" if optimizer is None else optimizer,
                                  tuple(log_lo), tuple(log_hi), int(maxiter)), build)
    theta_d = {p: jnp.asarray(v) for p, v in zip(free, problem.theta0)}
    c = loop.init(theta_d, problem._tgt)
    history, costs = [], []
    converged, message, iterations = False, MESSAGES[LIMIT], maxiter
    for it in range(maxiter):
        c = step(c, problem._tgt)
        status = int(c["status"])
        if status == NON_FINITE:
            message, iterations = MESSAGES[NON_FINITE], it
            break
        loss = float(c["loss"])
        history.append(loss)
        costs.append(loss)
        if progress is not None:
            progress.update(it + 1, loss)      # iterations done, 1..maxiter
        if status == REACHED:     # this iteration's loss met the targets
            converged, message, iterations = True, MESSAGES[REACHED], it + 1
            break
    if not bool(c["has_best"]):
        raise FitError(f"the first iteration already failed: {message}.")
    theta = np.array([float(c["best_theta"][p]) for p in free])
    return Solution(theta, c["best_m"], np.asarray(history), iterations, converged, message,
                    traces[0], len(costs), np.asarray(costs))

