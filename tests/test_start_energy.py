"""Hunt-Crossley's reference depth from the start energy (diffpen.stability.depth,
diffpen.start_energy): a contact that stiffens with depth is judged at the depth where it
would store twice the start's energy, where the scene lets energy bound it, host and traced,
for balls, ropes, ramps, rotating boxes, large scenes and passive custom terms."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen import stability, start_energy


def _hertz_ball(**plane):
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    s.add_plane(**plane)
    return s


def test_a_hertz_contact_is_bounded_at_the_depth_its_start_energy_reaches():
    """Regression: the safe step took Hunt-Crossley's stiffness at a penetration of the full
    radius, so the Hertz ball (1 kg, n 1.5, k 1e6 N/m^1.5, c 3e4, dropped from 1 m: 1.4 cm
    deep at most) was refused at dt 1 ms (w h 0.69 counted, 0.42 real). Where the scene lets
    energy bound the depth (diffpen.stability.depth), a rollout counts the depth at which the
    contact would store twice the start's energy (1.9 cm here: w h 0.45): the drop runs,
    with the traced flag clear; from 30 m, or at k 1e7, it is still refused, and the traced
    flag (parameters under jit) says the same. A vmapped start state, a body starting in
    contact, a named (fittable) floor or a linear law keep the radius."""
    sim = dp.compile(_hertz_ball(), 1e-3, law="hunt_crossley", exponent=1.5)
    assert sim.analysis.depth_exponent == 1.5
    p = sim.params(k=1e6, c=3e4)
    traj = sim.rollout(p, 600, save_every=600)          # through the first bounce
    assert not bool(np.asarray(traj.aux[stability.FLAG])[-1])
    assert float(traj.position[-1, 0, 2]) > 0.3           # it bounced back up
    assert sim.stability(p).safe
    high = sim.state_from(body=[0], position=[[0.0, 0.0, 30.0]])
    with pytest.raises(dp.StabilityError, match="past its safe step"):
        sim.rollout(p, 10, state=high)
    assert not sim.stability(p, high).safe
    with pytest.raises(dp.StabilityError):
        sim.rollout(sim.params(k=1e7, c=3e4), 10)

    # one jitted function for both values (a new jit per call compiled the same program twice)
    flag = jax.jit(lambda k: sim.rollout(sim.params(k=k, c=3e4), 2, save_every=2)
                   .aux[stability.FLAG][-1])
    assert not bool(flag(1e6)) and bool(flag(1e7))
    # a traced start: the radius again, and the error says how the traced flag counts it
    with pytest.raises(dp.StabilityError, match="check_stability=False and read the "
                                                "rollout's traced flag"):
        jax.vmap(lambda z: sim.rollout(p, 2, state=sim.state_from(
            body=[0], position=jnp.stack([0.0, 0.0, z])[None])).position[-1, 0, 2])(
            jnp.array([1.0, 1.1]))
    resting = sim.state_from(body=[0], position=[[0.0, 0.0, 0.099]])
    assert sim.start_energy(resting) is None
    assert dp.compile(_hertz_ball(), 1e-3).analysis.depth_exponent is None


def test_anchored_springs_count_their_stored_energy_at_the_start():
    """The start energy of two Hertz boxes joined by an anchored spring, one of them also hung
    from a world point (both springs stretched, the first box turned): the springs' ``k x^2 /
    2`` at their anchors (turned with the box) and gravity's potential down to each box sunk
    face down, as a hand computation gives it; the traced form equals it; without params
    (no spring stiffness) the radius stays."""
    from tuning.pose import rotmat
    half, q = 0.05, np.array([0.9, 0.1, 0.2, 0.3]) / np.linalg.norm([0.9, 0.1, 0.2, 0.3])
    s = dp.Scene()
    a = s.add_box((half,) * 3, 1.0, (0.0, 0.0, 0.5), orientation=tuple(q))
    b = s.add_box((half,) * 3, 1.0, (0.3, 0.0, 0.5))
    s.add_anchored_spring(a, b, (half, 0.0, 0.0), (-half, 0.0, 0.0), k=200.0, rest_length=0.15)
    s.add_anchored_spring(a, None, (0.0, 0.0, half), (0.0, 0.0, 1.0), k=100.0,
                          rest_length=0.4, group="hang")
    s.add_plane()
    sim = dp.compile(s, 1e-3, law="hunt_crossley", exponent=1.5)
    p = sim.params(k=1e5, c=1e2)
    start = sim.init_state()
    rot = rotmat(q)
    x = np.array([0.0, 0.0, 0.5])
    stretch = (np.linalg.norm(x + rot @ [half, 0, 0] - [0.3 - half, 0.0, 0.5]) - 0.15,
               np.linalg.norm(x + rot @ [0, 0, half] - [0.0, 0.0, 1.0]) - 0.4)
    sink = np.sqrt(3.0) * half - half
    want = 0.5 * 200.0 * stretch[0] ** 2 + 0.5 * 100.0 * stretch[1] ** 2 + 2 * 9.81 * (0.5 + sink)
    assert min(abs(v) for v in stretch) > 1e-3
    assert sim.start_energy(start, p) == pytest.approx(want, rel=1e-12)
    assert float(jax.jit(lambda st: start_energy.traced(sim, p, st))(start)) == pytest.approx(
        want, rel=1e-12)
    assert sim.start_energy(start) is None


def test_traced_starts_and_named_floors_count_their_start_energy_in_the_traced_flag():
    """Regression: a traced start state (jax.vmap over where the Hertz ball starts) or a
    named, fittable floor kept the radius as the reference depth, so the traced flag of a
    drop from 1 m was raised as it is from 30 m. The traced flag now counts the start
    energy from traced values too: under vmap the 1 m drop is clear and the 30 m drop is
    flagged (the up-front check cannot read traced values: it still refuses them); a named
    floor counts from its offset in the params, concrete (the up-front check) or traced
    (under jit: clear at 0, flagged where the raised floor starts in contact with the
    ball, and where it is lowered 30 m)."""
    sim = dp.compile(_hertz_ball(), 1e-3, law="hunt_crossley", exponent=1.5)
    p = sim.params(k=1e6, c=3e4)

    def flag_from(z):
        state = sim.state_from(body=[0], position=jnp.stack([0.0, 0.0, z])[None])
        return sim.rollout(p, 2, state=state, save_every=2,
                           check_stability=False).aux[stability.FLAG][-1]
    assert np.asarray(jax.jit(jax.vmap(flag_from))(jnp.array([1.0, 30.0]))).tolist() == [
        False, True]
    named = dp.compile(_hertz_ball(name="ground"), 1e-3, law="hunt_crossley", exponent=1.5)
    assert named.analysis.depth_exponent == 1.5
    q = named.params(k=1e6, c=3e4)
    assert named.start_energy(named.init_state()) is None          # no offset given
    assert named.start_energy(named.init_state(), q) == pytest.approx(9.81)
    traj = named.rollout(q, 600, save_every=600)                    # the gate counts it
    assert not bool(np.asarray(traj.aux[stability.FLAG])[-1])

    def flag_at(offset):
        r = q._replace(extra={**q.extra, "plane_offset": {"ground": offset}})
        return named.rollout(r, 2, save_every=2,
                             check_stability=False).aux[stability.FLAG][-1]
    assert [bool(jax.jit(flag_at)(o)) for o in (0.0, 0.95, -30.0)] == [False, True, True]


def _hertz_rope(**first):
    """Three 1 kg balls (radius 0.1 m) 0.3 m apart at 1 m, joined by springs at their rest
    length (k 500 N/m, c 1 N s/m), over the ground; ``first``: the first ball's options."""
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0), **first)
    for i in (1, 2):
        s.add_sphere(0.1, 1.0, (0.3 * i, 0.0, 1.0))
        s.add_spring(i - 1, i, k=500.0, c=1.0)
    s.add_plane()
    return s


def test_a_hertz_rope_is_bounded_at_the_depth_its_start_energy_reaches():
    """Regression: any spring kept the radius as Hunt-Crossley's reference depth, so three
    Hertz balls joined by springs (k 3e5 N/m^1.5, c 3e4, dropped from 1 m) were refused at
    dt 1 ms (their 10 cm radius counted; the balls sink under 5 cm). A damped spring gives
    back no more than it stored, so where every free body collides, the start energy
    (the springs' own ``k x^2 / 2`` included, their k from the params) bounds the depth as
    for one ball: the drop runs with the traced flag clear and sinks less than counted; a
    spring stretched by 1 cm adds its 0.025 J, one stretched by 1 m is refused; a plastic
    spring counts what it stores against its current rest length (its rest length only
    follows its compressed length, which lowers what it stores). Without params a stretched
    spring keeps the radius, and so does a free body no plane holds up (it could pull the
    others in)."""
    from diffpen.stability.depth import energy_depth
    sim = dp.compile(_hertz_rope(), 1e-3, law="hunt_crossley", exponent=1.5)
    assert sim.analysis.depth_exponent == 1.5
    p = sim.params(k=3e5, c=3e4)
    assert not stability.report(sim.analysis, p).safe             # at the radius: refused
    assert sim.stability(p).safe
    energy = sim.start_energy(sim.init_state())
    assert energy == pytest.approx(3 * 9.81 * 1.0, rel=1e-12)    # at rest, counted from z = 0
    traj = sim.rollout(p, 700, observe=lambda s: jnp.min(s.position[:, 2]))
    assert not bool(np.asarray(traj.aux[stability.FLAG])[-1])
    deepest = 0.1 - float(np.min(np.asarray(traj.observed)))
    assert 0.0 < deepest < float(energy_depth(1.5, 3e5, energy)) < 0.1
    stretched = sim.state_from(body=[0], position=[[-0.01, 0.0, 1.0]])
    assert sim.start_energy(stretched) is None                    # no spring stiffness given
    assert sim.start_energy(stretched, p) == pytest.approx(3 * 9.81 + 0.5 * 500.0 * 0.01 ** 2,
                                                           rel=1e-9)
    sim.rollout(p, 10, state=stretched)                           # its springs' energy counts
    far = sim.state_from(body=[0], position=[[-1.0, 0.0, 1.0]])   # 1 m: 250 J more
    with pytest.raises(dp.StabilityError):
        sim.rollout(p, 10, state=far)
    # a plastic spring counts what it stores against its current rest length (State.aux): a
    # rest length shortened to 0.5 m stores 100 N/m x (0.1 m)^2 / 2 at the start's 0.6 m
    scene = _hertz_rope()
    scene.add_plastic_spring(0, 2, k=100.0, yield_strain=0.1)
    plastic = dp.compile(scene, 1e-3, law="hunt_crossley", exponent=1.5)
    assert plastic.analysis.depth_exponent == 1.5
    q = plastic.params(k=3e5, c=3e4)
    start = plastic.init_state()
    assert plastic.start_energy(start, q) == pytest.approx(3 * 9.81, rel=1e-12)
    shortened = start._replace(aux={**start.aux, "plastic_rest": jnp.array([0.5])})
    assert plastic.start_energy(shortened, q) == pytest.approx(3 * 9.81 + 0.5, rel=1e-12)
    assert float(jax.jit(lambda st: start_energy.traced(plastic, q, st))(shortened)) == (
        pytest.approx(3 * 9.81 + 0.5, rel=1e-12))
    loose = dp.compile(_hertz_rope(collide=False), 1e-3, law="hunt_crossley", exponent=1.5)
    assert loose.analysis.depth_exponent is None


def _hertz_drop_counts_its_start_energy(scene, steps):
    """The Hertz ball of ``scene`` (1 kg, dropped from 1 m; k 1e6 N/m^1.5, c 3e4) at dt
    0.7 ms: refused at the radius, its start energy counted (9.81 J, host and traced), and
    ``steps`` steps run with the traced flag clear. Returns its centre (steps, 3), m, and the
    energy, J."""
    sim = dp.compile(scene, 7e-4, law="hunt_crossley", exponent=1.5)
    assert sim.analysis.depth_exponent == 1.5
    p = sim.params(k=1e6, c=3e4)
    assert not stability.report(sim.analysis, p).safe             # at the radius: refused
    energy = sim.start_energy(sim.init_state(), p)
    assert energy == pytest.approx(9.81, rel=1e-12)
    assert float(jax.jit(lambda st: start_energy.traced(sim, p, st))(sim.init_state())) == (
        pytest.approx(9.81, rel=1e-12))
    traj = sim.rollout(p, steps, observe=lambda s: s.position[0])
    assert not bool(np.asarray(traj.aux[stability.FLAG])[-1])
    return np.asarray(traj.observed), energy


def test_a_ramp_over_a_floor_is_bounded_at_the_depth_its_start_energy_reaches():
    """Regression: a plane that is not a horizontal floor kept the radius as Hunt-Crossley's
    reference depth, so the Hertz ball (1 kg, k 1e6 N/m^1.5, c 3e4) dropped from 1 m onto a
    20 deg ramp over the floor was refused at dt 0.7 ms (w h 0.67 and c h / m 1.29 at its
    10 cm radius). Every colliding body stays above every plane, so one horizontal floor
    bounds gravity's potential whatever the other planes' tilt: the start energy counts
    (9.81 J, host and traced), the drop runs with the traced flag clear, and the ball, which
    hits the ramp, rolls down it and lands on the floor, sinks into either less than
    counted. A ramp alone keeps the radius (nothing holds a body up)."""
    from diffpen.stability.depth import energy_depth
    tilt = np.deg2rad(20.0)
    normal = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    scene.add_plane()
    scene.add_plane(normal=tuple(normal), offset=0.3)
    x, energy = _hertz_drop_counts_its_start_energy(scene, 4000)
    floor, ramp = 0.1 - x[:, 2], 0.1 - (x @ normal - 0.3)
    assert x[-1, 0] > 1.0 and floor.max() > 0.0 and ramp.max() > 0.0   # ramp, then floor
    assert max(floor.max(), ramp.max()) < float(energy_depth(1.5, 1e6, energy)) < 0.1
    tilted = dp.Scene()
    tilted.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    tilted.add_plane(normal=tuple(normal), offset=0.3)
    assert dp.compile(tilted, 7e-4, law="hunt_crossley",
                      exponent=1.5).analysis.depth_exponent is None


def test_a_trough_of_tilted_planes_is_bounded_at_the_depth_its_start_energy_reaches():
    """Regression: without a horizontal floor every scene kept the radius, so the Hertz ball
    (1 kg, k 1e6 N/m^1.5, c 3e4) dropped from 1 m into a V-trough of two planes tilted
    30 deg was refused at dt 0.7 ms. The two normals, each weighted 1 / (2 cos 30 deg), sum
    to the up direction, so a body above both is no lower than the weighted sum of their
    offsets (the weak dual of the trough's lowest point): the start energy counts (9.81 J,
    host and traced), the drop runs with the traced flag clear and sinks into either plane
    less than counted. So does a funnel of three tilted planes, and a ramp sloping into a
    wall; a ramp sloping away from the wall does not hold a body up."""
    from diffpen.stability import depth
    from diffpen.stability.depth import energy_depth
    tilt = np.deg2rad(30.0)
    normals = [np.array([s * np.sin(tilt), 0.0, np.cos(tilt)]) for s in (1.0, -1.0)]
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.05, 0.0, 1.0))
    for n in normals:
        scene.add_plane(normal=tuple(n))
    [(planes, w)] = depth._floors(scene)
    assert planes == (0, 1) and w == pytest.approx([0.5 / np.cos(tilt)] * 2, rel=1e-12)
    x, energy = _hertz_drop_counts_its_start_energy(scene, 3000)
    deepest = [float(np.max(0.1 - x @ n)) for n in normals]
    assert min(deepest) > 0.0 and max(deepest) < float(energy_depth(1.5, 1e6, energy)) < 0.1

    def held(*planes):
        funnel = dp.Scene()
        funnel.add_sphere(0.1, 1.0, (0.0, 0.0, 2.0))
        for n in planes:
            funnel.add_plane(normal=n, offset=-1.0)
        return depth._floors(funnel)
    azimuths = np.deg2rad([0.0, 120.0, 240.0])
    [(_, w)] = held(*[(np.sin(tilt) * np.cos(a), np.sin(tilt) * np.sin(a), np.cos(tilt))
                      for a in azimuths])
    assert w == pytest.approx([1.0 / (3.0 * np.cos(tilt))] * 3, rel=1e-12)
    ramp = (np.sin(tilt), 0.0, np.cos(tilt))                      # slopes down towards +x
    assert held(ramp, (-1.0, 0.0, 0.0))                            # a wall at its foot
    assert not held(ramp, (1.0, 0.0, 0.0))                         # a wall at its top


def test_a_body_that_collides_with_nothing_leaves_the_start_energy_alone():
    """Regression: the start energy counted every free body, also one that collides with
    nothing (and, in a scene that qualifies, hangs on no spring), whose energy never reaches
    a contact: a 1 kg particle 5 m up loosened the Hertz ball's bound (58.9 J instead of
    9.81), and one 1000 m below the floor made it negative (-9800 J), so the stability
    analysis stopped on a misleading error about negative stiffness; a particle 0.5 m below
    the floor would have halved the energy counted, and the safe step with it. Now only bodies
    that collide count: 9.81 J wherever the particle is, host and traced."""
    for z in (5.0, -0.5, -1000.0):
        scene = dp.Scene()
        scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
        scene.add_particle(1.0, (3.0, 0.0, z), collide=False)
        scene.add_plane()
        sim = dp.compile(scene, 1e-3, law="hunt_crossley", exponent=1.5)
        p = sim.params(k=1e6, c=3e4)
        assert sim.start_energy(sim.init_state(), p) == pytest.approx(9.81, rel=1e-12)
        assert float(jax.jit(lambda st: start_energy.traced(sim, p, st))(
            sim.init_state())) == pytest.approx(9.81, rel=1e-12)
        assert sim.stability(p).safe


def test_boxes_side_by_side_count_their_start_energy():
    """Regression: the check that no two bodies start touching compared every pair of
    colliding bodies by their bounding spheres, boxes with boxes too, which never touch: two
    Hertz cubes (10 cm, 0.37 kg) 2 cm apart, 20 cm up, kept the radius (their half-diagonals
    overlap). Only pairs that have a contact are compared now (sphere-sphere, a sphere or
    particle with a box): the two cubes count their potential energy, host and traced; a
    sphere inside a cube's bounding sphere still keeps the radius."""
    scene = dp.Scene()
    for x in (0.0, 0.12):
        scene.add_box((0.05,) * 3, 0.37, (x, 0.0, 0.2))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3, law="hunt_crossley", exponent=1.5)
    want = 2 * 0.37 * 9.81 * (0.2 + (math.sqrt(3.0) - 1.0) * 0.05)   # sunk face down
    assert sim.start_energy(sim.init_state()) == pytest.approx(want, rel=1e-12)
    assert float(jax.jit(lambda st: start_energy.traced(sim, sim.params(k=1e5, c=1e3), st))(
        sim.init_state())) == pytest.approx(want, rel=1e-12)
    scene.add_sphere(0.02, 0.1, (0.06, 0.08, 0.2))     # 9 cm from both centres
    sim = dp.compile(scene, 1e-3, law="hunt_crossley", exponent=1.5)
    assert sim.start_energy(sim.init_state()) is None


def test_a_custom_term_declared_passive_keeps_the_start_energy_bound():
    """Any custom term kept the radius as Hunt-Crossley's reference depth (it could give
    energy back). A term declared passive (``TermBuilder(..., passive=True)``: an air drag
    ``-0.05 |v| v`` here) lets the Hertz ball (k 1e6 N/m^1.5, c 3e4, from 1 m) count its
    start energy as without it: the drop runs at dt 1 ms with the traced flag clear. The
    same term undeclared keeps the radius, and the step is refused."""
    def air_drag(ctx):
        def force(params, state):
            v = state.velocity
            return -0.05 * jnp.sqrt(jnp.sum(v * v, axis=1, keepdims=True) + 1e-12) * v, None
        return dp.terms.Term("air_drag", force)
    for term, exponent in ((dp.terms.TermBuilder(air_drag, passive=True), 1.5),
                           (dp.terms.with_bound(air_drag, None, passive=True), 1.5),
                           (air_drag, None), (dp.terms.TermBuilder(air_drag), None)):
        sim = dp.compile(_hertz_ball(), 1e-3, law="hunt_crossley", exponent=1.5,
                         terms=(*dp.terms.BUILTIN, term))
        assert sim.analysis.depth_exponent == exponent
        p = sim.params(k=1e6, c=3e4)
        if exponent is None:
            with pytest.raises(dp.StabilityError, match="past its safe step"):
                sim.rollout(p, 10)
            continue
        traj = sim.rollout(p, 600, save_every=600)
        assert not bool(np.asarray(traj.aux[stability.FLAG])[-1])
        assert float(traj.position[-1, 0, 2]) > 0.3          # it bounced back up
    with pytest.raises(dp.SceneError, match="passive must be True or False"):
        dp.compile(_hertz_ball(), 1e-3, law="hunt_crossley", exponent=1.5,
                   terms=(*dp.terms.BUILTIN, dp.terms.TermBuilder(air_drag, passive="yes")))


def test_more_than_512_colliding_bodies_count_their_start_energy():
    """Regression: with more than 512 colliding bodies the start energy was not counted (its
    check that no two bodies start touching compared every pair at once), so 600 Hertz beads
    (1 g, radius 5 mm, a 10 x 6 x 10 grid 2 cm apart, 5-23 cm up; k 1e8 N/m^1.5, c 1e3)
    kept the radius and were refused at dt 4 us. On the host the check now sweeps along x:
    the beads count their potential energy (0.824 J) and the step is inside the safe step;
    two beads touching give None; the sweep agrees with every pair compared on random
    placements. A traced start state of that many bodies still keeps the radius."""
    from diffpen.stability import depth
    scene = dp.Scene()
    grid = [(0.02 * i, 0.02 * j, 0.05 + 0.02 * k)
            for i in range(10) for j in range(6) for k in range(10)]
    for pos in grid:
        scene.add_sphere(0.005, 0.001, pos)
    scene.add_plane()
    sim = dp.compile(scene, 4e-6, law="hunt_crossley", exponent=1.5)
    p = sim.params(k=1e8, c=1e3)
    assert not stability.report(sim.analysis, p).safe             # at the radius: refused
    want = 0.001 * 9.81 * sum(z for _, _, z in grid)
    assert sim.start_energy(sim.init_state()) == pytest.approx(want, rel=1e-12)
    assert sim.stability(p).safe
    touching = sim.state_from(body=[1], position=[[0.0, 0.0, 0.059]])   # 9 mm above bead 0
    assert sim.start_energy(touching) is None
    assert float(start_energy.traced(sim, p, sim.init_state())) == math.inf
    rng = np.random.default_rng(0)
    for n in (2, 40, 300):
        for spread in (0.1, 1.0):
            x = rng.uniform(0.0, spread, (n, 3))
            r = rng.uniform(0.001, 0.03, n)
            kind = rng.integers(0, 3, n)                  # particles, spheres, boxes
            gap = np.linalg.norm(x[:, None] - x[None], axis=-1) - (r[:, None] + r[None])
            pairs = depth._can_touch(kind[:, None], kind[None]) & ~np.eye(n, dtype=bool)
            assert depth._touching(x, r, kind) == bool(np.any(pairs & (gap <= 0.0)))


def test_a_rotating_box_is_bounded_at_the_depth_its_start_energy_reaches():
    """Regression: rotating bodies kept the radius as Hunt-Crossley's reference depth (for the
    cube, its 9.1 cm half-diagonal). The start energy now bounds their depth too, with the
    rotation's kinetic energy and the potential a box can release by sinking face down
    (its half-diagonal less its half-width) counted: a spinning Hertz cube thrown at the
    board (k 1.5e6 N/m^1.5, a step the radius refuses, w h 1.5x its safe limit) counts its
    depth at 7 mm, runs inside the safe step with the traced flag clear, and its corners reach
    less deep than counted. A box whose corner starts on the plane keeps the radius (its
    bounding sphere may touch the plane while its corners are clear: that start counts)."""
    from diffpen.geometry import box_corners
    from diffpen.stability.depth import energy_depth
    from tuning.pose import rotmat
    half = 0.0524
    scene = dp.Scene()
    scene.add_box((half,) * 3, 0.37, (0.0, 0.0, 0.25), (0.5, 0.0, -1.0),
                  orientation=(0.9, 0.3, 0.2, 0.1), angular_velocity=(3.0, -5.0, 2.0),
                  inertia=(8.1e-4,) * 3)
    scene.add_plane()
    sim = dp.compile(scene, 1.0 / 148 / 8, law=dp.laws.hunt_crossley(1.5))
    start = sim.init_state()
    energy = sim.start_energy(start)
    w = np.asarray(start.angular_velocity[0])
    r = float(np.hypot(half, np.hypot(half, half)))
    want = (0.5 * 0.37 * 1.25 + 0.5 * 8.1e-4 * w @ w
            + 0.37 * 9.81 * (0.25 + r - half))
    assert energy == pytest.approx(want, rel=1e-12)
    p = sim.params(k=1.5e6, c=1e3)
    assert not stability.report(sim.analysis, p).safe             # at the radius: refused
    assert sim.stability(p).safe                                    # at the counted depth
    traj = sim.rollout(p, 600, observe=lambda s: s)               # lands, bounces, tumbles
    assert not bool(traj.aux[stability.FLAG][-1])
    counted = float(energy_depth(1.5, 1.5e6, energy))
    # to numpy once: indexing a jax array dispatches (and first compiles) a program per call
    seen = jax.tree_util.tree_map(np.asarray, traj.observed)
    lowest = min(float(seen.position[i, 0, 2]) + float(np.min(
        (box_corners((half,) * 3) @ rotmat(seen.orientation[i, 0]).T)[:, 2]))
        for i in range(600))
    assert 0.0 < -lowest < counted < 0.01                   # it sank, less than counted
    on = sim.state_from(body=[0], position=[[0.0, 0.0, half + 0.01]],
                        orientation=[[1.0, 0.0, 0.0, 0.0]])
    assert sim.start_energy(on) is not None                 # flat, 1 cm clear: counts
    touching = sim.state_from(body=[0], position=[[0.0, 0.0, half]],
                              orientation=[[1.0, 0.0, 0.0, 0.0]])
    assert sim.start_energy(touching) is None


@pytest.mark.parametrize("centre", [-0.5, -1.0])
def test_a_body_started_deeper_than_its_radius_is_bounded_at_its_start_depth(centre):
    """Regression: a Hertz ball (n 1.5, k 1e6, 1 kg, radius 0.1 m) started 0.6 or 1.1 m deep
    (allow_overlap) kept its radius as reference depth, where the contact is 2.4-3.3x softer:
    at that safe step its launch gained 19-27% of its energy, with the gate's "ok". Now the
    start depth D: the safe step 0.5 / sqrt(n k D^(n-1) / m), and the launch keeps the 7.3%
    of a ball started at its radius (w h = 0.5)."""
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, centre), allow_overlap=True)
    scene.add_plane()
    depth = 0.1 - centre
    sim = dp.compile(scene, 1e-3, law="hunt_crossley", exponent=1.5)
    p = sim.params(k=1e6, c=0.0)
    safe = sim.stability(p).safe_dt
    assert safe == pytest.approx(0.5 / math.sqrt(1.5e6 * depth ** 0.5), rel=1e-6)
    run = dp.compile(scene, safe, law="hunt_crossley", exponent=1.5)
    traj = run.rollout(p, int(0.5 / safe))
    z, v = float(traj.position[-1, 0, 2]), float(traj.velocity[-1, 0, 2])
    e0 = 1e6 * depth ** 2.5 / 2.5 + 9.81 * centre
    assert 0.5 * v * v + 9.81 * z < 1.08 * e0


def test_a_sphere_started_deep_inside_a_free_body_takes_that_depth():
    """Regression: start depths counted planes and fixed spheres only: a Hertz sphere (r 2 cm,
    0.1 kg, k 1e6 N/m^1.5, no gravity) started 0.4 m deep in a free 1e6 kg sphere kept its
    2 cm radius as reference depth, took 5 auto substeps and left with 10.6% more energy
    than the contact stored (in the same sphere fixed: 0.4 m, 7 substeps, +5.3%). Now both
    bodies of the pair take the 0.4 m."""
    k, n, depth = 1e6, 1.5, 0.4
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_sphere(0.5, 1e6, (0.0, 0.0, 0.0), allow_overlap=True)
    scene.add_sphere(0.02, 0.1, (0.5 + 0.02 - depth, 0.0, 0.0), allow_overlap=True)
    scene.add_material("default", k=k, c=0.0)
    sim = dp.compile(scene, 1e-3, law=dp.laws.hunt_crossley(n), substeps="auto")
    traj = sim.rollout(sim.params(), 400, save_every=400)
    v = np.asarray(traj.velocity[-1])
    ke = 0.5 * np.sum(np.array([1e6, 0.1])[:, None] * v * v)
    assert ke / (k * depth ** (n + 1) / (n + 1)) - 1.0 < 0.06
