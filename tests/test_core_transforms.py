"""Core simulator: jit against eager, vmap against a loop, one program per argument kind, float32
beside float64; terms a scene does not need are not traced; per-pair forces."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from jaxpr_scopes import traced_scopes


# --------------------------------------------------------------------------- transforms
def test_jit_matches_eager(ball_sim):
    params, state = ball_sim.params(k=1e4, c=20.0), ball_sim.init_state()
    s_jit = state
    for _ in range(5):
        s_jit = ball_sim.step(params, s_jit)
    with jax.disable_jit():
        s_eager = state
        for _ in range(5):
            s_eager = ball_sim.step(params, s_eager)
        traj_eager = ball_sim.rollout(params, steps=5)
    np.testing.assert_allclose(s_jit.position, s_eager.position, rtol=1e-14)
    np.testing.assert_allclose(traj_eager.position[-1], s_jit.position, rtol=1e-14)


def test_vmap_matches_loop_and_does_not_recompile(ball_sim):
    ks = jnp.array([5e3, 1e4, 2e4])
    cs = jnp.array([10.0, 20.0, 40.0])

    def apex(k, c):
        return ball_sim.rollout(ball_sim.params(k=k, c=c), steps=600,
                                save_every=600).position[-1, 0, 2]
    batched = jax.vmap(apex)(ks, cs)
    before = ball_sim.rollout_cache_size()
    looped = [float(apex(k, c)) for k, c in zip([5e3, 1e4, 2e4], [10.0, 20.0, 40.0])]
    after_first = ball_sim.rollout_cache_size()
    for k in (1.5e4, 3e4, 7e3):          # new values, same structure: no new compilation
        apex(k, 33.0)
    assert ball_sim.rollout_cache_size() == after_first <= before + 1
    np.testing.assert_allclose(batched, looped, rtol=1e-12)


def test_rollout_cache_size_counts_programs_not_argument_kinds(ball_sim):
    """rollout_cache_size counted the jitted function's dispatch entries: python floats,
    then a jax array k, then jax arrays k and c gave 1, 2, 3 with no program traced or
    compiled. It counts traced programs now."""
    before = ball_sim.rollout_cache_size()
    ball_sim.rollout(ball_sim.params(k=1e4, c=20.0), 123, save_every=123)
    once = ball_sim.rollout_cache_size()
    assert once <= before + 1
    ball_sim.rollout(ball_sim.params(k=jnp.asarray(2e4), c=20.0), 123, save_every=123)
    ball_sim.rollout(ball_sim.params(k=jnp.asarray(3e4), c=jnp.asarray(9.0)), 123,
                     save_every=123)
    assert ball_sim.rollout_cache_size() == once
    ball_sim.rollout(ball_sim.params(k=1e4, c=20.0), 124, save_every=124)   # a new length
    assert ball_sim.rollout_cache_size() == once + 1


def test_save_every_keeps_every_nth_state(ball_sim):
    p = ball_sim.params(k=1e4, c=20.0)
    full = ball_sim.rollout(p, steps=100)
    some = ball_sim.rollout(p, steps=100, save_every=10)
    assert some.position.shape == (10, 1, 3)
    np.testing.assert_allclose(some.position, full.position[9::10], rtol=1e-14)
    np.testing.assert_allclose(some.time, full.time[9::10], rtol=1e-14)
    # a rollout continues from the final state
    cont = ball_sim.rollout(p, steps=50, state=ball_sim.rollout(p, steps=50).final)
    np.testing.assert_allclose(cont.position[-1], full.position[-1], rtol=1e-14)


def test_float32_works_alongside_float64():
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3, dtype=jnp.float32)
    traj = sim.rollout(sim.params(k=1e4, c=20.0), steps=1000, save_every=10)
    assert traj.position.dtype == jnp.float32
    g = jax.jit(jax.grad(lambda k: sim.rollout(sim.params(k=k, c=20.0), steps=1000,
                                               save_every=1000).position[-1, 0, 2]))(
        jnp.float32(1e4))
    # the continuous (event-located) derivative is +2.44e-5 m per N/m
    assert g.dtype == jnp.float32 and np.isfinite(g) and g > 0.0


# --------------------------------------------------------------------------- left-out terms
def _scopes(sim, params):
    names, jaxpr = traced_scopes(sim, params)
    return " ".join(names), jaxpr


def test_scene_without_contacts_springs_or_gravity_traces_none_of_them():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_particle(mass=1.0, position=(0.0, 0.0, 1.0), velocity=(1.0, 0.0, 0.0))
    sim = dp.compile(scene, dt=1e-3)
    text, jaxpr = _scopes(sim, sim.params())
    assert "contact" not in text and "spring" not in text and "gravity" not in text
    # only the integrator's arithmetic is left: no sqrt, max, select, scatter or gather
    prims = {e.primitive.name for e in jaxpr.jaxpr.eqns}
    assert not prims & {"sqrt", "max", "select_n", "scatter-add", "gather", "pjit"}


def test_each_term_is_traced_only_when_the_scene_has_it(ball_sim):
    text, _ = _scopes(ball_sim, ball_sim.params(k=1e4, c=20.0))
    assert "contact_plane" in text and "gravity" in text
    assert "spring" not in text and "sphere_sphere" not in text and "fixed_sphere" not in text

    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    a = scene.add_particle(1.0, (0.0, 0.0, 0.0))
    b = scene.add_particle(1.0, (1.0, 0.0, 0.0))
    scene.add_spring(a, b, k=10.0)
    sim = dp.compile(scene, dt=1e-3)
    text, _ = _scopes(sim, sim.params())
    assert "springs" in text and "contact" not in text and "gravity" not in text


def test_pairs_of_fixed_things_are_never_evaluated():
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.05), pinned=True)     # pinned, touching the plane
    scene.add_sphere(0.1, 1.0, (0.15, 0.0, 0.05), pinned=True)    # overlapping the first
    scene.add_sphere(0.1, 1.0, (5.0, 0.0, 1.0))
    scene.add_plane()
    # rows: in columns a per-body column of the 3 bodies would also have the shape (3,)
    sim = dp.compile(scene, dt=1e-3, layout="rows")
    assert "contact_sphere_sphere" in sim.terms
    # one free sphere: 1 plane pair, 2 sphere pairs (free-pinned), none pinned-pinned
    jaxpr = jax.make_jaxpr(sim.term("contact_sphere_sphere").force)(
        sim.params(k=1e4, c=1.0), sim.init_state())
    shapes = {v.aval.shape for e in jaxpr.jaxpr.eqns for v in e.outvars
              if v.aval.dtype.kind == "f"}          # (static row picks are integers)
    assert (2,) in shapes and (3,) not in shapes      # per-pair depths: 2 pairs, not 3
    f, _ = sim.forces(sim.params(k=1e4, c=1.0), sim.init_state())
    np.testing.assert_array_equal(np.asarray(f[:2]), 0.0)   # pinned pair gets no force


def test_spring_forces_are_equal_and_opposite():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    a = scene.add_particle(1.0, (0.0, 0.0, 0.0), velocity=(0.3, -0.2, 0.1))
    b = scene.add_particle(3.0, (1.0, 0.5, -0.2))
    scene.add_spring(a, b, k=10.0, c=2.0, rest_length=0.5)
    sim = dp.compile(scene, dt=1e-3)
    f, _ = sim.forces(sim.params(), sim.init_state())
    np.testing.assert_allclose(f[0], -f[1], rtol=1e-14)
    d = np.array([-1.0, -0.5, 0.2])
    L = np.linalg.norm(d)
    u = d / L
    rate = u @ np.array([0.3, -0.2, 0.1])
    np.testing.assert_allclose(f[0], (-10.0 * (L - 0.5) - 2.0 * rate) * u, rtol=1e-13)


@pytest.mark.parametrize("normals", [
    [(0.0, 0.0, 1.0)],                                            # the ground: one slice
    [(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0)],        # walls: +-1 per column
    [(0.3, -0.2, 0.9), (0.0, 0.6, 0.8)],                          # tilted: products
])
def test_plane_contact_forces_match_the_per_pair_law(normals):
    """Plane normals enter the step as constants (zeros left out); the forces must equal the
    pair law F = (k ramp(d) - c gate(d) n.v) n summed over planes, d = r - (n.x - offset)."""
    from diffpen import laws
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0), allow_overlap=True)   # particles inside planes
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.06, 0.06, (5, 3))
    v = rng.normal(size=(5, 3))
    for xi, vi in zip(x, v):          # particles (radius 0): no sphere-sphere contact
        scene.add_particle(mass=1.0, position=xi, velocity=vi)
    unit = [np.asarray(n) / np.linalg.norm(n) for n in normals]
    offsets = [0.02 * (i + 1) for i in range(len(normals))]
    for n, off in zip(normals, offsets):
        scene.add_plane(normal=n, offset=off)
    sim = dp.compile(scene, dt=1e-3, smoothing=0.05)
    k, c = 3e3, 7.0
    f, _ = sim.forces(sim.params(k=k, c=c), sim.init_state())
    want = np.zeros((5, 3))
    for n, off in zip(unit, offsets):
        d = -(x @ n - off)
        mag = np.asarray(laws.linear_contact(jnp.asarray(d), jnp.asarray(v @ n), k, c, 0.05))
        want += mag[:, None] * n
    assert np.abs(want).max() > 1.0                     # some spheres really are in contact
    np.testing.assert_allclose(np.asarray(f), want, rtol=1e-12, atol=1e-12)
    # the constant normals keep a float32 simulator in float32 (with x64 on)
    sim32 = dp.compile(scene, dt=1e-3, smoothing=0.05, dtype=jnp.float32)
    s32 = sim32.step(sim32.params(k=k, c=c), sim32.init_state())
    assert s32.position.dtype == s32.velocity.dtype == jnp.float32
    f32, _ = sim32.forces(sim32.params(k=k, c=c), sim32.init_state())
    np.testing.assert_allclose(np.asarray(f32), want, rtol=1e-4, atol=1e-3)
