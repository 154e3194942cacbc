"""Standard errors, correlations and undetermined directions of a least-squares fit.

Used by :func:`tuning.trajfit.fit_records` at its fitted point: from the residuals ``r`` (m,)
and their Jacobian ``J`` (m, p) in the fit's own coordinates (log values for log-space leaves,
the values themselves for signed ones), and which record each residual belongs to.

* Undetermined directions: eigenvectors of the diagonally scaled ``J^T J`` below 1e-8 of its
  largest eigenvalue; a Jacobian column below :data:`BLIND_RATIO` of the largest is round-off
  (a leaf with no effect on the records) and counts as no direction at all.
* Standard errors: per parameter the larger of Gauss-Newton's ``s^2 (J^T J)^-1`` and the
  records-as-clusters sandwich (:func:`record_sandwich`); infinite for a parameter the records
  do not determine, with NaN correlations.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["BLIND_RATIO", "parameter_errors", "record_sandwich"]

#: a fitted leaf whose Jacobian column is below this fraction of the largest column's norm
#: does not act on the records (round-off): undetermined, infinite standard error
BLIND_RATIO = 1e-8


def record_sandwich(inv, J, r, rows):
    """Records-as-clusters covariance ``inv B inv * R / (R - 1)`` (``inv`` = (J^T J)^-1,
    ``B`` = sum over records of ``g g^T``, ``g = J_r^T r_r`` the record's score): what the
    fitted values would scatter by if the records were measured again, whatever the errors
    within one record share (the noise of its first frame, which fixes its start state;
    correlated frames). None with fewer than two records or without ``rows``."""
    if rows is None:
        return None
    R = int(rows.max()) + 1 if rows.size else 0
    if R < 2:
        return None
    g = np.zeros((R, J.shape[1]))
    np.add.at(g, rows, J * np.asarray(r)[:, None])
    return inv @ (g.T @ g) @ inv * (R / (R - 1.0))


def parameter_errors(J, r, cost: float, free, values: dict, rows, nuisance: int = 0):
    """``(stderr, corr, undetermined)`` at a fitted point.

    Args:
      J: (m, p) Jacobian of the residuals w.r.t. the fit's coordinates.  r: (m,) residuals.
      cost: ``r @ r`` (NaN when the point is not a result).
      free: the p fitted leaves (``.name``, ``.log``).  values: ``{name: fitted value}``.
      rows: (m,) int, the record of each residual (None: no sandwich).
      nuisance: parameters fitted besides the p and eliminated from ``J`` (the records'
        start offsets of :mod:`tuning.start_refine`): degrees of freedom the noise estimate
        loses too.
    Returns:
      stderr ``{name: float}`` in the leaf's own units (inf where undetermined), corr (p, p)
      (NaN rows and columns where undetermined), undetermined: a list of
      ``{"eigenvalue_ratio", "direction": {name: component}}``.
    """
    names = [f.name for f in free]
    m = int(np.count_nonzero(np.any(J != 0, axis=1)))
    p = len(free)
    # a column below BLIND_RATIO of the largest is round-off (a leaf with no effect on the
    # records, e.g. the damping of a body at rest): no direction, so no error
    norms = np.linalg.norm(J, axis=0) if J.size else np.zeros(p)
    J = np.where(norms <= BLIND_RATIO * max(float(norms.max(initial=0.0)), 1e-300), 0.0, J)
    JtJ = J.T @ J
    scale = np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    S = JtJ / np.outer(scale, scale)
    ev, evec = np.linalg.eigh(S)
    loose_dirs = ev < 1e-8 * max(ev[-1], 1e-300)
    undetermined = [{"eigenvalue_ratio": float(ev[i] / max(ev[-1], 1e-300)),
                     "direction": {names[j]: float(evec[j, i]) for j in range(p)}}
                    for i in range(p) if loose_dirs[i]]
    s2 = cost / max(m - p - int(nuisance), 1)
    # no error for parameters the records do not depend on at all, nor for those with an
    # entry above 0.1 in an undetermined direction's unit vector (only a combination of
    # them is determined: pinv below keeps the determined part alone, which would give
    # them a small error that means nothing)
    blind = (np.diag(JtJ) <= 0.0) | np.any(np.abs(evec[:, loose_dirs]) > 0.1, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.linalg.pinv(S, rcond=1e-12) / np.outer(scale, scale)
        cov = inv * s2
        robust = record_sandwich(inv, J, r, rows)
        if robust is not None:
            # the larger of the two per parameter: the classical one treats every residual
            # as independent noise; the sandwich takes in what a record's residuals share
            # (its start state's noise, correlated frames), with few records noisily
            var = np.maximum(np.diag(cov), np.diag(robust))
            keep = np.sqrt(np.maximum(var, 0.0) / np.maximum(np.diag(cov), 1e-300))
            cov = cov * np.outer(keep, keep)
        se_x = np.where(blind, np.inf, np.sqrt(np.maximum(np.diag(cov), 0.0)))
        corr = np.where(np.outer(blind, blind) | np.outer(blind, ~blind)
                        | np.outer(~blind, blind), np.nan, cov / np.outer(se_x, se_x))
    stderr = {f.name: float(math.inf if blind[i] else values[f.name] * se_x[i] if f.log
                            else se_x[i]) for i, f in enumerate(free)}
    return stderr, corr, undetermined
