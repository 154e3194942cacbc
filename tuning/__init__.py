"""tuning: fit contact stiffness and damping of diffpen scenes to targets and to measured
trajectories, sweep parameters with vmap, and the ``diffpen`` command line.

Metrics (:mod:`tuning.metrics`) are exact on the simulated trajectory and differentiable;
fits (:mod:`tuning.fit`) run in log space with any optax transformation or
Levenberg-Marquardt (:mod:`tuning.lm`); :mod:`tuning.bounce` is the bouncing-ball problem
behind ``diffpen fit``; :mod:`tuning.batch_fit` runs many fits at once, sharded over devices;
:mod:`tuning.sysid` identifies k and c from a measured record with standard errors;
:mod:`tuning.sweep` evaluates grids in vmapped chunks with resumable, atomic output;
:mod:`tuning.scenefile` reads TOML scenes. Submodules import lazily (the
generic ``tuning.fit.fit`` and ``tuning.sweep.sweep`` keep their module names).
"""
from __future__ import annotations

import importlib

__all__ = [
    # metrics
    "ball_metrics", "BallMetrics", "apex_heights", "settling_time", "contact_durations",
    "resting_height",
    # fitting
    "fit_bounce", "FitResult", "FitError", "default_optimizer", "bounce_metrics_fn",
    "check_bounce_targets",
    # batched fits
    "fit_batch", "BatchFitter", "BatchFitResult",
    # trajectories
    "fit_trajectory", "TrajectoryFit", "load_csv", "synthetic_record",
    # sweeps
    "SweepResult", "grid_points", "random_points", "load_sweep",
    # scenes
    "SCENES", "SceneSetup", "load_scene_file",
]

_WHERE = {
    "ball_metrics": "metrics", "BallMetrics": "metrics", "apex_heights": "metrics",
    "settling_time": "metrics", "contact_durations": "metrics", "resting_height": "metrics",
    "fit_bounce": "bounce", "FitResult": "fit", "FitError": "fit",
    "default_optimizer": "fit", "bounce_metrics_fn": "bounce", "check_bounce_targets": "bounce",
    "fit_batch": "batch_fit", "BatchFitter": "batch_fit", "BatchFitResult": "batch_fit",
    "fit_trajectory": "sysid", "TrajectoryFit": "sysid", "load_csv": "sysid",
    "synthetic_record": "sysid",
    "SweepResult": "sweep", "grid_points": "sweep",
    "random_points": "sweep", "load_sweep": "sweep",
    "SCENES": "scenes", "SceneSetup": "scenes", "load_scene_file": "scenefile",
}


def __getattr__(name):
    if name in _WHERE:
        mod = importlib.import_module(f".{_WHERE[name]}", __name__)
        return getattr(mod, name)
    raise AttributeError(f"module 'tuning' has no attribute {name!r}")
