"""Stable time steps: closed forms of physics-notes.md section 4, the amplification matrices
against the JAX steps, the limit seen empirically, the network bound, StabilityError and
substeps="auto"."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen import integrators, stability
from diffpen.state import State

EXPLICIT = ["semi_implicit_euler", "verlet", "rk4"]


def test_closed_form_limits():
    k, m, c = 1e4, 2.0, 30.0
    K, C = k / m, c / m
    # symplectic Euler: k h^2 + 2 c h = 4 m at the limit
    h = stability.mode_stable_dt("semi_implicit_euler", K, C)
    assert k * h * h + 2 * c * h == pytest.approx(4 * m, rel=1e-12)
    w = math.sqrt(K)
    assert stability.mode_stable_dt("semi_implicit_euler", K, 0.0) == pytest.approx(2 / w)
    assert stability.mode_stable_dt("verlet", K, 0.0) == pytest.approx(2 / w, rel=1e-8)
    assert stability.mode_stable_dt("rk4", K, 0.0) == pytest.approx(2 * math.sqrt(2) / w,
                                                                    rel=1e-8)
    # pure dashpot, explicit: h < 2 m / c
    assert stability.mode_stable_dt("semi_implicit_euler", 0.0, C) == pytest.approx(2 * m / c)
    assert math.isinf(stability.mode_stable_dt("implicit_euler", K, C))


@pytest.mark.parametrize("integrator", EXPLICIT + ["implicit_euler"])
def test_amplification_matrix_is_the_jax_step(integrator):
    K, C, h = 900.0, 7.0, 3e-3

    def accel(params, state):
        return -K * state.position - C * state.velocity, None
    step = integrators.INTEGRATORS[integrator](accel, h)
    cols = []
    for x, v in ((1.0, 0.0), (0.0, 1.0)):
        s = step(None, State(jnp.zeros(()), jnp.full((1, 3), x), jnp.full((1, 3), v)))
        cols.append([float(s.position[0, 0]), float(s.velocity[0, 0])])
    np.testing.assert_allclose(np.array(cols).T,
                               stability.mode_amplification(integrator, K, C, h), atol=1e-12)


@pytest.mark.parametrize("integrator", EXPLICIT)
def test_limit_is_where_the_spring_blows_up(integrator):
    """2% below the computed limit the damped spring decays; 2% above it grows."""
    k, c, m = 1e4, 10.0, 1.0
    h = stability.mode_stable_dt(integrator, k / m, c / m)
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    p = scene.add_particle(mass=m, position=(0.0, 0.0, 1.01))
    scene.add_spring(p, (0.0, 0.0, 0.0), k=k, c=c, rest_length=1.0)
    amp = {}
    for f in (0.98, 1.02):
        sim = dp.compile(scene, f * h, integrator=integrator)
        traj = sim.rollout(sim.params(), 1500, check_stability=False, check_finite=False)
        amp[f] = float(jnp.max(jnp.abs(traj.position[-100:, 0, 2] - 1.0)))
    assert amp[0.98] < 0.01 and amp[1.02] > 0.1


def _chain(n, k, m, pinned_top=True):
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    prev = scene.add_particle(mass=m, position=(0.0, 0.0, 0.0), pinned=pinned_top)
    for i in range(1, n + 1):
        b = scene.add_particle(mass=m, position=(0.0, 0.0, -0.1 * i))
        scene.add_spring(prev, b, k=k, group="g")
        prev = b
    return scene


def test_network_bound_is_safe_and_tight_for_a_chain():
    n, k, m = 12, 500.0, 0.1
    sim = dp.compile(_chain(n, k, m), 1e-3)
    rep = sim.stability(sim.params())
    # exact highest frequency of the fixed-free chain: eigenvalues of M^-1 K
    Kmat = np.zeros((n, n))
    for i in range(n):
        Kmat[i, i] = 2 * k if i < n - 1 else k
        if i + 1 < n:
            Kmat[i, i + 1] = Kmat[i + 1, i] = -k
    w_true = math.sqrt(np.max(np.linalg.eigvalsh(Kmat / m)))
    assert w_true <= rep.omega_max <= 1.05 * w_true
    assert rep.stable_dt == pytest.approx(2 / rep.omega_max)
    assert rep.margin == pytest.approx(rep.stable_dt / 1e-3)
    assert math.isclose(rep.safe_dt, rep.stable_dt)    # springs only: no contact tightening


@pytest.fixture(scope="module")
def ball_scene():
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0))
    scene.add_plane()
    return scene


def test_stability_error_names_dt_and_substeps(ball_scene):
    sim = dp.compile(ball_scene, 1e-3)
    params = sim.params(k=1e8, c=50.0)
    with pytest.raises(dp.StabilityError, match="substeps=") as info:
        sim.rollout(params, 10)
    err = info.value
    K, C = 1e8, 50.0
    # the safe step: w h <= 0.5 (tighter than linear stability, 2 / w ~ 2e-4 s)
    assert err.stable_dt == pytest.approx(min(stability.SAFE_WH / math.sqrt(K),
                                              stability.mode_stable_dt("semi_implicit_euler",
                                                                       K, C)))
    assert err.substeps == math.floor(1e-3 / err.stable_dt) + 1
    assert f"{err.stable_dt:.3g}" in str(err) and "unstable" in str(err)
    # the advice works: with that many substeps the same run is stable and sane
    fixed = dp.compile(ball_scene, 1e-3, substeps=err.substeps)
    assert fixed.stability(params).stable
    traj = fixed.rollout(params, 1500)
    # at the safe step the rebound energy error stays within (w h)^2 / 4 = 6.25%
    assert np.max(np.asarray(traj.position[:, 0, 2])) - 0.1 <= 0.9 * (1 + 0.0625)
    # one fewer is refused
    with pytest.raises(dp.StabilityError):
        dp.compile(ball_scene, 1e-3, substeps=err.substeps - 1).rollout(params, 10)


def test_auto_substeps_pick_the_smallest_sufficient_count(ball_scene):
    sim = dp.compile(ball_scene, 1e-3, substeps="auto")
    params = sim.params(k=1e8, c=50.0)
    with pytest.raises(dp.SceneError, match="auto"):
        jax.jit(lambda p: sim.rollout(p, 10).position)(params)   # no count picked yet
    traj = sim.rollout(params, 200)
    need = sim.stability(params).substeps_needed
    assert sim._auto_last == need > 1
    assert np.all(np.isfinite(np.asarray(traj.position)))
    # jit-traced params then reuse the picked count
    out = jax.jit(lambda p: sim.rollout(p, 200).position)(params)
    np.testing.assert_allclose(out, traj.position, atol=1e-12)
    # soft contact: one substep
    sim.rollout(sim.params(k=1e4, c=20.0), 10)
    assert sim._auto_last == 1


def test_stable_but_unsafe_step_is_refused_with_its_reason(ball_scene):
    """w h = 1: linearly stable (limit 2) but past the safe step 0.5."""
    sim = dp.compile(ball_scene, 1e-3)
    params = sim.params(k=1e6, c=0.0)
    rep = sim.stability(params)
    assert rep.stable and not rep.safe and rep.safe_dt == pytest.approx(0.5e-3)
    with pytest.raises(dp.StabilityError, match="stable but past its safe step"):
        sim.rollout(params, 10)


def test_implicit_euler_never_raises(ball_scene):
    sim = dp.compile(ball_scene, 1e-2, integrator="implicit_euler")
    rep = sim.stability(sim.params(k=1e9, c=0.0))
    assert rep.stable and math.isinf(rep.stable_dt)
    sim.rollout(sim.params(k=1e9, c=0.0), 10)


def test_sphere_sphere_packed_bound_is_tighter():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    for i in range(4):
        scene.add_sphere(radius=0.1, mass=1.0, position=(0.25 * i, 0.0, 0.0))
    sim = dp.compile(scene, 1e-3)
    rep = sim.stability(sim.params(k=1e4, c=0.0))
    # one head-on contact between equal spheres: w^2 = 2 k / m
    assert rep.omega_max == pytest.approx(math.sqrt(2e4))
    assert rep.packed_dt < rep.stable_dt
    assert "another sphere" in rep.limiting
