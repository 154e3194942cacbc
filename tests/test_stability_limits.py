"""The step limits' own computation: the rk4 and Verlet mode limits (a grid search of the
closed-form 2x2 spectral radius) and the words a friction limit uses."""
import math

import numpy as np
import pytest

import diffpen as dp


def test_a_mode_limit_takes_few_amplification_evaluations():
    """The stability gate of rk4 and Verlet rollouts finds each new parameter value's mode
    limit on the host: it bisected 60 times with a LAPACK eigensolve each (10 ms a mode,
    13-20 ms a rollout; audit12). Now grids of the closed-form 2x2 radius: a handful of
    evaluations, the same limits (the undamped closed forms to 1e-12, a damped one against
    the eigenvalues of the amplification matrix just below and just above it)."""
    from diffpen.integrators import resolve
    from diffpen.stability.modes import _mode_stable_dt
    for name, undamped in (("rk4", 2.0 * math.sqrt(2.0)), ("verlet", 2.0)):
        rec, calls = resolve(name), []
        counted = rec._replace(amplification=lambda K, C, h, a=rec.amplification: (
            calls.append(1), a(K, C, h))[1])
        assert _mode_stable_dt(counted, 4.0e6, 0.0) == pytest.approx(undamped / 2e3, rel=1e-12)
        h = _mode_stable_dt(counted, 3.7e6, 850.0)
        assert len(calls) <= 30, len(calls)
        radius = [np.max(np.abs(np.linalg.eigvals(rec.amplification(3.7e6, 850.0, x))))
                  for x in (h * (1 - 1e-9), h * (1 + 1e-9))]
        assert radius[0] <= 1.0 + 1e-9 < radius[1], radius
    # an overdamped mode at rk4's limit, both eigenvalues near 1: the radius's closed form
    # cancelled there and passed a step of radius 1 + 2.0e-9 (audit15)
    rk4 = resolve("rk4")
    for K, C in ((1.0, 1e6), (1e-12, 1.0), (3.0, 1e4)):
        h = _mode_stable_dt(rk4, K, C)
        assert np.max(np.abs(np.linalg.eigvals(rk4.amplification(K, C, h)))) <= 1.0 + 1.01e-9


def test_a_friction_limit_says_it_counts_bodies_that_never_touch():
    """audit13: a box hung on springs 0.66 m above a rough floor made the fit and evaluate
    refuse dt = 1 ms, the limit set by friction it never feels; the limit still counts
    every body that can touch the material, and its words now say so and how to leave such
    a body out."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("floor", k=1e4, c=10.0, friction=0.3)
    box = scene.add_box((0.1, 0.05, 0.04), 1.2, (0.0, 0.0, 0.5))
    scene.add_anchored_spring(box, None, (0.0, 0.0, 0.04), (0.0, 0.0, 0.9), k=250.0, c=1.0,
                              rest_length=0.3)
    scene.add_plane(material="floor", offset=-0.2)
    sim = dp.compile(scene, 1e-3)
    rep = sim.stability(sim.params())
    assert not rep.stable and "friction of material 'floor'" in rep.limiting
    assert "whether or not it reaches it" in rep.limiting and "collide = false" in rep.limiting


def test_the_closed_form_limit_neither_overflows_nor_cancels():
    """Regression (audit17): semi-implicit Euler's limit ``(-C + sqrt(C^2 + 4 K)) / K``
    overflowed in float32 (C^2 from C ~ 2e19 1/s, 4 K from K ~ 9e37 1/s^2): a limit of inf,
    so a traced float32 rollout with a spring damper of 1e20 1/s went NaN with its
    ``unstable`` flag clear; and it cancelled to 0 for an overdamped spring (``diffpen
    simulate ball --k 1e-300``: "the safe step is 0 s ... lower that stiffness")."""
    import jax
    import jax.numpy as jnp

    from diffpen.integrators import semi_implicit_euler_stable_dt as limit
    assert limit(1e-300, 1.0) == pytest.approx(2.0, rel=1e-12)
    assert limit(1e4, 20.0) == pytest.approx((-20.0 + math.sqrt(400.0 + 4e4)) / 1e4, rel=1e-14)
    assert limit(0.0, 0.0) == math.inf and limit(0.0, 5.0) == pytest.approx(0.4)
    assert math.isnan(limit(math.nan, 1.0)) and math.isnan(limit(1.0, math.nan))
    for k, c in ((1e38, 0.0), (0.0, 1e20), (1e38, 1e20), (1e-30, 1e15)):
        traced = float(limit(jnp.float32(k), jnp.float32(c), xp=jnp))
        assert traced == pytest.approx(limit(k, c), rel=1e-5), (k, c)
    scene = dp.Scene()
    a = scene.add_particle(1.0, (0.0, 0.0, 1.0), pinned=True)
    b = scene.add_particle(1.0, (0.3, 0.0, 1.0))
    scene.add_spring(a, b, k=100.0, c=0.5)
    sim = dp.compile(scene, dt=1e-3, dtype=jnp.float32)
    flag = jax.jit(lambda c: sim.rollout(sim.params(spring_k=100.0, spring_c=c), 20,
                                         save_every=20).aux["unstable"][-1])
    assert [bool(flag(jnp.float32(c))) for c in (0.5, 1e20, 1e30)] == [False, True, True]


def test_steps_of_ones_own_loop_given_traced_params_set_the_flag():
    """Regression (audit17): ``sim.step`` in a user's own jitted ``lax.scan`` with traced
    params past the safe step left ``aux["unstable"]`` False (a ball dropped from 0.3 m at
    k 1e8 N/m ended at 0.89 m moving up); only rollouts set it. Each step given traced
    params now sets it as a rollout does; safe params keep it clear."""
    import jax

    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.3))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3)

    @jax.jit
    def run(k):
        def body(s, _):
            return sim.step(sim.params(k=k, c=10.0), s), None
        return jax.lax.scan(body, sim.init_state(), None, length=30)[0]
    safe, past = run(1e4), run(1e8)
    assert not bool(safe.aux["unstable"]) and bool(past.aux["unstable"])
    assert set(safe.aux) == set(sim.init_state().aux)          # the carry keeps its shape
    params = sim.params(k=1e4, c=10.0)          # concrete params, a traced state (audit18)

    from diffpen.stepping import flag_mode
    modes = []

    @jax.jit
    def from_height(z):
        s = sim.init_state()
        s = s._replace(position=s.position.at[0, 2].set(z))
        modes.append(flag_mode(params, s, True))
        return jax.lax.scan(lambda s, _: (sim.step(params, s), None), s, None, length=5)[0]
    assert not bool(from_height(0.3).aux["unstable"])
    assert bool(from_height(float("nan")).aux["unstable"])
    # audit19: with concrete params (the gate checked them) only the state's own checks run
    # per step, not the bound (under a law stiffening with depth it cost 2.5-3.6x the step)
    assert set(modes) == {"values"} and flag_mode(params, sim.init_state(), True) is None


def test_a_traced_start_state_that_is_not_finite_sets_the_flag():
    """Regression (audit17): a start state with NaN in it, given to a rollout under
    ``jax.jit`` or ``jax.vmap`` (where it cannot be refused up front as a concrete one is),
    gave a NaN trajectory with ``aux["unstable"]`` clear: a sweep took it for a result."""
    import jax
    import jax.numpy as jnp

    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.3))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3)
    params = sim.params(k=1e4, c=10.0)

    @jax.jit
    @jax.vmap
    def flag(z):
        s = sim.init_state()
        s = s._replace(position=s.position.at[0, 2].set(z))
        return sim.rollout(params, 10, state=s, save_every=10).aux["unstable"][-1]
    np.testing.assert_array_equal(flag(jnp.array([0.3, jnp.nan, jnp.inf])),
                                  [False, True, True])
