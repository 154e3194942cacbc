"""A batched rollout that records every state to keep a few numbers warns (issue: the
natural user code under vmap ran 15-34x the floor with no word said); the fast forms and
unbatched calls stay silent, and give the same numbers."""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen.checks import RECORDING_WARN_STEPS
from tuning.scenes import ball_scene

STEPS = 100


@pytest.fixture(scope="module")
def sim():
    return dp.compile(ball_scene(), dt=1e-3)


def _caught(fn):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = fn()
    return out, [x for x in w if issubclass(x.category, dp.PerformanceWarning)]


def test_natural_batched_form_warns_at_the_callers_line(sim):
    ks = jnp.array([5e3, 1e4, 2e4])
    out, w = _caught(lambda: jax.vmap(
        lambda k: sim.rollout(sim.params(k=k, c=20.0), STEPS).position[-1, 0, 2])(ks))
    assert len(w) == 1
    msg = str(w[0].message)
    assert "save_every=steps" in msg and "observe=" in msg and "save_every=1" in msg
    assert w[0].filename == __file__                  # points at the user's code
    fast, w_fast = _caught(lambda: jax.vmap(lambda k: sim.rollout(
        sim.params(k=k, c=20.0), STEPS, save_every=STEPS).position[-1, 0, 2])(ks))
    assert w_fast == []
    np.testing.assert_array_equal(np.asarray(out), np.asarray(fast))


@pytest.mark.parametrize("kind", ["save_every_1", "observe", "unbatched", "jit", "short",
                                  "batched_state"])
def test_fast_forms_and_unbatched_calls_are_silent(sim, kind):
    ks = jnp.array([5e3, 1e4])
    p0 = sim.params(k=1e4, c=20.0)
    calls = {
        "save_every_1": lambda: jax.vmap(lambda k: sim.rollout(
            sim.params(k=k, c=20.0), STEPS, save_every=1).position)(ks),
        "observe": lambda: jax.vmap(lambda k: sim.rollout(
            sim.params(k=k, c=20.0), STEPS, observe=lambda s: s.position[0, 2]).observed)(ks),
        "unbatched": lambda: sim.rollout(p0, STEPS).position,
        "jit": lambda: jax.jit(lambda k: sim.rollout(
            sim.params(k=k, c=20.0), STEPS).position[-1])(1e4),
        "short": lambda: jax.vmap(lambda k: sim.rollout(
            sim.params(k=k, c=20.0), RECORDING_WARN_STEPS - 1).position)(ks),
    }
    if kind == "batched_state":
        s0 = sim.init_state()
        starts = jax.vmap(lambda z: s0._replace(position=s0.position.at[0, 2].set(z)))(
            jnp.array([1.0, 1.2]))
        _, w = _caught(lambda: jax.vmap(lambda s: sim.rollout(p0, STEPS, s).position[-1])(
            starts))
        assert len(w) == 1                             # a batch of start states counts too
        return
    _, w = _caught(calls[kind])
    assert w == []
