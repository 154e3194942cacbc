"""Rigid bodies with friction: a sliding box stops at v^2 / (2 mu g), boxes and rigid spheres on
rough planes and fixed spheres."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import diffpen as dp
from jaxpr_scopes import traced_scopes

G = 9.81


def _scopes(sim, params):
    return " ".join(traced_scopes(sim, params)[0])


@pytest.fixture(scope="module")
def sliding_box():
    """A 1 kg box sliding at 2 m/s on a plane with smooth Coulomb friction (slip 2 mm/s)."""
    scene = dp.Scene()
    scene.add_material("default", friction=0.4, slip_speed=2e-3)
    scene.add_box((0.1, 0.1, 0.05), 1.0, (0.0, 0.0, 0.05 - G / 4e5), (2.0, 0.0, 0.0))
    scene.add_plane()
    return dp.compile(scene, dt=1e-4)


def _slide(sim, mu, steps=6000):
    return sim.rollout(sim.params(k=1e5, c=300.0, extra={"friction": {"default": mu}}),
                       steps=steps, save_every=steps // 60, check_finite=False)


def test_box_sliding_with_friction_stops_after_v0_squared_over_2_mu_g(sliding_box):
    traj = _slide(sliding_box, 0.4)
    t, vx = np.asarray(traj.time), np.asarray(traj.velocity[:, 0, 0])
    sliding = vx > 0.05
    np.testing.assert_allclose(vx[sliding], 2.0 - 0.4 * G * t[sliding], atol=2e-3)
    np.testing.assert_allclose(float(traj.position[-1, 0, 0]), 4.0 / (2 * 0.4 * G), rtol=1e-3)
    np.testing.assert_allclose(np.asarray(traj.velocity[-1]), 0.0, atol=1e-3)


def test_friction_gradient_matches_closed_form_and_finite_differences(sliding_box):
    def stop(mu):
        return _slide(sliding_box, mu).position[-1, 0, 0]
    mu = 0.4
    g = float(jax.jit(jax.grad(stop))(mu))
    # the values by the rollout program the test above compiled (no jit of its own)
    fd = float((stop(mu + 1e-5) - stop(mu - 1e-5)) / 2e-5)
    np.testing.assert_allclose(g, fd, rtol=1e-4)
    np.testing.assert_allclose(g, -4.0 / (2 * mu * mu * G), rtol=5e-3)   # d/dmu v0^2/(2 mu g)


def test_frictionless_box_traces_no_friction():
    scene = dp.Scene()
    scene.add_box((0.1, 0.1, 0.05), 1.0, (0.0, 0.0, 0.3))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3)
    assert "friction" not in sim.params(k=1e4, c=10.0).extra
    assert "friction" not in _scopes(sim, sim.params(k=1e4, c=10.0))


def test_sliding_rigid_ball_ends_rolling_at_five_sevenths_of_its_speed():
    """A solid ball launched without spin on a rough plane: friction mu m g decelerates it
    and spins it up until it rolls, at v = 5/7 v0 with w r = v, after t = 2 v0 / (7 mu g)."""
    mu, v0, r, m, k = 0.3, 2.0, 0.1, 1.0, 1e5
    scene = dp.Scene()
    scene.add_material("default", friction=mu, slip_speed=2e-3)
    ball = scene.add_rigid_sphere(r, m, (0.0, 0.0, r - m * G / k), (v0, 0.0, 0.0))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-4)
    traj = sim.rollout(sim.params(k=k, c=np.sqrt(k * m)), steps=3000, save_every=30)
    t, v = np.asarray(traj.time), np.asarray(traj.velocity[:, ball, 0])
    w = np.asarray(traj.angular_velocity[:, ball, 1])
    sliding = t < 0.9 * 2 * v0 / (7 * mu * G)
    np.testing.assert_allclose(v[sliding], v0 - mu * G * t[sliding], atol=1e-3)
    np.testing.assert_allclose(w[sliding] * r, 2.5 * mu * G * t[sliding], atol=2.5e-3)
    np.testing.assert_allclose([v[-1], w[-1] * r], [5 / 7 * v0, 5 / 7 * v0], rtol=1e-4)


def test_rk4_turns_a_free_body_at_fourth_order():
    """rk4 advanced the orientation once with its weighted angular velocity (a first-order
    quaternion update): second order on a tumbling body, no better than verlet (1.3e-4,
    3.3e-5 rad at dt 1e-2, 5e-3 s). The orientation is now a variable of the Runge-Kutta
    step itself. Reference: Euler's equations in the body frame by scipy DOP853."""
    inertia, w0, horizon = np.array([1.0, 2.0, 3.0]) * 0.01, np.array([1.0, 3.0, 0.5]), 1.0

    def rhs(t, y):
        q, wb = y[:4], y[4:]
        dq = np.r_[-0.5 * q[1:] @ wb, 0.5 * (q[0] * wb + np.cross(q[1:], wb))]
        return np.r_[dq, np.cross(inertia * wb, wb) / inertia]
    ref = solve_ivp(rhs, (0.0, horizon), np.r_[1.0, 0.0, 0.0, 0.0, w0], method="DOP853",
                    rtol=1e-13, atol=1e-14).y[:4, -1]
    ref /= np.linalg.norm(ref)
    errs = []
    for dt in (1e-2, 5e-3):
        s = dp.Scene(gravity=(0.0, 0.0, 0.0))
        b = s.add_box((0.1, 0.2, 0.3), 1.0, (0.0, 0.0, 0.0), angular_velocity=tuple(w0),
                      inertia=tuple(inertia))
        sim = dp.compile(s, dt, integrator="rk4")
        n = int(round(horizon / dt))
        q = np.asarray(sim.rollout(sim.params(), n, save_every=n).orientation[-1, b])
        errs.append(np.linalg.norm(q * np.sign(q @ ref) - ref))
    assert errs[0] < 1e-8
    assert errs[0] / errs[1] == pytest.approx(16.0, rel=0.05)


def test_a_pinned_body_given_a_velocity_under_vmap_stays_in_place():
    """A pinned body never moves. A concrete start state giving it a velocity is refused up
    front; one built under vmap (or jit) cannot be checked, so the step holds the pin: before,
    a pinned particle given 0.2 m/s drifted 0.1 m in 0.5 s and a pinned box given 2 rad/s
    turned by 1 rad (its spring anchor with it)."""
    s = dp.Scene(gravity=(0, 0, -9.81))
    bx = s.add_box((0.1, 0.1, 0.1), 1.0, (0, 0, 1.0), pinned=True)
    pin = s.add_particle(1.0, (1.0, 0, 1.0), pinned=True)
    bob = s.add_rigid_sphere(0.05, 0.2, (0.0, 0.0, 0.5))
    s.add_anchored_spring(bx, bob, anchor_a=(0.1, 0, -0.1), k=100.0)
    s.add_spring(pin, bob, k=20.0, group="tie")
    sim = dp.compile(s, dt=1e-3)
    start = sim.init_state()

    def run(v, w):
        st = sim.state_from(body=[bx, pin], velocity=v)
        st = sim.state_from(st, body=[bx], angular_velocity=w, frame="body")
        return sim.rollout(sim.params(k=1e4, c=10.0), 100, st, save_every=100).final
    v = jnp.array([[[0.2, 0, 0], [0, 0.3, 0]], [[0.0, 0, 0], [0, 0, 0]]])
    w = jnp.array([[[0.0, 0, 2.0]], [[0.0, 0, 0]]])
    # the start states built under vmap, in one compiled program with the rollout (vmap
    # alone ran state_from op by op: ~30 small programs)
    end = jax.jit(jax.vmap(run))(v, w)
    # to numpy once: indexing jax arrays compiles a program per index
    end = jax.tree_util.tree_map(np.asarray, end)
    start = jax.tree_util.tree_map(np.asarray, start)
    for row in range(2):
        np.testing.assert_array_equal(end.position[row, bx], start.position[bx])
        np.testing.assert_array_equal(end.position[row, pin], start.position[pin])
        np.testing.assert_array_equal(end.orientation[row, bx], start.orientation[bx])
    # the free sphere moved the same in both rows: the pins' given motion did not reach it
    np.testing.assert_allclose(end.position[0, bob], end.position[1, bob], rtol=0, atol=1e-12)


def test_building_and_placing_a_start_state_compiles_nothing(caplog):
    """``dp.compile``, ``init_state`` and ``state_from`` with concrete values work on the
    host: ``jnp.asarray`` of a host array and eager JAX updates compiled a small program for
    every new shape (9 for one ``state_from``, 2 each for building and for ``init_state``),
    about 30 ms each, at every start of a command or a script. Traced values (jit) still take
    the JAX path, with the same result."""
    import logging
    scene = dp.Scene()
    for i in range(10):                  # body counts no other test builds: fresh shapes
        scene.add_sphere(0.05, 1.0, (0.2 * i, 0.0, 0.5))
    boxes = [scene.add_box((0.1, 0.05, 0.02), 1.0, (0.0, y, 0.5)) for y in (1.0, 2.0)]
    scene.add_plane()
    pose = dict(velocity=(0.0, 0.0, -1.0), orientation=[(1, 0, 0, 0), (0.9, 0.1, 0.0, 0.0)],
                angular_velocity=[(0.0, 0.0, 0.0), (1.0, 2.0, 3.0)], frame="body")
    where = np.array([(0.6, 1.1, 0.7), (0.0, 2.0, 0.4)])
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        sim = dp.compile(scene, dt=1e-3)
        start = sim.init_state()
        placed = sim.state_from(start, body=boxes, position=where, **pose)
        placed = sim.state_from(placed, body=3, velocity=(1.0, 0.0, 0.0))
    compiled = [r.getMessage() for r in caplog.records if "XLA compilation" in r.getMessage()]
    assert compiled == [], compiled
    traced = jax.jit(lambda pos: sim.state_from(
        sim.state_from(start, body=boxes, position=pos, **pose), body=3,
        velocity=(1.0, 0.0, 0.0)))(where)
    for name in ("position", "velocity", "orientation", "angular_velocity"):
        np.testing.assert_allclose(np.asarray(getattr(placed, name)),
                                   np.asarray(getattr(traced, name)), rtol=1e-14, atol=1e-15)
    assert float(np.linalg.norm(np.asarray(placed.orientation)[boxes[1]])) == pytest.approx(1.0)
    assert np.asarray(placed.velocity)[3].tolist() == [1.0, 0.0, 0.0]
