"""diffpen: differentiable penalty-contact simulation in JAX, built for tuning stiffness
and damping.

Scene (what exists; static) -> ``compile`` (a simulator holding only the terms the scene
needs) -> ``Params`` (k, c: what you differentiate) -> ``State`` / ``Trajectory``.
"""
import os as _os


def _configure_xla_cpu() -> None:
    """Turn off XLA CPU's experimental YNN fusions for this process (jaxlib 0.10.x).

    On jaxlib 0.10 they made a batched rollout 140x slower from batch ~4096 on (2.2 s instead
    of 16 ms for 4096 balls x 2000 steps, measured), and change nothing measurable elsewhere.
    Applied through ``XLA_FLAGS`` before JAX starts its CPU backend (no effect if it already
    has); skipped when ``XLA_FLAGS`` already names the option, when
    ``DIFFPEN_KEEP_XLA_FLAGS=1``, or for other jaxlib versions.
    """
    if _os.environ.get("DIFFPEN_KEEP_XLA_FLAGS") == "1":
        return
    flags = _os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_experimental_ynn_fusion_type" in flags:
        return
    try:
        import jaxlib
        version = tuple(int(v) for v in jaxlib.__version__.split(".")[:2])
    except Exception:
        return
    if version == (0, 10):
        _os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_experimental_ynn_fusion_type=").strip()


_configure_xla_cpu()

from . import geometry, integrators, laws, physical, stability  # noqa: E402
from . import autodiff, broadphase, builders, plastic, rigid, rollout, terms  # noqa: E402
from .autodiff import grad, value_and_grad  # noqa: E402
from .compile import Simulator, compile  # noqa: E402
from .errors import NonFiniteError, PerformanceWarning, SceneError, StabilityError  # noqa: E402
from .integrators import Integrator  # noqa: E402
from .scene import Scene  # noqa: E402
from .state import ContactParams, Params, SpringParams, State, Trajectory  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Scene", "compile", "Simulator", "Integrator", "value_and_grad", "grad",
    "Params", "ContactParams", "SpringParams", "State", "Trajectory",
    "SceneError", "StabilityError", "NonFiniteError", "PerformanceWarning",
    "laws", "geometry", "integrators", "physical", "builders", "plastic",
    "rigid", "broadphase", "stability", "autodiff", "rollout", "terms",
]
