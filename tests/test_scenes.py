"""tuning.scenes: the one bouncing-ball builder and the built-in scenes that use it."""
import numpy as np
import pytest

import diffpen as dp
from tuning import scenes


def test_ball_scene_places_the_sphere_above_the_ground_plane():
    s = scenes.ball_scene(radius=0.2, mass=3.0, height=0.7, velocity=-1.5, gravity=9.0)
    (body,), (plane,) = s.bodies, s.planes
    assert body.radius == 0.2 and body.mass == 3.0
    np.testing.assert_array_equal(body.position, (0.0, 0.0, 0.7))
    np.testing.assert_array_equal(body.velocity, (0.0, 0.0, -1.5))
    np.testing.assert_array_equal(s.gravity, (0.0, 0.0, -9.0))
    np.testing.assert_array_equal(plane.normal, (0.0, 0.0, 1.0))
    assert plane.offset == 0.0


def test_ball_scene_without_gravity_has_a_zero_gravity_vector():
    g = np.asarray(scenes.ball_scene(gravity=0.0).gravity)
    assert np.all(g == 0.0) and not np.any(np.signbit(g))


def test_built_in_ball_is_the_ball_scene():
    setup = scenes.ball(radius=0.15, mass=2.0, drop=0.6, gravity=9.5)
    ref = scenes.ball_scene(radius=0.15, mass=2.0, height=0.6, gravity=9.5)
    assert repr(setup.scene.bodies) == repr(ref.bodies)
    assert repr(setup.scene.planes) == repr(ref.planes)
    np.testing.assert_array_equal(setup.scene.gravity, ref.gravity)


def test_built_in_ball_refuses_a_start_in_contact():
    with pytest.raises(dp.SceneError, match="Raise --drop"):
        scenes.ball(radius=0.1, drop=0.1)
