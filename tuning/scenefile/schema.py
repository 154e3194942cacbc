"""Scene-file schema constants: size guards, the top-level and ``[fit]`` keys, name
patterns, and small helpers shared by the readers."""
from __future__ import annotations

import inspect
import re

from ..records import MAX_MAGNITUDE


#: size guards (raise them by argument of :func:`load_scene_file`)
MAX_STEPS = 10_000_000
MAX_BODIES = 200_000
MAX_DENSE_PAIRS = 500_000          # contact pairs evaluated every step without a broad phase
MAX_TRAJECTORY_BYTES = 8 * 2**30   # a rollout saving every step
#: contact k (N/m) and c (N s/m) of materials that give neither their own nor a top-level one:
#: the built-in ball's (:func:`tuning.scenes.ball`; c was 10 here, so the same ball written as
#: a scene file bounced to 0.65 m against 0.47 m and did not settle)
DEFAULT_K = 1e4
DEFAULT_C = 20.0
#: positions, centres and anchor points must lie within this distance of the origin, m
MAX_COORD = 1e6
#: start velocities (m/s) and angular velocities (rad/s) per component: the records' bound
#: (tuning.records.MAX_MAGNITUDE); body masses, kg (1e300 kg passed, and `diffpen simulate`
#: reported a decay time of 0 s as valid)
MAX_SPEED = MAX_MAGNITUDE["velocity"]
MAX_MASS = 1e12

BODY_TABLES = ("spheres", "particles", "boxes", "rigid_spheres")
BUILDER_TABLES = ("ropes", "cloths", "jellies", "crumple_bars")
TOP = {"description", "gravity", "dt", "duration", "law", "exponent", "integrator",
       "allow_overlap",
       "smoothing", "substeps", "plastic_smoothing", "broadphase", "k", "c", "materials",
       *BODY_TABLES, "planes", "fixed_spheres", "spring_groups", "springs",
       "anchored_springs", "plastic_springs", "drag", *BUILDER_TABLES, "fit"}
#: [fit] keys; extended by fits that need more
FIT = {"body", "plane", "params", "bounds", "space", "settle_tol", "targets", "data", "method",
       "maxiter", "lr", "weights", "observe", "first_state", "flight_frames", "horizon"}
TARGETS = {"apex_heights", "settling_time", "contact_durations", "restitution",
           "max_penetration", "decay_time"}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
_NODE = re.compile(r"^([A-Za-z_][A-Za-z0-9_\-]*)\[\s*(-?\d+(?:\s*,\s*-?\d+)*)\s*\]$")


def is_scene_path(arg: str) -> bool:
    """Whether a command-line SCENE argument names a scene file rather than a built-in scene:
    a ``.toml`` suffix in any case (``ball.TOML`` is a file, never the built-in ``ball``)."""
    return isinstance(arg, str) and arg.lower().endswith(".toml")


def _x64() -> bool:
    import jax
    return bool(jax.config.jax_enable_x64)


def _takes(fn, name: str) -> bool:
    """Whether ``fn`` accepts keyword ``name`` (options newer than some library builds)."""
    try:
        return name in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
