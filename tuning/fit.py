"""Fit any subset of a simulator's parameters to weighted targets.

The fitted leaves of the :class:`diffpen.Params` pytree are optimised in log space
(``theta = log value``, so k and c stay positive and steps are relative), projected onto box
bounds after every step. Two methods:

* ``method="optax"``: any ``optax.GradientTransformation`` on the loss
  ``sum_j w_j ((m_j - t_j) / |t_j|)^2``; frozen leaves are partitioned out with
  ``optax.multi_transform`` (``optax.set_to_zero``), so the optimiser never sees them.
* ``method="lm"``: Levenberg-Marquardt (:mod:`tuning.lm`) on the residual vector with a
  forward-mode (``jax.jacfwd``) Jacobian; for a handful of parameters it needs far fewer
  iterations.

Each method jit-compiles ONE iteration function before the loop; later iterations only call
it (``FitResult.traces`` counts the traces so tests can check it). ``metrics_fn(params)`` must
be traceable; it returns a dict of scalars/arrays from which the targets are read.

This module holds the problem-independent pieces (:class:`FitResult`, :class:`FitError`,
bounds, the target residuals, the progress bar); the bouncing-ball problem behind
``diffpen fit`` is :mod:`tuning.bounce`.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

import diffpen as dp

from . import params as P
from .stable import FLAG, contact_unstable, safe_contact_bounds

__all__ = ["FitResult", "FitError", "fit", "default_optimizer", "Progress",
           "default_bounds"]


class FitError(ValueError):
    """A fitting problem that cannot be set up (bad targets, bounds or parameter names)."""


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
    loss_history: (iterations + 1,) loss after each iteration (the first entry is the start).
    iterations: iterations run.  seconds: wall time of the loop, compilation included.
    traces: how many times the residual function was traced (fixed per method, whatever
      the number of iterations: the loop compiles once).
    evaluations: compiled-function calls (iterations, LM trial points and start search).
    eval_history: (evaluations,) loss at every evaluated point, in order.
    message: what happened, in words.  stderr: ``{path: standard error}`` or None.
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


def default_optimizer(learning_rate: float = 0.05) -> optax.GradientTransformation:
    """Adam on log-parameters with global-norm clipping and a decaying step: steps are
    relative changes (0.05 = 5 %), halved every 60 iterations so the fit settles to ~1e-4."""
    schedule = optax.exponential_decay(learning_rate, transition_steps=60, decay_rate=0.5)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adam(schedule))


def default_bounds(path: str, value: float, dt: float | None = None,
                   mass: float | None = None) -> tuple[float, float]:
    """Box bounds for a fitted leaf (SI units).

    Contact/spring stiffness 1e-2..1e9 N/m and damping 1e-6..1e6 N s/m, tightened to the
    symplectic-Euler stability limit ``k dt^2 + 2 c dt < 4 m`` when ``dt`` and the smallest
    moving ``mass`` are given (k <= 2 m / dt^2, c <= m / dt). Other leaves: value/1e4..1e4 x.
    """
    if path.endswith(".k"):
        lo, hi = 1e-2, 1e9
        if dt is not None and mass is not None:
            hi = min(hi, 2.0 * mass / dt ** 2)
    elif path.endswith(".c"):
        lo, hi = 1e-6, 1e6
        if dt is not None and mass is not None:
            hi = min(hi, mass / dt)
    else:
        lo, hi = abs(value) / 1e4, abs(value) * 1e4
    return lo, hi


from .progress import Progress  # noqa: E402  (re-exported: tuning.fit.Progress)


def safe_bounds(free, x0, bounds: dict | None, sim=None) -> tuple[np.ndarray, np.ndarray]:
    """Box bounds (lo, hi) (n,) in SI units for the ``free`` leaves with start values ``x0``:
    ``bounds[path]`` or :func:`default_bounds`, and, when the simulator ``sim`` is given, every
    contact k and c capped at :func:`tuning.stable.safe_contact_bounds` of ``sim`` (the safe
    explicit step of its lightest movable body), so an optimiser cannot walk past the safe step.
    Raises :class:`FitError` when a given lower bound is already past it."""
    bounds = bounds or {}
    lo = np.array([bounds.get(p, default_bounds(p, v))[0] for p, v in zip(free, x0)], float)
    hi = np.array([bounds.get(p, default_bounds(p, v))[1] for p, v in zip(free, x0)], float)
    if sim is not None:
        k_max, c_max = safe_contact_bounds(sim)
        for i, p in enumerate(free):
            cap = (k_max if p.endswith(".k") else c_max) if p.startswith("contact.") else None
            if cap is not None and hi[i] > cap:
                if lo[i] >= cap:
                    raise FitError(f"the lower bound {lo[i]:g} of {p!r} is past the safe step "
                                   f"of this simulator ({cap:g} at dt={float(sim.dt):g} s); "
                                   "lower it, or use a smaller dt or more substeps.")
                hi[i] = cap
    return lo, hi


# --------------------------------------------------------------------------- targets
def _normalise_targets(targets: dict) -> dict:
    if not targets:
        raise FitError("no targets: give at least one, e.g. {'apex_heights': [0.4]}.")
    out = {}
    for name, val in targets.items():
        arr = np.atleast_1d(np.asarray(val, dtype=float))
        if arr.size == 0:
            raise FitError(f"target {name!r} is empty.")
        if not np.all(np.isfinite(arr)):
            raise FitError(f"target {name!r} must be finite, got {val!r}.")
        if np.any(arr == 0.0):
            raise FitError(f"target {name!r} has a zero entry; targets are compared relatively "
                           "(|achieved - target| / |target|): give a non-zero value.")
        out[name] = arr
    return out


def _spec(targets: dict, weights: dict | None, rtol) -> tuple:
    """Static description of the residual vector: (name, count, weight, rtol) per target."""
    weights = weights or {}
    spec = []
    for name, arr in targets.items():
        w = float(weights.get(name, 1.0))
        if not w > 0.0:
            raise FitError(f"weight of target {name!r} must be > 0, got {w!r}.")
        tol = float(rtol.get(name, 1e-3) if isinstance(rtol, dict) else rtol)
        spec.append((name, arr.size, w, tol))
    return tuple(spec)


def _residuals(metrics: dict, targets: dict, spec: tuple):
    """Weighted relative residuals (m,). Absent events (nan) count as a value of 0."""
    parts = []
    for name, count, w, _ in spec:
        if name not in metrics:
            raise FitError(f"target {name!r} is not a metric of this problem; metrics: "
                           f"{sorted(metrics)}.")
        m = jnp.atleast_1d(metrics[name])[:count]
        if m.shape[0] < count:
            raise FitError(f"target {name!r} has {count} entries but the metric has only "
                           f"{m.shape[0]}.")
        m = jnp.where(jnp.isfinite(m), m, 0.0)
        tgt = jnp.asarray(targets[name], dtype=m.dtype)
        parts.append(math.sqrt(w) * (m - tgt) / jnp.abs(tgt))
    return jnp.concatenate(parts)


def _achieved(metrics: dict, targets: dict, spec: tuple) -> tuple[dict, dict, bool]:
    ach, rel, ok = {}, {}, True
    for name, count, _, tol in spec:
        m = np.atleast_1d(np.asarray(metrics[name], dtype=float))[:count]
        t = targets[name]
        err = np.abs(m - t) / np.abs(t)
        err = np.where(np.isfinite(err), err, np.inf)
        ach[name] = m.tolist() if np.ndim(metrics[name]) else float(m[0])
        rel[name] = float(np.max(err))
        ok = ok and bool(np.all(err <= tol))
    if "unstable" in metrics and bool(np.any(np.asarray(metrics["unstable"]))):
        ok = False        # past the safe step: never a result (tuning.stable)
    return ach, rel, ok


#: a residual rms above this many times the expected noise means the model does not explain
#: the record (a good fit leaves ~1x: the noise itself)
RESIDUAL_FACTOR = 3.0


def residual_reached(rms: float, noise: float, dt_error: float = 0.0,
                     factor: float = RESIDUAL_FACTOR) -> bool:
    """Whether a trajectory fit explains its record: the residual rms (m) is within
    ``factor`` times what noise alone leaves, ``sqrt(noise^2 + dt_error^2)`` (the record's
    estimated noise and the model's discretisation error, m). NaN never counts as reached."""
    expected = math.sqrt(float(noise) ** 2 + float(dt_error) ** 2)
    return bool(math.isfinite(rms) and rms <= factor * expected)


# --------------------------------------------------------------------------- fit
def fit(metrics_fn: Callable, params0: dp.Params, targets: dict, *, free=None,
        bounds: dict | None = None, weights: dict | None = None, rtol=1e-3,
        method: str = "optax", optimizer: optax.GradientTransformation | None = None,
        maxiter: int = 300, progress: bool | None = None, label: str = "fit",
        starts: list | None = None, n_starts: int = 3,
        search: Callable | None = None, sim=None) -> FitResult:
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
      maxiter: iteration limit.  progress: draw a progress bar (default: stderr is a tty).
      starts: extra start points ``[{path: value}, ...]``; with ``method="lm"`` they are
        ranked by cost and LM runs from the best ``n_starts`` (all with the same compiled
        function) until one reaches the targets; the best result is kept.
      search: ``search(evaluate, slices, log_lo, log_hi) -> [theta, ...]`` (LM only): a
        problem-specific search for start points in log space; ``evaluate(theta) -> (r, J,
        metrics)`` is the fit's compiled residual/Jacobian function and ``slices`` maps each
        target to its rows of ``r``.
      sim: the simulator behind ``metrics_fn`` (optional, recommended): contact k and c are
        then bounded inside its safe step (:func:`safe_bounds`), and when ``metrics_fn`` has
        no ``"unstable"`` entry the fit adds :func:`tuning.stable.contact_unstable`; a point
        past the safe step is never returned as reached.
    Returns:
      :class:`FitResult`.
    """
    starts_extra = starts
    scalar = {k for k, v in targets.items() if np.ndim(v) == 0}
    targets = _normalise_targets(targets)
    spec = _spec(targets, weights, rtol)
    flat0 = P.flatten(params0)
    free = list(P.default_free(params0) if free is None else free)
    if not free:
        raise FitError("nothing to fit: 'free' is empty.")
    for p in free:
        if p not in flat0:
            raise FitError(f"unknown parameter {p!r}; this scene has {list(flat0)}.")
    bounds = dict(bounds or {})
    for p in bounds:
        if p not in flat0:
            raise FitError(f"bounds given for unknown parameter {p!r}; known: {list(flat0)}.")
    x0 = np.array([float(flat0[p]) for p in free])
    if np.any(x0 <= 0.0):
        bad = [p for p, v in zip(free, x0) if v <= 0.0]
        raise FitError(f"fitted parameters need a positive start value (fitting is in log "
                       f"space); got {dict(zip(bad, x0[x0 <= 0.0]))}.")
    lo, hi = safe_bounds(free, x0, bounds, sim)
    if np.any(~(lo > 0.0)) or np.any(hi <= lo):
        raise FitError(f"bounds must satisfy 0 < lo < hi; got lo={lo}, hi={hi}.")
    x0 = np.clip(x0, lo, hi)
    log_lo, log_hi = np.log(lo), np.log(hi)
    tgt = {k: jnp.asarray(v) for k, v in targets.items()}
    traces = [0]
    evals = [0]
    eval_costs: list = []

    def params_of(theta):
        flat = dict(flat0)
        for i, p in enumerate(free):
            flat[p] = jnp.exp(theta[i])
        return P.unflatten(params0, flat)

    def residual_fn(theta):
        traces[0] += 1
        params = params_of(theta)
        m = metrics_fn(params)
        if sim is not None and FLAG not in m:
            m = {**m, FLAG: contact_unstable(sim, params)}
        return _residuals(m, tgt, spec), m

    bar = Progress(maxiter, label, progress)
    t_start = time.perf_counter()
    theta0 = np.log(x0)
    starts = [theta0]
    for st in (starts_extra or []):
        unknown = set(st) - set(free)
        if unknown:
            raise FitError(f"start values given for parameters that are not fitted: "
                           f"{sorted(unknown)}.")
        x = np.array([float(st.get(p, v)) for p, v in zip(free, x0)])
        starts.append(np.log(np.clip(x, lo, hi)))
    if method == "lm":
        from .lm import levenberg_marquardt   # here: tuning.lm imports FitError, Progress
        def rj(theta):
            r, m = residual_fn(theta)
            J = jax.jacfwd(lambda th: residual_fn(th)[0])(theta)
            return r, J, m
        rj_compiled = jax.jit(rj)

        def rj_jit(theta):
            evals[0] += 1
            out = rj_compiled(theta)
            r0 = np.asarray(out[0])
            eval_costs.append(float(r0 @ r0))
            return out
        tols = np.concatenate([np.full(c, tol * math.sqrt(w)) for _, c, w, tol in spec])
        if search is not None:   # problem-specific start search, same compiled function
            slices, pos = {}, 0
            for name, count, _, _ in spec:
                slices[name] = slice(pos, pos + count)
                pos += count
            found = search(lambda th: rj_jit(jnp.asarray(th)), slices, log_lo, log_hi)
            starts = [np.clip(np.asarray(th, float), log_lo, log_hi) for th in found] + starts
        if len(starts) > 1:   # rank the starts by their cost (same compiled function)
            costs = []
            for th in starts:
                r0 = np.asarray(rj_jit(jnp.asarray(th))[0])
                costs.append(float(r0 @ r0) if np.all(np.isfinite(r0)) else np.inf)
            starts = [starts[i] for i in np.argsort(costs)[:n_starts]]
        best = None
        used = 0
        for th in starts:
            out = levenberg_marquardt(rj_jit, th, log_lo, log_hi,
                                      maxiter=maxiter,
                                      stop=lambda r: bool(np.all(np.abs(r) <= tols)),
                                      progress=bar, offset=used)
            used += out.iterations
            if best is None or out.cost_history[-1] < best.cost_history[-1]:
                best = out
            if out.message == "targets reached":
                break
        theta = best.x
        history = np.asarray(best.cost_history)
        iterations, converged, message = used, best.converged, best.message
        metrics = rj_jit(jnp.asarray(theta))[2]
    elif method == "optax":
        opt = optimizer if optimizer is not None else default_optimizer()
        # The optimiser state covers every leaf; optax's partitioning sends the frozen ones
        # to set_to_zero, so only the free leaves ever move.
        labels = {p: ("free" if p in free else "frozen") for p in flat0}
        tx = optax.multi_transform({"free": opt, "frozen": optax.set_to_zero()}, labels)
        idx = {p: i for i, p in enumerate(free)}

        def loss_fn(theta_d):
            theta = jnp.stack([theta_d[p] for p in free])
            r, m = residual_fn(theta)
            return jnp.sum(r * r), (r, m)

        @jax.jit
        def step(theta_d, state):
            # forward mode for a handful of parameters (diffpen.value_and_grad's choice)
            (loss, (r, m)), g = dp.value_and_grad(loss_fn, has_aux=True)(theta_d)
            upd, state = tx.update(g, state, theta_d)
            new = optax.apply_updates(theta_d, upd)
            new = {p: (jnp.clip(v, log_lo[idx[p]], log_hi[idx[p]]) if p in idx else v)
                   for p, v in new.items()}
            return new, state, loss, r, m

        theta_d = {p: jnp.log(jnp.maximum(jnp.asarray(v, float), 1e-300)) for p, v in
                   flat0.items()}
        theta_d.update({p: jnp.asarray(v) for p, v in zip(free, theta0)})
        state = tx.init(theta_d)
        tols = np.concatenate([np.full(c, tol * math.sqrt(w)) for _, c, w, tol in spec])
        history, best = [], (np.inf, theta_d, None, True)
        converged, message, iterations = False, "iteration limit reached", maxiter
        for it in range(maxiter):
            new, state, loss, r, m = step(theta_d, state)
            loss = float(loss)
            if not math.isfinite(loss):
                message = "loss became non-finite; stopped (try a smaller learning rate or dt)"
                iterations = it
                break
            history.append(loss)
            evals[0] += 1
            eval_costs.append(loss)
            bad = bool(np.any(np.asarray(m[FLAG]))) if FLAG in m else False
            if best[2] is None or (loss < best[0] and not bad) or (
                    best[3] and (not bad or loss < best[0])):
                best = (loss, theta_d, m, bad)   # stable points first, then the lowest loss
            bar.update(it, loss)
            if np.all(np.abs(np.asarray(r)) <= tols) and not bad:
                converged, message, iterations = True, "targets reached", it
                break
            theta_d = new
        if best[2] is None:
            raise FitError(f"the first iteration already failed: {message}.")
        theta_d, metrics = best[1], best[2]
        theta = np.array([float(theta_d[p]) for p in free])
        history = np.asarray(history)
    else:
        raise FitError(f"unknown method {method!r}; use 'optax' or 'lm'.")
    bar.close()
    params = params_of(jnp.asarray(theta))
    seconds = time.perf_counter() - t_start
    achieved, rel, reached = _achieved(metrics, targets, spec)
    values = {p: float(np.exp(t)) for p, t in zip(free, theta)}
    at_bound = [p for p, t, a, b in zip(free, theta, log_lo, log_hi)
                if np.isclose(t, a, atol=1e-9) or np.isclose(t, b, atol=1e-9)]
    if not reached and "unstable" in metrics and bool(np.any(np.asarray(metrics["unstable"]))):
        message = (f"targets NOT reached ({message}): the rollout at the fitted values is past "
                   "its safe step (State.aux['unstable']), so its metrics are not a result; "
                   "use a smaller dt or tighter bounds")
    elif not reached:
        message = (f"targets NOT reached ({message}); closest achieved values are reported"
                   + (f"; parameters at their bounds: {at_bound}" if at_bound else ""))
    tlist = {k: (float(v[0]) if k in scalar else v.tolist()) for k, v in targets.items()}
    return FitResult(params=params, values=values, targets=tlist, achieved=achieved,
                     rel_error=rel, reached=reached, converged=converged,
                     loss_history=history, iterations=int(iterations), seconds=seconds,
                     traces=traces[0], message=message, evaluations=evals[0],
                     eval_history=np.asarray(eval_costs),
                     start={p: float(v) for p, v in zip(free, x0)})
