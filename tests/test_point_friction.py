"""Smooth Coulomb friction of spheres that do not rotate and of particles on rough planes.

A material's friction acted on box corners and rigid spheres only: a particle or an
``add_sphere`` ball launched at 2 m/s on a plane of friction 0.3 slid on at 2 m/s, with no
friction in its params and no word of it (so rope, cloth and jelly nodes never felt a rough
floor). Closed forms: sliding, the speed falls at ``mu g`` and the body stops after
``v0^2 / (2 mu g)``; on a slope of angle ``a`` it accelerates at ``g (sin a - mu cos a)``.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp

G = 9.81
K, C, MU, SLIP = 1e5, 300.0, 0.3, 1e-3
V0 = np.array([0.8, 0.6, 0.0])          # 1 m/s along (0.8, 0.6)


@pytest.fixture(scope="module", params=["particle", "sphere"])
def slider(request):
    """A 1 kg particle, or a 1 kg sphere of radius 0.1 m that does not rotate, launched at
    1 m/s along the rough floor z = 0 from its resting depth m g / k (dt 1e-4 s)."""
    scene = dp.Scene()
    scene.add_material("rough", friction=MU, slip_speed=SLIP)
    if request.param == "particle":
        scene.add_particle(1.0, (0.0, 0.0, -G / K), tuple(V0), allow_overlap=True)
    else:
        scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.1 - G / K), tuple(V0))
    scene.add_plane(material="rough")
    return dp.compile(scene, dt=1e-4)


def _slide(sim, mu, steps=4000):
    return sim.rollout(sim.params(k=K, c=C, extra={"friction": {"rough": mu}}), steps=steps,
                       save_every=40)


def test_a_sliding_particle_or_sphere_stops_after_v0_squared_over_2_mu_g(slider):
    assert slider.params(k=K, c=C).extra["friction"] == {"rough": MU}
    traj = _slide(slider, MU)
    t = np.asarray(traj.time)
    v = np.asarray(traj.velocity[:, 0])
    speed = np.linalg.norm(v[:, :2], axis=1)
    sliding = speed > 0.05
    np.testing.assert_allclose(speed[sliding], 1.0 - MU * G * t[sliding], atol=1e-4)
    # along its launch direction, no torque and no turn
    np.testing.assert_allclose(v[sliding, :2] / speed[sliding, None],
                               np.broadcast_to(V0[:2], (sliding.sum(), 2)), atol=1e-9)
    moved = np.asarray(traj.position[-1, 0, :2])           # from (0, 0)
    np.testing.assert_allclose(moved, V0[:2] / (2 * MU * G), rtol=1e-3)
    np.testing.assert_allclose(v[-1], 0.0, atol=1e-4)


def test_the_stop_distance_gradient_is_the_closed_forms(slider):
    def stop(mu):
        return _slide(slider, mu).position[-1, 0, 0]
    g = float(jax.jit(jax.grad(stop))(MU))
    fd = float((stop(MU + 1e-5) - stop(MU - 1e-5)) / 2e-5)
    np.testing.assert_allclose(g, fd, rtol=1e-4)
    # d/dmu of 0.8 v0^2 / (2 mu g)
    np.testing.assert_allclose(g, -0.8 / (2 * MU * MU * G), rtol=5e-3)


@pytest.mark.parametrize("mu", [0.3, 0.7])
def test_a_particle_on_a_rough_slope_slides_at_g_sin_minus_mu_cos(mu):
    """A 30 deg slope: mu 0.3 slides at g (sin a - mu cos a) = 2.356 m/s^2 (4.905 without
    friction); mu 0.7 > tan a holds it: it creeps at the smooth law's viscous speed, below
    twice the slip speed."""
    a = np.radians(30.0)
    normal = (0.0, -np.sin(a), np.cos(a))
    scene = dp.Scene()
    scene.add_material("rough", friction=mu, slip_speed=SLIP)
    scene.add_particle(1.0, (0.0, 0.0, -G * np.cos(a) / K), allow_overlap=True)
    scene.add_plane(normal, material="rough")
    sim = dp.compile(scene, dt=1e-4)
    traj = sim.rollout(sim.params(k=K, c=C), steps=3000, save_every=30)
    down = np.array([0.0, -np.cos(a), -np.sin(a)])      # down the slope
    t = np.asarray(traj.time)
    speed = np.asarray(traj.velocity[:, 0]) @ down
    late = t > 0.05
    if mu < np.tan(a):
        np.testing.assert_allclose(speed[late], G * (np.sin(a) - mu * np.cos(a)) * t[late],
                                   atol=2e-3)
    else:
        assert np.all(np.abs(speed[late]) < 2 * SLIP)


def test_rope_nodes_on_a_rough_floor_feel_its_friction():
    """A rope of 5 nodes laid on a rough floor and launched sideways at 1 m/s stops after
    v0^2 / (2 mu g), every node alike (its springs stay at rest length)."""
    from diffpen.builders import add_rope
    scene = dp.Scene()
    scene.add_material("rough", friction=MU, slip_speed=SLIP)
    nodes = add_rope(scene, 5, (0.0, 0.0, 0.0), (0.4, 0.0, 0.0), mass=0.1, k=500.0, c=0.5,
                     pinned=(), velocity=(0.0, 1.0, 0.0))
    scene.add_plane(material="rough")
    sim = dp.compile(scene, dt=1e-4)
    traj = sim.rollout(sim.params(k=K, c=30.0), steps=4000, save_every=4000)
    moved = np.asarray(traj.position[-1, nodes, 1])
    np.testing.assert_allclose(moved, 1.0 / (2 * MU * G), rtol=2e-3)
    np.testing.assert_allclose(np.asarray(traj.velocity[-1, nodes]), 0.0, atol=1e-4)


def test_friction_on_particles_counts_in_the_safe_step():
    """Below the slip speed friction is a damper of rate mu g / s: at s = 1e-6 m/s and mu 0.5
    that is 4.9e6 1/s, past what dt 1e-4 s can take, and the rollout is refused."""
    scene = dp.Scene()
    scene.add_material("rough", friction=0.5, slip_speed=1e-6)
    scene.add_particle(1.0, (0.0, 0.0, 0.0))
    scene.add_plane(material="rough")
    sim = dp.compile(scene, dt=1e-4)
    with pytest.raises(dp.StabilityError, match="set by friction of material 'rough' below "
                       "its slip speed 1e-06 m/s"):
        sim.rollout(sim.params(k=1e3, c=1.0), steps=10)


@pytest.mark.parametrize("mu", [0.3, 0.7])
def test_a_particle_on_a_rough_fixed_sphere_slides_or_holds_by_the_slope(mu):
    """A particle at rest 20 deg from the top of a fixed sphere of radius 1 m (contacts with
    fixed spheres were frictionless): mu 0.3 < tan 20 deg starts sliding at
    g (sin a - mu cos a) = 0.589 m/s^2 (3.355 without friction); mu 0.7 holds it, creeping
    below twice the slip speed. The derivative of the speed w.r.t. mu is -g cos a t."""
    a = np.radians(20.0)
    up = np.array([np.sin(a), 0.0, np.cos(a)])
    scene = dp.Scene()
    scene.add_material("rough", friction=mu, slip_speed=SLIP)
    scene.add_particle(1.0, tuple(up * (1.0 - G * np.cos(a) / K)), allow_overlap=True)
    scene.add_fixed_sphere((0.0, 0.0, 0.0), 1.0, material="rough")
    sim = dp.compile(scene, dt=1e-4)

    def speed(m):
        """Speed down the sphere gained from 0.02 to 0.05 s (past the smooth law's start,
        where it grips below the slip speed), m/s."""
        p = sim.params(k=K, c=C, extra={"friction": {"rough": m}})
        v = sim.rollout(p, steps=500, save_every=100).velocity[:, 0]
        down = v @ jnp.asarray([np.cos(a), 0.0, -np.sin(a)])
        return down[4] - down[1]
    t = 0.03
    if mu < np.tan(a):
        np.testing.assert_allclose(float(speed(mu)), G * (np.sin(a) - mu * np.cos(a)) * t,
                                   rtol=2e-2)
        np.testing.assert_allclose(float(jax.grad(speed)(mu)), -G * np.cos(a) * t, rtol=2e-2)
    else:
        v = sim.rollout(sim.params(k=K, c=C), steps=500, save_every=500).velocity[-1, 0]
        assert float(jnp.linalg.norm(v)) < 2 * SLIP


def test_a_spring_pressing_a_body_on_a_rough_plane_counts_in_the_safe_step():
    """Regression: friction's viscous rate below the slip speed was bounded at the weight
    m g only. A 1 kg ball pressed onto a rough plane (mu 0.5, slip speed 1 cm/s) by a spring
    of 1000 N passed the gate at dt 4e-4 s ("ok", margin 1.25) and never stopped: its
    sliding velocity flipped between +0.099 and -0.102 m/s every step. The springs' start
    tension is counted now: refused there, naming friction; with the substeps it asks for
    the ball stops (as at dt 1e-5 s)."""
    scene = dp.Scene()
    scene.add_material("rough", 1e6, 200.0, friction=0.5, slip_speed=0.01)
    ball = scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.1), velocity=(0.5, 0.0, 0.0))
    scene.add_plane(material="rough")
    scene.add_spring(ball, (0.0, 0.0, 0.1 - 10.0), k=100.0, rest_length=0.0)
    sim = dp.compile(scene, 4e-4)
    with pytest.raises(dp.StabilityError, match="friction of material 'rough'"):
        sim.rollout(sim.params(), 10)
    auto = dp.compile(scene, 4e-4, substeps="auto")
    v = np.asarray(auto.rollout(auto.params(), 500, save_every=10).velocity[-5:, 0, 0])
    assert np.all(np.abs(v) < 1e-4), v


def test_a_spring_stiffened_at_rollout_time_counts_in_the_friction_bound():
    """Regression (audit17): the springs' tension in friction's bound was taken at the
    scene's stiffness. The same ball held by a spring of 1 N/m in the scene, given 1000 N/m
    by the rollout's params (as fits and sweeps do), passed the gate and the traced flag and
    chattered at +-0.1 m/s for ever. The bound now scales the load by the params' k:
    refused concrete, flagged traced, and still fine at the scene's own k."""
    scene = dp.Scene()
    scene.add_material("rough", 1e6, 200.0, friction=0.5, slip_speed=0.01)
    ball = scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.1), velocity=(0.5, 0.0, 0.0))
    scene.add_plane(material="rough")
    scene.add_spring(ball, (0.0, 0.0, 0.1 - 10.0), k=0.1, rest_length=0.0, group="press")
    sim = dp.compile(scene, 4e-4)
    stiff = sim.params(springs={"press": (100.0, 0.0)})
    with pytest.raises(dp.StabilityError, match="friction of material 'rough'"):
        sim.rollout(stiff, 10)
    sim.rollout(sim.params(), 10)                              # the scene's own: safe

    @jax.jit
    def flag(k):
        p = sim.params(springs={"press": (k, 0.0)})
        return sim.rollout(p, 10, save_every=10).aux["unstable"][-1]
    assert bool(flag(100.0)) and not bool(flag(0.1))


def _primitive_counts(jaxpr, acc=None) -> dict:
    """How many times each primitive appears in ``jaxpr`` and the jaxprs inside it."""
    from jax.extend.core import ClosedJaxpr, Jaxpr
    acc = {} if acc is None else acc
    for eqn in jaxpr.eqns:
        acc[eqn.primitive.name] = acc.get(eqn.primitive.name, 0) + 1
        for v in eqn.params.values():
            for sub in (v if isinstance(v, (tuple, list)) else [v]):
                if isinstance(sub, (ClosedJaxpr, Jaxpr)):
                    _primitive_counts(getattr(sub, "jaxpr", sub), acc)
    return acc


@pytest.mark.parametrize("law", ["linear", "events"])
def test_friction_takes_the_contacts_own_normal_force_without_evaluating_the_law_again(law):
    """Regression: the friction of spheres and particles was its own term, which evaluated
    the contact law again for its normal force: a rolling ball on a rough plane computed the
    step window twice per step (4 ``abs`` against 2 without friction), and with the
    event-exact law two sets of per-contact step factors per rollout. Friction is now
    applied by the contact term from the force it has just computed (as the box corners'
    friction is): the step has the frictionless ball's contact arithmetic."""
    def ball(friction):
        s = dp.Scene()
        s.add_material("m", k=1e4, c=20.0, friction=friction, slip_speed=0.01)
        s.add_plane(material="m")
        s.add_rigid_sphere(0.1, 1.0, (0.0, 0.0, 0.099), velocity=(1.0, 0.0, 0.0))
        return dp.compile(s, 1e-3, law=dp.laws.linear(events=True) if law == "events"
                          else law)
    rough, smooth = ball(0.5), ball(0.0)
    counts = [_primitive_counts(jax.make_jaxpr(sim.step_function())(
        sim.params(), sim.init_state()).jaxpr) for sim in (rough, smooth)]
    assert counts[0].get("abs", 0) == counts[1].get("abs", 0), counts
    assert len(rough.context.factor_sites) == len(smooth.context.factor_sites)
    traj = rough.rollout(rough.params(), 300)
    # rolls: v = w r after the slip (5/7 of 1 m/s), on the plane
    np.testing.assert_allclose(traj.velocity[-1, 0, 0], 0.1 * traj.angular_velocity[-1, 0, 1],
                               rtol=1e-6)
