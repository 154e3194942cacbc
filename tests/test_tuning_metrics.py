"""Bounce metrics: exact on known signals, and within 0.1% of event-located values of an
independent ODE solution of the ball scene (scipy, adaptive RK with event location)."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from tuning import metrics as M

R, MASS, DROP, G = 0.1, 1.0, 1.0, 9.81
K, C = 1e4, 30.0


def test_apex_of_sampled_parabola_is_exact_vertex():
    # Three bounces of exact parabolas, sampled coarsely and off the vertex.
    t = np.arange(0.0, 3.0, 0.0137)
    h = np.full_like(t, -0.001)
    arcs = ((-0.8, 0.9), (1.0, 1.7), (1.8, 2.3))       # the first one is the drop
    for t0, t1 in arcs:
        m = (t > t0) & (t < t1)
        tm = 0.5 * (t0 + t1)
        h[m] = 0.5 * G * ((0.5 * (t1 - t0)) ** 2 - (t[m] - tm) ** 2)
    apex_fn = jax.jit(M.apex_heights, static_argnums=1, static_argnames="after_contact")
    apex, valid = apex_fn(jnp.asarray(h), 3)
    want = [0.5 * G * (0.5 * (b - a)) ** 2 for a, b in arcs]
    assert np.asarray(valid).tolist() == [True, True, False]
    np.testing.assert_allclose(np.asarray(apex)[:2], want[1:], rtol=1e-12)
    # with after_contact=False the drop's top (inside the record) counts too
    apex_all, valid_all = apex_fn(jnp.asarray(h), 3, after_contact=False)
    np.testing.assert_allclose(np.asarray(apex_all), want, rtol=1e-12)


def test_rank_select_and_max_penetration_match_numpy():
    """The first n selected samples in order (nan and invalid past the last), and the
    deepest sample, against plain numpy on random masks, empty and full masks included."""
    rng = np.random.default_rng(0)
    rank_select = jax.jit(M._rank_select, static_argnums=2)     # one compile for all cases
    max_penetration = jax.jit(M.max_penetration)
    for density in (0.0, 0.002, 0.05, 1.0):
        for _ in range(5):
            values = rng.normal(size=300)
            mask = rng.random(300) < density
            got, valid = rank_select(jnp.asarray(values), jnp.asarray(mask), 3)
            want = values[np.flatnonzero(mask)[:3]]
            assert np.asarray(valid).sum() == len(want) and np.asarray(valid)[:len(want)].all()
            np.testing.assert_array_equal(np.asarray(got)[:len(want)], want)
            assert np.isnan(np.asarray(got)[len(want):]).all()
            h = values.copy()
            h[rng.integers(300)] = h.min()            # a tie: the first one counts
            i = int(np.clip(np.argmax(-h), 1, 298))
            dm, d0, dp_ = -h[i - 1], -h[i], -h[i + 1]
            q = dm - 2 * d0 + dp_
            ref = d0 - (dp_ - dm) ** 2 / (8 * q) if q < 0 and d0 >= dm and d0 >= dp_ else d0
            np.testing.assert_allclose(float(max_penetration(jnp.asarray(h))),
                                       max(ref, -h.min(), 0.0), rtol=1e-12)


def test_settling_time_is_last_exceedance_interpolated():
    t = jnp.linspace(0.0, 1.0, 101)
    z = jnp.where(t < 0.5, 0.01 * (0.5 - t) / 0.5, 0.0) + 0.2     # straight line into rest
    z = z.at[30].set(0.2 + 0.05)                                     # an early spike
    settling_time = jax.jit(M.settling_time)          # one compile for both signals
    ts, ok = settling_time(t, z, 0.2, tol=0.002)
    assert bool(ok)
    # |z - rest| = 0.01 (0.5 - t) / 0.5 = 0.002  ->  t = 0.4 exactly (linear between samples)
    assert float(ts) == pytest.approx(0.4, rel=1e-12)
    _, ok = settling_time(t, z + 0.01 * t, 0.2, tol=0.002)   # drifts away: never settles
    assert not bool(ok)


def _event_reference(sim, params, steps, tol=1e-3):
    """Event-located values on the per-step trajectory (numpy): the highest position of each
    flight between lift-off and the next touch-down (to ~1e-8 m at this step), contact
    start/end and the last band exceedance interpolated between consecutive steps."""
    s0 = sim.init_state()
    tr = sim.rollout(params, steps, s0)
    t = np.concatenate([[0.0], np.asarray(tr.time)])
    z = np.concatenate([[DROP], np.asarray(tr.position[:, 0, 2])])
    v = np.concatenate([[0.0], np.asarray(tr.velocity[:, 0, 2])])
    h = z - R
    gap = 0.5 * sim.smoothing
    lift = np.nonzero((h[:-1] <= gap) & (h[1:] > gap))[0] + 1
    land = np.nonzero((h[:-1] > gap) & (h[1:] <= gap))[0]
    apex = np.array([h[a:b + 1].max() for a, b in zip(lift, land[land > lift[0]])])
    # (z + v^2 / 2g at the lift-off state is off by h v / 2 for symplectic Euler: its
    # positions, not its (z, v) pairs, lie on the free-flight parabola)
    assert np.all(h[lift] + v[lift] ** 2 / (2 * G) - apex[:len(lift)] > 0.0)

    def cross(a, b, i):
        return t[i] + a / (a - b) * (t[i + 1] - t[i])
    down = [cross(h[i], h[i + 1], i) for i in np.nonzero((h[:-1] >= 0) & (h[1:] < 0))[0]]
    up = [cross(h[i], h[i + 1], i) for i in np.nonzero((h[:-1] < 0) & (h[1:] >= 0))[0]]
    rest = R - MASS * G / float(params.contact["default"].k)
    e = np.abs(z - rest)
    i = np.nonzero(e > tol)[0][-1]
    settle = t[i] + (e[i] - tol) / (e[i] - e[i + 1]) * (t[i + 1] - t[i])
    fine, _ = jax.jit(lambda h: M.apex_heights(h, 3, flight_gap=gap))(jnp.asarray(h))
    # (the metric, every step)
    return {"apex": apex, "contact": np.array(up) - np.array(down[:len(up)]),
            "settle": settle, "pen": -h.min(), "metric_every_step": np.asarray(fine)}


@pytest.fixture(scope="module")
def ball_run():
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_sphere(radius=R, mass=MASS, position=(0.0, 0.0, DROP))
    scene.add_plane()
    sim = dp.compile(scene, 1e-4)
    params = sim.params(k=K, c=C)
    s0 = sim.init_state()
    traj = sim.rollout(params, 25000, s0, save_every=10)       # saved every 1 ms
    # jitted: one compile instead of one per eager operation
    metrics = jax.jit(lambda traj, params: M.ball_metrics(sim, traj, params, n_apex=3,
                                                          state0=s0))
    return sim, params, metrics(traj, params)


def test_metrics_match_event_located_values(ball_run):
    sim, params, m = ball_run
    ref = _event_reference(sim, params, 25000)
    np.testing.assert_allclose(np.asarray(m.apex_heights), ref["apex"][:3], rtol=1e-3)
    # the parabola vertex does not depend on the save interval (every step vs every 10th)
    np.testing.assert_allclose(np.asarray(m.apex_heights), ref["metric_every_step"],
                               rtol=1e-10)
    np.testing.assert_allclose(np.asarray(m.contact_durations), ref["contact"][:3], rtol=1e-3)
    assert float(m.max_penetration) == pytest.approx(ref["pen"], rel=1e-3)
    assert float(m.settling_time) == pytest.approx(ref["settle"], rel=1e-3)
    e = np.sqrt(ref["apex"][:3] / np.concatenate([[DROP - R], ref["apex"][:2]]))
    np.testing.assert_allclose(np.asarray(m.restitution), e, rtol=1e-3)
    assert float(m.resting_height) == pytest.approx(R - MASS * G / K, rel=1e-12)
    # and the restitution is the physical one: within 1% of the closed form with gravity
    # during contact (docs/physics-notes.md section 2: e ~ e0 - (1 + e0) (c / k) g / v_in)
    e0 = float(dp.physical.restitution(K, C, MASS))
    v_in = math.sqrt(2 * G * (DROP - R))
    assert float(m.restitution[0]) == pytest.approx(e0 - (1 + e0) * C / K * G / v_in, rel=1e-2)


def test_metric_gradients_match_finite_differences():
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_sphere(radius=R, mass=MASS, position=(0.0, 0.0, DROP))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3)

    def apex1(c):
        p = sim.params(k=K, c=c)
        tr = sim.rollout(p, 1200, sim.init_state(), check_finite=False)
        return M.ball_metrics(sim, tr, p, n_apex=1).apex_heights[0]
    vg = jax.jit(jax.value_and_grad(apex1))        # one compile for values and gradient
    g = float(vg(C)[1])
    h = 1e-4
    fd = (float(vg(C + h)[0]) - float(vg(C - h)[0])) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-4)
    assert g < 0.0          # more damping, lower bounce


def test_scene_metrics_compile_once_per_simulator(caplog, tmp_path):
    """Regression: the built-in ball scene's and a scene file's ``SceneSetup.metrics`` (what
    `diffpen simulate` reports) built a new ``jax.jit`` at every call, so each call compiled
    again (0.8-1.5 s); a second call with new values now compiles nothing and equals the
    metrics computed directly."""
    import logging

    from tuning.scenefile import load_scene_file
    from tuning.scenes import get_scene
    path = tmp_path / "ball.toml"
    path.write_text("dt = 1e-3\n[[spheres]]\nradius = 0.1\nmass = 1.0\n"
                    "position = [0.0, 0.0, 0.5]\n[[planes]]\n")
    for setup in (get_scene("ball"), load_scene_file(str(path)).setup):
        sim = dp.compile(setup.scene, 1e-3)
        runs = [(p, sim.rollout(p, 400)) for p in (sim.params(k=1e4, c=10.0),
                                                    sim.params(k=1.2e4, c=12.0))]
        setup.metrics(sim, *runs[0][::-1])
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
            got = setup.metrics(sim, *runs[1][::-1])
        assert [r.getMessage() for r in caplog.records
                if r.getMessage().startswith("Compiling")] == []
        want = M.ball_metrics(sim, runs[1][1], runs[1][0], n_apex=3).apex_heights
        np.testing.assert_allclose(np.asarray(got["apex_heights"]), np.asarray(want),
                                   rtol=1e-12)
