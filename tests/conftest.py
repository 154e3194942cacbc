"""Tests run in float64 (diffrax-style): enabled before any array is made.

Session-scoped fixtures hold the simulators several test files share, so each compiles (and
each of its jitted programs traces) once per test session.
"""
import jax
import pytest

jax.config.update("jax_enable_x64", True)


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
