"""sim.step checks its params and state as a rollout does; a rollout's size check counts an
observe= output; `diffpen simulate` refuses a size with the library's own estimate."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen.state import ContactParams


@pytest.fixture(scope="module")
def sim(ball_sim):
    """The quick-start ball of conftest.py, compiled at dt = 1e-3 s."""
    return ball_sim


def test_step_refuses_what_rollout_refuses(sim):
    """sim.step stepped a 2-body state on a 1-body simulator by broadcasting, and accepted a
    NaN start and a negative k edited in with _replace."""
    p, s0 = sim.params(k=1e4, c=20.0), sim.init_state()
    bad_k = p._replace(contact={"default": ContactParams(np.float64(-1e4), np.float64(20.0))})
    for params, state, words in [
            (None, s0, "step needs the params pytree from sim.params"),
            (p, s0._replace(position=jnp.ones((2, 3)), velocity=jnp.zeros((2, 3))),
             "state.position has shape (2, 3), this simulator needs (1, 3)"),
            (p, s0._replace(position=s0.position.at[0, 2].set(jnp.nan)),
             "the start state is not finite: state.position of body 0"),
            (bad_k, s0, "contact k of material 'default' (N/m) must be >= 0")]:
        with pytest.raises(dp.SceneError) as e:
            sim.step(params, state)
        assert words in str(e.value)
    assert np.isfinite(np.asarray(sim.step(p, s0).position)).all()
    # traced params still step (checked for shape, not value)
    z = jax.jit(lambda k: sim.step(sim.params(k=k, c=20.0), s0).position[0, 2])(1e4)
    assert np.isfinite(float(z))


def test_step_casts_params_to_the_simulators_dtype(ball_scene):
    """float64 params on a float32 simulator upcast the stepped state to float64 (a state
    rollout then refuses); rollout casts them, and so does step."""
    sim32 = dp.compile(ball_scene, 1e-3, dtype=jnp.float32)
    p64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64),
                                 sim32.params(k=1e4, c=20.0))
    s1 = sim32.step(p64, sim32.init_state())
    assert s1.position.dtype == jnp.float32 and s1.velocity.dtype == jnp.float32
    sim32.step(p64, s1)                                 # the stepped state steps again


def test_rollout_size_check_counts_the_observed_output(sim, monkeypatch):
    """An observe= output counted 0 bytes: 2e9 steps observing one position passed and
    compiled a 44.7 GiB output. Lowered only: nothing runs."""
    from diffpen import checks
    monkeypatch.setattr(checks, "memory_bytes", lambda: 2.0 ** 30)
    p = sim.params(k=1e4, c=20.0)

    def obs(s):
        return s.position[0]
    with pytest.raises(dp.SceneError) as e:
        jax.jit(lambda p: sim.rollout(p, 10 ** 8, observe=obs).observed).lower(p)
    assert ("would store 100000000 observed outputs of 32 B each" in str(e.value)
            and "more than half" in str(e.value) and "save_every=" in str(e.value))
    stored, _ = checks.estimate(sim, 10 ** 8, 10, obs)
    assert stored == 10 ** 7 * (3 * 8 + 8)
    assert sim.rollout(p, 10, observe=obs).observed.shape == (10, 3)


def test_simulate_refuses_with_the_librarys_estimate(capsys, monkeypatch):
    """`diffpen simulate` counted 6 floats per body where the library counts 12 for a
    columns-layout ball: between the two it passed its own check and failed in the library
    with advice for options it does not have (save_every=, observe=)."""
    monkeypatch.setenv("DIFFPEN_CACHE", "0")
    from diffpen import checks
    from tuning.cli import main
    steps = 10 ** 4                   # rows 480 kB, columns 960 kB; half the memory: 750 kB
    monkeypatch.setattr(checks, "memory_bytes", lambda: 1.5e6)
    rc = main(["simulate", "ball", "--steps", str(steps)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert f"--steps {steps} keeps {steps} states of 1 bodies: about 960000 B" in err
    assert "lower --steps" in err
    assert "save_every" not in err and "Traceback" not in err


def test_rollout_substeps_auto_points_to_compile(sim):
    """sim.rollout(substeps="auto") said only "must be a positive int or None"; 'auto' is an
    option of dp.compile, and the message now says so."""
    with pytest.raises(dp.SceneError) as e:
        sim.rollout(sim.params(k=1e4, c=20.0), 10, substeps="auto")
    assert 'dp.compile(scene, dt, substeps="auto")' in str(e.value)


def test_step_checks_values_in_its_own_program(monkeypatch):
    """sim.step converted the whole state to NumPy before every step to check its values (a
    third of a small step's time); the step's program now computes one validity flag
    (``checks.state_values_ok``) and the error is worded only when it is clear. A loop of
    valid steps, pins and rotation included, never takes that slow path; an invalid state
    still raises the rollout's error, before the stepped state is returned: a NaN, a pinned
    body moving, a quaternion off unit norm."""
    from diffpen import checks
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0), pinned=True)
    scene.add_box((0.05, 0.05, 0.05), 1.0, (0.3, 0.0, 0.5), angular_velocity=(0.0, 1.0, 2.0))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3)
    p, s = sim.params(k=1e4, c=20.0), sim.init_state()
    worded, original = [], checks.check_state_values
    monkeypatch.setattr(checks, "check_state_values", lambda *a: worded.append(1) or original(*a))
    for _ in range(5):
        s = sim.step(p, s)
    assert not worded and np.all(np.isfinite(np.asarray(s.position)))
    bad_v = s._replace(velocity=s.velocity.at[1, 0].set(jnp.inf))
    for bad, words in [
            (bad_v, "state.velocity of body 1 is"),
            (s._replace(velocity=s.velocity.at[0, 2].set(1.0)),
             "state.velocity of body 0 is [0.0, 0.0, 1.0], but that body is pinned"),
            (s._replace(orientation=s.orientation.at[1].set(jnp.array([1.0, 0.1, 0.0, 0.0]))),
             "state.orientation of body 1 has norm 1.00499"),
            (s._replace(time=jnp.asarray(jnp.nan, s.position.dtype)),
             "the start state's time is nan")]:
        with pytest.raises(dp.SceneError) as e:
            sim.step(p, bad)
        assert words in str(e.value)
    assert len(worded) == 4
    # a concrete state stepped with traced params (inside the caller's jit) is checked too
    with pytest.raises(dp.SceneError, match="state.velocity of body 1 is"):
        jax.jit(lambda k: sim.step(sim.params(k=k, c=20.0), bad_v).position)(1e4)


def test_python_float_params_share_the_programs_of_arrays(sim, caplog):
    """Regression: rollout and forces cast params to the simulator's dtype only inside their
    jitted functions, so params holding Python floats (weak-typed: ``ContactParams(1.1e4,
    20.0)``, or leaves set by ``tuning.trajfit.with_leaves``) traced and compiled a second
    program (0.2-0.5 s a rollout) next to the one of arrays; they are cast first now."""
    import logging
    p = sim.params(k=1e4, c=20.0)
    sim.rollout(p, 40)
    sim.forces(p, sim.init_state())
    traced = sim.rollout_cache_size()
    floats = p._replace(contact={"default": ContactParams(1.1e4, 21.0)})
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        traj = sim.rollout(floats, 40)
        f = sim.forces(floats, sim.init_state())
    assert [r.getMessage() for r in caplog.records
            if r.getMessage().startswith("Compiling")] == []
    assert sim.rollout_cache_size() == traced
    assert np.all(np.isfinite(np.asarray(traj.position))) and np.all(np.isfinite(np.asarray(f[0])))
