"""The error of the fitting code: :class:`FitError`, a problem that cannot be set up.

It lives apart from the fitting modules so that all of them (:mod:`tuning.problem`,
:mod:`tuning.lm`, :mod:`tuning.optimise`, :mod:`tuning.fit`, :mod:`tuning.batch_fit`, ...)
can raise it without importing each other. ``tuning.fit.FitError`` is the same class.
"""
from __future__ import annotations

__all__ = ["FitError", "positive_int", "check_starts_keep"]


class FitError(ValueError):
    """A fitting problem that cannot be set up (bad targets, bounds or parameter names)."""


def positive_int(name: str, value, what: str) -> int:
    """``value`` as an int >= 1 (no bools, no floats), else :class:`FitError` naming ``name``
    and ``what`` it counts."""
    import numpy as np
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise FitError(f"{name} must be a positive integer ({what}), got {value!r}.")
    return int(value)


def check_starts_keep(starts, keep, names: tuple = ("starts", "keep")) -> None:
    """Refuse a negative ``starts`` count and a ``keep`` that is not a whole number from 1 to
    the start points there are (the given values and ``starts`` more): it was clamped to them
    without a word. ``names``: how the caller spells the two (the command: ``--starts``,
    ``--keep``). Raises :class:`FitError`."""
    import numpy as np
    s_name, k_name = names
    if isinstance(starts, (int, np.integer)) and starts < 0:
        raise FitError(f"{s_name} = {starts}: give a count >= 0 or a list of start values.")
    n = 1 + (starts if isinstance(starts, (int, np.integer)) else len(starts))
    if isinstance(keep, bool) or not isinstance(keep, (int, np.integer)) or not 1 <= keep <= n:
        raise FitError(f"{k_name} = {keep!r}: LM runs from the best `{k_name}` (a whole "
                       f"number) of the {n} start point(s) (the given values and {s_name} "
                       f"more); give 1 ... {n}, or more starts.")
