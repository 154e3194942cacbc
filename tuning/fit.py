"""Fit any subset of a simulator's parameters to weighted targets.

The fitted leaves of the :class:`diffpen.Params` pytree are optimised in log space
(``theta = log value``, so k and c stay positive and steps are relative), projected onto box
bounds after every step. :func:`fit` builds the :class:`tuning.problem.Problem` (targets,
residuals, bounds) and hands it to one of two methods:

* ``method="optax"``: any ``optax.GradientTransformation`` on the loss
  ``sum_j w_j ((m_j - t_j) / |t_j|)^2`` (:func:`tuning.optimise.fit_optax`, the loop that
  :mod:`tuning.batch_fit` runs too) on the free leaves only: frozen leaves are constants of
  the loss, so the optimiser never sees them and nothing differentiates them.
* ``method="lm"``: Levenberg-Marquardt (:func:`tuning.lm.fit_lm`) on the residual vector with a
  forward-mode (``jax.jacfwd``) Jacobian; for a handful of parameters it needs far fewer
  iterations.

Each method jit-compiles ONE iteration function before the loop; later iterations only call
it (``FitResult.traces`` counts the traces so tests can check it). ``metrics_fn(params)`` must
be traceable; it returns a dict of scalars/arrays from which the targets are read.

This module holds :func:`fit` and its :class:`FitResult`, and re-exports the names that moved
(``FitError``: :mod:`tuning.errors`; bounds, ``residual_reached``: :mod:`tuning.problem`;
``default_optimizer``: :mod:`tuning.optimise`; ``Progress``: :mod:`tuning.progress`). The
bouncing-ball problem behind ``diffpen fit`` is :mod:`tuning.bounce`.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

import diffpen as dp

from .errors import FitError, positive_int
from .lm import fit_lm
from .optimise import default_optimizer, fit_optax, settling
from .problem import (RESIDUAL_FACTOR, Problem, default_bounds, residual_reached,
                      safe_bounds)
from .progress import Progress

__all__ = ["FitResult", "FitError", "fit", "result_message", "default_optimizer", "Progress",
           "default_bounds", "safe_bounds", "residual_reached", "RESIDUAL_FACTOR"]


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit`.

    params: fitted :class:`diffpen.Params`.
    values: ``{path: fitted value}`` of the free leaves (SI units).
    targets: ``{metric: target}``.  achieved: ``{metric: value}`` measured on the fitted
      trajectory with the exact metric definitions (same entries as ``targets``).
    rel_error: ``{metric: max |achieved - target| / |target|}``.
    reached: every target within its tolerance.  converged: the stopping rule fired (not
      the iteration limit).
    loss_history: loss per iteration, the first entry at the start: LM (iterations + 1,),
      the start then the loss after each iteration (of the run kept, with several starts);
      optax (iterations,): each iteration evaluates the loss at its point, then steps.
    iterations: iterations run (LM with several starts: all runs together); a progress bar
      ends at this count.  seconds: wall time of the loop, compilation included.
    traces: how many times the residual function was traced (fixed per method, whatever
      the number of iterations: the loop compiles once).
    evaluations: compiled-function calls (iterations, LM trial points and start search).
    eval_history: (evaluations,) loss at every evaluated point, in order.
    message: what happened, in words.  stderr: ``{path: standard error}`` or None.
    metrics: every entry ``metrics_fn`` returns, at the fitted point (numpy arrays: those
      the targets do not name too, e.g. ``decay_valid``), from the fit's own last evaluation.
    """
    params: dp.Params
    values: dict
    targets: dict
    achieved: dict
    rel_error: dict
    reached: bool
    converged: bool
    loss_history: np.ndarray
    iterations: int
    seconds: float
    traces: int
    message: str
    stderr: dict | None = None
    start: dict | None = None
    evaluations: int = 0
    eval_history: np.ndarray | None = None
    notes: list = dataclasses.field(default_factory=list)
    metrics: dict | None = None


# --------------------------------------------------------------------------- fit
def check_method(method) -> None:
    """Refuse a ``method`` other than ``"lm"`` and ``"optax"``, saying how to ask for Adam or
    SGD (the ``diffpen`` command's ``--method adam|sgd``): ``method="optax"`` with
    ``optimizer=`` (default :func:`tuning.optimise.default_optimizer`, Adam)."""
    if method in ("lm", "optax"):
        return
    hint = (f" For {method}, use method='optax', optimizer=optax.{method.lower()}(lr) (the "
            "default optimizer is Adam with a decaying step)."
            if isinstance(method, str) and method.lower() in ("adam", "sgd") else "")
    raise FitError(f"unknown method {method!r}; use 'optax' or 'lm'.{hint}")


def fit(metrics_fn: Callable, params0: dp.Params, targets: dict, *, free=None,
        bounds: dict | None = None, weights: dict | None = None, rtol=1e-3,
        method: str = "optax", optimizer: optax.GradientTransformation | None = None,
        maxiter: int = 300, progress: bool | None = False, label: str = "fit",
        starts: list | None = None, n_starts: int = 3,
        search: Callable | None = None, sim=None, state=None) -> FitResult:
    """Fit the ``free`` leaves of ``params0`` so that ``metrics_fn(params)`` meets ``targets``.

    Args:
      metrics_fn: traceable ``params -> {metric: scalar or (n,) array}``.
      params0: start :class:`diffpen.Params` (also supplies the frozen leaves).
      targets: ``{metric: value or list}``; a list is compared with the metric's first
        entries (e.g. ``{"apex_heights": [0.4, 0.2], "settling_time": 1.5}``).
      free: leaf paths to fit (see :mod:`tuning.params`); default every contact k and c.
      bounds: ``{path: (lo, hi)}`` in SI units; default :func:`default_bounds`.
      weights: ``{metric: weight}`` (default 1).
      rtol: relative tolerance per metric (float or dict); the fit stops when all are met.
      method: ``"optax"`` (first order, any optax transformation) or ``"lm"``.
      optimizer: optax transformation for ``method="optax"`` (default
        :func:`default_optimizer`); it acts on log-parameters.
      maxiter: iteration limit (>= 1; with ``method="lm"``, of each run from a start
        point).  progress: False (default): print nothing; None or True: a progress bar on
        stderr when it is a terminal, else a line every 5 s (what the `diffpen` command
        passes).
      starts: extra start points ``[{path: value}, ...]``; with ``method="lm"`` they are
        ranked by cost and LM runs from the best ``n_starts`` (>= 1; all with the same
        compiled function) until one reaches the targets; the best result is kept. With
        ``method="optax"`` the loop runs from the start of lowest cost among ``params0`` and
        these (for several optax runs at once: :func:`tuning.batch_fit.fit_batch`).
      search: ``search(evaluate, slices, log_lo, log_hi) -> [theta, ...]`` (LM only): a
        problem-specific search for start points in log space; ``evaluate(theta) -> (r, J,
        metrics)`` is the fit's compiled residual/Jacobian function and ``slices`` maps each
        target to its rows of ``r``.
      sim: the simulator behind ``metrics_fn`` (optional, recommended): contact k and c are
        then bounded inside its safe step (:func:`safe_bounds`), and when ``metrics_fn`` has
        no ``"unstable"`` entry the fit adds :func:`tuning.stable.params_unstable`; a point
        past the safe step is never returned as reached.
      state: with ``sim``, the concrete start state of ``metrics_fn``'s rollouts (e.g.
        ``sim.init_state()``), so that a Hunt-Crossley contact's safe step counts its
        stiffness at the depth that state's energy allows, as the rollout does
        (:mod:`diffpen.stability.depth`), in the bounds and the added flag alike; default
        None: at the bodies' radii (conservative for any start; a Hertz ball's fit may then
        be bounded below the stiffness its rollout runs at).
    Returns:
      :class:`FitResult`.
    """
    check_method(method)
    positive_int("maxiter", maxiter, "the iteration limit")
    positive_int("n_starts", n_starts, "how many start points LM runs from")
    problem = Problem.build(metrics_fn, params0, targets, free=free, bounds=bounds,
                            weights=weights, rtol=rtol, sim=sim, state=state)
    bar = Progress(maxiter, label, progress)
    t_start = time.perf_counter()
    if method == "lm":
        sol = fit_lm(problem, maxiter=maxiter, starts=starts, n_starts=n_starts,
                     search=search, progress=bar)
    else:
        points = problem.start_points(starts)   # the same check of the extra starts as LM
        if len(points) > 1:
            # optax runs from one point: the start of lowest cost (stable points first)
            cost = problem.program("start_cost", lambda: jax.jit(
                lambda th, tgt: _start_cost(problem, th, tgt)))
            best = min(points, key=lambda th: float(cost(jnp.asarray(th), problem._tgt)))
            problem = dataclasses.replace(problem, x0=np.exp(np.asarray(best, float)))
        sol = fit_optax(problem, optimizer, maxiter=maxiter, progress=bar)
    bar.close()
    return _result(problem, sol, time.perf_counter() - t_start)


def _start_cost(problem: Problem, theta, targets):
    """Sum of squared residuals at ``theta`` against ``targets``; inf past the safe step or
    where not finite."""
    r, m = problem.evaluate(theta, targets)
    bad = jnp.any(jnp.asarray(m["unstable"])) if "unstable" in m else False
    c = jnp.sum(r * r)
    return jnp.where(bad | ~jnp.isfinite(c), jnp.inf, c)


def _result(problem: Problem, sol, seconds: float) -> FitResult:
    """The :class:`FitResult` of an optimiser's solution on ``problem``."""
    theta, metrics, message = sol.theta, sol.metrics, sol.message
    params = problem.params_of(jnp.asarray(theta))
    achieved, rel, reached = problem.achieved(metrics)
    values = {p: float(np.exp(t)) for p, t in zip(problem.free, theta)}
    message = result_message(message, reached, metrics, problem.spec,
                             at_bounds(problem.free, theta, problem.leaves))
    return FitResult(params=params, values=values, targets=problem.target_values(),
                     achieved=achieved, rel_error=rel, reached=reached,
                     converged=sol.converged, loss_history=sol.history,
                     iterations=int(sol.iterations), seconds=seconds, traces=sol.traces,
                     message=message, evaluations=sol.evaluations,
                     eval_history=sol.eval_history,
                     start={p: float(v) for p, v in zip(problem.free, problem.x0)},
                     metrics={k: np.asarray(v) for k, v in metrics.items()})


def at_bounds(free, theta, leaves) -> list:
    """The paths of ``free`` whose log value in ``theta`` (P,) lies on a bound of ``leaves``
    (:class:`tuning.problem.FreeLeaves`)."""
    return [p for p, t, a, b in zip(free, theta, leaves.log_lo, leaves.log_hi)
            if np.isclose(t, a, atol=1e-9) or np.isclose(t, b, atol=1e-9)]


def result_message(message: str, reached: bool, metrics: dict, spec: tuple,
                   at_bound=()) -> str:
    """What a fit did, in words: the optimiser's ``message`` when the targets are
    ``reached``, else why not (``metrics`` at the reported point, the target ``spec``,
    the fitted paths ``at_bound``). :func:`fit` and each row of
    :func:`tuning.batch_fit.fit_batch` say the same."""
    if reached:
        return message
    if message == "targets reached":      # the residuals met every tolerance
        message = "every residual within its tolerance"
    if "unstable" in metrics and bool(np.any(np.asarray(metrics["unstable"]))):
        return (f"targets NOT reached ({message}): the rollout at the fitted values is past "
                "its safe step (State.aux['unstable']), so its metrics are not a result; "
                "use a smaller dt or tighter bounds")
    if (settling(spec) and "settled" in metrics
            and not bool(np.all(np.asarray(metrics["settled"])))):
        return (f"targets NOT reached ({message}): the motion has not settled within the "
                "rollout at the fitted values, so its settling_time is only the rollout's "
                "end, not a result; use a longer rollout (diffpen fit --duration, a scene "
                "file's duration, or duration= of tuning.fit_bounce)" + (
                    f"; parameters at their bounds: {list(at_bound)}, so these targets may "
                    "be out of this law's reach within them" if at_bound else ""))
    return (f"targets NOT reached ({message}); closest achieved values are reported"
            + (f"; parameters at their bounds: {list(at_bound)}" if at_bound else ""))
