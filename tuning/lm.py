"""Levenberg-Marquardt: box-projected nonlinear least squares on a flat parameter vector.

:func:`levenberg_marquardt` minimises ``|r(x)|^2`` given a function that returns the
residuals and their Jacobian (jitted by the caller, so every trial point reuses one compiled
function), with Marquardt's diagonal scaling (each entry floored at :data:`SCALE_FLOOR`
times the largest), an optional limit on the change of any one parameter per trial step and
a projection onto box bounds after every step; :func:`residuals_and_jacobian` gives the
residuals and their forward-mode Jacobian from one trace. :func:`fit_lm` runs it on a
:class:`tuning.problem.Problem` (behind :func:`tuning.fit.fit` with ``method="lm"``: a
forward-mode Jacobian, several starts and an optional problem-specific start search sharing
one compiled function);
:func:`tuning.sysid.fit_trajectory` runs it on log-parameters too.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .errors import FitError
from .problem import Problem, Solution, target_slices, tolerances
from .progress import Progress
from .stable import FLAG, unsafe_start

__all__ = ["LMResult", "levenberg_marquardt", "residuals_and_jacobian", "fit_lm",
           "SCALE_FLOOR", "MAX_LOG_STEP", "FTOL_EPS", "precision_ftol"]

#: Marquardt's scaling ``diag(J^T J)`` is floored at this fraction of its largest entry. The
#: step in each parameter is about the one that parameter would need alone, so a parameter the
#: residuals barely depend on would get a huge step (out of range, rejected) and the others
#: could only creep while ``lam`` climbs.
SCALE_FLOOR = 1e-6
#: :func:`fit_lm`'s largest change of one log-parameter in a trial step (a factor e^2 = 7.4);
#: a rejected trial that hit it halves it for the next trial of the same iteration.
MAX_LOG_STEP = 2.0
#: the relative cost decrease that stops :func:`levenberg_marquardt` is at least this many
#: machine epsilons of the residuals' dtype: a smaller decrease is rounding (float32 residuals
#: resolve a relative cost change of ~1e-7, far above the default ftol 1e-12), and steps taken
#: on it follow the noise of the float32 Jacobian rather than the records.
FTOL_EPS = 10.0


def precision_ftol(ftol: float, dtype) -> float:
    """The stopping tolerance on the relative cost decrease actually used for residuals of
    ``dtype``: ``max(ftol, FTOL_EPS x eps)`` (eps the dtype's machine epsilon; float64 for a
    non-float dtype). Dimensionless. float64 keeps any ``ftol`` above 2.2e-15 (the default
    1e-12 unchanged); float32 gets at least 1.19e-6. ``ftol <= 0`` (the cost test switched
    off) stays 0."""
    if not ftol > 0.0:
        return 0.0
    dt = np.dtype(dtype)
    eps = float(np.finfo(dt if np.issubdtype(dt, np.floating) else np.float64).eps)
    return max(float(ftol), FTOL_EPS * eps)


def warn_record_precision(dtype, stacklevel: int = 3) -> None:
    """Warn that a fit to records is less reliable in ``dtype`` when it is narrower than
    float64: its Jacobians are noisy (a fit can stop at a worse point), and a step-error
    estimate of its standard errors counts the rounding as step error (about 10x the
    float64 figure on a bouncing ball's record)."""
    dt = np.dtype(dtype)
    if dt.itemsize < 8:
        import warnings
        warnings.warn(f"record fits are less reliable in {dt.name} (its Jacobians are noisy: "
                      "a fit can stop at a worse point, and its time step's part of the "
                      "standard errors counts the rounding): enable float64 with "
                      "jax.config.update('jax_enable_x64', True) before building the "
                      "simulator (the diffpen command always runs float64).",
                      stacklevel=stacklevel)


@dataclasses.dataclass
class LMResult:
    """Levenberg-Marquardt outcome on a flat parameter vector ``x`` (log space)."""
    x: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    cost_history: list
    iterations: int
    converged: bool
    message: str


def residuals_and_jacobian(fn: Callable, x):
    """``(r, J, aux)`` for ``fn(x) -> (r, aux)``: residuals (m,), their Jacobian (m, n) by
    forward mode (one tangent per parameter, few parameters) and ``fn``'s other output, all
    from one forward-mode pass, so ``fn`` (a rollout) is traced once, not once for the
    values and once more for the Jacobian. Pure: call it inside the caller's ``jax.jit``."""
    def with_values(xx):
        r, aux = fn(xx)
        return r, (r, aux)
    J, (r, aux) = jax.jacfwd(with_values, has_aux=True)(x)
    return r, J, aux


def levenberg_marquardt(res_and_jac: Callable, x0, lo, hi, *,
                        maxiter: int = 50, xtol: float = 1e-8, ftol: float = 1e-12,
                        stop: Callable | None = None, lam0: float = 1e-3,
                        progress: Progress | None = None, offset: int = 0,
                        max_step: float | None = None, accept=None,
                        resume: dict | None = None,
                        on_iteration: Callable | None = None) -> LMResult:
    """Box-projected Levenberg-Marquardt with Marquardt's diagonal scaling (floored at
    :data:`SCALE_FLOOR` times its largest entry).

    Args:
      res_and_jac: ``x (p,) -> (r (m,), J (m, p), ...)`` (jitted by the caller; extra
        outputs are ignored). Trial points reuse it, so one compiled function serves all.
      x0, lo, hi: (p,) start and bounds.
      stop: ``stop(r) -> bool``: extra success test on the residuals.
      accept: ``accept(extra) -> bool`` (``extra``: the outputs of ``res_and_jac`` after
        ``r`` and ``J``, at the same point): ``stop`` counts only where it also holds (e.g.
        a settling time that is a result: the motion settled within the rollout).
      max_step: largest change of any one entry of ``x`` in a trial step (None: no limit);
        larger entries are cut to it, and a rejected trial that was cut halves it for the
        next trial of the same iteration.
      xtol: a step whose largest entry is below this (with ``lam < 1``) stops the fit.
      ftol: a relative cost decrease below this stops the fit; raised to
        :func:`precision_ftol` of the residuals' dtype (float32: 1.19e-6), so "step below
        tolerance" never rests on rounding; 0 switches the test off.
      on_iteration: called after every iteration (its end decided) with the state a later
        call resumes from: ``{"x", "lam", "iterations", "cost_history", "done",
        "converged", "message"}`` (plain floats and lists; JSON-ready).
      resume: such a state: continue from it (``x0`` and ``lam0`` are then not read). The
        next iteration depends only on ``x`` and ``lam``, so a resumed call ends where an
        uninterrupted one would, bit for bit; a state with ``done`` returns at once.
    Returns: :class:`LMResult` (``jacobian`` evaluated at ``x``).
    """
    x = np.clip(np.asarray(x0 if resume is None else resume["x"], dtype=float), lo, hi)
    out = res_and_jac(jnp.asarray(x))
    r, J, extra = np.asarray(out[0]), np.asarray(out[1]), out[2:]
    ftol = precision_ftol(ftol, r.dtype)
    if not np.all(np.isfinite(r)):
        raise FitError("the residuals are not finite at the start point: the simulation "
                       "blew up or produced nan; use a smaller dt or another start.")
    cost = float(r @ r)
    hist = [cost]
    lam = lam0
    message, converged, it = "iteration limit reached", False, 0
    if resume is not None:
        lam, it = float(resume["lam"]), int(resume["iterations"])
        hist = [float(c) for c in resume["cost_history"]]
        if resume["done"]:
            return LMResult(x, r, J, hist, it, bool(resume["converged"]), resume["message"])

    def notify(done: bool) -> None:
        if on_iteration is not None:
            on_iteration({"x": [float(v) for v in x], "lam": float(lam), "iterations": it,
                          "cost_history": list(hist), "done": done, "converged": converged,
                          "message": message})
    for it in range(it + 1, maxiter + 1):
        if stop is not None and stop(r) and (accept is None or accept(extra)):
            message, converged, it = "targets reached", True, it - 1
            break
        JtJ = J.T @ J
        g = J.T @ r
        d = np.diag(JtJ).copy()
        d = np.maximum(d, SCALE_FLOOR * d.max()) if d.max() > 0.0 else np.ones_like(d)
        improved = False
        radius = np.inf if max_step is None else float(max_step)
        for _ in range(12):
            try:
                step = -np.linalg.solve(JtJ + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            cut = bool(np.any(np.abs(step) > radius))
            step = np.clip(step, -radius, radius)
            xn = np.clip(x + step, lo, hi)
            out = res_and_jac(jnp.asarray(xn))
            rn, Jn, en = np.asarray(out[0]), np.asarray(out[1]), out[2:]
            cn = float(rn @ rn) if np.all(np.isfinite(rn)) else np.inf
            if cn < cost:
                improved = True
                break
            lam *= 4.0
            if cut:
                radius *= 0.5
        if not improved:
            message, converged = "no further decrease (local minimum)", True
            hist.append(cost)
            if progress is not None:
                progress.update(offset + it, cost)
            notify(True)
            break
        dx = np.max(np.abs(xn - x))
        rel_drop = (cost - cn) / max(cost, 1e-300)
        x, r, J, extra = xn, rn, Jn, en
        cost = float(r @ r)
        hist.append(cost)
        lam = max(lam / 3.0, 1e-12)
        if progress is not None:
            progress.update(offset + it, cost)
        # a tiny step only means convergence when it was not forced by heavy damping
        if (dx < xtol and lam < 1.0) or rel_drop < ftol or cost == 0.0:
            message, converged = "step below tolerance", True
            notify(True)
            break
        notify(False)
    return LMResult(x, r, J, hist, it, converged, message)


def fit_lm(problem: Problem, *, maxiter: int = 50, starts: list | None = None,
           n_starts: int = 3, search: Callable | None = None,
           progress: Progress | None = None) -> Solution:
    """Levenberg-Marquardt on ``problem`` in log space, with a forward-mode Jacobian
    (``jax.jacfwd``: few parameters) and ONE compiled residual/Jacobian function for every
    evaluated point; a trial step changes no log-parameter by more than :data:`MAX_LOG_STEP`.

    Args:
      maxiter: iteration limit of each LM run (``Solution.iterations`` adds up all runs).
      starts: extra start points ``[{path: value}, ...]``; with the problem's own start they
        are ranked by cost and LM runs from the best ``n_starts`` until one reaches the
        targets; the best result is kept.
      search: ``search(evaluate, slices, log_lo, log_hi) -> [theta, ...]``: a problem-specific
        search for start points in log space, tried before the others; ``evaluate(theta) ->
        (r, J, metrics)`` is the compiled function and ``slices`` maps each target to its
        rows of ``r`` (:func:`tuning.problem.target_slices`).
      progress: a :class:`tuning.progress.Progress` or None.
    Returns: :class:`tuning.problem.Solution` (the loss is ``|r|^2``).
    """
    traces, costs = [0], []
    log_lo, log_hi = problem.leaves.log_lo, problem.leaves.log_hi

    def rj(theta, targets):
        traces[0] += 1
        r, J, m = residuals_and_jacobian(lambda th: problem.evaluate(th, targets), theta)
        if FLAG in m:   # past the safe step: nan residuals, so LM rejects the point
            r = jnp.where(jnp.any(m[FLAG]), jnp.nan, r)
        return r, J, m
    rj_compiled = problem.program("lm", lambda: jax.jit(rj))

    blocked = [0]

    def evaluate(theta):
        out = rj_compiled(theta, problem._tgt)
        r0 = np.asarray(out[0])
        costs.append(float(r0 @ r0))
        if FLAG in out[2] and bool(np.any(np.asarray(out[2][FLAG]))):
            blocked[0] += 1
        return out
    tols = tolerances(problem.spec)
    def settled(extra):             # a settling time counts only where the motion settled
        m = extra[0]
        return "settled" not in m or bool(np.all(np.asarray(m["settled"])))
    accept = settled if any(s.name == "settling_time" for s in problem.spec) else None
    points = problem.start_points(starts)
    if search is not None:   # problem-specific start search, same compiled function
        found = search(lambda th: evaluate(jnp.asarray(th)), target_slices(problem.spec),
                       log_lo, log_hi)
        points = [np.clip(np.asarray(th, float), log_lo, log_hi) for th in found] + points
    if len(points) > 1:   # rank the starts by their cost (same compiled function)
        ranked = []
        for th in points:
            r0 = np.asarray(evaluate(jnp.asarray(th))[0])
            ranked.append(float(r0 @ r0) if np.all(np.isfinite(r0)) else np.inf)
        # starts past the safe step (nan residuals: rj) or blown up are never run
        points = [points[i] for i in np.argsort(ranked)[:n_starts] if np.isfinite(ranked[i])]
        if not points:
            raise unsafe_start(None)
    if progress is not None:   # every run may take maxiter iterations
        progress.total = maxiter * len(points)
    best = None
    used = 0
    for th in points:
        try:
            out = levenberg_marquardt(evaluate, th, log_lo, log_hi, maxiter=maxiter,
                                      max_step=MAX_LOG_STEP,
                                      stop=lambda r: bool(np.all(np.abs(r) <= tols)),
                                      accept=accept,
                                      progress=progress, offset=used)
        except FitError:
            m0 = evaluate(jnp.asarray(th))[2]
            if FLAG in m0 and bool(np.any(np.asarray(m0[FLAG]))):
                raise unsafe_start({n: float(v) for n, v in
                                    zip(problem.free, np.exp(th))}) from None
            raise
        used += out.iterations
        if best is None or out.cost_history[-1] < best.cost_history[-1]:
            best = out
        if out.message == "targets reached":
            break
    message = best.message
    if blocked[0] and best.message != "targets reached":
        message += (f"; {blocked[0]} trial point(s) past the simulator's safe step were "
                    "rejected (a smaller dt or more substeps lets the fit go further)")
    metrics = evaluate(jnp.asarray(best.x))[2]
    return Solution(best.x, metrics, np.asarray(best.cost_history), used, best.converged,
                    message, traces[0], len(costs), np.asarray(costs))
