"""What a :class:`diffpen.Scene` holds: bodies, springs, colliders, materials and groups as
frozen records, and the input checks every ``Scene.add_*`` call runs (each raises
:class:`diffpen.SceneError` saying what to change).

Units: SI (metres, kilograms, seconds, newtons).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .errors import SceneError

__all__ = ["DEFAULT", "Body", "Spring", "AnchoredSpring", "Plane", "FixedSphere", "Drag",
           "PlasticSpring", "Material", "SpringGroup", "finite", "vec3", "finite_vec",
           "positive", "number"]

DEFAULT = "default"


def _real_array(name: str, value, what: str) -> np.ndarray:
    """``value`` as a float array, refusing what would only be coerced: strings, bools,
    None, complex numbers, objects."""
    if value is None or isinstance(value, (str, bytes, bool, np.bool_)):
        hint = ": write it without quotes" if isinstance(value, str) else ""
        raise SceneError(f"{name} must be {what}, got {value!r}{hint}.")
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):
        raise SceneError(f"{name} must be {what}, got {value!r}.") from None
    if raw.dtype.kind not in "iuf":
        raise SceneError(f"{name} must be {what} (real numbers), got {value!r}.")
    return raw.astype(float)


def finite(name: str, value) -> None:
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"{name} must be finite, got {value!r}: replace NaN/inf with a number.")


def vec3(name: str, value) -> tuple[float, float, float]:
    """``value`` as 3 finite floats (x, y, z)."""
    return tuple(float(a) for a in finite_vec(name, value, 3, "3 numbers (x, y, z)"))


def finite_vec(name: str, value, size: int, what: str | None = None) -> np.ndarray:
    """``value`` as a (size,) float array of finite numbers: one flat sequence, nothing
    coerced (a bool or a string among the numbers is refused, and so is a (1, 3) or (3, 1)
    array, which had been flattened into a (3,) one)."""
    what = what or f"{size} numbers"
    if isinstance(value, (list, tuple)) and any(
            isinstance(v, (str, bytes, bool, np.bool_)) for v in value):
        raise SceneError(f"{name} must be {what}, got {value!r}: numbers only (no True, "
                         "False or text).")
    arr = _real_array(name, value, what)
    if arr.shape != (size,):
        raise SceneError(f"{name} must be {what}, one flat sequence, got {value!r} (shape "
                         f"{arr.shape}).")
    finite(name, value)
    return arr


def unit_vector(arr: np.ndarray) -> tuple[np.ndarray, float]:
    """``(arr / |arr|, |arr|)`` of a finite vector without overflow or underflow: scaled by
    its largest entry first (``np.linalg.norm`` of (1e200, 1e200, 0) is inf, and the
    division gave a zero normal or quaternion). ``|arr|`` is inf where it overflows and 0
    for a zero vector (then the unit vector is zeros)."""
    arr = np.asarray(arr, dtype=float)
    scale = float(np.max(np.abs(arr), initial=0.0))
    if scale == 0.0:
        return np.zeros_like(arr), 0.0
    if 1e-150 < scale < 1e150:          # no overflow or underflow: one rounding, as before
        length = float(np.linalg.norm(arr))
        return arr / length, length
    scaled = arr / scale
    length = float(np.linalg.norm(scaled))
    with np.errstate(over="ignore"):
        return scaled / length, scale * length


def number(name: str, value) -> float:
    """A finite real number (no strings, bools or arrays: they are refused, not coerced)."""
    arr = _real_array(name, value, "a number")
    if arr.shape != ():
        raise SceneError(f"{name} must be one number, got {value!r}.")
    finite(name, arr)
    return float(arr)


def positive(name: str, value, *, allow_zero: bool = False) -> float:
    arr = _real_array(name, value, "a number")
    if arr.shape != ():
        raise SceneError(f"{name} must be one number, got {value!r}.")
    v = float(arr)
    finite(name, v)
    if v < 0.0 or (v == 0.0 and not allow_zero):
        need = "non-negative" if allow_zero else "positive"
        raise SceneError(f"{name} must be {need}, got {v!r}.")
    return v


@dataclasses.dataclass(frozen=True)
class Body:
    """A point mass (``radius == 0``), a sphere or a box. ``pinned`` bodies never move.

    Rigid bodies (``rigid=True``: boxes and rigid spheres) also carry an orientation (unit
    quaternion w, x, y, z, body to world), a world-frame angular velocity (rad/s) and the
    body-frame principal moments of inertia (kg m^2). A box's ``radius`` is the radius of
    its bounding sphere, m; ``half_extents`` are its half side lengths, m.
    """
    kind: str
    mass: float
    radius: float
    position: tuple[float, float, float]
    velocity: tuple[float, float, float]
    pinned: bool
    material: str
    collide: bool
    rigid: bool = False
    orientation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    angular_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float] | None = None
    half_extents: tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True)
class Spring:
    """Damped spring between bodies ``a`` and ``b`` (``b is None``: the world point ``anchor``)."""
    a: int
    b: int | None
    anchor: tuple[float, float, float] | None
    rest_length: float
    group: str


@dataclasses.dataclass(frozen=True)
class AnchoredSpring:
    """Damped spring between anchor points fixed in rigid bodies (the paper's ``Spring_c``).

    ``anchor_a`` / ``anchor_b`` are in the body frames of ``a`` / ``b``, m. With ``b is None``
    the second end is the fixed world point ``anchor_b``.
    """
    a: int
    b: int | None
    anchor_a: tuple[float, float, float]
    anchor_b: tuple[float, float, float]
    rest_length: float
    group: str


@dataclasses.dataclass(frozen=True)
class Plane:
    """Fixed half-space ``normal . p <= offset`` (``normal`` unit, pointing out of the solid)."""
    normal: tuple[float, float, float]
    offset: float
    material: str
    #: when set, the offset is the differentiable ``params.extra["plane_offset"][name]`` (m)
    name: str | None = None


@dataclasses.dataclass(frozen=True)
class FixedSphere:
    """Fixed spherical obstacle."""
    center: tuple[float, float, float]
    radius: float
    material: str


@dataclasses.dataclass(frozen=True)
class Drag:
    """Velocity drag ``F = -c v`` on body ``body``; ``c`` (N s/m) is per ``group``."""
    body: int
    group: str


@dataclasses.dataclass(frozen=True)
class PlasticSpring:
    """Spring between bodies ``a`` and ``b`` whose rest length shortens irreversibly when it is
    compressed by more than ``yield_strain * rest_length`` (see :mod:`diffpen.terms.plastic`).
    Stiffness and damping come from spring ``group``; the yield strain is per group too."""
    a: int
    b: int
    rest_length: float
    group: str


@dataclasses.dataclass
class Material:
    """Contact material: default penalty stiffness ``k`` (N/m) and damping ``c`` (N s/m);
    Coulomb ``friction`` coefficient (on planes: box corners, spheres and particles; on fixed
    spheres: spheres and particles; see :mod:`diffpen.terms.rigid`) and the
    ``slip_speed`` (m/s) below which friction is smoothed into a viscous law."""
    k: float | None = None
    c: float | None = None
    friction: float = 0.0
    slip_speed: float = 0.01


@dataclasses.dataclass
class SpringGroup:
    """Spring group sharing one stiffness ``k`` (N/m) and damping ``c`` (N s/m)."""
    k: float
    c: float
