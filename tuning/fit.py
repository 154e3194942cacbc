"""Fit any subset of a simulator's parameters to weighted targets.

The fitted leaves of the :class:`diffpen.Params` pytree are optimised in log space
(``theta = log value``, so k and c stay positive and steps are relative), projected onto box
bounds after every step. Two methods:

* ``method="optax"``: any ``optax.GradientTransformation`` on the loss
  ``sum_j w_j ((m_j - t_j) / |t_j|)^2``; frozen leaves are partitioned out with
  ``optax.multi_transform`` (``optax.set_to_zero``), so the optimiser never sees them.
* ``method="lm"``: Levenberg-Marquardt on the residual vector with a forward-mode
  (``jax.jacfwd``) Jacobian; for a handful of parameters it needs far fewer iterations.

Each method jit-compiles ONE iteration function before the loop; later iterations only call
it (``FitResult.traces`` counts the traces so tests can check it). ``metrics_fn(params)`` must
be traceable; it returns a dict of scalars/arrays from which the targets are read.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

import diffpen as dp

from . import params as P

__all__ = ["FitResult", "FitError", "fit", "default_optimizer", "levenberg_marquardt",
           "LMResult", "Progress", "default_bounds"]


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


class Progress:
    """One-line progress bar on stderr, drawn only when stderr is a terminal."""

    def __init__(self, total: int, label: str = "fit", enabled: bool | None = None):
        self.total = total
        self.label = label
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._last = 0.0

    def update(self, i: int, loss: float, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if not force and now - self._last < 0.05:
            return
        self._last = now
        width = 24
        done = int(width * min(i, self.total) / max(self.total, 1))
        bar = "#" * done + "." * (width - done)
        sys.stderr.write(f"\r{self.label} [{bar}] {i}/{self.total} loss {loss:.3e}")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


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
    return ach, rel, ok


# --------------------------------------------------------------------------- LM
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


def levenberg_marquardt(res_and_jac: Callable, x0, lo, hi, *,
                        maxiter: int = 50, xtol: float = 1e-8, ftol: float = 1e-12,
                        stop: Callable | None = None, lam0: float = 1e-3,
                        progress: Progress | None = None, offset: int = 0) -> LMResult:
    """Box-projected Levenberg-Marquardt with Marquardt's diagonal scaling.

    Args:
      res_and_jac: ``x (p,) -> (r (m,), J (m, p), ...)`` (jitted by the caller; extra
        outputs are ignored). Trial points reuse it, so one compiled function serves all.
      x0, lo, hi: (p,) start and bounds.
      stop: ``stop(r) -> bool``: extra success test on the residuals.
    Returns: :class:`LMResult` (``jacobian`` evaluated at ``x``).
    """
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    r, J = (np.asarray(a) for a in res_and_jac(jnp.asarray(x))[:2])
    if not np.all(np.isfinite(r)):
        raise FitError("the residuals are not finite at the start point: the simulation "
                       "blew up or produced nan; use a smaller dt or another start.")
    cost = float(r @ r)
    hist = [cost]
    lam = lam0
    message, converged, it = "iteration limit reached", False, 0
    for it in range(1, maxiter + 1):
        if stop is not None and stop(r):
            message, converged, it = "targets reached", True, it - 1
            break
        JtJ = J.T @ J
        g = J.T @ r
        d = np.diag(JtJ).copy()
        d[d <= 0.0] = 1.0
        improved = False
        for _ in range(12):
            try:
                step = -np.linalg.solve(JtJ + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            xn = np.clip(x + step, lo, hi)
            rn, Jn = (np.asarray(a) for a in res_and_jac(jnp.asarray(xn))[:2])
            cn = float(rn @ rn) if np.all(np.isfinite(rn)) else np.inf
            if cn < cost:
                improved = True
                break
            lam *= 4.0
        if not improved:
            message, converged = "no further decrease (local minimum)", True
            hist.append(cost)
            break
        dx = np.max(np.abs(xn - x))
        rel_drop = (cost - cn) / max(cost, 1e-300)
        x, r, J = xn, rn, Jn
        cost = float(r @ r)
        hist.append(cost)
        lam = max(lam / 3.0, 1e-12)
        if progress is not None:
            progress.update(offset + it, cost)
        # a tiny step only means convergence when it was not forced by heavy damping
        if (dx < xtol and lam < 1.0) or rel_drop < ftol or cost == 0.0:
            message, converged = "step below tolerance", True
            break
    return LMResult(x, r, J, hist, it, converged, message)


# --------------------------------------------------------------------------- fit
def fit(metrics_fn: Callable, params0: dp.Params, targets: dict, *, free=None,
        bounds: dict | None = None, weights: dict | None = None, rtol=1e-3,
        method: str = "optax", optimizer: optax.GradientTransformation | None = None,
        maxiter: int = 300, progress: bool | None = None, label: str = "fit",
        starts: list | None = None, n_starts: int = 3,
        search: Callable | None = None) -> FitResult:
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
    lo = np.array([bounds.get(p, default_bounds(p, v))[0] for p, v in zip(free, x0)], float)
    hi = np.array([bounds.get(p, default_bounds(p, v))[1] for p, v in zip(free, x0)], float)
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
        m = metrics_fn(params_of(theta))
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
        history, best = [], (np.inf, theta_d, None)
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
            if loss < best[0]:
                best = (loss, theta_d, m)
            bar.update(it, loss)
            if np.all(np.abs(np.asarray(r)) <= tols):
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
    if not reached:
        message = (f"targets NOT reached ({message}); closest achieved values are reported"
                   + (f"; parameters at their bounds: {at_bound}" if at_bound else ""))
    tlist = {k: (float(v[0]) if k in scalar else v.tolist()) for k, v in targets.items()}
    return FitResult(params=params, values=values, targets=tlist, achieved=achieved,
                     rel_error=rel, reached=reached, converged=converged,
                     loss_history=history, iterations=int(iterations), seconds=seconds,
                     traces=traces[0], message=message, evaluations=evals[0],
                     eval_history=np.asarray(eval_costs),
                     start={p: float(v) for p, v in zip(free, x0)})


# --------------------------------------------------------------------------- bouncing body
#: Metrics a bounce fit can target, with their default relative tolerances.
BOUNCE_METRICS = {"apex_heights": 1e-3, "settling_time": 5e-3, "contact_durations": 2e-3,
                  "restitution": 1e-3, "max_penetration": 2e-3}


def _fall_time(h0: float, v0: float, g: float) -> float:
    """Time for the lowest point to reach the surface from height h0 (m), velocity v0 (m/s)."""
    return (v0 + math.sqrt(v0 * v0 + 2.0 * g * h0)) / g


def check_bounce_targets(scene: dp.Scene, targets: dict, *, body: int = 0, plane: int = 0,
                         settle_tol: float = 1e-3) -> dict:
    """Validate bounce targets against the scene BEFORE anything is compiled.

    Raises :class:`FitError` saying what to change for targets no (k, c) can reach: an apex at
    or above the drop height, apexes that do not decrease, a settling time shorter than the
    fall to the ground (plus the flights the apex targets imply), non-positive values.
    Returns a dict of facts used by the fit (drop apex, fall time, gravity, mass, radius).
    """
    unknown = set(targets) - set(BOUNCE_METRICS)
    if unknown:
        raise FitError(f"unknown target(s) {sorted(unknown)}; bounce fits know "
                       f"{sorted(BOUNCE_METRICS)}.")
    if not scene.planes:
        raise FitError("a bounce fit needs a plane for the body to bounce on.")
    if not 0 <= body < scene.n_bodies:
        raise FitError(f"body {body} is not in the scene ({scene.n_bodies} bodies).")
    b = scene.bodies[body]
    pl = scene.planes[plane]
    n = np.asarray(pl.normal)
    g = float(-np.dot(scene.gravity, n))
    if g <= 0.0:
        raise FitError("bounce targets need gravity pointing into the plane.")
    h0 = float(np.dot(b.position, n) - pl.offset - b.radius)
    v0 = float(np.dot(b.velocity, n))
    if h0 <= 0.0:
        raise FitError(f"body {body} starts in contact (lowest point {h0:.4g} m above the "
                       "plane): start it above the surface.")
    drop = h0 + max(v0, 0.0) ** 2 / (2.0 * g)
    t_fall = _fall_time(h0, v0, g)
    tg = _normalise_targets(targets)
    for name, arr in tg.items():
        if np.any(arr <= 0.0):
            raise FitError(f"target {name!r} must be positive, got {arr.tolist()}.")
    apex = tg.get("apex_heights")
    if apex is not None:
        if apex[0] >= drop:
            raise FitError(
                f"infeasible target: first apex {apex[0]:.4g} m is not below the drop height "
                f"{drop:.4g} m (lowest point); a passive contact cannot add energy. Give an "
                f"apex below {drop:.4g} m or raise the drop height.")
        if np.any(np.diff(apex) >= 0.0):
            raise FitError(f"infeasible target: apex heights must decrease bounce by bounce, "
                           f"got {apex.tolist()}.")
    e = tg.get("restitution")
    if e is not None and np.any(e >= 1.0):
        raise FitError(f"infeasible target: restitution must be below 1, got {e.tolist()}.")
    ts = tg.get("settling_time")
    if ts is not None:
        need = t_fall
        if apex is not None:   # the flights of the targeted bounces that leave the band
            need += float(np.sum(2.0 * np.sqrt(2.0 * apex[apex > settle_tol] / g)))
        if ts[0] <= need:
            what = "the fall to the ground" if apex is None else (
                "the fall plus the flights of the targeted bounces")
            raise FitError(
                f"infeasible target: settling time {ts[0]:.4g} s is shorter than {what} "
                f"({need:.4g} s); the body cannot be within {settle_tol:g} m of rest before. "
                f"Give a settling time above {need:.4g} s.")
    return {"drop": drop, "t_fall": t_fall, "g": g, "mass": b.mass, "radius": b.radius,
            "h0": h0, "v0": v0, "material": pl.material}


def bounce_metrics_fn(sim, steps: int, *, body: int = 0, plane: int = 0, n_apex: int = 3,
                      settle_tol: float = 1e-3, save_every: int = 1) -> Callable:
    """``params -> {metric: value}`` for a sphere bouncing on a plane (traceable).

    Rolls out ``steps`` steps of ``sim`` and returns the fields of
    :class:`tuning.metrics.BallMetrics` as a dict. A settling time not reached within the
    rollout is reported as the rollout's end time (a lower bound) for the optimiser.
    """
    from .metrics import ball_metrics
    t_end = steps * sim.dt

    def metrics_fn(params):
        s0 = sim.init_state()
        traj = sim.rollout(params, steps, s0, save_every=save_every, check_finite=False)
        m = ball_metrics(sim, traj, params, body=body, plane=plane, n_apex=n_apex,
                         settle_tol=settle_tol, state0=s0)._asdict()
        m["settling_time"] = jnp.where(m["settled"], m["settling_time"], t_end)
        return m
    return metrics_fn


def first_guess_bounce(info: dict, targets: dict, *, law: str = "linear", k0: float = 1e4):
    """Closed-form start (k, c) from bounce targets (physics-notes.md section 2).

    The first apex gives the restitution ``e = sqrt(A_1 / H_0)`` and so the damping ratio; a
    contact-duration target gives w0 and hence k; otherwise k stays ``k0`` (a settling-time
    target is then met by a 1-D search over k, see :func:`fit_bounce`).
    Returns (k N/m, c N s/m, zeta or None).
    """
    m = info["mass"]
    zeta = None
    if "apex_heights" in targets:
        e = math.sqrt(float(np.atleast_1d(targets["apex_heights"])[0]) / info["drop"])
        zeta = float(dp.physical.zeta_from_restitution(e, "no_tension" if law == "no_tension"
                                                       else "linear"))
    elif "restitution" in targets:
        e = float(np.atleast_1d(targets["restitution"])[0])
        zeta = float(dp.physical.zeta_from_restitution(e, "no_tension" if law == "no_tension"
                                                       else "linear"))
    if zeta is not None and "contact_durations" in targets:
        tc = float(np.atleast_1d(targets["contact_durations"])[0])
        k, c = dp.physical.kc_from_restitution(math.exp(-math.pi * zeta / math.sqrt(
            1 - zeta * zeta)), tc, m)
        return float(k), float(c), zeta
    z = 0.1 if zeta is None else zeta
    return k0, 2.0 * z * math.sqrt(k0 * m), zeta


def fit_bounce(scene: dp.Scene, targets: dict, *, dt: float = 1e-3, law: str = "linear",
               body: int = 0, plane: int = 0, settle_tol: float = 1e-3, k0: float | None = None,
               c0: float | None = None, free=None, method: str = "lm", optimizer=None,
               maxiter: int | None = None, rtol=None, weights: dict | None = None,
               duration: float | None = None, progress: bool | None = None,
               first_guess: bool = True, **compile_kw) -> FitResult:
    """Fit contact k and c of a sphere bouncing on a plane to apex/settling/contact targets.

    Checks the targets against the scene first (:func:`check_bounce_targets`), then compiles,
    starts from the closed-form first guess (:func:`first_guess_bounce`; with apex and
    settling-time targets, :func:`_apex_settle_search` scans k with c solved for the apex and
    bisects the settling time along that curve), and runs :func:`fit`. Stiffness stays below
    the accuracy limit ``w0 dt <= 0.25`` of the explicit step.

    Bounce heights alone fix only the damping ratio: with apex/restitution targets but no
    settling-time or contact-duration target, k is held at ``k0`` and only c is fitted (the
    result's ``notes`` say so).

    Args:
      scene: the scene (the body must start above the plane).
      targets: ``{"apex_heights": [m, ...], "settling_time": s, "contact_durations": [s],
        "restitution": [...], "max_penetration": m}``; apexes are of the lowest point above
        the surface.
      dt: time step, s.  law: contact law.  settle_tol: settling band, m.
      k0, c0: start values (N/m, N s/m); default from the first guess.
      free: leaf paths to fit (default: k and c of the plane's material).
      method: ``"lm"`` (default) or ``"optax"`` (with ``optimizer``).
      maxiter: default 40 (lm) or 400 (optax).
      rtol: per-metric relative tolerances (default :data:`BOUNCE_METRICS`).
      duration: rollout length, s (default: covers the targets with margin).
    Returns: :class:`FitResult` (``notes`` lists what was held fixed and why).
    """
    info = check_bounce_targets(scene, targets, body=body, plane=plane, settle_tol=settle_tol)
    tg = {k: np.atleast_1d(np.asarray(v, float)) for k, v in targets.items()}
    notes = []
    mat = info["material"]
    g, m = info["g"], info["mass"]
    n_apex = max([tg[k].size for k in ("apex_heights", "restitution", "contact_durations")
                  if k in tg] + [1])
    if duration is None:
        if "settling_time" in tg:
            duration = 1.4 * float(tg["settling_time"][0]) + 0.2
        else:
            a = tg.get("apex_heights", np.array([0.5 * info["drop"]]))
            flights = np.sum(2.0 * np.sqrt(2.0 * np.maximum(a, 1e-6) / g))
            duration = 1.3 * (info["t_fall"] + flights) + 0.3
    steps = int(math.ceil(duration / dt))
    sim = dp.compile(scene, dt, law=law, **compile_kw)
    mfn = bounce_metrics_fn(sim, steps, body=body, plane=plane, n_apex=n_apex,
                            settle_tol=settle_tol)
    kk, cc, zeta = first_guess_bounce(info, tg, law=law, k0=1e4 * m if k0 is None else k0)
    heights_only = (("apex_heights" in tg or "restitution" in tg)
                    and not ({"settling_time", "contact_durations", "max_penetration"} & set(tg)))
    kpath, cpath = f"contact.{mat}.k", f"contact.{mat}.c"
    if free is None:
        free = [kpath, cpath]
        if heights_only:
            free = [cpath]
            notes.append(f"bounce heights alone fix only the damping ratio (zeta ~ "
                         f"{zeta:.3g}); k is held at {kk:.4g} N/m and only c is fitted. Give a "
                         "settling-time or contact-duration target to fit k as well.")
    # Accuracy limit of the explicit step: w0 dt <= 0.25 keeps the contact's restitution
    # within ~0.5% of the continuous model (physics-notes.md section 4); beyond it a fit
    # would tune the integrator's error instead of the contact.
    kmax = (0.25 / dt) ** 2 * m
    starts = None
    if (first_guess and k0 is None and zeta is not None and "settling_time" in tg
            and "contact_durations" not in tg and kpath in free):
        # k is set by the settling time: start LM from the best points of a 1-D scan over k
        # at the damping ratio the apex implies (ranked with the fit's own compiled function).
        ks = np.geomspace(1e-3 * kmax, kmax, 32)
        starts = [{kpath: float(k), cpath: float(2.0 * zeta * math.sqrt(k * m))}
                  for k in ks if cpath in free]
        notes.append(f"start: damping ratio {zeta:.4g} from the first apex; k from the best "
                     f"of a 32-point scan over {ks[0]:.3g}..{ks[-1]:.3g} N/m (w0 dt <= 0.25)")
    if c0 is not None:
        cc = c0
    if k0 is not None:
        kk = k0
    if kk > kmax:
        notes.append(f"start k {kk:.4g} N/m lowered to {kmax:.4g} N/m, the accuracy limit "
                     f"w0 dt <= 0.25 at dt = {dt:g} s (use a smaller dt for stiffer contact)")
        kk = kmax
    params0 = sim.params(contact={mat: (kk, cc)})
    bounds = {kpath: (min(1e-3 * kmax, kk), kmax), cpath: (1e-6, m / dt)}
    tol = dict(BOUNCE_METRICS)
    if rtol is not None:
        tol.update(rtol if isinstance(rtol, dict) else {k: rtol for k in tol})
    search = None
    if starts is not None and method == "lm" and free == [kpath, cpath]:
        search = _apex_settle_search([math.log(s[kpath]) for s in starts],
                                     [math.log(s[cpath]) for s in starts])
        notes[-1] += ("; along the curve where the first apex is met (Newton on c), the "
                      "settling time is matched by bisection on k")
        starts = None
    res = fit(mfn, params0, dict(targets), free=free,
              bounds={p: bounds[p] for p in free if p in bounds},
              weights=weights, rtol=tol, method=method, optimizer=optimizer,
              maxiter=maxiter or (40 if method == "lm" else 400), progress=progress,
              label="diffpen fit", starts=starts, search=search)
    res.notes = notes + res.notes
    return res


def _apex_settle_search(log_ks, log_cs, *, newton: int = 6, bisect: int = 10):
    """Start search for (k, c) from a first-apex and a settling-time target.

    The settling time is piecewise continuous in (k, c): it jumps whenever a small bounce's
    apex crosses the settling band. A local method stalls at those jumps, so: on a scan over
    k, c is solved by Newton so that the first apex is met exactly (smooth in c); along that
    curve the settling-time residual is bracketed between scan points and bisected in log k.
    A bracket holds either a root or a jump; every bracket's end point is returned, best
    first, for Levenberg-Marquardt to polish.
    """
    def run(evaluate, slices, lo, hi):
        ia = slices["apex_heights"].start
        js = slices["settling_time"].start

        def on_curve(lk, lc):
            r = None
            for _ in range(newton):
                r, J, _ = evaluate(np.array([lk, lc]))
                r, J = np.asarray(r), np.asarray(J)
                if not np.all(np.isfinite(r)) or abs(r[ia]) < 1e-5 or J[ia, 1] == 0.0:
                    break
                lc = float(np.clip(lc - np.clip(r[ia] / J[ia, 1], -0.5, 0.5), lo[1], hi[1]))
            return lc, r

        pts = []
        for lk, lc in zip(log_ks, log_cs):
            lk = float(np.clip(lk, lo[0], hi[0]))
            if pts:   # warm start: same damping ratio as the previous point on the curve
                lc = pts[-1][1] + 0.5 * (lk - pts[-1][0])
            lc, r = on_curve(lk, float(np.clip(lc, lo[1], hi[1])))
            if r is not None and np.all(np.isfinite(r)):
                pts.append((lk, lc, r))
        out = []
        for (ka, ca, ra), (kb, cb, rb) in zip(pts[:-1], pts[1:]):
            if np.sign(ra[js]) == np.sign(rb[js]):
                continue
            for _ in range(bisect):
                km = 0.5 * (ka + kb)
                cm, rm = on_curve(km, 0.5 * (ca + cb))
                if not np.all(np.isfinite(rm)):
                    break
                if np.sign(rm[js]) == np.sign(ra[js]):
                    ka, ca, ra = km, cm, rm
                else:
                    kb, cb, rb = km, cm, rm
            out += [(float(ra @ ra), ka, ca), (float(rb @ rb), kb, cb)]
        out += [(float(r @ r), k, c) for k, c, r in pts]
        out.sort()
        return [np.array([k, c]) for _, k, c in out[:6]]
    return run
