"""Integrators: convergence order against closed forms, implicit Euler (stiff, dense vs CG,
gradients vs finite differences), substeps, and the unchanged default step."""
import math

import jax
import numpy as np
import pytest

import diffpen as dp
from diffpen import integrators

EXPLICIT = ["semi_implicit_euler", "verlet", "rk4"]
ALL = EXPLICIT + ["implicit_euler"]
K, M, C, X0 = 100.0, 1.0, 2.0, 0.1          # w0 = 10 rad/s, zeta = 0.1


def spring_scene(c=C):
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    p = scene.add_particle(mass=M, position=(0.0, 0.0, 1.0 + X0))
    scene.add_spring(p, (0.0, 0.0, 0.0), k=K, c=c, rest_length=1.0)
    return scene


def damped_closed_form(t, c=C):
    w0 = math.sqrt(K / M)
    z = c / (2 * math.sqrt(K * M))
    wd = w0 * math.sqrt(1 - z * z)
    return X0 * np.exp(-z * w0 * t) * (np.cos(wd * t) + z * w0 / wd * np.sin(wd * t))


def chain_scene(n=4, k=400.0, c=1.0, m=0.2):
    """Vertical chain: body 0 pinned at z = 2 m, n free particles 0.25 m apart, gravity."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    top = scene.add_particle(mass=m, position=(0.0, 0.0, 2.0), pinned=True)
    prev = top
    for i in range(1, n + 1):
        b = scene.add_particle(mass=m, position=(0.05 * i, 0.0, 2.0 - 0.25 * i))
        scene.add_spring(prev, b, k=k, c=c, rest_length=0.25, group="chain")
        prev = b
    return scene


def spring_error(integrator, dt, T=1.0):
    sim = dp.compile(spring_scene(), dt, integrator=integrator)
    traj = sim.rollout(sim.params(), int(round(T / dt)))
    x = np.asarray(traj.position)[:, 0, 2] - 1.0
    return np.max(np.abs(x - damped_closed_form(np.asarray(traj.time))))


@pytest.mark.parametrize("integrator,order", [("semi_implicit_euler", 1), ("verlet", 2),
                                              ("rk4", 4), ("implicit_euler", 1)])
def test_convergence_order_on_damped_spring(integrator, order):
    e1, e2 = spring_error(integrator, 4e-3), spring_error(integrator, 2e-3)
    assert math.log2(e1 / e2) == pytest.approx(order, abs=0.25)
    assert e2 < {1: 2e-2, 2: 1e-4, 4: 1e-8}[order]


def test_implicit_euler_stiff_ball_is_stable():
    """k = 1e9 N/m at dt = 1e-3 s (w h = 31.6, explicit limit 2): no NaN, energy out of
    contact never grows, every rebound is slower than its impact, penetration is bounded by
    one step of travel, and the ball comes to rest on the plane."""
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3, integrator="implicit_euler")
    traj = sim.rollout(sim.params(k=1e9, c=100.0), 3000)
    z, vz = np.asarray(traj.position)[:, 0, 2], np.asarray(traj.velocity)[:, 0, 2]
    assert np.all(np.isfinite(z)) and np.all(np.isfinite(vz))
    free = z >= 0.1 - 2e-8                                   # rest penetration m g / k = 1e-8
    energy = 9.81 * z + 0.5 * vz ** 2
    assert np.max(energy[free]) <= 9.81 * 1.0 * (1 + 1e-9)
    v_in = math.sqrt(2 * 9.81 * 0.9)
    assert np.max(0.1 - z) <= v_in * 1e-3 + 1e-6
    assert np.max(vz) <= v_in
    assert abs(z[-1] - 0.1) < 1e-4 and abs(vz[-1]) < 1e-2


@pytest.fixture(scope="module")
def chain():
    scene = chain_scene()
    return dp.compile(scene, 1e-3, integrator="implicit_euler")


def _chain_rollout(sim, solver, k, c, steps=100):
    """Positions (steps, n, 3) of the chain under implicit_euler with the given solver."""
    step = integrators.implicit_euler(sim.acceleration, sim.dt,
                                      inv_mass=1.0 / sim.mass * ~sim.pinned, solver=solver,
                                      cg_tol=1e-13)
    params = sim.params(spring_k=k, spring_c=c)

    def body(s, _):
        s = step(params, s)
        return s, s.position
    return jax.lax.scan(body, sim.init_state(), None, length=steps)[1]


def _chain_loss(pos):
    """The last particle's final z + 0.3 x."""
    return pos[-1, -1, 2] + 0.3 * pos[-1, -1, 0]


@pytest.fixture(scope="module")
def chain_runs(chain):
    """Per solver, one jitted program, compiled once for the tests below: ``run(k, c) ->
    ((loss, positions), (d loss / dk, d loss / dc))`` (reverse mode through the solves;
    positions (steps, n, 3) as :func:`_chain_rollout` gives them)."""
    def loss(k, c, solver):
        pos = _chain_rollout(chain, solver, k, c)
        return _chain_loss(pos), pos
    return {solver: jax.jit(lambda k, c, solver=solver: jax.value_and_grad(
        loss, (0, 1), has_aux=True)(k, c, solver)) for solver in ("dense", "cg")}


def test_implicit_dense_and_cg_agree(chain, chain_runs):
    dense = np.asarray(chain_runs["dense"](400.0, 1.0)[0][1])
    cg = np.asarray(chain_runs["cg"](400.0, 1.0)[0][1])
    np.testing.assert_allclose(cg, dense, rtol=0, atol=1e-9)
    # and the simulator's own implicit step is the dense one for this small scene
    np.testing.assert_allclose(chain.rollout(chain.params(), 100).position, dense, atol=1e-12)


def test_implicit_solver_is_chosen_through_compile(chain_runs):
    """Regression: the README's ``solver="cg"`` had no public way in (``dp.compile(...,
    solver="cg")`` is a TypeError); ``dp.integrators.implicit_euler_with(solver)`` is the
    record, passed to compile as any other."""
    rec = dp.integrators.implicit_euler_with("cg")
    sim = dp.compile(chain_scene(), 1e-3, integrator=rec)
    # its name tells it apart (a saved sweep's key held the same simulator for each solver)
    assert sim.integrator == "implicit_euler[cg]"
    assert dp.integrators.implicit_euler_with("auto").name == "implicit_euler"
    params = sim.params(spring_k=400.0, spring_c=1.0)
    pos = sim.rollout(params, 100).position
    np.testing.assert_allclose(pos, chain_runs["cg"](400.0, 1.0)[0][1], rtol=0, atol=1e-9)
    # conjugate gradients' loop, not the dense solve this small scene takes by default
    def solves(sim):
        text = str(jax.make_jaxpr(sim.step)(params, sim.init_state()))
        return {p for p in ("while", "triangular_solve") if f"= {p}[" in text}
    assert solves(sim) == {"while"}
    dense = dp.compile(chain_scene(), 1e-3, integrator=dp.integrators.implicit_euler_with("dense"))
    assert solves(dense) == {"triangular_solve"}
    with pytest.raises(dp.SceneError, match="solver must be one of"):
        dp.integrators.implicit_euler_with("cholesky")


@pytest.mark.parametrize("solver", ["dense", "cg"])
def test_implicit_euler_gradients_match_finite_differences(chain_runs, solver):
    run = chain_runs[solver]

    def loss(k, c):             # the value: no second compile for the differences
        return float(run(k, c)[0][0])
    k0, c0 = 400.0, 1.0
    gk, gc = run(k0, c0)[1]
    hk, hc = 1e-4 * k0, 1e-4 * c0
    fk = (loss(k0 + hk, c0) - loss(k0 - hk, c0)) / (2 * hk)
    fc = (loss(k0, c0 + hc) - loss(k0, c0 - hc)) / (2 * hc)
    assert abs(gk) > 1e-7 and abs(gc) > 1e-7
    np.testing.assert_allclose(gk, fk, rtol=1e-5)
    np.testing.assert_allclose(gc, fc, rtol=1e-5)


@pytest.mark.parametrize("integrator", EXPLICIT)
def test_explicit_gradients_match_finite_differences(integrator):
    sim = dp.compile(chain_scene(n=2), 2e-3, integrator=integrator)

    def final_z(k, c):
        return sim.rollout(sim.params(spring_k=k, spring_c=c), 150).position[-1, -1, 2]
    value_and_grad = jax.jit(jax.value_and_grad(final_z, (0, 1)))
    gk, gc = value_and_grad(400.0, 1.0)[1]

    def loss(k, c):                 # the value: no second compile for the differences
        return float(value_and_grad(k, c)[0])
    fk = (loss(400.04, 1.0) - loss(399.96, 1.0)) / 0.08
    fc = (loss(400.0, 1.0001) - loss(400.0, 0.9999)) / 2e-4
    np.testing.assert_allclose([gk, gc], [fk, fc], rtol=1e-5)


@pytest.mark.parametrize("integrator", ALL)
def test_substeps_equal_smaller_dt(integrator):
    scene = chain_scene(n=2)
    coarse = dp.compile(scene, 4e-3, integrator=integrator, substeps=4)
    fine = dp.compile(scene, 1e-3, integrator=integrator)
    a = coarse.rollout(coarse.params(), 50)
    b = fine.rollout(fine.params(), 200, save_every=4)
    np.testing.assert_allclose(a.position, b.position, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.time, b.time, rtol=1e-12)


def test_default_step_traces_nothing_extra():
    """substeps=1 with the default integrator: the step is the plain semi-implicit Euler."""
    scene = chain_scene(n=2)
    sim = dp.compile(scene, 1e-3)
    plain = integrators.semi_implicit_euler(sim.acceleration, 1e-3)
    args = (sim.params(), sim.init_state())
    step = sim.step_function()
    assert str(jax.make_jaxpr(step)(*args)) == str(jax.make_jaxpr(plain)(*args))
    assert "scan" not in str(jax.make_jaxpr(step)(*args))


def test_implicit_euler_cg_refuses_rigid_states_clearly():
    sim = dp.compile(spring_scene(), 1e-3, integrator="implicit_euler")
    s = sim.init_state()
    rigid = s._replace(orientation=np.array([[1.0, 0.0, 0.0, 0.0]]),
                       angular_velocity=np.zeros((1, 3)))
    step = integrators.implicit_euler(sim.acceleration, sim.dt, solver="cg")
    with pytest.raises(dp.SceneError, match=r"rigid.*implicit_euler_with\('dense'\)"):
        step(sim.params(), rigid)


def test_bad_substeps_and_solver_are_refused():
    with pytest.raises(dp.SceneError, match="substeps"):
        dp.compile(spring_scene(), 1e-3, substeps=0)
    with pytest.raises(dp.SceneError, match="solver"):
        integrators.implicit_euler(lambda p, s: (s.position, None), 1e-3, solver="lu")


def test_implicit_euler_iterative_solve_is_right_on_a_nonsymmetric_system():
    """Above DENSE_MAX_DOF, solver="auto" took conjugate gradients, which assume a symmetric
    system; dampers with relative motion across their axis make it non-symmetric, and on
    17 spinning damped dumbbells (102 DOF) the first step's velocity came out (-3.38, 6.68)
    m/s against the dense solve's (3.07, -4.81). "auto" takes GMRES there now."""
    import functools
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    for i in range(17):
        a = s.add_particle(1.0, (-0.05, 0.0, float(i)), (0.0, -5.0, 0.0))
        b = s.add_particle(1.0, (0.05, 0.0, float(i)), (0.0, 5.0, 0.0))
        s.add_spring(a, b, k=1e3, c=100.0, rest_length=0.08)
    dense = integrators.INTEGRATORS["implicit_euler"]._replace(
        name="implicit_euler_dense", make=functools.partial(integrators.implicit_euler,
                                                            solver="dense"))
    out = {}
    for name, integ in (("auto", "implicit_euler"), ("dense", dense)):
        sim = dp.compile(s, 1e-2, integrator=integ)
        out[name] = np.asarray(sim.rollout(sim.params(), 3).velocity)
    np.testing.assert_allclose(out["auto"], out["dense"], rtol=1e-7, atol=1e-9)


def test_a_renamed_semi_implicit_euler_record_steps_as_the_built_in():
    """The centred laws' velocity lag and the spin limit were keyed on the name
    "semi_implicit_euler": the same record under another name switched the centred
    correction off (4.6e-4 m apart) and let a 1:2:3 box spin up from 60 to 164 rad/s."""
    from diffpen import integrators
    rec = integrators.INTEGRATORS["semi_implicit_euler"]._replace(name="my_sie")
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.3))
    s.add_plane()
    law = dp.laws.linear(centred=True)
    a = dp.compile(s, 1e-3, law=law)
    b = dp.compile(s, 1e-3, law=law, integrator=rec)
    np.testing.assert_array_equal(a.rollout(a.params(k=1e4, c=20.0), 400).position,
                                  b.rollout(b.params(k=1e4, c=20.0), 400).position)
    box = dp.Scene(gravity=(0.0, 0.0, 0.0))
    box.add_box((0.1, 0.2, 0.3), 1.0, (0.0, 0.0, 0.0), angular_velocity=(0.0, 60.0, 1.0),
                inertia=(1.0, 2.0, 3.0))
    sim = dp.compile(box, 1e-3, integrator=rec)
    with pytest.raises(dp.StabilityError, match="spins at"):
        sim.rollout(sim.params(), 10)


def test_an_iterative_implicit_solve_that_misses_sets_the_flag():
    """Regression: inside a rollout's ``lax.scan`` of two or more steps, GMRES and CG (JAX
    0.10, CPU) returned a relative residual of 3.7e-3 at a cloth's first contact with a
    fixed sphere, against the 1e-10 asked, where the same step alone solves to 1e-16; the
    rollout left its own step loop by 2e-4 m and its gradients were off by up to 5%, with
    nothing said (the default implicit_euler takes GMRES above 96 degrees of freedom). Each
    iterative solve is now checked with one more product, and the rollout's stability flag
    says when it missed; the steps that solve right keep it clear."""
    from diffpen.builders import add_cloth
    scene = dp.Scene()                  # a cloth falling at 1 m/s, 1 cm above a fixed sphere
    add_cloth(scene, 4, 4, spacing=0.1, mass=0.16, origin=(-0.15, -0.15, 0.3925),
              velocity=(0.0, 0.0, -1.0), structural=(60.0, 0.02), shear=(20.0, 0.01),
              bend=(1.0, 0.0))
    scene.add_fixed_sphere((0.0, 0.0, 0.2), 0.2)
    scene.add_plane()
    gmres = dp.compile(scene, 5e-4, integrator=integrators.implicit_euler_with("gmres"))
    p = gmres.params(k=2e3, c=1.0)
    out = gmres.rollout(p, 12)
    flag = np.asarray(out.aux["unstable"])
    assert not flag[:8].any()                                 # apart: solved, no flag
    if flag[-1]:
        return          # the miss is said (on this jaxlib: 2.9e-7 m off after 12 steps)
    # no flag: then the rollout must be right, as the dense solver's
    dense = dp.compile(scene, 5e-4, integrator=integrators.implicit_euler_with("dense"))
    gap = np.abs(np.asarray(out.position - dense.rollout(p, 12).position)).max()
    assert gap < 1e-9, (flag, gap)


def test_messages_about_the_flag_name_a_missed_iterative_solve():
    """Regression: the flag also means an iterative implicit solve missed its system (above),
    but tuning's messages said only "past the safe step" and advised a smaller dt or softer
    contact, which need not cure a missed solve. Simulators whose implicit_euler takes GMRES
    or CG now name that cause and its remedy; the others keep their words. Which solver a
    step takes is one rule (``integrators.solves_iteratively``)."""
    from diffpen.builders import add_cloth
    from tuning.stable import solver_miss, unsafe_start
    cloth = dp.Scene()                                  # 36 particles: 108 unknowns > 96
    add_cloth(cloth, 6, 6, spacing=0.1, mass=0.36, origin=(0.0, 0.0, 0.5))
    small = dp.Scene()                                  # one sphere: 3 unknowns
    small.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.5))
    iterative = {(name, scene_name): integrators.solves_iteratively(
        integrators.implicit_euler_with(name) if name != "rk4" else "rk4",
        3 * len(scene.bodies)) for name in ("auto", "dense", "gmres", "cg", "rk4")
        for scene_name, scene in (("cloth", cloth), ("small", small))}
    assert {key for key, it in iterative.items() if it} == {
        ("auto", "cloth"), ("gmres", "cloth"), ("gmres", "small"), ("cg", "cloth"),
        ("cg", "small")}
    assert integrators.solves_iteratively("implicit_euler", 108)
    assert not integrators.solves_iteratively("implicit_euler", 108, rigid=True)
    for solver, named in (("auto", True), ("dense", False)):
        sim = dp.compile(cloth, 1e-3, integrator=integrators.implicit_euler_with(solver))
        words = str(unsafe_start({"k": 1.0}, sim.dt, sim))
        assert ("implicit_euler_with('dense')" in words) is named, words
        assert ("iterative implicit solve missed" in solver_miss(sim)) is named
    assert solver_miss(dp.compile(small, 1e-3)) == ""
