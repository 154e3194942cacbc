"""Core simulator: closed-form physics, gradients, bad input (transforms and left-out terms:
test_core_transforms.py)."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen import physical

G = 9.81


# --------------------------------------------------------------------------- fixtures
def drop_scene(gravity=(0.0, 0.0, -G), z0=1.0, vz=0.0, r=0.1, m=1.0):
    scene = dp.Scene(gravity=gravity)
    scene.add_sphere(radius=r, mass=m, position=(0.0, 0.0, z0), velocity=(0.0, 0.0, vz))
    scene.add_plane()
    return scene


@pytest.fixture(scope="module")
def spring_sim():
    """A 2 kg particle on a world spring along x, no gravity, initial stretch 0.1 m."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    p = scene.add_particle(mass=2.0, position=(1.1, 0.0, 0.0))
    scene.add_spring(p, (0.0, 0.0, 0.0), k=50.0, c=0.0, rest_length=1.0)
    return dp.compile(scene, dt=1e-3)


# --------------------------------------------------------------------------- closed forms
def test_free_fall_matches_closed_form():
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_particle(mass=1.0, position=(0.0, 0.0, 10.0), velocity=(1.0, 0.0, 2.0))
    h = 1e-3
    sim = dp.compile(scene, dt=h)
    assert sim.terms == ()               # no contact, no springs: only gravity
    traj = sim.rollout(sim.params(), steps=1000)
    n = np.arange(1, 1001)
    t = n * h
    position = np.asarray(traj.position)
    z = position[:, 0, 2]
    # Symplectic Euler is exact for the discrete recursion ...
    np.testing.assert_allclose(z, 10.0 + 2.0 * t - G * h * h * n * (n + 1) / 2, rtol=1e-12)
    # ... and first-order close to the continuous closed form (gap g h t / 2).
    cont = 10.0 + 2.0 * t - 0.5 * G * t * t
    assert np.max(np.abs(z - cont)) <= 0.5 * G * h * t[-1] * (1 + 1e-9)
    np.testing.assert_allclose(position[:, 0, 0], 1.0 * t, rtol=1e-12)
    np.testing.assert_allclose(traj.time, t, rtol=1e-12)


def _crossings(t, x):
    """Times of upward zero crossings of x(t), linearly interpolated."""
    i = np.nonzero((x[:-1] < 0) & (x[1:] >= 0))[0]
    return t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])


def test_undamped_spring_period_and_bounded_energy(spring_sim):
    traj = spring_sim.rollout(spring_sim.params(), steps=4000)
    x = np.asarray(traj.position)[:, 0, 0] - 1.0
    v = np.asarray(traj.velocity)[:, 0, 0]
    t = np.asarray(traj.time)
    w0 = math.sqrt(50.0 / 2.0)
    period = np.diff(_crossings(t, x)).mean()
    # symplectic Euler raises the frequency by ~(1 + (w h)^2 / 24): far below 1e-4 here
    assert period == pytest.approx(2 * math.pi / w0, rel=1e-4)
    energy = 0.5 * 2.0 * v ** 2 + 0.5 * 50.0 * x ** 2
    e0 = 0.5 * 50.0 * 0.1 ** 2
    # bounded (no drift): symplectic Euler's energy oscillates with amplitude ~ w h / 2
    assert np.max(np.abs(energy / e0 - 1.0)) < w0 * 1e-3


def test_damped_spring_decay_matches_closed_form(spring_sim):
    m, k, c = 2.0, 50.0, 1.0
    traj = spring_sim.rollout(spring_sim.params(spring_c=c), steps=3000)
    t = np.asarray(traj.time)
    x = np.asarray(traj.position)[:, 0, 0] - 1.0
    w0 = math.sqrt(k / m)
    z = c / (2 * math.sqrt(k * m))
    wd = w0 * math.sqrt(1 - z * z)
    exact = 0.1 * np.exp(-z * w0 * t) * (np.cos(wd * t) + z * w0 / wd * np.sin(wd * t))
    assert np.max(np.abs(x - exact)) < 1e-3 * 0.1 * 5   # first order in h: w h = 5e-3


@pytest.fixture(scope="module")
def impact_sims():
    """Ball 1 m/s onto the plane, no gravity, exact ramp (width 0), dt = 1e-5, per law."""
    out = {}
    for law in ("linear", "no_tension", "hunt_crossley"):
        scene = drop_scene(gravity=(0.0, 0.0, 0.0), z0=0.1 + 1e-4, vz=-1.0)
        out[law] = dp.compile(scene, dt=1e-5, law=law, smoothing=0.0)
    return out


def _restitution(sim, k, cs, steps=5000):
    run = jax.vmap(lambda c: sim.rollout(sim.params(k=k, c=c), steps=steps,
                                         save_every=steps).velocity[-1, 0, 2])
    return np.asarray(run(jnp.asarray(cs))) / 1.0


@pytest.mark.parametrize("law", ["linear", "no_tension"])
def test_restitution_matches_closed_form(impact_sims, law):
    k, m = 1e4, 1.0
    zetas = np.array([0.1, 0.3, 0.5])
    cs = 2 * zetas * math.sqrt(k * m)
    e = _restitution(impact_sims[law], k, cs)
    expected = np.asarray(physical.restitution(k, cs, m, law))
    # the table of docs/physics-notes.md section 2
    table = {"linear": [0.729, 0.372, 0.163], "no_tension": [0.744, 0.451, 0.298]}[law]
    np.testing.assert_allclose(expected, table, atol=1.5e-3)
    np.testing.assert_allclose(e, expected, rtol=5e-3)


def test_hunt_crossley_restitution_depends_on_a_vin_only(impact_sims):
    k = 1e4
    a = np.array([0.1, 0.3, 1.0])            # s/m; v_in = 1 m/s
    e = _restitution(impact_sims["hunt_crossley"], k, a * k)
    expected = np.asarray(physical.hunt_crossley_restitution(a * 1.0))
    np.testing.assert_allclose(e, expected, rtol=5e-3)
    # e depends on a v_in only: 10x k with the same a gives the same e
    e10 = _restitution(impact_sims["hunt_crossley"], 10 * k, a * 10 * k)
    np.testing.assert_allclose(e10, expected, rtol=5e-3)
    np.testing.assert_allclose(physical.hunt_crossley_a_from_restitution(expected, 1.0), a,
                               rtol=1e-6)


def test_contact_time_matches_closed_form(impact_sims):
    k, m, zeta = 1e4, 1.0, 0.3
    c = 2 * zeta * math.sqrt(k * m)
    sim = impact_sims["linear"]
    traj = sim.rollout(sim.params(k=k, c=c), steps=5000)
    gap = np.asarray(traj.position)[:, 0, 2] - 0.1
    t = np.asarray(traj.time)
    inside = np.nonzero(gap < 0)[0]
    i0, i1 = inside[0], inside[-1]
    t_in = t[i0 - 1] - gap[i0 - 1] * (t[i0] - t[i0 - 1]) / (gap[i0] - gap[i0 - 1])
    t_out = t[i1] - gap[i1] * (t[i1 + 1] - t[i1]) / (gap[i1 + 1] - gap[i1])
    assert t_out - t_in == pytest.approx(float(physical.contact_time(k, c, m)), rel=2e-3)


def test_resting_penetration_is_mg_over_k(ball_sim):
    k, m = 1e4, 1.0
    traj = ball_sim.rollout(ball_sim.params(k=k, c=2 * math.sqrt(k * m)), steps=3000,
                            save_every=3000)
    z = float(np.asarray(traj.position)[-1, 0, 2])
    assert 0.1 - z == pytest.approx(m * G / k, rel=1e-6)


# --------------------------------------------------------------------------- physical forms
@pytest.mark.parametrize("law", ["linear", "no_tension"])
def test_physical_parameterisation_round_trip(law):
    m = 0.7
    e, tc = jnp.array([0.2, 0.5, 0.9]), jnp.array([0.01, 0.02, 0.005])
    f = lambda ee: physical.kc_from_restitution(ee, 0.01, m, law)[1]

    @jax.jit
    def conversions(e, tc):     # one compiled program for all the conversions below
        k, c = physical.kc_from_restitution(e, tc, m, law)
        back = physical.restitution(k, c, m, law), physical.contact_time(k, c, m, law)
        return back, (jax.grad(f)(0.5), f(0.5 + 1e-6), f(0.5 - 1e-6))
    (back_e, back_tc), (g, f_up, f_down) = conversions(e, tc)
    np.testing.assert_allclose(back_e, e, rtol=1e-9)
    np.testing.assert_allclose(back_tc, tc, rtol=1e-9)
    # differentiable: d k / d e vs central differences
    fd = (f_up - f_down) / 2e-6
    assert float(g) == pytest.approx(float(fd), rel=1e-6)


def test_overdamped_no_tension_still_lets_go(impact_sims):
    """The no-tension closed forms returned e = 0 for zeta >= 1 (and NaN from
    kc_from_restitution below e = exp(-2)); the contact ends where its force reaches zero,
    so it always lets go: e(1) = exp(-2), continued by arccosh above. Checked against the
    simulator (dt 1e-5, no gravity) at zeta 1 and 1.5, and round-tripped below exp(-2)."""
    k, m = 1e4, 1.0
    zetas = np.array([1.0, 1.5])
    cs = 2 * zetas * math.sqrt(k * m)
    e_lo, tc = jnp.array([0.1, 0.02, 0.135, 0.1354]), jnp.array([0.01, 0.02, 0.005, 0.01])

    def e_nt(c):
        return physical.restitution(k, c, m, "no_tension")

    @jax.jit
    def closed_forms(cs, e_lo, tc):     # one compiled program for the closed forms below
        kk, cc = physical.kc_from_restitution(e_lo, tc, m, "no_tension")
        back = (physical.restitution(kk, cc, m, "no_tension"),
                physical.contact_time(kk, cc, m, "no_tension"))
        smooth = jax.grad(e_nt)(200.0), e_nt(200.0 + 1e-4), e_nt(200.0 - 1e-4)
        linear = physical.contact_time(k, 300.0, m), physical.restitution(k, 300.0, m)
        return e_nt(cs), back, smooth, linear
    e, (back_e, back_tc), (g, e_up, e_down), (t_lin, e_lin) = jax.tree_util.tree_map(
        np.asarray, closed_forms(cs, e_lo, tc))
    assert e[0] == pytest.approx(math.exp(-2.0), rel=1e-12)
    np.testing.assert_allclose(_restitution(impact_sims["no_tension"], k, cs), e, rtol=5e-3)
    np.testing.assert_allclose(back_e, e_lo, rtol=1e-9)
    np.testing.assert_allclose(back_tc, tc, rtol=1e-9)
    # smooth through zeta = 1 (the series there meets both closed forms)
    fd = (e_up - e_down) / 2e-4
    assert float(g) == pytest.approx(float(fd), rel=1e-6)
    # the linear law's overdamped contact never lets go
    assert float(t_lin) == math.inf
    assert float(e_lin) == 0.0


@pytest.mark.parametrize("call, words", [
    (lambda: physical.kc_from_restitution(0.0, 0.01, 1.0), "restitution e must be in (0, 1]"),
    (lambda: physical.kc_from_restitution(1.2, 0.01, 1.0), "got 1.2"),
    (lambda: physical.kc_from_restitution(0.5, 0.0, 1.0), "contact time t_c"),
    (lambda: physical.kc_from_restitution(0.5, 0.01, -1.0), "mass (kg)"),
    (lambda: physical.kc_from_time_constant(0.01, 0.0, 1.0), "damping ratio zeta"),
    (lambda: physical.hunt_crossley_a_from_restitution(-0.1, 1.0), "restitution e"),
    # regressions: these two took anything (nan, a negative ratio, inf)
    (lambda: physical.natural_frequency(-1.0, 1.0), "stiffness k (N/m) must be a finite"),
    (lambda: physical.natural_frequency(float("nan"), 1.0), "stiffness k (N/m)"),
    (lambda: physical.natural_frequency(1e4, 0.0), "mass (kg) must be a finite number > 0"),
    (lambda: physical.damping_ratio(1e4, -5.0, 1.0), "damping c (N s/m) must be"),
    (lambda: physical.damping_ratio(1e4, 5.0, 0.0), "mass (kg)"),
])
def test_physical_conversions_refuse_out_of_range_values(call, words):
    """Out-of-range inputs gave NaN, inf, a negative c or a bare ZeroDivisionError."""
    with pytest.raises(ValueError) as e:
        call()
    assert words in str(e.value)


def test_elastic_limits_of_the_conversions():
    k, c = physical.kc_from_restitution(1.0, 0.01, 1.0)
    assert float(c) == 0.0 and float(k) == pytest.approx((math.pi / 0.01) ** 2)
    assert float(physical.hunt_crossley_a_from_restitution(1.0, 2.0)) == 0.0
    # its slope there is -3 / (2 v_in), not 0 (a fit starting at e = 1 got no gradient)
    g = jax.jit(jax.grad(lambda e: physical.hunt_crossley_a_from_restitution(e, 2.0)))
    assert float(g(1.0)) == pytest.approx(-0.75, rel=1e-9)
    # e -> a -> e, one compiled program for every e
    round_trip = jax.jit(lambda e: physical.hunt_crossley_restitution(
        physical.hunt_crossley_a_from_restitution(e, 2.0) * 2.0))
    for e in (0.9989, 0.9991, 0.99999):        # both sides of the series' switch
        assert float(round_trip(e)) == pytest.approx(e, rel=1e-10), e


def test_time_constant_round_trip():
    k, c = physical.kc_from_time_constant(0.02, 0.8, 1.5)
    tau, zeta = physical.time_constant(k, c, 1.5)
    assert float(tau) == pytest.approx(0.02, rel=1e-12)
    assert float(zeta) == pytest.approx(0.8, rel=1e-12)
    assert float(c) == pytest.approx(2 * 1.5 / 0.02)


def test_simulated_restitution_from_physical_parameters(impact_sims):
    k, c = physical.kc_from_restitution(0.5, 0.01, 1.0)
    assert _restitution(impact_sims["linear"], float(k), [float(c)])[0] == pytest.approx(
        0.5, rel=5e-3)


# --------------------------------------------------------------------------- gradients
def _central(f, x, rel):
    h = rel * x
    return (f(x + h) - f(x - h)) / (2 * h)


@pytest.fixture(scope="module")
def smooth_ball():
    """Ball dropped from 0.5 m, dt = 1e-4, smoothing 1e-3 m (C1 in k and c)."""
    return dp.compile(drop_scene(z0=0.5), dt=1e-4, smoothing=1e-3)


def _apex_after_first_bounce(sim, k, c):
    """The apex and, beside it, the final (z, v)."""
    # 0.4 m of fall takes 0.286 s; the contact ~0.03 s; then flight: at t = 0.4 s the ball
    # is rising, and the exact free-flight apex is z + v^2 / (2 g).
    traj = sim.rollout(sim.params(k=k, c=c), steps=4000, save_every=4000)
    z, v = traj.position[-1, 0, 2], traj.velocity[-1, 0, 2]
    return z + v * v / (2 * G), (z, v)


def test_gradient_of_apex_matches_finite_differences(smooth_ball):
    k, c = 1e4, 20.0
    # one compiled program: its values serve the central differences too
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda k, c: _apex_after_first_bounce(smooth_ball, k, c), (0, 1), has_aux=True))
    (_, (z, v)), (gk, gc) = value_and_grad(k, c)
    assert float(v) > 0.0 and float(z) > 0.1

    def value(k, c):
        return float(value_and_grad(k, c)[0][0])
    fk = _central(lambda x: value(x, c), k, 1e-5)
    fc = _central(lambda x: value(k, x), c, 1e-5)
    assert float(gk) == pytest.approx(float(fk), rel=1e-4)
    assert float(gc) == pytest.approx(float(fc), rel=1e-4)
    assert float(gc) < 0.0          # more damping, lower bounce


def test_gradient_of_final_state_matches_finite_differences(smooth_ball):
    def final_z(k, c):
        return smooth_ball.rollout(smooth_ball.params(k=k, c=c), steps=3000,
                                   save_every=3000).position[-1, 0, 2]
    k, c = 1e4, 50.0
    # one compiled program: its values serve the central differences too
    value_and_grad = jax.jit(jax.value_and_grad(final_z, (0, 1)))
    gk, gc = value_and_grad(k, c)[1]

    def value(k, c):
        return float(value_and_grad(k, c)[0])
    assert float(gk) == pytest.approx(_central(lambda x: value(x, c), k, 1e-5), rel=1e-4)
    assert float(gc) == pytest.approx(_central(lambda x: value(k, x), c, 1e-5), rel=1e-4)


def test_spring_gradients_match_finite_differences(spring_sim):
    def final_x(k, c):
        p = spring_sim.params(spring_k=k, spring_c=c)
        return spring_sim.rollout(p, steps=500, save_every=500).position[-1, 0, 0]
    # one compiled program: its values serve the central differences too
    value_and_grad = jax.jit(jax.value_and_grad(final_x, (0, 1)))
    gk, gc = value_and_grad(50.0, 1.0)[1]

    def value(k, c):
        return float(value_and_grad(k, c)[0])
    assert float(gk) == pytest.approx(_central(lambda x: value(x, 1.0), 50.0, 1e-6), rel=1e-6)
    assert float(gc) == pytest.approx(_central(lambda x: value(50.0, x), 1.0, 1e-6), rel=1e-6)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("build, match", [
    (lambda s: s.add_sphere(radius=0.1, mass=-1.0, position=(0, 0, 1)), "mass"),
    (lambda s: s.add_sphere(radius=0.0, mass=1.0, position=(0, 0, 1)), "radius"),
    (lambda s: s.add_sphere(radius=0.1, mass=1.0, position=(0, float("nan"), 1)), "finite"),
    (lambda s: s.add_particle(mass=1.0, position=(0, 0)), "3 numbers"),
    (lambda s: s.add_particle(mass=float("inf"), position=(0, 0, 0)), "finite"),
    (lambda s: s.add_spring(0, 5, k=1.0), "names body 5"),
    (lambda s: s.add_spring(0, 0, k=1.0), "itself"),
    (lambda s: s.add_spring(0, (1, 1, 1)), "give k="),
    (lambda s: s.add_spring(0, (1, 1, 1), k=-3.0), "non-negative"),
    (lambda s: s.add_plane(normal=(0, 0, 0)), "non-zero"),
    (lambda s: s.add_fixed_sphere((0, 0, 0.5), 0.6), "inside fixed sphere"),
    (lambda s: s.add_sphere(0.1, 1.0, (0, 0, 0), material="rubber"), "unknown material"),
])
def test_bad_scene_input_raises_clear_error(build, match):
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.5))
    with pytest.raises(dp.SceneError, match=match):
        build(scene)


@pytest.mark.parametrize("kwargs, match", [
    (dict(dt=0.0), "dt must be a positive"),
    (dict(dt=-1e-3), "dt must be a positive"),
    (dict(dt=float("nan")), "dt must be a positive"),
    (dict(dt=1e-3, integrator="magic"), "unknown integrator"),
    (dict(dt=1e-3, law="sticky"), "unknown contact law"),
    (dict(dt=1e-3, smoothing=-1.0), "smoothing width"),
])
def test_bad_compile_input_raises_clear_error(kwargs, match):
    with pytest.raises(dp.SceneError, match=match):
        dp.compile(drop_scene(), **kwargs)


def test_bad_params_raise_clear_error(ball_sim):
    with pytest.raises(dp.SceneError, match="must be >= 0"):
        ball_sim.params(k=-1.0, c=1.0)
    with pytest.raises(dp.SceneError, match="finite"):
        ball_sim.params(k=float("nan"), c=1.0)
    with pytest.raises(dp.SceneError, match="has no k"):
        ball_sim.params()
    with pytest.raises(dp.SceneError, match="steps must be"):
        ball_sim.rollout(ball_sim.params(k=1.0, c=1.0), steps=0)
    with pytest.raises(dp.SceneError, match="save_every"):
        ball_sim.rollout(ball_sim.params(k=1.0, c=1.0), steps=10, save_every=3)


def test_empty_scene_is_rejected():
    with pytest.raises(dp.SceneError, match="no bodies"):
        dp.compile(dp.Scene(), dt=1e-3)


def test_non_finite_rollout_is_reported_not_returned():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_particle(mass=1.0, position=(0.0, 0.0, 0.0))
    p = scene.add_particle(mass=1.0, position=(1.1, 0.0, 0.0))
    scene.add_spring(p, (2.0, 0.0, 0.0), k=1e9, rest_length=1.0)
    sim = dp.compile(scene, dt=1e-2)       # w h = 316: far past the limit of 2
    with pytest.raises(dp.NonFiniteError, match="body 1") as info:
        sim.rollout(sim.params(), steps=400, check_stability=False)
    assert 0 < info.value.step < 400 and info.value.body == 1
    # observed output only: the same check, without a step to name
    with pytest.raises(dp.NonFiniteError, match="observed state became NaN/inf"):
        sim.rollout(sim.params(), steps=400, check_stability=False, save_every=100,
                    observe=_first_x)
    # the check computed on the host (no flag from the rollout's program) says the same
    traj = sim.rollout(sim.params(), steps=400, check_stability=False, check_finite=False)
    with pytest.raises(dp.NonFiniteError, match="body 1"):
        dp.checks.check_finite_trajectory(traj, 1, sim.dt)


def _first_x(state):
    return state.position[:, 0]


def test_a_checked_rollout_compiles_one_program(caplog):
    """The finite check's flag comes out of the rollout's own program: a first rollout
    compiles that program and nothing else (a separate jitted check compiled once more per
    trajectory shape, ~110 programs in the test suite)."""
    sim = dp.compile(drop_scene(z0=0.5), 1e-3)
    p = sim.params(k=1e4, c=20.0)
    for kw in ({}, {"save_every": 10}, {"save_every": 10, "observe": _first_x}):
        caplog.clear()
        with jax.log_compiles(), caplog.at_level("WARNING"):
            sim.rollout(p, 30, **kw)
        compiled = [r.getMessage().split(" with ")[0] for r in caplog.records
                    if r.getMessage().startswith("Compiling ")]
        assert compiled == ["Compiling jit(_rollout_impl)"], (kw, compiled)


def test_checkpointed_rollout_gives_the_same_values_and_gradients(smooth_ball):
    def loss(k, c, ck):
        traj = smooth_ball.rollout(smooth_ball.params(k=k, c=c), steps=400, save_every=4,
                                   checkpoint=ck)
        return jnp.sum(traj.position[:, 0, 2] ** 2)
    value_and_grad = jax.jit(jax.value_and_grad(loss, (0, 1)), static_argnums=2)
    plain = value_and_grad(1e4, 20.0, None)
    ckpt = value_and_grad(1e4, 20.0, 20)
    np.testing.assert_allclose(ckpt[0], plain[0], rtol=1e-12)
    np.testing.assert_allclose(ckpt[1], plain[1], rtol=1e-9)
    with pytest.raises(dp.SceneError, match="checkpoint"):
        smooth_ball.rollout(smooth_ball.params(k=1e4, c=1.0), steps=400, checkpoint=30)


def test_banded_springs_match_direct_sum():
    """Lattice springs go through dense index bands; forces equal a direct per-spring sum."""
    from diffpen.builders import add_cloth
    from diffpen.terms import spring_bands
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    nodes = add_cloth(scene, 6, 5, 0.1, mass=3.0, structural=(100.0, 0.5), shear=(50.0, 0.2),
                      bend=(10.0, 0.1), pinned=[(0, 0)], collide=False)
    extra = scene.add_particle(0.2, (0.3, 0.7, 0.1))
    scene.add_spring(extra, int(nodes[2, 3]), k=30.0, c=0.3, group="odd")  # generic path
    sim = dp.compile(scene, dt=1e-3)
    springs = [s for s in scene.springs if s.b is not None]
    ia = np.array([s.a for s in springs])
    ib = np.array([s.b for s in springs])
    bands, rest = spring_bands(ia, ib)
    assert len(bands) >= 4 and 0 < len(rest) < len(springs) // 4
    rng = np.random.default_rng(1)
    state = sim.init_state()
    x = np.asarray(state.position) + 0.02 * rng.normal(size=state.position.shape)
    v = rng.normal(size=state.position.shape)
    params = sim.params()
    f, _ = sim.forces(params, state._replace(position=jnp.asarray(x), velocity=jnp.asarray(v)))
    expected = np.zeros_like(x)
    for s in springs:
        k, c = (float(params.springs[s.group].k), float(params.springs[s.group].c))
        d = x[s.a] - x[s.b]
        L = np.linalg.norm(d)
        u = d / L
        fs = (-k * (L - s.rest_length) - c * u @ (v[s.a] - v[s.b])) * u
        expected[s.a] += fs
        expected[s.b] -= fs
    np.testing.assert_allclose(np.asarray(f), expected, rtol=1e-11, atol=1e-11)


def _height(s):
    return s.position[:, 2]


def test_observe_saves_only_what_is_asked(ball_sim):
    p = ball_sim.params(k=1e4, c=20.0)
    full = ball_sim.rollout(p, steps=200, save_every=4)
    obs = ball_sim.rollout(p, steps=200, save_every=4, observe=_height)
    assert obs.position is None and obs.velocity is None
    np.testing.assert_array_equal(obs.observed, full.position[:, :, 2])
    np.testing.assert_array_equal(obs.time, full.time)

    def loss(k, observe):
        traj = ball_sim.rollout(ball_sim.params(k=k, c=20.0), steps=200, observe=observe)
        z = traj.position[:, :, 2] if observe is None else traj.observed
        return jnp.sum(z ** 2)
    grad = jax.jit(jax.grad(loss), static_argnums=1)
    np.testing.assert_allclose(grad(1e4, _height), grad(1e4, None), rtol=1e-12)
    with pytest.raises(ValueError, match="observe"):
        obs.final


def test_simulator_is_frozen_and_forces_compile_once(ball_sim, caplog):
    """A Simulator holds pure jitted functions: nothing can be reassigned on it, and
    ``forces`` is one compiled program reused for new parameter values (unjitted it was
    dispatched op by op: seconds per first call)."""
    with pytest.raises(AttributeError, match="frozen"):
        ball_sim.dt = 2e-3
    state = ball_sim.init_state()
    ball_sim.forces(ball_sim.params(k=1e4, c=1.0), state)      # compiled here at most
    pressed = state._replace(position=state.position - 0.95)      # 5 cm into the ground
    params = ball_sim.params(k=2e4, c=3.0)
    caplog.clear()
    with jax.log_compiles(), caplog.at_level("WARNING"):
        f, _ = ball_sim.forces(params, pressed)
    assert not [r for r in caplog.records if "Compiling" in r.getMessage()]
    np.testing.assert_allclose(np.asarray(f)[0, 2], 2e4 * 0.05, rtol=1e-2)


def test_editing_a_scene_after_compiling_does_not_reach_the_simulator():
    """Regression: ``Simulator.scene`` was the caller's Scene, so a sphere added after
    compiling gave ``sim.init_state()`` two bodies against the step's one, and a rollout from
    that state ran the new sphere with the first one's mass and radius (through the plane).
    The simulator keeps a snapshot: its start state, materials and checks are the compiled
    scene's; the edited scene compiles into a simulator of its own."""
    scene = drop_scene(z0=0.5)
    sim = dp.compile(scene, 1e-3)
    scene.add_sphere(radius=0.2, mass=3.0, position=(1.0, 0.0, 0.3))
    scene.materials["default"].k = 123.0
    assert sim.scene is not scene and len(sim.scene.bodies) == 1
    assert sim.init_state().position.shape == (1, 3) == sim.rollout(
        sim.params(k=1e4, c=20.0), 5, state=sim.init_state()).position.shape[1:]
    assert sim.scene.materials["default"].k != 123.0
    with pytest.raises(dp.SceneError):
        sim.rollout(sim.params(k=1e4, c=20.0), 5,
                    state=dp.compile(scene, 1e-3).init_state())
    # the snapshot's overlap index is its own: adding to the edited scene leaves it alone
    assert {i for ids in sim.scene._overlap.cells.values() for i in ids} == {0}
    # and the start state is the compiled one's even where the snapshot itself is edited
    sim.scene.add_sphere(radius=0.2, mass=3.0, position=(1.0, 0.0, 0.3))
    assert sim.init_state().position.shape == (1, 3)
    # each call its own arrays: a state donated to a jitted function (deleted) left the
    # simulator's own start state deleted with it
    donate = jax.jit(lambda s: s.position + 1.0, donate_argnums=0)
    donate(sim.init_state())
    assert sim.rollout(sim.params(k=1e4, c=20.0), 5).position.shape == (5, 1, 3)
    assert float(sim.init_state().position[0, 2]) == 0.5


def test_an_integrator_record_steps_like_its_name():
    """Passing the built-in record INTEGRATORS["semi_implicit_euler"] instead of its name
    dropped the velocity lag of the centred laws (a ball 7 mm apart)."""
    from diffpen import integrators
    law = dp.laws.linear(centred=True)
    by_name = dp.compile(drop_scene(z0=0.5), 1e-3, law=law)
    by_record = dp.compile(drop_scene(z0=0.5), 1e-3, law=law,
                           integrator=integrators.INTEGRATORS["semi_implicit_euler"])
    a = by_name.rollout(by_name.params(k=1e4, c=20.0), 800, save_every=800).position
    b = by_record.rollout(by_record.params(k=1e4, c=20.0), 800, save_every=800).position
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_left_out_dict_fields_are_new_dicts_per_instance():
    """Regression: ``State.aux``, ``Trajectory.aux`` and ``Params.extra`` defaulted to one
    shared ``{}``, so writing into one state's aux changed every later state's default. Each
    now gets its own; a field given (None included, as in a vmap axes spec) is kept."""
    z = np.zeros((1, 3))
    first = dp.State(0.0, z, z)
    first.aux["mark"] = 1.0
    assert dp.State(0.0, z, z).aux == {}
    assert dp.State(0.0, z, z, aux=None).aux is None
    traj = dp.Trajectory(np.zeros(1), z[None], z[None])
    traj.aux["mark"] = 1.0
    assert dp.Trajectory(np.zeros(1), z[None], z[None]).aux == {}
    params = dp.Params({}, {})
    params.extra["mark"] = 1.0
    assert dp.Params({}, {}).extra == {} and dp.Params({}, {}, None).extra is None
    leaves, tree = jax.tree_util.tree_flatten(first)
    assert jax.tree_util.tree_unflatten(tree, leaves).aux == {"mark": 1.0}
    import inspect                            # help() shows the fields and their defaults
    assert str(inspect.signature(dp.Params)) == "(contact, springs, extra={})"
