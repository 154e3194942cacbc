"""Stable time steps of the integrators on ONE damped oscillator mode ``x'' = -K x - C v``.

K = w^2 in 1/s^2, C = 2 zeta w in 1/s. The largest stable step is computed from the
integrator's own amplification matrix (the method applied to that linear mode); the closed
forms of docs/physics-notes.md section 4 are its special cases. ``safe_dt`` tightens the limit for
penalty contact (``SAFE_WH``, ``SAFE_CH``). See :mod:`diffpen.stability` for the overview.
"""
from __future__ import annotations

import functools
import math

import numpy as np

from ..errors import SceneError
from ..integrators import Integrator, resolve

__all__ = ["mode_amplification", "mode_stable_dt", "stable_dt", "safe_dt", "SAFE_WH", "SAFE_CH"]


def mode_amplification(integrator, K, C, h):
    """Amplification matrix (..., 2, 2) of one step of ``integrator`` (a name or an
    :class:`diffpen.integrators.Integrator`) on ``x'' = -K x - C v``.

    Args: K (1/s^2), C (1/s), h (s): arrays that broadcast. Maps (x, v) -> (x', v').
    It is the integrator record's own ``amplification`` (tests compare it against the JAX
    steps). Raises SceneError for methods without a step limit (no amplification).
    """
    rec = resolve(integrator)
    if rec.amplification is None:
        raise SceneError(f"integrator {rec.name!r} has no step limit (no amplification "
                         "matrix to analyse).")
    return rec.amplification(K, C, h)


def _spectral_radius_2x2(M, xp):
    """Spectral radius of (..., 2, 2) matrices from their trace and determinant (traceable)."""
    tr = M[..., 0, 0] + M[..., 1, 1]
    det = M[..., 0, 0] * M[..., 1, 1] - M[..., 0, 1] * M[..., 1, 0]
    # tr^2 - 4 det without its cancellation where both eigenvalues are near 1 (an
    # overdamped mode at rk4's limit: the radius read 1 + 1e-9 against 1 + 2e-9)
    half = M[..., 0, 0] - M[..., 1, 1]
    disc = half * half + 4.0 * M[..., 0, 1] * M[..., 1, 0]
    root = xp.sqrt(xp.abs(disc))
    real = 0.5 * xp.maximum(xp.abs(tr + root), xp.abs(tr - root))
    return xp.where(disc >= 0.0, real, xp.sqrt(xp.abs(det)))


def mode_stable_dt(integrator, K: float, C: float) -> float:
    """Largest step h (s) for which ``integrator`` (a name or an
    :class:`diffpen.integrators.Integrator`) is stable on ``x'' = -K x - C v``.

    ``inf`` for methods without amplification (implicit) or a mode with K = C = 0. The
    integrator's closed form when it has one (semi-implicit Euler: exact), else found by
    search on the spectral radius of its amplification matrix (stable: radius <= 1 + 1e-9),
    starting from the closed-form undamped / pure-dashpot limits: the first unstable step of
    a log grid, narrowed by grids inside its bracket to float64's spacing.
    """
    return _mode_stable_dt(resolve(integrator), float(K), float(C))


@functools.lru_cache(maxsize=4096)
def _mode_stable_dt(rec: Integrator, K: float, C: float) -> float:
    if rec.amplification is None or (K <= 0.0 and C <= 0.0):
        return math.inf
    if rec.stable_dt is not None:
        return float(rec.stable_dt(K, C))

    def unstable(h):            # the closed form of a 2x2 radius: eigvals cost ~10 ms a mode
        return _spectral_radius_2x2(rec.amplification(K, C, h), np) > 1.0 + 1e-9
    guess = min(2.0 / math.sqrt(K) if K > 0 else math.inf, 2.0 / C if C > 0 else math.inf)
    hi = guess
    while not unstable(hi):
        hi *= 2.0
        if hi > 1e3 * guess:
            return math.inf
    # the first crossing below hi: a fine log grid, then grids of 64 steps inside the first
    # unstable point's bracket (each round narrows it 64x: 9 rounds reach float64's spacing)
    grid, lo = np.geomspace(guess * 1e-3, hi, 400), 0.0
    for _ in range(10):
        first = int(np.argmax(unstable(grid)))
        lo, hi = (grid[first - 1] if first > 0 else lo), grid[first]
        if hi - lo <= 4.0 * np.spacing(hi):
            break
        grid = np.linspace(lo, hi, 65)[1:]
    return float(lo)


def stable_dt(integrator, K: float, C: float) -> float:
    """Largest stable step (s) of ``integrator`` for a scene whose largest mode rates are
    bounded by K (1/s^2) and C (1/s): the smallest of the mode limits at (K, C), (K, 0) and
    (0, C), since the stiffest and the most damped modes need not be the same."""
    cands = [mode_stable_dt(integrator, K, C)]
    if K > 0.0 and C > 0.0:
        cands += [mode_stable_dt(integrator, K, 0.0), mode_stable_dt(integrator, 0.0, C)]
    return min(cands)


#: Explicit integrators are held to ``w_c h <= SAFE_WH`` and ``C_c h <= SAFE_CH`` for the
#: contact springs (w_c^2 = k_contact / m, C_c = c_contact / m) besides linear stability.
#: Linear stability alone (w h < 2 for semi-implicit Euler) is not enough with penalty
#: contact: a contact switches on and off between steps, and the work done by a force held
#: over a step while the body crosses the contact boundary grows like
#: ``(w h)^2 / 4`` of the energy (measured on a ball at 10 m/s and on a ball released from a
#: full-radius overlap: 6% at w h = 0.5, 2% at 0.3, 0.2% at 0.1 for semi-implicit Euler, and
#: up to 470% for velocity Verlet at w h = 1.9). ``C h <= 1`` keeps dashpots from overshooting
#: (no velocity reversal within a step).
SAFE_WH = 0.5
SAFE_CH = 1.0
#: ... and to ``SAFE_STABLE`` of the stability limit of the stiffest and most damped modes
#: (springs too, damping included): as the step nears it, a stable oscillation's amplitude
#: grows without bound (``1 / sqrt(1 - (w h / 2)^2)`` for semi-implicit Euler and Verlet
#: undamped: 2.3x at 0.9 of the limit, 7x at 0.99, 700x at 0.999999), and a damped mode stops
#: decaying (its eigenvalue nears -1: a spring of damping ratio 0.25 at 0.999 of its damped
#: limit rang at the step's Nyquist frequency, larger after 0.5 s than at its start).
SAFE_STABLE = 0.9


def safe_dt(integrator, Kc: float, Cc: float, stable: float, K: float = 0.0,
            wh: float = SAFE_WH) -> float:
    """Largest inner step (s) the rollout accepts (a step equal to it is accepted): the
    stability limit ``stable`` (s), tightened for explicit integrators to ``SAFE_STABLE`` of
    it and of the undamped limit of the stiffest mode ``K`` (1/s^2), ``sqrt(Kc) h <= wh``
    (``SAFE_WH``, or the contact law's own) and ``Cc h <= SAFE_CH`` where Kc (1/s^2), Cc
    (1/s) bound the contact springs alone (springs that never switch off need no more than
    that)."""
    if not resolve(integrator).explicit:
        return stable
    cands = [SAFE_STABLE * stable]
    if K > 0.0:
        cands.append(SAFE_STABLE * mode_stable_dt(integrator, K, 0.0))
    if Kc > 0.0:
        cands.append(wh / math.sqrt(Kc))
    if Cc > 0.0:
        cands.append(SAFE_CH / Cc)
    return min(cands)


#: relative rounding allowance of "a step equal to the safe step is accepted" (dt / substeps
#: and the safe step are computed along different paths)
SAFE_TIE = 1e-12

