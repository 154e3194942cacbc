"""The batched ball fast path equals the generic rollout and sweep bit for bit."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from tuning import ball_fast
from tuning import sweep as sw
from tuning.bounce import bounce_metrics_fn

STEPS = 600      # dropped from 0.4 m: the first contact at ~0.24 s, then bounces


def ball(drop=0.4, **extra):
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, drop), **extra)
    scene.add_plane()
    return scene


@pytest.mark.parametrize("law", ["linear", "no_tension", "hunt_crossley"])
def test_heights_equal_the_vmapped_rollout(law):
    sim = dp.compile(ball(), 1e-3, law=law)
    ks = jnp.asarray(np.geomspace(1e3, 1e5, 5))
    cs = jnp.asarray(np.geomspace(1.0, 100.0, 5))
    z, v = jax.jit(lambda k, c: ball_fast.ball_heights(sim, k, c, STEPS, velocities=True))(ks, cs)
    traj = jax.jit(jax.vmap(lambda k, c: sim.rollout(sim.params(k=k, c=c), STEPS,
                                                     save_every=1)))(ks, cs)
    assert z.shape == (STEPS, 5)
    np.testing.assert_array_equal(z, traj.position[:, :, 0, 2].T)
    np.testing.assert_array_equal(v, traj.velocity[:, :, 0, 2].T)
    assert float(jnp.min(z)) < 0.1           # the rows reach the plane: the contact is tested


def test_sweep_equals_the_generic_sweep():
    sim = dp.compile(ball(), 1e-3)
    mfn = bounce_metrics_fn(sim, STEPS, n_apex=2)
    axes = {"contact.default.k": np.geomspace(1e3, 1e5, 4),
            "contact.default.c": np.geomspace(1.0, 100.0, 3)}
    pts, shape = sw.grid_points(axes)
    names = list(axes)
    p0 = sim.params(k=1e4, c=10.0)
    generic = sw.sweep(mfn, p0, pts, names, chunk=5, progress=False, shape=shape)
    fast = sw.sweep(mfn, p0, pts, names, chunk=5, progress=False, shape=shape,
                    evaluate=ball_fast.ball_sweep_evaluator(sim, STEPS, p0, names, n_apex=2))
    assert set(fast.metrics) == set(generic.metrics)
    for key, value in generic.metrics.items():
        np.testing.assert_array_equal(fast.metrics[key], value, err_msg=key)
    assert np.isfinite(generic.metrics["contact_durations"][:, 0]).sum() >= 8    # contacts


def test_other_scenes_take_the_generic_path():
    assert ball_fast.supports(dp.compile(ball(), 1e-3)) is None
    assert "semi-implicit" in ball_fast.supports(dp.compile(ball(), 1e-3, integrator="rk4"))
    two = ball()
    two.add_sphere(radius=0.1, mass=1.0, position=(1.0, 0.0, 0.5))
    assert "one body" in ball_fast.supports(dp.compile(two, 1e-3))
    assert "horizontal" in ball_fast.supports(dp.compile(ball(velocity=(1.0, 0.0, 0.0)), 1e-3))
    sim = dp.compile(ball(), 1e-3)
    with pytest.raises(ValueError, match="sweeps"):
        ball_fast.ball_sweep_evaluator(sim, STEPS, sim.params(k=1e4, c=10.0), ["gravity"])


def test_eager_heights_compile_once(caplog):
    """Regression: called outside jit, ball_heights ran an eager scan over a new closure and
    compiled it again at every call (0.1 s a call); a call with new values now compiles
    nothing and equals the jitted call bit for bit."""
    import logging
    sim = dp.compile(ball(), 1e-3)
    ks, cs = jnp.asarray([2e3, 5e3]), jnp.asarray([2.0, 5.0])
    ks2, cs2 = jnp.asarray([4e3, 1e4]), jnp.asarray([4.0, 10.0])
    ball_fast.ball_heights(sim, ks, cs, STEPS)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        z = ball_fast.ball_heights(sim, ks2, cs2, STEPS)
    assert [r.getMessage() for r in caplog.records
            if r.getMessage().startswith("Compiling")] == []
    jitted = jax.jit(lambda k, c: ball_fast.ball_heights(sim, k, c, STEPS))(ks2, cs2)
    np.testing.assert_array_equal(np.asarray(z), np.asarray(jitted))


def test_a_sweep_whose_metrics_cannot_say_unstable_warns():
    """Regression (audit22): a user's metrics function without an "unstable" entry had its
    points past the safe step returned as results (a ball swept to k 1e8 N/m at dt 1 ms
    ended 85 m up) and ``result.unstable`` 0, without a word. It warns now, once, naming the
    entry; with the entry (or False where nothing can go unstable) it is silent."""
    import warnings
    sim = dp.compile(ball(), 1e-3)
    p0 = sim.params(k=1e4, c=10.0)
    pts = np.array([[1e3], [1e4], [1e5]])
    names = ["contact.default.k"]
    double = lambda p: {"k2": 2.0 * p.contact["default"].k}                    # noqa: E731
    with pytest.warns(UserWarning, match="no 'unstable' entry") as seen:
        res = sw.sweep(double, p0, pts, names, chunk=2, progress=False)
    assert len([w for w in seen if "unstable" in str(w.message)]) == 1
    np.testing.assert_allclose(res.metrics["k2"], 2.0 * pts[:, 0])
    flagged = lambda p: {**double(p), "unstable": jnp.asarray(False)}          # noqa: E731
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sw.sweep(flagged, p0, pts, names, chunk=2, progress=False,
                 batch_map=lambda f: jax.jit(jax.vmap(f)))
