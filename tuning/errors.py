"""The error of the fitting code: :class:`FitError`, a problem that cannot be set up.

It lives apart from the fitting modules so that all of them (:mod:`tuning.problem`,
:mod:`tuning.lm`, :mod:`tuning.optimise`, :mod:`tuning.fit`, :mod:`tuning.batch_fit`, ...)
can raise it without importing each other. ``tuning.fit.FitError`` is the same class.
"""
from __future__ import annotations

__all__ = ["FitError", "positive_int"]


class FitError(ValueError):
    """A fitting problem that cannot be set up (bad targets, bounds or parameter names)."""


def positive_int(name: str, value, what: str) -> int:
    """``value`` as an int >= 1 (no bools, no floats), else :class:`FitError` naming ``name``
    and ``what`` it counts."""
    import numpy as np
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise FitError(f"{name} must be a positive integer ({what}), got {value!r}.")
    return int(value)
