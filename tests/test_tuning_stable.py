"""tuning.stable: the traced flag under jit, vmap and grad; the parameter form of the flag is
diffpen's own (springs count too); the safe contact bounds sit exactly at diffpen's limit."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from tuning.stable import (contact_unstable, params_unstable, rollout_unstable,
                           safe_contact_bounds, safe_contact_limits)


def ball_sim(dt=1e-3, **kw):
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.3))
    scene.add_plane()
    return dp.compile(scene, dt, **kw)


def test_traced_stability_flag_under_jit_vmap_and_grad():
    """tuning.stable reads the rollout's flag (or its parameter form) inside traced code; the
    safe bounds are diffpen's limit less the 1% margin: just past them the flag is set."""
    sim = ball_sim()
    kmax, cmax = safe_contact_bounds(sim)
    assert np.sqrt(kmax / 1.0) * 1e-3 < dp.stability.SAFE_WH and cmax * 1e-3 < 1.0

    def flag(k):
        p = sim.params(k=k, c=1.0)
        traj = sim.rollout(p, 20, check_finite=False, check_stability=False)
        return rollout_unstable(sim, traj, p)
    ks = jnp.array([0.5, 1.0, 1.001 / 0.99, 1.5, 4.0]) * kmax
    np.testing.assert_array_equal(jax.jit(jax.vmap(flag))(ks), [False, False, True, True, True])
    assert not bool(jax.jit(flag)(0.5 * kmax))
    g = jax.grad(lambda k: jnp.where(params_unstable(sim, sim.params(k=k, c=1.0)), 0.0, k))
    assert float(g(0.5 * kmax)) == 1.0 and float(g(2.0 * kmax)) == 0.0
    assert contact_unstable is params_unstable
    # the flag from the parameters alone agrees with the rollout's
    for k in np.asarray(ks):
        assert bool(params_unstable(sim, sim.params(k=float(k), c=1.0))) == bool(flag(k))
    traced = jax.jit(lambda k: params_unstable(sim, sim.params(k=k, c=1.0)))
    assert bool(traced(jnp.nan)) and not bool(traced(0.5 * kmax))     # non-finite: unstable
    # (N,) contact values (a sweep's points): one flag per point
    p = sim.params(k=1.0, c=1.0)
    p = p._replace(contact={"default": p.contact["default"]._replace(k=ks)})
    np.testing.assert_array_equal(params_unstable(sim, p), [False, False, True, True, True])


def test_params_flag_counts_springs_like_the_rollout():
    """Regression: the parameter form of the flag looked at contact k and c only, so a spring
    past the safe step was called stable while the rollout flagged it."""
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.5))
    scene.add_plane()
    scene.add_spring(0, (0.0, 0.0, 1.0), k=1.0, c=0.0)
    sim = dp.compile(scene, 1e-3)
    p = sim.params(k=1e3, c=1.0, spring_k=5e6)          # w h = 2.2 for the spring alone
    traj = sim.rollout(p, 2, check_finite=False, check_stability=False)
    assert bool(traj.aux["unstable"][-1])
    assert bool(params_unstable(sim, p))
    assert not bool(params_unstable(sim, sim.params(k=1e3, c=1.0, spring_k=1e3)))


def test_safe_contact_bounds_use_the_inner_step_and_the_lightest_movable_body():
    scene = dp.Scene()
    scene.add_sphere(0.1, 2.0, (0.0, 0.0, 0.3))
    scene.add_sphere(0.1, 0.5, (0.5, 0.0, 0.3))
    scene.add_sphere(0.1, 0.1, (1.0, 0.0, 0.3), pinned=True)
    scene.add_plane()
    sim = dp.compile(scene, 2e-3, substeps=4)
    assert safe_contact_bounds(sim) == safe_contact_limits(5e-4, 0.5)
    assert safe_contact_bounds(sim, mass=2.0) == safe_contact_limits(5e-4, 2.0)
    k, c = safe_contact_limits(5e-4, 0.5)
    assert k == pytest.approx(0.99 * (dp.stability.SAFE_WH / 5e-4) ** 2 * 0.5, rel=1e-15)
    assert c == pytest.approx(0.99 * dp.stability.SAFE_CH * 0.5 / 5e-4, rel=1e-15)
    assert safe_contact_bounds(ball_sim(integrator="implicit_euler")) == (math.inf, math.inf)


def test_safe_contact_bounds_are_in_the_contact_laws_units():
    """The caps of fits were written for N/m and N s/m whatever the law: a Hunt-Crossley ball
    (k N/m^1.5, c N s/m^2.5) was capped at the linear numbers, which for a 0.1 m ball are
    2.1x too strict on k and 32x on c. They are now divided by the law's stiffness and
    damping at the reference depth (the ball's radius), the depth diffpen's own bound uses,
    and the flag agrees: just inside them the parameters are safe, just past them not."""
    lin = safe_contact_bounds(ball_sim())
    sim = ball_sim(law=dp.laws.hunt_crossley(1.5))
    k_max, c_max = safe_contact_bounds(sim)
    d = 0.1
    assert k_max == pytest.approx(lin[0] / (1.5 * d ** 0.5), rel=1e-12)
    assert c_max == pytest.approx(lin[1] / d ** 1.5, rel=1e-12)
    assert not bool(params_unstable(sim, sim.params(k=0.98 * k_max, c=1.0)))
    assert bool(params_unstable(sim, sim.params(k=1.05 * k_max, c=1.0)))
    assert not bool(params_unstable(sim, sim.params(k=1.0, c=0.98 * c_max)))
    assert bool(params_unstable(sim, sim.params(k=1.0, c=1.05 * c_max)))
    # linear laws keep their numbers
    assert safe_contact_bounds(ball_sim(law="no_tension")) == lin


def test_fit_bounds_count_the_start_energys_depth_as_the_rollout_does():
    """The fit bounds and the flag they add took a Hunt-Crossley stiffness at the full radius
    whatever the start, so a Hertz ball (1 kg, k 1e6 N/m^1.5, dropped from 1 m: it sinks
    1.4 cm) could not be fitted inside them (k <= 5.2e5) though its rollout runs safely at
    dt 1 ms. Given the rollouts' start state, the bounds count the depth at which the contact
    stores twice its energy, as the rollout's own traced flag does: k_max is where that flag
    turns, and the damping cap holds down to the fit's lowest k. Without a state: the radius."""
    from tuning.problem import FreeLeaves, with_flag
    from tuning.scenes import ball_scene
    sim = dp.compile(ball_scene(mass=1.0, radius=0.1, height=1.0), 1e-3,
                     law=dp.laws.hunt_crossley(1.5))
    start = sim.init_state()
    k_rad, c_rad = safe_contact_bounds(sim)
    k_max, c_max = safe_contact_bounds(sim, state=start)
    assert k_rad < 6e5 and 1.2e6 < k_max < 1.3e6 and c_max == c_rad

    def rollout_flag(k, c):
        traj = sim.rollout(sim.params(k=k, c=c), 4, start, check_stability=False)
        return bool(rollout_unstable(sim, traj, None))
    for k, bad in ((0.99 * k_max, False), (1.02 * k_max, True)):
        assert rollout_flag(k, 10.0) is bad
        assert bool(params_unstable(sim, sim.params(k=k, c=10.0), start)) is bad
    assert bool(params_unstable(sim, sim.params(k=0.99 * k_max, c=10.0)))   # at the radius
    # damping: its depth is the one of the smallest k the box lets the fit reach
    _, c_cap = safe_contact_bounds(sim, state=start, k_min=1e5)
    assert c_cap > 3.0 * c_rad
    assert rollout_flag(1e5, 0.99 * c_cap) is False and rollout_flag(1e5, 1.02 * c_cap) is True
    params0 = sim.params(k=3e5, c=1e4)
    free = ["contact.default.k", "contact.default.c"]
    box = {"contact.default.k": (1e5, 1e7), "contact.default.c": (1e2, 1e6)}
    leaves = FreeLeaves.build(params0, free, box, sim, state=start)
    assert leaves.hi.tolist() == pytest.approx([k_max, c_cap], rel=1e-12)
    assert FreeLeaves.build(params0, free, box, sim).hi.tolist() == pytest.approx(
        [k_rad, c_rad], rel=1e-12)
    from tuning.batch_fit import BatchFitter
    rows = BatchFitter(lambda p: {"k": p.contact["default"].k}, params0, free=free,
                       bounds=box, sim=sim, state=start)
    assert rows.hi.tolist() == pytest.approx([k_max, c_cap], rel=1e-12)
    assert not bool(rows.metrics_fn(sim.params(k=1e6, c=1e4))["unstable"])
    flagged = with_flag(lambda p: {"k": p.contact["default"].k}, sim, start)
    assert not bool(flagged(sim.params(k=1e6, c=1e4))["unstable"])
    assert bool(with_flag(lambda p: {}, sim)(sim.params(k=1e6, c=1e4))["unstable"])


def test_implicit_float32_bounds_stop_at_the_precision_limit():
    """implicit_euler had (inf, inf) contact bounds, so a float32 fit walked into stiffnesses
    its dtype cannot resolve (wrong gradients, no flag). The k bound is now the precision
    limit of diffpen.stability (1% inside): just inside it the parameters are clear, just
    past it flagged (a sweep marks such points unstable). float64 keeps (inf, inf)."""
    from tuning.scenes import ball_scene
    scene = ball_scene(mass=1e-4, height=0.3)
    sim = dp.compile(scene, 1e-3, integrator="implicit_euler", dtype=jnp.float32)
    k_max, c_max = safe_contact_bounds(sim)
    eps = float(jnp.finfo(jnp.float32).eps)
    # the ball's static deflection m g / k at half its resolution of positions, eps x 0.1 m
    assert k_max == pytest.approx(0.99 * 1e-4 * 9.81 / (0.5 * eps * 0.1), rel=1e-9)
    assert math.isinf(c_max)
    assert not bool(params_unstable(sim, sim.params(k=0.98 * k_max, c=0.1)))
    assert bool(params_unstable(sim, sim.params(k=1.02 * k_max, c=0.1)))
    sim64 = dp.compile(scene, 1e-3, integrator="implicit_euler", dtype=jnp.float64)
    assert safe_contact_bounds(sim64) == (math.inf, math.inf)
