"""Tests run in float64 (diffrax-style): enabled before any array is made.

XLA compiles the tests' programs with its LLVM backend at -O0: compiling dominates the suite
(the test programs run a few hundred steps each), and -O0 compiles them about 30% faster in
CPU time (measured on test_broadphase, test_rigid, test_integrators, test_core). It changes
no floating-point semantics (XLA never enables fast-math at any level); results may differ
from -O2 builds by rounding where fused multiply-adds are formed, which every tolerance here
covers. Set DIFFPEN_TEST_XLA_OPT=1 to test at XLA's default level.

Session-scoped fixtures hold the simulators several test files share, so each compiles (and
each of its jitted programs traces) once per test session.
"""
import os

if (os.environ.get("DIFFPEN_TEST_XLA_OPT") != "1"
        and "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", "")):
    # before JAX starts its CPU backend (importing jax does not start it)
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_backend_optimization_level=0").strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)


def pytest_configure(config):
    """The controller of a pytest-xdist run makes a compilation cache its workers share
    (they inherit its environment), so a program two workers compile (a session fixture's
    simulator, a module's rollout) is compiled once; fresh for every session, removed at its
    end (:func:`pytest_unconfigure`). DIFFPEN_TEST_CACHE=0 turns it off."""
    if hasattr(config, "workerinput") or os.environ.get("DIFFPEN_TEST_CACHE") == "0":
        return
    if getattr(config.option, "numprocesses", None):
        import tempfile
        os.environ["DIFFPEN_TEST_CACHE_DIR"] = tempfile.mkdtemp(prefix="diffpen-test-cache-")
        config._diffpen_cache = os.environ["DIFFPEN_TEST_CACHE_DIR"]


def pytest_unconfigure(config):
    path = getattr(config, "_diffpen_cache", None)
    if path is not None:
        import shutil
        shutil.rmtree(path, ignore_errors=True)


if os.environ.get("DIFFPEN_TEST_CACHE_DIR") and os.environ.get("PYTEST_XDIST_WORKER"):
    jax.config.update("jax_compilation_cache_dir", os.environ["DIFFPEN_TEST_CACHE_DIR"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)


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
