"""The error of the fitting code: :class:`FitError`, a problem that cannot be set up.

It lives apart from the fitting modules so that all of them (:mod:`tuning.problem`,
:mod:`tuning.lm`, :mod:`tuning.optimise`, :mod:`tuning.fit`, :mod:`tuning.batch_fit`, ...)
can raise it without importing each other. ``tuning.fit.FitError`` is the same class.
"""
from __future__ import annotations

__all__ = ["FitError"]


class FitError(ValueError):
    """A fitting problem that cannot be set up (bad targets, bounds or parameter names)."""
