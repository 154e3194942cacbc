"""Stable time steps: closed forms of docs/physics-notes.md section 4, the amplification matrices
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
    record = integrators.INTEGRATORS[integrator]
    # the step compiled once (both columns: new values, same shapes), not run op by op
    step = jax.jit(lambda x, v, step=record.make(accel, h): step(None, State(
        jnp.zeros(()), jnp.full((1, 3), x), jnp.full((1, 3), v))))
    cols = []
    for x, v in ((1.0, 0.0), (0.0, 1.0)):
        s = step(x, v)
        cols.append([float(s.position[0, 0]), float(s.velocity[0, 0])])
    if record.explicit:
        amp = stability.mode_amplification(integrator, K, C, h)
    else:       # implicit: the record has no step limit; its analysis is still the step
        amp = integrators.backward_euler_amplification(K, C, h)
        with pytest.raises(dp.SceneError, match="no step limit"):
            stability.mode_amplification(integrator, K, C, h)
    np.testing.assert_allclose(np.array(cols).T, amp, atol=1e-12)
    # the same matrix evaluated with jax.numpy (what the traced stability flag uses)
    fn = record.amplification or integrators.backward_euler_amplification
    # (traced, as the flag evaluates it: one compiled program)
    np.testing.assert_allclose(np.asarray(jax.jit(lambda: fn(K, C, h, xp=jnp))()), amp,
                               rtol=1e-14, atol=0)


def test_backward_euler_has_no_step_limit():
    """The implicit record has no amplification because its radius stays below 1."""
    h = np.geomspace(1e-4, 1e3, 50)
    for K, C in ((1e4, 0.0), (1e8, 10.0), (0.0, 50.0)):
        amp = integrators.backward_euler_amplification(K, C, h)
        radius = np.max(np.abs(np.linalg.eigvals(amp)), axis=-1)
        assert np.all(radius < 1.0 if K > 0.0 else radius <= 1.0 + 1e-12)  # dashpot: x kept
    assert integrators.INTEGRATORS["implicit_euler"].amplification is None


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
        amp[f] = float(np.max(np.abs(np.asarray(traj.position)[-100:, 0, 2] - 1.0)))
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
    # springs only: no contact tightening, SAFE_STABLE of the undamped limit
    assert math.isclose(rep.safe_dt, stability.SAFE_STABLE * rep.stable_dt)


@pytest.mark.parametrize("frac", [0.95, 0.999999])
def test_a_step_near_the_springs_stability_limit_is_refused(frac):
    """Springs had no margin: a particle on an undamped spring released at 1 cm stretch
    reached 7.1 cm at 0.99 of the limit and 70.8 m at 0.999999 (semi-implicit Euler's
    amplitude 1 / sqrt(1 - (w h / 2)^2)), all accepted as safe. Within 10% of the limit
    the rollout is refused; at 0.9 the amplitude stays within its 2.3x."""
    k, m = 100.0, 1.0
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    p = s.add_particle(m, (0.01, 0.0, 0.0))
    s.add_spring(p, (0.0, 0.0, 0.0), k=k, c=0.0, rest_length=0.0)
    limit = 2.0 / math.sqrt(k / m)
    sim = dp.compile(s, frac * limit)
    with pytest.raises(dp.StabilityError, match="within 10% of its stability limit"):
        sim.rollout(sim.params(), 10)
    flag = jax.jit(lambda q: sim.rollout(q, 2).aux["unstable"][-1])(sim.params())
    assert bool(flag)
    ok = dp.compile(s, 0.899 * limit)
    x = np.asarray(ok.rollout(ok.params(), 2000).position)[:, p, 0]
    wh = 0.899 * 2.0
    assert float(np.max(np.abs(x))) <= 0.01 * 1.01 / math.sqrt(1.0 - (wh / 2.0) ** 2)


@pytest.mark.parametrize("frac", [0.95, 0.999])
def test_a_step_near_a_damped_springs_limit_is_refused(frac):
    """SAFE_STABLE held only the undamped limit: a spring of damping ratio 0.25 (k 1e4 N/m,
    c 50 N s/m, 1 kg) has its damped semi-implicit Euler limit (k h^2 + 2 c h = 4 m,
    0.015616 s) below 0.9 of the undamped one, so the safe step was the damped limit itself:
    at 0.999 of it the particle rang at the Nyquist frequency, 1.2 cm after 0.5 s from a 1 cm
    start (physically 4e-8 m), accepted and unflagged. Now held to 0.9 of the damped limit."""
    k, c, m = 1e4, 50.0, 1.0
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    p = s.add_particle(m, (1.01, 0.0, 0.0))
    s.add_spring(p, (0.0, 0.0, 0.0), k=k, c=c, rest_length=1.0)
    limit = (-2.0 * c + math.sqrt(4.0 * c * c + 16.0 * m * k)) / (2.0 * k)
    sim = dp.compile(s, frac * limit)
    rep = sim.stability(sim.params())
    assert rep.stable_dt == pytest.approx(limit)
    assert rep.safe_dt == pytest.approx(stability.SAFE_STABLE * limit)
    with pytest.raises(dp.StabilityError, match="within 10% of its stability limit"):
        sim.rollout(sim.params(), 10)
    flag = jax.jit(lambda q: sim.rollout(q, 2).aux["unstable"][-1])(sim.params())
    assert bool(flag)
    ok = dp.compile(s, stability.SAFE_STABLE * limit)   # at the safe step: accepted, decays
    x = np.asarray(ok.rollout(ok.params(), int(0.5 / ok.dt)).position)[:, p, 0] - 1.0
    assert abs(float(x[-1])) < 1e-6


def test_a_step_equal_to_the_safe_step_is_accepted(ball_sim):
    """The safe step is the largest accepted (c h / m <= 1, w h <= 0.5): a rollout at it was
    refused ("needs c h / m < 1") and the advice asked for one substep more than the rule."""
    params = ball_sim.params(k=1e4, c=2000.0)           # c h / m = 1 at substeps=2
    rep = ball_sim.stability(params)
    assert rep.safe_dt == pytest.approx(5e-4) and rep.substeps_needed == 2
    assert stability.report(ball_sim, params, substeps=2).safe
    ball_sim.rollout(params, 4, substeps=2)
    flag = jax.jit(lambda q: ball_sim.rollout(q, 2, substeps=2).aux["unstable"][-1])(params)
    assert not bool(flag)


def test_a_step_a_rounding_above_the_safe_step_is_accepted_traced_too():
    """dt = 3 x the safe step with 3 substeps lands 2e-16 (relative) above it: the gate
    accepted it (a step equal to the safe step is), but the traced flag, what fits and
    sweeps read, compared strictly and flagged it unstable. The error's advice, rounded up
    to 4 digits ("use dt <= 0.006647 s" for 0.00664694), was refused too."""
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    a = s.add_particle(0.3, (0.0, 0.0, 1.0))
    b = s.add_particle(0.7, (0.0, 0.0, 0.5))
    s.add_spring(a, b, k=1e4, c=0.0, rest_length=0.4)
    base = dp.compile(s, dt=1e-3)
    safe = stability.report(base, base.params()).safe_dt
    sim = dp.compile(s, dt=3 * safe, substeps=3)
    tr = sim.rollout(sim.params(), 5)
    assert not bool(np.asarray(tr.aux["unstable"]).any())
    over = dp.compile(s, dt=1.001 * safe)
    with pytest.raises(dp.StabilityError) as info:
        over.rollout(over.params(), 5)
    advised = float(str(info.value).split("Use dt <= ")[1].split(" s")[0])
    ok = dp.compile(s, dt=advised)
    ok.rollout(ok.params(), 5)


def test_anchored_springs_count_the_tension_gravity_can_hang_on_them():
    """A 1 g, 1 cm link between a world point and a 10 kg weight on anchored springs at rest
    length: loaded, the springs' tension (~98 N) turns the link at ~7700 rad/s, but the bound
    counted the start stretch (0) alone: omega_max 2739 rad/s, and at 0.9 of that safe step
    (5.9e-4 s) the link spun up to 3.75e4 rad/s and tipped 89.5 deg, unflagged. The bound
    now counts twice the weight of the bodies the springs join."""
    a, k = 0.005, 1e3
    sc = dp.Scene(gravity=(0.0, 0.0, -9.81))
    link = sc.add_box((a, a, a), 1e-3, (0.0, 0.0, 0.9 - a), collide=False)
    w = sc.add_sphere(0.03, 10.0, (0.0, 0.0, 0.9 - 2 * a - 0.1), collide=False)
    sc.add_anchored_spring(link, None, anchor_a=(0, 0, a), anchor_b=(0.0, 0.0, 1.0), k=k,
                           c=0.0, group="s")
    sc.add_anchored_spring(link, w, anchor_a=(0, 0, -a), group="s")
    sim = dp.compile(sc, dt=5.9e-4)
    rep = sim.stability(sim.params())
    # the loaded link's turning mode: tension m g on both springs at lever a, I = m_l a^2 / 6
    w_loaded = math.sqrt(2.0 * 10.0 * 9.81 * a / (1e-3 * (2 * a) ** 2 / 6.0))
    assert rep.omega_max >= w_loaded
    with pytest.raises(dp.StabilityError):
        sim.rollout(sim.params(), 10)
    ok = dp.compile(sc, dt=rep.safe_dt)
    # the same springs lying free (hung from nothing) carry no weight: no such rows
    free = dp.Scene(gravity=(0.0, 0.0, -9.81))
    l2 = free.add_box((a, a, a), 1e-3, (0.0, 0.0, 0.9 - a), collide=False)
    w2 = free.add_sphere(0.03, 10.0, (0.0, 0.0, 0.9 - 2 * a - 0.1), collide=False)
    free.add_anchored_spring(l2, w2, anchor_a=(0, 0, -a), k=k, c=0.0, group="s")
    weightless = dp.Scene(gravity=(0.0, 0.0, 0.0))
    l3 = weightless.add_box((a, a, a), 1e-3, (0.0, 0.0, 0.9 - a), collide=False)
    w3 = weightless.add_sphere(0.03, 10.0, (0.0, 0.0, 0.9 - 2 * a - 0.1), collide=False)
    weightless.add_anchored_spring(l3, w3, anchor_a=(0, 0, -a), k=k, c=0.0, group="s")
    rates = [(lambda sim: sim.stability(sim.params()).omega_max)(dp.compile(x, 1e-4))
             for x in (free, weightless)]
    assert rates[0] == pytest.approx(rates[1], rel=1e-12)
    st = ok.state_from(body=link, angular_velocity=(1e-3, 0.0, 0.0), frame="body")
    tr = ok.rollout(ok.params(), int(0.3 / rep.safe_dt), state=st)
    assert float(np.max(np.abs(np.asarray(tr.angular_velocity)[:, link]))) < 0.1


def test_stability_error_names_dt_and_substeps(ball_scene, ball_sim):
    sim = ball_sim
    params = sim.params(k=1e8, c=50.0)
    with pytest.raises(dp.StabilityError, match="substeps=") as info:
        sim.rollout(params, 10)
    err = info.value
    K, C = 1e8, 50.0
    # the safe step: w h <= 0.5 (tighter than linear stability, 2 / w ~ 2e-4 s)
    assert err.stable_dt == pytest.approx(min(
        stability.SAFE_WH / math.sqrt(K),
        stability.SAFE_STABLE * stability.mode_stable_dt("semi_implicit_euler", K, C)))
    # the fewest substeps whose inner step is at most the safe step (equal is accepted)
    assert err.substeps == math.ceil(1e-3 / err.stable_dt * (1.0 - 1e-12))
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


@pytest.fixture(scope="module")
def auto_sim(ball_scene):
    """The quick-start ball at dt = 1e-3 s with ``substeps="auto"`` (shared: its rollout
    programs are compiled once for the tests that run the same steps and substeps)."""
    return dp.compile(ball_scene, 1e-3, substeps="auto")


def test_auto_substeps_pick_the_smallest_sufficient_count(auto_sim):
    sim = auto_sim
    params = sim.params(k=1e8, c=50.0)
    need = sim.stability(params).substeps_needed
    assert need > 1
    traj = sim.rollout(params, 200)
    assert np.all(np.isfinite(np.asarray(traj.position)))
    # the pick is the count needed: the same as giving it, and one fewer is refused
    np.testing.assert_allclose(sim.rollout(params, 200, substeps=need).position,
                               traj.position, rtol=0, atol=0)
    with pytest.raises(dp.StabilityError):
        sim.rollout(params, 10, substeps=need - 1)
    # soft contact: one substep (the plain step)
    soft = sim.params(k=1e4, c=20.0)
    assert sim.stability(soft).substeps_needed == 1
    np.testing.assert_allclose(sim.rollout(soft, 10).position,
                               sim.rollout(soft, 10, substeps=1).position, rtol=0, atol=0)


def test_auto_substeps_under_jit_need_the_count_and_never_reuse_an_earlier_call(auto_sim):
    """Under jit the traced program depends only on its arguments: an earlier concrete call
    picks nothing for it. Without a count "auto" refuses; with one, it runs, and the traced
    flag says whether the count was enough."""
    sim = auto_sim
    params = sim.params(k=1e8, c=50.0)
    need = sim.stability(params).substeps_needed
    sim.rollout(params, 20)                            # a concrete call first ...
    with pytest.raises(dp.SceneError, match="substeps=N"):  # ... is not reused under jit
        jax.jit(lambda p: sim.rollout(p, 20).position)(params)
    run = jax.jit(lambda p, n: sim.rollout(p, 200, substeps=n), static_argnums=1)
    traj = run(params, need)
    np.testing.assert_allclose(traj.position, sim.rollout(params, 200).position, atol=1e-12)
    assert not bool(traj.aux["unstable"][-1])
    assert bool(run(params, need - 1).aux["unstable"][-1])


def test_stable_but_unsafe_step_is_refused_with_its_reason(ball_sim):
    """w h = 1: linearly stable (limit 2) but past the safe step 0.5."""
    sim = ball_sim
    params = sim.params(k=1e6, c=0.0)
    rep = sim.stability(params)
    assert rep.stable and not rep.safe and rep.safe_dt == pytest.approx(0.5e-3)
    with pytest.raises(dp.StabilityError, match="stable but past its safe step"):
        sim.rollout(params, 10)


@pytest.fixture(scope="module")
def implicit_ball(ball_scene):
    """The quick-start ball, implicit Euler at dt = 1e-2 s (shared, never mutated)."""
    return dp.compile(ball_scene, 1e-2, integrator="implicit_euler")


def test_implicit_euler_never_raises(implicit_ball):
    sim = implicit_ball
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


# --------------------------------------------------------------------------- traced flag
CUBE_HALF, CUBE_MASS, CUBE_I = 0.0524, 0.37, 8.1e-4     # the cube-toss cube (data README)


@pytest.fixture(scope="module")
def cube_sim():
    """The issue's case: the tossed cube at an inner step h = 1/1480 s."""
    scene = dp.Scene()
    scene.add_box((CUBE_HALF,) * 3, CUBE_MASS, (0.0, 0.0, 0.145), (0.3, 0.0, -0.5),
                  orientation=(0.96, 0.2, 0.15, 0.1), angular_velocity=(1.0, -2.0, 0.5),
                  inertia=(CUBE_I,) * 3)
    scene.add_plane()
    return dp.compile(scene, 1.0 / 1480.0)


def test_a_bowl_of_planes_counts_its_contacts_pushing_together():
    """A ball resting at the bottom of a bowl of 16 planes tilted 3 degrees feels ~16 k. The
    bound counted one plane contact (w 100 rad/s, true 400): at 0.9 of that step the
    resting ball launched itself with no error. Mutually orthogonal planes (a floor with
    walls) and opposite walls still count as one contact."""
    from diffpen.terms.contact import plane_crowding
    assert plane_crowding([(0, 0, 1)]) == 1.0
    assert plane_crowding([(0, 0, 1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]) \
        == pytest.approx(1.0)
    a = math.radians(30.0)                        # a V groove: 2 cos^2 a
    assert plane_crowding([(math.sin(a), 0, math.cos(a)), (-math.sin(a), 0, math.cos(a))]) \
        == pytest.approx(2.0 * math.cos(a) ** 2)
    n, r, k, tilt = 16, 0.1, 1e4, math.radians(3.0)
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    for i in range(n):
        phi = 2.0 * math.pi * i / n
        s.add_plane(normal=(-math.sin(tilt) * math.cos(phi), -math.sin(tilt) * math.sin(phi),
                            math.cos(tilt)))
    s.add_sphere(r, 1.0, (0.0, 0.0, r / math.cos(tilt) - 9.81 / (n * k)), allow_overlap=True)
    probe = dp.compile(s, 1e-3)
    rep = probe.stability(probe.params(k=k, c=0.0))
    w_true = math.sqrt(n * k * math.cos(tilt) ** 2)
    assert w_true <= rep.omega_max <= 1.01 * w_true
    with pytest.raises(dp.StabilityError):          # 0.9 of the one-contact safe step
        sim = dp.compile(s, 0.9 * 0.5 / 100.0)
        sim.rollout(sim.params(k=k, c=0.0), 10)
    sim = dp.compile(s, 0.9 * rep.safe_dt)
    z = np.asarray(sim.rollout(sim.params(k=k, c=0.0), 1000).position)[:, 0, 2]
    assert float(np.max(z) - np.min(z)) < 1e-4         # it stays at rest


def test_traced_flag_is_raised_under_jit_vmap_and_grad(cube_sim):
    """k = 2e6 N/m at h = 1/1480 s: outside jit rollout raises StabilityError; under jit,
    vmap and grad nothing can be raised, and the rollout's flag is set instead (sticky,
    saved at every step); a safe k leaves it clear."""
    sim = cube_sim
    stiff, soft = sim.params(k=2e6, c=20.0), sim.params(k=2e4, c=20.0)
    assert not sim.stability(stiff).safe and sim.stability(soft).safe
    with pytest.raises(dp.StabilityError):
        sim.rollout(stiff, 40)

    def run(k):
        return sim.rollout(sim.params(k=k, c=20.0), 40, check_finite=False)
    flags = np.asarray(jax.jit(run)(2e6).aux["unstable"])
    assert flags.dtype == bool and flags.shape == (40,) and flags.all()

    # vmap and grad (as batched fits run them, under jit): each candidate keeps its own flag,
    # which comes out with the value; the gradient is computed as usual
    def loss(k):
        traj = run(k)
        return traj.position[-1, 0, 2], traj.aux["unstable"][-1]
    (z, flag), g = jax.jit(jax.vmap(jax.value_and_grad(loss, has_aux=True)))(
        jnp.asarray([2e4, 2e6, 5e4]))
    np.testing.assert_array_equal(np.asarray(flag), [False, True, False])
    assert np.all(np.isfinite(np.asarray(g)))
    # grad of concrete values outside jit still gets the up-front check
    with pytest.raises(dp.StabilityError):
        jax.grad(lambda k: loss(k)[0])(2e6)


def test_flag_is_sticky_across_rollouts(ball_sim):
    sim = ball_sim
    run = jax.jit(lambda k, s: sim.rollout(sim.params(k=k, c=20.0), 10, state=s,
                                           check_finite=False))
    first = run(1e8, sim.init_state())
    assert np.asarray(first.aux["unstable"]).all()
    after = run(1e4, first.final)                        # a safe run does not clear it
    assert np.asarray(after.aux["unstable"]).all()
    assert not np.asarray(run(1e4, sim.init_state()).aux["unstable"]).any()


@pytest.mark.parametrize("integrator", EXPLICIT)
def test_traced_flag_agrees_with_the_up_front_check(integrator, ball_scene):
    """Over stiffnesses across the limit, the traced flag is set exactly where the concrete
    gate refuses (contacts: the safe step; a spring chain: linear stability from the
    integrator's amplification matrix)."""
    ks = np.geomspace(1e3, 1e9, 41)
    for scene, c in ((ball_scene, 30.0), (_chain(4, 1.0, 0.1), 0.5)):
        sim = dp.compile(scene, 1e-3, integrator=integrator)
        if scene is ball_scene:
            params = [sim.params(k=k, c=c) for k in ks]
        else:
            params = [sim.params(spring_k=k, spring_c=c) for k in ks]
        want = np.array([not sim.stability(p).safe for p in params])
        assert want.any() and not want.all()

        def flag(k, sim=sim, chain=scene is not ball_scene):
            p = sim.params(spring_k=k, spring_c=c) if chain else sim.params(k=k, c=c)
            return sim.rollout(p, 1, check_finite=False).aux["unstable"][-1]
        got = np.asarray(jax.jit(jax.vmap(flag))(jnp.asarray(ks)))
        np.testing.assert_array_equal(got, want)


def test_implicit_flag_stays_clear(ball_scene, implicit_ball):
    sim = implicit_ball
    # traced, as a rollout evaluates it (one compiled program each, not op by op)
    assert not bool(jax.jit(lambda p: stability.unsafe(sim.analysis, p))(
        sim.params(k=1e9, c=0.0)))
    explicit = dp.compile(ball_scene, 1e-2)
    assert bool(jax.jit(lambda p: stability.unsafe(explicit.analysis, p))(
        explicit.params(k=1e9, c=0.0)))



def test_traced_implicit_precision_flag_agrees_with_the_up_front_refusal():
    """float32 implicit_euler: the precision refusal (static deflection below the dtype's
    resolution, or (w h)^2 eps past IMPLICIT_PRECISION) ran on concrete values only, so under
    jit / vmap / grad a 0.1 g ball at k = 1e7 N/m ran unflagged (d z / dk -87 against m g / k^2
    ~ 1e-17) and a sweep counted 0 unstable points. The rollout's flag now says the same as
    the up-front check, point by point; float64 keeps it clear."""
    from tuning.scenes import ball_scene
    resting = dp.compile(ball_scene(mass=1e-4, height=0.3), 1e-3, integrator="implicit_euler",
                         dtype=jnp.float32)
    free = dp.Scene()                       # no gravity: only the (w h)^2 eps limit applies
    free.add_sphere(0.01, 1e-4, (0.0, 0.0, 0.05))
    free.add_plane()
    swamped = dp.compile(free, 1e-2, integrator="implicit_euler", dtype=jnp.float32)
    ks = np.array([1e3, 1e5, 3e5, 1e7, 1e9])
    for sim in (resting, swamped):
        want = []
        for k in ks:
            try:                            # the up-front check of an eager rollout
                stability.gate(sim, sim.params(k=float(k), c=0.0))
                want.append(False)
            except dp.StabilityError:
                want.append(True)
        assert any(want) and not all(want)
        flag = jax.jit(jax.vmap(lambda k, sim=sim: sim.rollout(
            sim.params(k=k, c=0.0), 2, save_every=2).aux["unstable"][-1]))
        np.testing.assert_array_equal(np.asarray(flag(jnp.asarray(ks, jnp.float32))), want)
    sim64 = dp.compile(free, 1e-2, integrator="implicit_euler", dtype=jnp.float64)
    assert not bool(jax.jit(lambda p: stability.unsafe(sim64.analysis, p))(
        sim64.params(k=1e9, c=0.0)))


def _box_on_board(law, k, c, friction=0.18):
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("board", k=k, c=c, friction=friction, slip_speed=0.01)
    scene.add_box((0.0524,) * 3, mass=0.37, inertia=(8.1e-4,) * 3, position=(0.0, 0.0, 0.15),
                  orientation=(0.9, 0.3, 0.2, 0.1), material="board")
    scene.add_plane(material="board")
    return dp.compile(scene, dt=1.0 / 148 / 8, law=law)


def test_rigid_contact_bounds_take_the_laws_stiffness_at_the_reference_depth():
    """Box corners were bounded as if every law were linear: a Hunt-Crossley k (N/m^n) and c
    (N s/m^(n+1)) counted as N/m and N s/m (Hertz's damping rows of the cube 37x too large;
    with the board's friction its safe c was 434 instead of 674 N s/m^2.5 at the cube toss's
    step). The corners now take the law's stiffness at the reference depth d (the body's
    radius), as sphere contacts always did, and a box at the new limit stays bounded."""
    k, c = 1e5, 1e3
    lin = _box_on_board("linear", k, c, friction=0.0)
    d = float(lin.analysis.d_ref[0])
    r_lin = lin.stability(lin.params())
    for n in (1.0, 1.5):
        hc = _box_on_board(dp.laws.hunt_crossley(n), k, c, friction=0.0)
        r = stability.report(hc.analysis, hc.params())      # no start energy: the radius
        # the same rows with (n k d^(n-1), c d^n) in place of (k, c)
        assert r.damping_rate == pytest.approx(r_lin.damping_rate * d ** n, rel=1e-9)
        assert r.omega_max ** 2 == pytest.approx(r_lin.omega_max ** 2 * n * d ** (n - 1.0),
                                                 rel=1e-9)
    # Hertz, with friction, at 0.9 of its new safe c (before: refused from 1/36 of it)
    hc = _box_on_board(dp.laws.hunt_crossley(1.5), k, c)
    c_safe = c / stability.report(hc.analysis, hc.params()).safe_margin
    sim = _box_on_board(dp.laws.hunt_crossley(1.5), k, 0.9 * c_safe)
    assert stability.report(sim.analysis, sim.params()).safe
    traj = sim.rollout(sim.params(), 1500)               # 1.27 s: lands, bounces, rocks
    z = np.asarray(traj.position[:, 0, 2])
    speed = np.abs(np.asarray(traj.velocity[:, 0]))
    # bounded: on the board (Hertz's damping vanishes with depth, so the resting cube keeps
    # a small rocking; an unstable step would grow it instead)
    assert np.all(np.isfinite(z)) and z.max() < 0.16 and z[-300:].min() > 0.045
    assert speed[-300:].max() < speed[600:900].max() < 1.0


def test_drag_is_in_the_stability_bound():
    """Drag had no rows in the stability bound: c = 100 N s/m on 1 kg at dt = 0.05 s
    (h c / m = 5, past the dashpot limit 2) was "no limit", the speed grew to 1e30 m/s and
    substeps="auto" kept one substep."""
    s = dp.Scene()
    b = s.add_particle(1.0, (0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
    s.add_drag(b, c=100.0)
    sim = dp.compile(s, 0.05)
    assert sim.stability(sim.params()).stable_dt == pytest.approx(0.02, rel=1e-6)
    with pytest.raises(dp.StabilityError, match="at most 0.018 s"):
        sim.rollout(sim.params(), 50)
    auto = dp.compile(s, 0.05, substeps="auto")
    v = np.asarray(auto.rollout(auto.params(), 50, save_every=50).velocity)[-1, b]
    assert np.all(np.isfinite(np.asarray(v)))
    assert float(np.linalg.norm(np.asarray(v))) < 1.0


def test_traced_flag_of_verlet_in_float32_agrees_with_the_up_front_check():
    """In float32 the traced flag compared the spectral radius with 1 + 1e-9 (= 1): a pure
    dashpot mode, |rho| = 1 exactly, read 1.000002 and every (k, c) of a verlet ball was
    flagged unstable (fits refused their start, sweeps returned NaN)."""
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.6))
    s.add_plane()
    sim = dp.compile(s, 1e-3, integrator="verlet", dtype=jnp.float32)
    flag = jax.jit(lambda p: sim.rollout(p, 10, save_every=10).aux["unstable"][-1])
    for k in (1e2, 1e3, 1e4):
        p = sim.params(k=k, c=20.0)
        assert sim.stability(p).safe
        assert not bool(flag(p)), k
    past = sim.params(k=1e7, c=20.0)                  # w h = 3.2: past the limit
    assert not sim.stability(past).safe and bool(flag(past))


def test_implicit_euler_refuses_a_resting_depth_its_dtype_cannot_resolve():
    """float32, k = 1e9 N/m under a 0.1 g ball: the static depth m g / k = 1e-12 m is far
    below float32's resolution of positions at the ball's size (1e-8 m); implicit_euler's
    linearisation, which differentiates the contact, gave NaN gradients without an error
    (diffpen report stability: 10 FAIL rows). Now a StabilityError asks for float64."""
    from tuning.scenes import ball_scene
    scene = ball_scene(mass=1e-4, height=0.5)
    sim = dp.compile(scene, 1e-5, integrator="implicit_euler", dtype=jnp.float32)
    with pytest.raises(dp.StabilityError, match="float64"):
        sim.rollout(sim.params(k=1e9, c=63.2), 10)
    # float64 resolves it, and a heavier body in float32 too
    sim64 = dp.compile(scene, 1e-5, integrator="implicit_euler", dtype=jnp.float64)
    s = sim64.state_from(body=0, velocity=(0.0, 0.0, -100.0))

    def z_end(kc):
        tr = sim64.rollout(sim64.params(k=kc[0], c=kc[1]), 1000, s, save_every=1000)
        return tr.position[-1, 0, 2]
    g = jax.jit(jax.jacfwd(z_end))(np.asarray([1e9, 63.2]))   # one compiled program
    assert np.isfinite(np.asarray(g)).all()
    heavy = dp.compile(ball_scene(mass=1.0, height=0.5), 1e-5, integrator="implicit_euler",
                       dtype=jnp.float32)
    heavy.rollout(heavy.params(k=1e9, c=63.2), 10)
    # between 1% and half of that resolution the gradients were finite and wrong: a 0.1 g
    # ball at rest, d z / dk -42.9 at k 5e5 N/m and +17.9 at 1e6 (m g / k^2 ~ 1e-15)
    light = dp.compile(ball_scene(mass=1e-4, height=0.3), 1e-3, integrator="implicit_euler",
                       dtype=jnp.float32)
    for k in (5e5, 1e6):
        with pytest.raises(dp.StabilityError, match="wrong or NaN gradients"):
            light.rollout(light.params(k=k, c=0.4 * np.sqrt(k * 1e-4)), 10)
    light.rollout(light.params(k=1e4, c=0.4), 10)
