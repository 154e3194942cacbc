"""diffpen: differentiable penalty-contact simulation in JAX, built for tuning stiffness
and damping.

Scene (what exists; static) -> ``compile`` (a simulator holding only the terms the scene
needs) -> ``Params`` (k, c: what you differentiate) -> ``State`` / ``Trajectory``.
"""
import os as _os


#: bytes up to which XLA CPU compiles a whole while loop (a rollout's ``lax.scan``) into one
#: kernel instead of launching every fusion of its body once per step (XLA's own limit: 1 kB)
SMALL_LOOP_BYTES = 1_000_000


def _configure_xla_cpu() -> None:
    """XLA CPU options for this process, applied through ``XLA_FLAGS`` before JAX starts its
    CPU backend; ``DIFFPEN_KEEP_XLA_FLAGS=1`` keeps the flags as they are. If JAX's backend
    already started (some JAX computation ran before ``import diffpen``), XLA has read its
    flags: a :class:`diffpen.PerformanceWarning` says so (import diffpen first).

    * A rollout's loop is compiled into a single kernel when its carry and body touch at most
      :data:`SMALL_LOOP_BYTES` (``xla_cpu_small_while_loop_byte_threshold``, a backend extra
      option; XLA's default, 1 kB, leaves every rollout loop launching each of its fusions
      once per step, and a compute-heavy fusion is then split over the cores with a
      synchronisation every step). Measured on 1024 batched balls x 2000 steps in the
      columns layout: 4.4 ms instead of 10.3 ms forward, 0.022 s instead of 0.032 s for the
      gradient; larger loops (65536 balls) keep XLA's per-fusion threading; batch 1, the
      spring networks and the spheres are unchanged. Added to the caller's own
      ``xla_backend_extra_options`` when ``XLA_FLAGS`` has some (left out when they set the
      threshold themselves).
    * jaxlib 0.10.x: XLA CPU's experimental YNN fusions are turned off. They made a batched
      rollout 140x slower from batch ~4096 on (2.2 s instead of 16 ms for 4096 balls x 2000
      steps, measured) and change nothing measurable elsewhere. Skipped when ``XLA_FLAGS``
      already names the option.
    """
    if _os.environ.get("DIFFPEN_KEEP_XLA_FLAGS") == "1":
        return
    before = _os.environ.get("XLA_FLAGS", "")
    option = f"xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}"
    tokens = before.split()
    extra = [i for i, t in enumerate(tokens) if t.startswith("--xla_backend_extra_options=")]
    if not extra:
        tokens.append("--xla_backend_extra_options=" + option)
    elif "xla_cpu_small_while_loop_byte_threshold" not in before:
        i = extra[-1]                       # XLA reads the last one: add ours to it
        value = tokens[i].split("=", 1)[1]
        tokens[i] = "--xla_backend_extra_options=" + (f"{value},{option}" if value else option)
    try:
        import jaxlib
        version = tuple(int(v) for v in jaxlib.__version__.split(".")[:2])
    except Exception:
        version = None
    if version == (0, 10) and "xla_cpu_experimental_ynn_fusion_type" not in before:
        tokens.append("--xla_cpu_experimental_ynn_fusion_type=")
    flags = " ".join(tokens)
    if flags != before.strip() and _backend_started():
        import warnings
        from .errors import PerformanceWarning
        warnings.warn("JAX's backend started before `import diffpen` (some JAX computation "
                      "ran first), so XLA has read its flags and diffpen's XLA CPU options "
                      "(rollout loops compiled into one kernel; jaxlib 0.10: YNN fusions "
                      "off) do not apply in this process: batched rollouts run up to ~3x "
                      "slower (results are the same). Import diffpen before any JAX "
                      f"computation, or start Python with XLA_FLAGS='{flags}'.",
                      PerformanceWarning, stacklevel=3)
    _os.environ["XLA_FLAGS"] = flags


def _backend_started() -> bool:
    """Whether JAX (if imported) has initialised a backend, i.e. read ``XLA_FLAGS``."""
    import sys
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
        return bool(getattr(xla_bridge, "_backends", None))
    except Exception:
        return False


_configure_xla_cpu()

from . import geometry, integrators, laws, physical, stability  # noqa: E402
from . import autodiff, broadphase, builders, rigid, rollout, terms  # noqa: E402
from .autodiff import grad, value_and_grad  # noqa: E402
from .compile import Simulator, compile  # noqa: E402
from .errors import (ContactWarning, NonFiniteError, PerformanceWarning,  # noqa: E402
                     SceneError, SpinWarning, StabilityError)
from .precision import PrecisionWarning  # noqa: E402
from .terms.plastic import CollapseWarning  # noqa: E402
from .integrators import Integrator  # noqa: E402
from .scene import Scene  # noqa: E402
from .state import ContactParams, Params, SpringParams, State, Trajectory  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Scene", "compile", "Simulator", "Integrator", "value_and_grad", "grad",
    "Params", "ContactParams", "SpringParams", "State", "Trajectory",
    "SceneError", "StabilityError", "NonFiniteError", "PerformanceWarning", "ContactWarning",
    "PrecisionWarning", "CollapseWarning", "SpinWarning",
    "laws", "geometry", "integrators", "physical", "builders",
    "rigid", "broadphase", "stability", "autodiff", "rollout", "terms",
]
