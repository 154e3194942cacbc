"""Exceptions raised by diffpen. Each message says what to change."""
from __future__ import annotations

import os
import sys
import warnings

__all__ = ["SceneError", "StabilityError", "NonFiniteError", "PerformanceWarning",
           "ContactWarning"]


class SceneError(ValueError):
    """Invalid scene or simulator input (raised before anything is compiled)."""


class StabilityError(ValueError):
    """An explicit integrator was asked to step past its stability limit."""

    def __init__(self, message: str, *, stable_dt: float | None = None,
                 substeps: int | None = None):
        super().__init__(message)
        self.stable_dt = stable_dt
        self.substeps = substeps


class NonFiniteError(FloatingPointError):
    """A rollout produced NaN or inf; the message names the first step and body."""

    def __init__(self, message: str, *, step: int | None = None, body: int | None = None):
        super().__init__(message)
        self.step = step
        self.body = body


class PerformanceWarning(UserWarning):
    """A call that works but runs several times slower than an equivalent form; the message
    names the fast form (filter it with ``warnings.simplefilter("ignore",
    diffpen.PerformanceWarning)``)."""


class ContactWarning(UserWarning):
    """A start state that drives a contact past what a penalty spring can hold (two spheres
    closing too fast for their contact: they would pass through each other); the message
    says what to change."""


class SpinWarning(UserWarning):
    """A rollout whose start was within its integrator's spin limit, in which a torque spun
    a rigid body past it (:mod:`diffpen.motion`): its results from there carry the
    integrator's energy error at that turn per step; the message says what to change."""


_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn(message: str, category: type[Warning]) -> None:
    """``warnings.warn(message, category)`` attributed to the first frame outside diffpen:
    the user's line that called into the library, whichever entry point (``rollout``,
    ``step``, ``forces``, ``dp.compile``) and however deep inside diffpen the warning is
    raised (a hand-counted ``stacklevel`` pointed ``sim.step``'s warnings at diffpen's own
    line)."""
    frame, level = sys._getframe(1), 2
    while frame is not None and frame.f_code.co_filename.startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
