"""Extending diffpen from outside the package with its public records only: a toy integrator
and a toy contact law are rolled out, analysed and gated like the built-in ones (no
registration, no edit of diffpen)."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen.integrators import Integrator, drift, kick


def drift_kick_euler(accel_fn, h):
    """Toy method: ``x' = x + h v``, then ``v' = v + h a(x', v)`` (semi-implicit Euler with
    the two halves swapped)."""
    def step(params, state):
        moved = drift(state, h)
        return kick(moved, accel_fn(params, moved), h)
    return step


def drift_kick_amplification(K, C, h, xp=np):
    """The toy step on ``x'' = -K x - C v``: x' = x + h v; v' = v + h (-K x' - C v)."""
    K, C, h = (xp.asarray(a, dtype=float) for a in (K, C, h))
    shape = xp.broadcast_shapes(K.shape, C.shape, h.shape)
    K, C, h = (xp.broadcast_to(a, shape) for a in (K, C, h))
    xx, xv = xp.ones_like(K), h
    vx, vv = -h * K, 1.0 - h * h * K - h * C
    return xp.stack([xp.stack([xx, xv], axis=-1), xp.stack([vx, vv], axis=-1)], axis=-2)


TOY = Integrator(name="drift_kick_euler", make=drift_kick_euler,
                 amplification=drift_kick_amplification, evaluations=1)


@pytest.fixture(scope="module")
def spring_and_ball():
    """A 1 kg particle on a world spring (no gravity) and the quick-start ball."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    p = scene.add_particle(mass=1.0, position=(0.0, 0.0, 1.1))
    scene.add_spring(p, (0.0, 0.0, 0.0), k=100.0, c=0.0, rest_length=1.0)
    return scene


def test_toy_integrator_rolls_out_as_written(spring_and_ball):
    sim = dp.compile(spring_and_ball, 1e-2, integrator=TOY)
    assert sim.integrator == "drift_kick_euler"
    traj = sim.rollout(sim.params(), 50)
    # the same recurrence by hand
    x, v, w2 = 0.1, 0.0, 100.0
    for _ in range(50):
        x = x + 1e-2 * v
        v = v + 1e-2 * (-w2 * x)
    np.testing.assert_allclose(float(traj.position[-1, 0, 2]) - 1.0, x, rtol=1e-12)
    np.testing.assert_allclose(float(traj.velocity[-1, 0, 2]), v, rtol=1e-12)
    # substeps go through the record's step factory too
    fine = dp.compile(spring_and_ball, 1e-3, integrator=TOY)
    coarse = dp.compile(spring_and_ball, 1e-2, integrator=TOY, substeps=10)
    np.testing.assert_allclose(coarse.rollout(coarse.params(), 5).position,
                               fine.rollout(fine.params(), 50, save_every=10).position,
                               atol=1e-12)


def test_toy_integrator_gets_the_stability_analysis_and_the_gate(spring_and_ball):
    """Its limit comes from its own amplification matrix (w h < 2 for this method); past it
    the rollout is refused up front and flagged under jit."""
    sim = dp.compile(spring_and_ball, 1e-2, integrator=TOY)
    k = 3e4                                           # w = 173 rad/s: w h = 1.73 < 2
    rep = sim.stability(sim.params(spring_k=k, spring_c=0.0))
    assert rep.integrator == "drift_kick_euler"
    assert rep.stable_dt == pytest.approx(2.0 / math.sqrt(k), rel=1e-8)
    assert rep.stable and rep.safe                    # no contact: safe = stable
    with pytest.raises(dp.StabilityError, match="drift_kick_euler"):
        sim.rollout(sim.params(spring_k=5e4, spring_c=0.0), 10)    # w h = 2.24

    def flag(k):
        p = sim.params(spring_k=k, spring_c=0.0)
        return sim.rollout(p, 10, check_finite=False).aux["unstable"][-1]
    np.testing.assert_array_equal(jax.jit(jax.vmap(flag))(jnp.asarray([3e4, 5e4])),
                                  [False, True])
    # substeps="auto" picks the count from the record's analysis
    auto = dp.compile(spring_and_ball, 1e-2, integrator=TOY, substeps="auto")
    p = auto.params(spring_k=5e4, spring_c=0.0)
    assert auto.stability(p).substeps_needed == 2
    assert np.all(np.isfinite(np.asarray(auto.rollout(p, 100).position)))


# --------------------------------------------------------------------------- a toy contact law
def _half_force(d, vn, k, c, width=0.0):
    """Toy law: half a no-tension spring-damper, ``max(k d - c vn, 0) / 2`` in contact."""
    return 0.5 * dp.laws.no_tension_contact(d, vn, k, c, width)


TOY_LAW = dp.laws.ContactLaw(
    name="half_no_tension", force=_half_force, averaged=None,
    energy=lambda d, k, width=0.0: 0.5 * k * dp.laws.ramp_integral(d, width),
    resting_depth=lambda load, k, width=0.0: dp.laws.ramp_inverse(2.0 * load / k, width),
    stiffness=lambda k, c, d_ref=None: (0.5 * k, 0.5 * c))


def test_toy_contact_law_rolls_out_and_sets_the_stability_gate(ball_scene):
    """A ContactLaw record made here: the ball rests at its resting depth, and the stability
    analysis sees its own stiffness (k / 2), up front and under jit."""
    sim = dp.compile(ball_scene, 1e-3, law=TOY_LAW)
    assert sim.law == "half_no_tension"
    k, c = 2e4, 100.0
    traj = sim.rollout(sim.params(k=k, c=c), 3000, save_every=3000)
    depth = 0.1 - float(traj.position[-1, 0, 2])
    assert depth == pytest.approx(float(TOY_LAW.resting_depth(9.81, k)), rel=1e-6)
    # the gate uses the law's stiffness: w = sqrt(k / 2 / m)
    rep = sim.stability(sim.params(k=k, c=c))
    assert rep.omega_max == pytest.approx(math.sqrt(0.5 * k), rel=1e-12)
    # past the toy's own safe step (w h = 0.5 at k / 2 = 2.5e5) it is refused and flagged
    with pytest.raises(dp.StabilityError):
        sim.rollout(sim.params(k=6e5, c=0.0), 10)
    flags = jax.jit(jax.vmap(lambda kk: sim.rollout(sim.params(k=kk, c=0.0), 5,
                                                    check_finite=False).aux["unstable"][-1]))
    np.testing.assert_array_equal(flags(jnp.asarray([4e5, 6e5])), [False, True])


def test_toy_contact_law_through_the_closed_form_starts():
    """The first guesses of tuning (bounce targets, trajectory fit) and the closed forms of
    diffpen.physical take a record made here: one that names the no_tension closed forms gets
    (k, c) meeting both restitution and contact time under them; one without closed forms
    starts from the linear law's and is refused by diffpen.physical, naming the law."""
    import dataclasses
    import types

    from tuning.bounce import first_guess_bounce
    from tuning.sysid import first_guess

    m, drop, apex, tc = 0.5, 1.0, 0.49, 0.01
    e = math.sqrt(apex / drop)
    info = {"mass": m, "drop": drop}
    targets = {"apex_heights": [apex], "contact_durations": [tc]}
    events = types.SimpleNamespace(restitution=np.array([e]), contact=np.array([tc]))

    toy_nt = dataclasses.replace(TOY_LAW, closed_form="no_tension")
    k, c, _ = first_guess_bounce(info, targets, law=toy_nt)
    assert float(dp.physical.restitution(k, c, m, toy_nt)) == pytest.approx(e, rel=1e-9)
    assert float(dp.physical.contact_time(k, c, m, toy_nt)) == pytest.approx(tc, rel=1e-9)
    assert first_guess(events, m, law=toy_nt) == pytest.approx((k, c), rel=1e-9)

    lin = first_guess_bounce(info, targets, law="linear")
    assert first_guess_bounce(info, targets, law=TOY_LAW) == pytest.approx(lin, rel=1e-12)
    assert first_guess(events, m, law=TOY_LAW) == pytest.approx(lin[:2], rel=1e-9)
    with pytest.raises(ValueError, match="half_no_tension"):
        dp.physical.restitution(k, c, m, TOY_LAW)


# --------------------------------------------------------------------------- a toy force term
def _toy_wall(ctx):
    """Toy term: a wall ``x = params.extra["toy_wall"]["x"]`` (m) pushing free bodies back
    along -x with the simulator's contact law and material "wall"'s (k, c); it counts in
    ``State.aux["toy_hits"]`` the steps that end with a body past the wall."""
    bodies = np.array([i for i in range(ctx.n) if not ctx.pinned[i]], dtype=np.int32)
    if not len(bodies):
        return None
    mat = np.full(len(bodies), ctx.material_index["wall"])

    def past(params, state):
        return state.position[bodies, 0] - params.extra["toy_wall"]["x"]

    def force(params, state):
        k, c = ctx.contact_kc(params, mat)
        f = ctx.law(past(params, state), -state.velocity[bodies, 0], k, c, ctx.width)
        fx = jnp.zeros(ctx.n, state.position.dtype).at[bodies].add(-f)
        return jnp.stack([fx, jnp.zeros_like(fx), jnp.zeros_like(fx)], axis=-1), None

    def update(params, state):
        hits = jnp.sum(past(params, state) > 0.0).astype(state.aux["toy_hits"].dtype)
        return {"toy_hits": state.aux["toy_hits"] + hits}

    return dp.terms.Term("toy_wall", force, extra={"toy_wall": {"x": 0.2}},
                         aux={"toy_hits": 0.0}, update=update)


def _toy_wall_bound(ctx):
    rows = [(i, "wall", 1.0, 1.0, "toy wall") for i in range(ctx.n) if not ctx.pinned[i]]
    return (dp.stability.Bound.of(rows, "contact", combine="contact"),)


TOY_WALL = dp.terms.TermBuilder(_toy_wall, bound=_toy_wall_bound,
                                materials=lambda ctx: ("wall",))


@pytest.fixture(scope="module")
def wall_sim():
    """A 1 kg particle at 1 m/s towards the toy wall at x = 0.2 m (no gravity), above a
    ground plane of material "ground"."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_material("ground", k=1e3, c=1.0)
    scene.add_material("wall", k=1e4, c=0.0)
    scene.add_plane(offset=-1.0, material="ground")
    scene.add_particle(1.0, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    return dp.compile(scene, 1e-3, terms=(*dp.terms.BUILTIN, TOY_WALL))


def test_toy_term_declares_its_material_extra_param_aux_and_bound(wall_sim):
    """A Term made here brings its contact material, its extra param and its aux state into
    the simulator's pytrees; its force bounces the particle at the wall the param places,
    its aux update runs after every step, and its bound sets the stability gate."""
    sim = wall_sim
    assert sim.terms == ("contact_plane", "toy_wall")
    assert sim.materials == ("ground", "wall")          # the builders' union, in order
    p = sim.params()
    assert (float(p.contact["wall"].k), float(p.contact["wall"].c)) == (1e4, 0.0)
    assert set(p.extra) == {"toy_wall"} and float(p.extra["toy_wall"]["x"]) == 0.2
    assert float(sim.init_state().aux["toy_hits"]) == 0.0

    traj = sim.rollout(p, 400)                          # reaches the wall at 0.2 s
    x = np.asarray(traj.position[:, 0, 0])
    # a linear spring wall: turns at x = wall + v / w (w = 100 rad/s), leaves at -v
    assert x.max() == pytest.approx(0.2 + 1.0 / 100.0, rel=2e-3)
    assert float(traj.velocity[-1, 0, 0]) == pytest.approx(-1.0, abs=5e-3)
    # the aux update ran after every step: it counted the steps that ended past the wall
    assert int(traj.aux["toy_hits"][-1]) == int(np.sum(x > 0.2)) > 0

    # the extra param is a differentiable leaf like the built-in ones
    moved = sim.rollout(sim.params(extra={"toy_wall": {"x": 0.25}}), 400)
    assert float(moved.position[:, 0, 0].max()) == pytest.approx(0.26, rel=2e-3)
    with pytest.raises(dp.SceneError, match="toy_wall"):
        sim.params(extra={"toy_wall": {"y": 0.1}})

    # its stability rows: w = sqrt(k / m), refused past the safe step
    assert sim.stability(p).omega_max == pytest.approx(100.0, rel=1e-12)
    with pytest.raises(dp.StabilityError):
        sim.rollout(sim.params(contact={"wall": (1e8, 0.0)}), 10)


def test_toy_term_material_must_be_in_the_scene(spring_and_ball):
    """A builder declaring a material the scene lacks is refused at compile, naming it."""
    with pytest.raises(dp.SceneError, match="'wall'.*add_material"):
        dp.compile(spring_and_ball, 1e-2, terms=(*dp.terms.BUILTIN, TOY_WALL))


def test_a_custom_extra_of_either_sign_does_not_set_the_stability_flag():
    """Regression: the traced flag held every extra entry but plane offsets to >= 0, so a
    term whose own check allows a negative value (a wall at x = -0.2 m) set aux["unstable"]
    on every rollout, concrete or jitted, well inside the safe step. The flag now follows
    each entry's check: its traced_range, or any finite value for a check without one."""
    def signed_wall(ctx):
        term = _toy_wall(ctx)
        return None if term is None else term._replace(
            checks={"toy_wall": lambda label, v: None})      # any sign
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_material("wall", k=1e4, c=0.0)
    scene.add_particle(1.0, (0.0, 0.0, 0.0), (-1.0, 0.0, 0.0))
    sim = dp.compile(scene, 1e-3, terms=(*dp.terms.BUILTIN, dp.terms.TermBuilder(
        signed_wall, bound=_toy_wall_bound, materials=lambda ctx: ("wall",))))
    p = sim.params(extra={"toy_wall": {"x": -0.2}})
    assert not bool(sim.rollout(p, 50, save_every=50).aux["unstable"][-1])
    run = jax.jit(lambda x: sim.rollout(sim.params(extra={"toy_wall": {"x": x}}), 50,
                                        save_every=50).aux["unstable"][-1])
    assert not bool(run(-0.2)) and bool(run(jnp.nan))
