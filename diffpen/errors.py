"""Exceptions raised by diffpen. Each message says what to change."""
from __future__ import annotations

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
