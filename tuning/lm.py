"""Levenberg-Marquardt: box-projected nonlinear least squares on a flat parameter vector.

:func:`levenberg_marquardt` minimises ``|r(x)|^2`` given a function that returns the
residuals and their Jacobian (jitted by the caller, so every trial point reuses one compiled
function), with Marquardt's diagonal scaling and a projection onto box bounds after every
step. :func:`tuning.fit.fit` (``method="lm"``) and :func:`tuning.sysid.fit_trajectory` run it
on log-parameters.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax.numpy as jnp
import numpy as np

from .fit import FitError, Progress

__all__ = ["LMResult", "levenberg_marquardt"]


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
