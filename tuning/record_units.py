"""Unit checks of motion records (:mod:`tuning.records`): records are in seconds and metres,
and the commonest slips (times in milliseconds, positions in centimetres or millimetres)
are refused with the fix, judged by the record's own motion: a body in flight falls at
about 9.81 m/s^2 in metres, 981 "per s^2" in centimetres."""
from __future__ import annotations

import math

import numpy as np

from .errors import FitError

__all__ = ["MS_SPAN", "MM_LIMIT", "FALL", "FALL_FACTOR", "fall_rate", "unit_slip"]

#: unit hints: a record spanning more than this with steps of at least 1 looks like milliseconds
MS_SPAN = 60.0
#: a height |z| beyond this (m) looks like centimetres or millimetres, unless the record falls
#: there at about FALL (m/s^2), within a factor FALL_FACTOR: in cm it would fall at 981, in mm
#: at 9810
MM_LIMIT = 20.0
FALL = 9.81
FALL_FACTOR = 10.0


def fall_rate(t: np.ndarray, p: np.ndarray, r: int) -> float | None:
    """Acceleration magnitude (record units/s^2) of the motion around sample ``r``, the one
    farthest from 0 in the last column of ``p`` (T, k) (z): a parabola fitted to the run of
    samples around it that stay beyond the middle of the record's range (a flight's top: no
    contact with the lowest surface lies in it). None when the record does not show one: fewer
    than 6 samples there, samples the parabola does not follow (rms misfit above a tenth of
    their span), or an acceleration within 5 standard errors of 0 (at rest, uniform motion)."""
    ok = np.isfinite(p).all(axis=1)
    r = int(np.count_nonzero(ok[:r]))
    t, p = t[ok], p[ok]
    u = np.sign(p[r, -1]) * p[:, -1]
    mid = 0.5 * (u.max() + u.min())
    a, b = r, r + 1
    while a > 0 and u[a - 1] > mid:
        a -= 1
    while b < len(u) and u[b] > mid:
        b += 1
    n = b - a
    if n < 6:
        return None
    s = t[a:b] - t[a:b].mean()
    A = np.stack([np.ones_like(s), s, s * s], axis=1)
    coef, *_ = np.linalg.lstsq(A, p[a:b], rcond=None)
    res = p[a:b] - A @ coef
    span = float(np.ptp(p[a:b], axis=0).max())
    rms = math.sqrt(float(np.mean(np.sum(res * res, axis=1))))
    if not span > 0.0 or rms > 0.1 * span:
        return None
    acc = 2.0 * float(np.linalg.norm(coef[2]))
    err = 2.0 * rms * math.sqrt(n / (n - 3) * float(np.linalg.inv(A.T @ A)[2, 2]))
    return acc if acc > 5.0 * err else None


def unit_slip(path: str, line: str, col: str, value: float, what: str, fall: float | None,
               api: str) -> FitError:
    """The refusal of a record beyond MM_LIMIT whose motion does not show metres."""
    head = f"{path}, line {line}, column {col}: {value:g} m is beyond {MM_LIMIT:g} m"
    if fall is not None and fall > FALL_FACTOR * FALL:
        return _error(f"{head} and the record falls there at about {fall:.0f} per s^2 "
                           f"({fall / FALL:.0f} g if it were metres): {what} look like "
                           "centimetres or millimetres, but records are in metres. Divide them by "
                           "100 or 1000.")
    shown = "no free fall" if fall is None else f"an acceleration of only {fall:.3g} m/s^2"
    return _error(f"{head} and the record shows {shown} around it to confirm metres (about "
                       f"{FALL:g} m/s^2 in flight): {what} look like centimetres or "
                       "millimetres, but records are in metres. Divide them by 100 or 1000; a "
                       "record that really is in metres is read in Python with "
                       f"tuning.records.{api}(path, check_units=False) (the diffpen commands "
                       "refuse it).")


def _error(text: str) -> FitError:
    from .records import RecordError        # tuning.records imports this module
    return RecordError(text)
