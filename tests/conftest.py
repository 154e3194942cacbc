"""Tests run in float64 (diffrax-style): enabled before any array is made.

XLA compiles the tests' programs for speed of compiling, not of running: compiling dominates
the suite (the test programs run a few hundred steps each). Two XLA CPU options do it:
``--xla_backend_optimization_level=0`` (LLVM at -O0) and, on jaxlib 0.10,
``--xla_cpu_use_fusion_emitters=false`` (XLA's classic elemental emitters instead of the MLIR
fusion emitters). Together they cut the compile time of the suite's programs 2-3x (measured:
the implicit-Euler box gradient 14.8 -> 6.1 s of CPU; test_core + test_autodiff 103 -> 31 s of
backend compile). Neither changes floating-point semantics (XLA never enables fast-math);
results may differ by rounding where fused multiply-adds are formed, which every tolerance here
covers. The library keeps XLA's defaults (the fusion emitters run batched rollouts ~1.2-1.5x
faster). Set DIFFPEN_TEST_XLA_OPT=1 to test with XLA's defaults.

The suite uses no persistent compilation cache: serialising and writing every executable
costs more than the few programs two pytest-xdist workers have in common (measured on
test_trajfit.py under two workers, runs interleaved: 121 and 115 s of CPU with a shared
cache, 95 and 79 s without; the whole suite 716 -> 489 s of CPU).
The diffpen commands the tests run in-process are kept off their own cache too
(``DIFFPEN_CACHE=0``, below): otherwise the first of them in a worker switched the persistent
cache on in ~/.cache/diffpen for every later test of that worker. Four files that run those
commands (test_trajfit, test_evaluate, test_cli_contract, test_scene_sweep; two workers, two
interleaved rounds) took 113 / 104 s without it and 113 / 99 s with it starting empty, as on
CI: the same within noise, so the choice rests on not writing to the user's home.

Python's cyclic garbage collector runs less often here (``gc.set_threshold(50000, 20, 100)``
below; CPython's defaults are 700, 10, 10). A test session keeps a large heap alive (compiled
simulators in session and module fixtures, JAX's trace and compile caches), and every
full collection walks all of it: 56 full collections took 30 s of the suite's 579 s of test
time (two workers), ~0.5 s each, and tracing (which allocates many short-lived objects)
triggered the younger collections thousands of times. With the thresholds below no full
collection runs in a session and the suite's test time fell 579 -> 508 s (wall 329 -> 266 s on
2 cores), with a worker's peak memory at 2.1 GB (test_trajfit, test_contact_events and
test_rigid in one process: 1.55 GB peak with the defaults, 1.61 GB with these). Garbage
without reference cycles is still freed at once, and the younger generations still collect
cycles. No test here depends on when garbage is collected (none uses gc or weakref).

Session-scoped fixtures hold the simulators several test files share, so each compiles (and
each of its jitted programs traces) once per test session.
"""
import gc
import os


def _fast_compile_flags(flags: str) -> str:
    """``flags`` (an ``XLA_FLAGS`` value) with the compile-time options above added, each only
    where the caller has not set it (an XLA flag unknown to the installed jaxlib aborts the
    process, so the emitter option is added on jaxlib 0.10 only, where it exists)."""
    tokens = flags.split()
    if "xla_backend_optimization_level" not in flags:
        tokens.append("--xla_backend_optimization_level=0")
    try:
        import jaxlib
        version = tuple(int(v) for v in jaxlib.__version__.split(".")[:2])
    except Exception:           # pragma: no cover - jaxlib is a dependency
        version = None
    if version == (0, 10) and "xla_cpu_use_fusion_emitters" not in flags:
        tokens.append("--xla_cpu_use_fusion_emitters=false")
    return " ".join(tokens)


# The diffpen commands the tests run in-process (``tuning.cli.main``) would otherwise turn on
# their persistent compilation cache (tuning/cli/_common.py: setup_jax) for the rest of the
# worker, writing every later executable of the session to ~/.cache/diffpen; subprocesses
# inherit the setting too.
os.environ["DIFFPEN_CACHE"] = "0"

if os.environ.get("DIFFPEN_TEST_XLA_OPT") != "1":
    # before JAX starts its CPU backend (importing jax does not start it)
    os.environ["XLA_FLAGS"] = _fast_compile_flags(os.environ.get("XLA_FLAGS", ""))

# fewer, cheaper cyclic collections: see the module docstring
gc.set_threshold(50000, 20, 100)

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

# A scene-file fit to records measures the time step's error by default (step_shift: its
# residuals compiled and evaluated once more at dt / 2, ~0.3-1 s a fit, ~40 fits in the
# suite); the tests that check it turn it back on (tests/test_trajfit.py).
import tuning.scene_fit  # noqa: E402

tuning.scene_fit.STEP_CHECK = False


@pytest.fixture(scope="session")
def ball_scene():
    """The quick-start ball: radius 0.1 m, 1 kg, centre at 1 m above the ground plane."""
    import diffpen as dp
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0))
    scene.add_plane()
    return scene


@pytest.fixture(scope="session")
def ball_sim(ball_scene):
    """The quick-start ball compiled at dt = 1e-3 s with the defaults (shared: never mutate
    it; a Simulator is frozen anyway)."""
    import diffpen as dp
    return dp.compile(ball_scene, dt=1e-3)


@pytest.fixture(scope="session")
def cube():
    """The real tosses' cube (0.37 kg, 5 cm half-width, inertia 8e-4 kg m^2) above a board
    plane named "ground" (offset -2 mm; k 3e3, c 30, friction 0.2), dt 1 ms."""
    import diffpen as dp
    scene = dp.Scene()
    scene.add_material("board", k=3e3, c=30.0, friction=0.2)
    scene.add_box((0.05, 0.05, 0.05), 0.37, (0.0, 0.0, 0.3), inertia=(8e-4,) * 3)
    scene.add_plane(material="board", name="ground", offset=-0.002)
    return dp.compile(scene, 1e-3)
