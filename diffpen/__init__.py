"""diffpen: differentiable penalty-contact simulation in JAX, built for tuning stiffness
and damping.

Scene (what exists; static) -> ``compile`` (a simulator holding only the terms the scene
needs) -> ``Params`` (k, c: what you differentiate) -> ``State`` / ``Trajectory``.
"""
from . import geometry, integrators, laws, physical, stability
from . import plastic  # registers the plastic-spring term  # noqa: E402
from . import builders
from . import rigid, broadphase  # register the rigid-body and broad-phase terms
from .compile import Simulator, compile
from .errors import NonFiniteError, SceneError, StabilityError
from .scene import Scene
from .state import ContactParams, Params, SpringParams, State, Trajectory

__version__ = "0.1.0"

__all__ = [
    "Scene", "compile", "Simulator",
    "Params", "ContactParams", "SpringParams", "State", "Trajectory",
    "SceneError", "StabilityError", "NonFiniteError",
    "laws", "geometry", "integrators", "physical", "builders", "plastic",
    "rigid", "broadphase", "stability",
]
