"""The start state of a record (tuning.first_state, tuning.record_batch.prepare) for bodies
that accelerate at row 0: the rate and angular acceleration of a body on springs, and the
integrator's velocity lag applied to velocity columns and to the bodies a record does not
observe, on records the simulator made itself."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen.rigid import inertia_diagonal
from tuning import first_state as first_state_mod
from tuning import pose
from tuning import trajfit as tf
from tuning.first_state import flight_frames, torque_free
from tuning.pose import exp_quat, qmul, rotmat
from tuning.record_batch import lag_start, start_states
from tuning.records import BodyRecord, Record
from tuning.scenefile import load_scene_file

from record_scenes import BALL_FIT, BOX as BOX_TEMPLATE

# the box of tests/test_trajfit.py (k 400, c 2), released at rest on two anchored springs
BOX = BOX_TEMPLATE.format(k=400.0, c=2.0)

ROPE = """
dt = 1e-3
[[ropes]]
n = 4
start = [0.0, 0.0, 1.0]
end = [0.3, 0.0, 1.0]
mass = 0.2
k = 300.0
c = 0.5
pinned = [0]
velocity = [0.0, 0.4, 0.0]
"""

# a 5 x 5 x 10 cm box tossed above the ground (no spring or drag: free flight)
TOSS = """
[[boxes]]
name = "box"
half_extents = [0.025, 0.025, 0.05]
mass = 0.2
position = [0.0, 0.0, 0.3]
[[planes]]
name = "ground"
"""


def _scene(tmp_path, text):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return load_scene_file(str(path))


@pytest.fixture(scope="module")
def rope(tmp_path_factory):
    """(scene file, semi-implicit Euler simulator, rk4 simulator at 25 us) of ROPE, compiled
    once for the tests that read it (shared: a Simulator is frozen)."""
    sf = _scene(tmp_path_factory.mktemp("rope"), ROPE)
    return sf, sf.compile(), sf.compile(integrator="rk4", dt=2.5e-5)


def _start_states(sim, batch):
    """:func:`start_states` of ``batch`` as one compiled function of the parameters (op by op
    it compiled each of its operations)."""
    return jax.jit(lambda params: start_states(sim, params, batch))


def _stepped_from(sim, params):
    """The state a semi-implicit Euler record starts its rollout from: the scene's rates
    less the lag (tuning.synthetic.synthetic_record), what the fit's start must find."""
    return lag_start(sim, sim.init_state(), [], 0.5 * sim.dt, params)


def test_spin_of_a_body_on_springs_takes_its_angular_acceleration(tmp_path):
    """Regression: a body on springs got the mean turn rate of its first 5 frames (no
    angular acceleration) and no velocity lag on it: the box released at rest on two
    springs, recorded by the fit's own integrator (1 ms frames, no velocity columns),
    started at 1.7 rad/s (5.9 rad/s from 5 ms frames, where the true k and c then
    evaluated to 17% and 69 deg). Now the rotation since row 0 gets the quadratic the
    positions get, and the rate the lag ``w - h alpha / 2``: both start at rest."""
    sf = _scene(tmp_path, BOX)
    sim = sf.compile()
    rec = tf.synthetic_record(sim, sf.params(sim), 0.02, 1e-3, {"box": 0}, velocities=False)
    batch = tf.prepare(sim, [rec], estimate="record")
    true = _stepped_from(sim, sf.params(sim))
    w = np.asarray(batch.start.angular_velocity)[0, 0] - np.asarray(true.angular_velocity)[0]
    v = np.asarray(batch.start.velocity)[0, 0] - np.asarray(true.velocity)[0]
    assert np.linalg.norm(w) < 0.1, w           # was 1.7 rad/s; 0.37 without the lag
    assert np.linalg.norm(v) < 2e-3, v          # 0.027 m/s without the lag
    # the same from 5 ms frames: far closer than the constant rate's 5.9 rad/s
    rec = tf.synthetic_record(sim, sf.params(sim), 0.05, 5e-3, {"box": 0}, velocities=False)
    w = np.asarray(tf.prepare(sim, [rec], estimate="record").start.angular_velocity)[0, 0]
    assert np.linalg.norm(w - np.asarray(true.angular_velocity)[0]) < 1.5, w


def test_velocity_columns_take_the_integrators_lag(rope):
    """Regression: velocity columns were taken as the state's velocity while velocities
    estimated from the frames took the lag ``v - h a / 2``: exact columns of a rope
    recorded by rk4 (the path's own rate) started semi-implicit Euler 5 mm/s off and
    moved a fit's k by -1.4% and c by -3.2% (-0.1%, +0.5% without the columns). Now both
    take it: the start with the columns is the one without them, and the state the
    rk4 path's rate less ``h a / 2``, ``a`` the acceleration at row 0."""
    sf, sim, ref = rope
    ids = {f"rope[{i}]": sf.names[f"rope[{i}]"] for i in (1, 2, 3)}
    rec = tf.synthetic_record(ref, ref.params(), 0.05, 5e-3, ids)
    bare = Record(rec.path, rec.t, {n: BodyRecord(b.position) for n, b in rec.bodies.items()})
    with_v, without = (tf.prepare(sim, [r], bodies=ids, estimate="record") for r in (rec, bare))
    s0 = ref.init_state()
    a, _ = ref.acceleration(ref.params(), s0)
    want = np.asarray(s0.velocity) - 0.5 * sim.dt * np.asarray(a)
    got = np.asarray(with_v.start.velocity)[0]
    np.testing.assert_allclose(got, want, atol=2e-4)          # the lag: 4.9 mm/s
    assert np.max(np.abs(got - np.asarray(s0.velocity))) > 4e-3
    # the frames alone give the same start to the quadratic's error (2.7 mm/s at the node
    # next to the pin)
    np.testing.assert_allclose(np.asarray(without.start.velocity)[0], want, atol=4e-3)


def test_unobserved_bodies_take_the_lag_too(rope):
    """Regression: the bodies a record does not observe start from the scene file's
    velocities, which took no lag while the observed ones did: the cloth of
    tests/test_trajfit.py observed at 4 of its 25 nodes, from a noise-free rk4 record
    without velocity columns, fitted c 7.5% low (+1.0% now). Now the scene file's
    velocities take ``- h a / 2`` at the start too: a rope observed at one node starts
    every free node at its rk4 rate less the lag."""
    sf, sim, ref = rope
    ids = {"rope[3]": sf.names["rope[3]"]}
    rec = tf.synthetic_record(ref, ref.params(), 0.05, 5e-3, ids)
    start = _start_states(sim, tf.prepare(sim, [rec], bodies=ids,
                                          estimate="record"))(sf.params(sim))
    s0 = ref.init_state()
    a, _ = ref.acceleration(ref.params(), s0)
    want = np.asarray(s0.velocity) - 0.5 * sim.dt * np.asarray(a)
    np.testing.assert_allclose(np.asarray(start.velocity)[0], want, atol=2e-4)
    assert np.max(np.abs(np.asarray(start.velocity)[0, 0])) == 0.0          # pinned
    # verlet and rk4 step from the path's own rate: nothing moves
    verlet = sf.compile(integrator="verlet")
    plain = _start_states(verlet, tf.prepare(verlet, [rec], bodies=ids,
                                             estimate="record"))(sf.params(verlet))
    np.testing.assert_allclose(np.asarray(plain.velocity)[0], np.asarray(s0.velocity),
                               atol=1e-12)


def test_the_lag_matches_the_simulators_own_steps(tmp_path):
    """The lag algebra on a record semi-implicit Euler made itself, frames at every step,
    no velocity columns: the start it returns is the state it started from (linear and
    angular), to the quadratic's error over 5 frames."""
    sf = _scene(tmp_path, BOX.replace("collide = false", "collide = false\nvelocity = "
                                      "[0.1, -0.2, 0.3]\nbody_angular_velocity = [0.5, 0.0, "
                                      "-1.0]"))
    sim = sf.compile()
    rec = tf.synthetic_record(sim, sf.params(sim), 0.01, 1e-3, {"box": 0}, velocities=False)
    b = rec.bodies["box"]
    s0 = _stepped_from(sim, sf.params(sim))
    for est in ("record", "fit"):
        p, v, q, w = tf.first_state(sim.scene, 0, rec.t, b.position, b.quaternion,
                                    estimate=est, lag=0.5 * sim.dt)
        np.testing.assert_allclose(v, np.asarray(s0.velocity)[0], atol=2e-3)
        np.testing.assert_allclose(w, np.asarray(s0.angular_velocity)[0], atol=0.1)
    with pytest.raises(AssertionError):         # without the lag: h alpha / 2 off
        np.testing.assert_allclose(tf.first_state(sim.scene, 0, rec.t, b.position,
                                                  b.quaternion, estimate="record")[3],
                                   np.asarray(s0.angular_velocity)[0], atol=0.1)


def test_a_record_the_fit_itself_made_starts_every_body_where_it_did(rope):
    """Regression: a record made by semi-implicit Euler started its rollout from the scene's
    velocities as the step's own, while the fit read them as rates and took the lag from
    the bodies it does not observe: a noise-free rope observed at its tip started its other
    nodes 4.9 mm/s off and fitted c 35% high. The record now steps from the scene's rates
    less the lag, and the fit's start is that state."""
    sf, sim, _ = rope
    ids = {"rope[3]": sf.names["rope[3]"]}
    rec = tf.synthetic_record(sim, sf.params(sim), 0.1, 5e-3, ids)
    start = _start_states(sim, tf.prepare(sim, [rec], bodies=ids,
                                          estimate="record"))(sf.params(sim))
    true = _stepped_from(sim, sf.params(sim))
    np.testing.assert_allclose(np.asarray(start.velocity)[0], np.asarray(true.velocity),
                               atol=2e-5)


@pytest.fixture(scope="module")
def hung_pair():
    """(simulator, a, b, record): sphere b hangs from sphere a on a stretched spring (k 60
    N/m), so b's acceleration at the start depends on a fitted value; contact values
    undeclared. The record (0.05 s, 5 ms frames) observes a only, made at k = 1e4, c = 1 for
    the contacts. Shared: never mutate them."""
    import diffpen as dp
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    a = s.add_sphere(0.03, 0.3, (0.0, 0.0, 0.7))
    b = s.add_sphere(0.03, 0.2, (0.0, 0.0, 0.4))
    s.add_spring(a, b, k=60.0, c=0.1, rest_length=0.25)
    sim = dp.compile(s, dt=1e-3)
    rec = tf.synthetic_record(sim, sim.params(k=1e4, c=1.0), 0.05, 5e-3, {"a": a})
    return sim, a, b, rec


def test_the_unobserved_bodies_lag_is_taken_at_the_simulated_parameters(hung_pair):
    """Regression: the unobserved bodies' lag evaluated ``sim.params()``, which a scene
    without declared contact values refuses: prepare crashed, with advice it could not
    follow. Then it was taken once, at the parameters given to prepare: a fit kept the lag
    of its start values, so two spheres on springs (only the upper one observed) fitted
    low.k 60.228 +- 0.019 from a start of (60, 150) and 59.898 +- 0.007 from (400, 25)
    against 59.990 from the truth, and the fit's "after" (0.4587%) was not what evaluate
    of the written file gave (0.3872%). Now prepare needs no parameters and every rollout
    takes the lag at its own (:func:`start_states`, inside :func:`simulate`)."""
    import diffpen as dp
    from tuning.errors import FitError
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    a = s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    b = s.add_sphere(0.1, 1.0, (1.0, 0.0, 1.0))
    s.add_plane()
    sim = dp.compile(s, dt=1e-3)
    p = sim.params(k=1e4, c=20.0)
    rec = tf.synthetic_record(sim, p, 0.05, 5e-3, {"ball": a})
    with pytest.raises(FitError, match=r"lag_start\(\.\.\., params=\.\.\.\)"):
        lag_start(sim, sim.init_state(), [a], 5e-4)
    batch = tf.prepare(sim, [rec], bodies={"ball": a})
    start = _start_states(sim, batch)(p)
    assert float(np.asarray(start.velocity)[0, b, 2]) == pytest.approx(0.5e-3 * 9.81,
                                                                       rel=1e-9)
    # a force that depends on a fitted value: b hangs from a on a stretched spring
    sim, a, b, rec = hung_pair
    batch = tf.prepare(sim, [rec], bodies={"a": a})
    seen = []
    first = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], batch.start)
    lagged = jax.jit(lambda p: lag_start(sim, first, [a], 5e-4, p).velocity[b, 2])
    starts = _start_states(sim, batch)          # both k: one program each
    for k in (60.0, 150.0):
        p = sim.params(k=1e4, c=1.0, spring_k=k)
        want = lagged(p)
        got = np.asarray(starts(p).velocity)[0, b, 2]
        assert float(got) == pytest.approx(float(want), rel=1e-9), k
        seen.append(float(got))
    assert abs(seen[1] - seen[0]) > 1e-3        # the lag moved with k (was the start's)


def test_a_missing_sample_in_the_flight_is_skipped_not_its_end(tmp_path):
    """Regression: the flight window of the "fit" estimate ended at the first row without a
    position (an empty x,y,z cell, a missing sample): with row 2 of a box toss at 148 Hz
    empty, 2 flight frames were left, the box counted as not in free flight and got a
    quadratic over 5 frames, 34 mm/s and 0.59 rad/s off (row 3: 20 mm/s, 0.40 rad/s)
    where the complete record is 3.4 mm/s and 0.020 rad/s off. Now the missing row is left
    out of the fit (the others keep their own times) and the window keeps its bounds,
    counted over the record's rows: the start stays within 1.5 times the complete record's
    own error (noise 0.3 mm, 3 mrad), whether the row lacks its position or its whole
    pose."""
    scene = _scene(tmp_path, TOSS).scene
    t = np.arange(30) / 148.0
    v_true, wb = np.array([0.3, -0.3, 0.6]), np.array([3.0, -4.0, 5.0])
    q0 = np.array([0.9, 0.3, 0.2, 0.1]) / np.linalg.norm([0.9, 0.3, 0.2, 0.1])
    w_true = rotmat(q0) @ wb
    pos = np.array([0.0, 0.0, 0.25]) + v_true * t[:, None] + \
        0.5 * np.array(scene.gravity) * t[:, None] ** 2
    quat = np.concatenate([[q0], torque_free(q0, wb, inertia_diagonal(scene.bodies[0]),
                                             t[1:])])
    rng = np.random.default_rng(1)
    pos = pos + 3e-4 * rng.standard_normal(pos.shape)
    quat = qmul(exp_quat(3e-3 * rng.standard_normal((30, 3))), quat)

    def errors(p, q):
        _, v, _, w = tf.first_state(scene, 0, t, p, q, estimate="fit")
        return np.linalg.norm(v - v_true), np.linalg.norm(w - w_true)

    err_v, err_w = errors(pos, quat)
    assert err_v < 5e-3 and err_w < 0.03, (err_v, err_w)
    low = pos - np.array([0.0, 0.0, 0.17])          # reaches the plane within the 30 rows
    n_low = flight_frames(scene, 0, low, quat, 0.005)
    assert 5 < n_low < 30
    for row in (2, 3):
        for blank_quat in (True, False):
            p, q = pos.copy(), quat.copy()
            p[row] = np.nan
            if blank_quat:
                q[row] = np.nan
            ev, ew = errors(p, q)
            assert ev < 1.5 * err_v and ew < 1.5 * err_w, (row, blank_quat, ev, ew)
            assert flight_frames(scene, 0, p, q, 0.005) == 30
            low_p = low.copy()
            low_p[row] = np.nan
            assert flight_frames(scene, 0, low_p, q, 0.005) == n_low     # the same contact


def test_observed_bodies_far_from_the_scene_start_warn_for_the_unobserved_ones(hung_pair):
    """Regression: a 2 x 2 x 2 jelly observed at 4 nodes, recorded dropping from 0.25 m
    while its scene file put it at 0.15 m: the 4 unobserved nodes started at the scene
    file's height, their edges to the observed ones stretched 100%, and evaluate at the
    true parameters gave 70% (0.30% with the scene at the record's height), silently. Now
    prepare warns when the observed bodies start far from the scene file's positions in a
    scene with bodies the record does not observe."""
    import warnings

    sim, a, b, rec = hung_pair
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tf.prepare(sim, [rec], bodies={"a": a})              # where the scene puts it
    body = rec.bodies["a"]
    lifted = Record("lifted.csv", rec.t, {"a": BodyRecord(body.position + [0.0, 0.0, 0.1])})
    with pytest.warns(UserWarning, match=r"far from the scene file.s positions or velocities: "
                                         r"lifted.csv \(100 mm\)"):
        tf.prepare(sim, [lifted], bodies={"a": a})
    # ... or moving otherwise: a rope observed at 3 nodes, swung at -1 m/s from a scene file
    # at +0.3 m/s, fitted k 15% off with no word (audit13)
    swung = Record("swung.csv", rec.t, {"a": BodyRecord(body.position + np.outer(
        rec.t - rec.t[0], [0.5, 0.0, 0.0]))})
    with pytest.warns(UserWarning, match=r"positions or velocities: swung.csv \(velocity "
                                         r"0.5 m/s off\)"):
        tf.prepare(sim, [swung], bodies={"a": a})
    # both at once: one record, counted once (the message said "2 record(s)" for it, audit32)
    moved = Record("moved.csv", rec.t, {"a": BodyRecord(swung.bodies["a"].position
                                                        + [0.0, 0.0, 0.1])})
    with pytest.warns(UserWarning, match=r"^1 record\(s\) start .* moved.csv \(100 mm, "
                                         r"velocity 0.5 m/s off\)\. "):
        tf.prepare(sim, [moved], bodies={"a": a})
    # every body observed: nothing starts from the scene file, no warning
    both = Record("both.csv", rec.t, {"a": BodyRecord(body.position + [0.0, 0.0, 0.1]),
                                      "b": BodyRecord(body.position - [0.0, 0.0, 0.2])})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tf.prepare(sim, [both], bodies={"a": a, "b": b})
    # ... unless far beyond the bodies' size in a scene tied to the world: a record in cm (a
    # box on world-anchored springs blew up and the fit blamed dt); a free pair is the same
    # pair anywhere (audit15: a ball 3 m along an infinite floor warned)
    cm = Record("cm.csv", rec.t, {n: BodyRecord(100.0 * r.position)
                                  for n, r in both.bodies.items()})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tf.prepare(sim, [cm], bodies={"a": a, "b": b})
    import diffpen as dp
    hung = dp.Scene(gravity=(0.0, 0.0, -9.81))
    ball = hung.add_sphere(0.03, 0.3, (0.0, 0.0, 0.7))
    hung.add_anchored_spring(ball, None, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), k=60.0, c=0.1,
                             rest_length=0.25)
    hung_sim = dp.compile(hung, 1e-3)
    with pytest.warns(UserWarning, match=r"more than 10 times their size .*: cm.csv .* metres"):
        tf.prepare(hung_sim, [Record("cm.csv", rec.t, {"a": BodyRecord(
            100.0 * body.position)})], bodies={"a": ball})
    floor = dp.Scene(gravity=(0.0, 0.0, -9.81))
    ball = floor.add_sphere(0.03, 0.3, (0.0, 0.0, 0.7))
    floor.add_plane()
    floor_sim = dp.compile(floor, 1e-3)
    along = Record("along.csv", rec.t, {"a": BodyRecord(body.position + [3.0, 0.0, 0.0])})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tf.prepare(floor_sim, [along], bodies={"a": ball})
    with pytest.warns(UserWarning, match=r"more than 10 times their size"):
        tf.prepare(floor_sim, [Record("up.csv", rec.t, {"a": BodyRecord(
            body.position + [0.0, 0.0, 3.0])})], bodies={"a": ball})


def test_first_state_removes_the_finite_difference_bias(cube):
    """A gravity parabola through the first flight frames gives the exact start velocity;
    row 0 with a biased velocity column keeps the bias."""
    t = np.arange(12) / 148.0
    v0 = np.array([0.3, -0.2, 0.5])
    w = np.array([1.0, -2.0, 3.0])
    pos = np.array([0.0, 0.0, 0.3]) + v0 * t[:, None] + 0.5 * np.array(cube.scene.gravity) * \
        t[:, None] ** 2
    quat = np.array([pose.qmul(pose.exp_quat(w * s), np.array([1.0, 0, 0, 0])) for s in t])
    vel = np.tile(v0 + np.array([0, 0, 0.023]), (12, 1))
    p, v, q, om = tf.first_state(cube.scene, 0, t, pos, quat, vel, None, estimate="fit")
    np.testing.assert_allclose(v, v0, atol=1e-9)
    np.testing.assert_allclose(p, pos[0], atol=1e-12)
    np.testing.assert_allclose(om, w, atol=1e-9)
    np.testing.assert_allclose(abs(q @ quat[0]), 1.0, atol=1e-12)
    p, v, q, om = tf.first_state(cube.scene, 0, t, pos, quat, vel, None, estimate="record")
    assert v[2] - v0[2] == pytest.approx(0.023)


@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "verlet"])
def test_a_record_of_the_simulator_itself_starts_from_its_own_velocity(integrator):
    """A ball dropped from rest, recorded by the simulator (no velocity columns) and fitted
    from the truth: the parabola through the first frames gave the continuous-time start
    velocity, -g h / 2 off the state semi-implicit Euler steps from, and the fit moved k by
    -2.3% and c by -1.3% away from the truth. Verlet traces the parabola from v itself."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("board", k=2e3, c=8.0)
    scene.add_sphere(radius=0.05, mass=0.2, position=(0.0, 0.0, 0.3))
    scene.add_plane(material="board")
    sim = dp.compile(scene, 1e-3, integrator=integrator)
    truth = sim.params()
    rec = tf.synthetic_record(sim, truth, 0.6, 5e-3, {"ball": 0}, velocities=False)
    b = tf.prepare(sim, [rec], bodies={"ball": 0}, estimate="fit")
    # the state the record stepped from: at rest less the lag (semi-implicit Euler)
    lag = 0.5 * sim.dt * 9.81 if integrator == "semi_implicit_euler" else 0.0
    np.testing.assert_allclose(np.asarray(b.start.velocity)[0, 0], [0.0, 0.0, lag],
                               atol=1e-9)
    if integrator == "semi_implicit_euler":
        free = [tf.Free("contact.board.k", 10.0, 1e5), tf.Free("contact.board.c", 0.01, 100.0)]
        r = tf.fit_records(sim, truth, b, free, horizons=(None,))
        assert r.values["contact.board.k"] == pytest.approx(2e3, rel=1e-6)
        assert r.values["contact.board.c"] == pytest.approx(8.0, rel=1e-6)


def test_first_state_uses_the_flight_frames_only(cube):
    """first_state(estimate="fit", max_frames=N) fits at most N frames and stops before the
    body comes within the margin of a plane: a parabola that bounces at frame 12 is
    recovered exactly with a cap of 30 frames (the frames after the bounce are left out),
    and with noise more flight frames give a closer start velocity (mean error over 20
    seeded records)."""
    g = np.array(cube.scene.gravity)
    t = np.arange(30) / 148.0
    v0 = np.array([0.4, 0.1, -0.2])
    flight = np.array([0.0, 0.0, 0.0994]) + v0 * t[:, None] + 0.5 * g * t[:, None] ** 2
    pos = flight.copy()
    pos[12:, 2] = 2 * pos[12, 2] - pos[12:, 2]                # a bounce at frame 12
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (30, 1))
    # the lowest face (0.05 below the centre) comes within 5 mm of the plane (offset
    # -0.002) at frame 12: frames 0-11 are the flight
    assert flight_frames(cube.scene, 0, pos, quat, 0.005) == 12
    p, v, _, _ = tf.first_state(cube.scene, 0, t, pos, quat, estimate="fit", max_frames=30)
    np.testing.assert_allclose(v, v0, atol=1e-9)
    np.testing.assert_allclose(p, pos[0], atol=1e-12)
    high = flight + np.array([0.0, 0.0, 0.5])                 # no plane in reach: 30 frames
    assert flight_frames(cube.scene, 0, high, quat, 0.005) == 30
    rng = np.random.default_rng(0)
    err = {10: [], 20: []}
    for _ in range(20):
        noisy = high + 5e-4 * rng.standard_normal(high.shape)
        for m in err:
            _, v, _, _ = tf.first_state(cube.scene, 0, t, noisy, quat, estimate="fit",
                                        max_frames=m)
            err[m].append(np.linalg.norm(v - v0))
    assert np.mean(err[20]) < 0.6 * np.mean(err[10])


@pytest.fixture(scope="module")
def flat_box():
    """A 20 x 5 x 2.5 cm box 2 m up (no plane), compiled for rk4 at 0.1 ms; the tests set
    its spin in the start state (Simulator.state_from). Shared: never mutate it."""
    scene = dp.Scene()
    scene.add_box((0.1, 0.05, 0.025), 0.5, (0.0, 0.0, 2.0),
                  orientation=(0.9, 0.3, 0.2, 0.1), velocity=(0.6, 0.1, 1.0),
                  angular_velocity=(0.0, 0.0, 0.0))
    return dp.compile(scene, 1e-4, integrator="rk4")


@pytest.mark.parametrize("rates, frames", [((3.0, 8.0, 2.0), 20), ((10.0, 30.0, 5.0), 40)])
def test_first_state_fits_torque_free_rotation(flat_box, rates, frames):
    """Regression: for a body with unequal principal moments the "fit" estimate took the
    angular velocity as constant in free flight; a 20 x 5 x 2.5 cm box turning at (3, 8, 2)
    rad/s (body frame) came out 22% off in x after 20 frames (2.39 against 3.06 rad/s in
    the world frame) and a rollout from it 4.4 deg off. Now its torque-free motion is fitted
    (Euler's equations) over a growing window of frames (at (10, 30, 5) rad/s over 40 frames
    a fit over all frames at once, started from their mean rate, ended at (68, 18, -8)
    against (9.3, 24.2, 18.8) rad/s): on frames of a diffpen rk4 rollout (0.1 ms steps, no
    plane in reach) the start angular velocity and orientation come out to 1e-6 (1e-5 at
    32 rad/s). Both cases roll out the one compiled box (``flat_box``) from a start state
    spinning at the rates."""
    sim = flat_box
    scene = sim.scene
    q0 = np.array(scene.bodies[0].orientation)
    w_world = pose.rotmat(q0) @ np.array(rates)
    start = sim.state_from(body=0, angular_velocity=w_world, frame="world")
    traj = sim.rollout(sim.params(), 40 * 50, start, save_every=50)
    t = np.concatenate([[0.0], np.asarray(traj.time)])
    pos = np.concatenate([[scene.bodies[0].position], np.asarray(traj.position[:, 0])])
    quat = np.concatenate([[q0], np.asarray(traj.orientation[:, 0])])
    p, v, q, om = tf.first_state(scene, 0, t[:frames + 1], pos[:frames + 1],
                                 quat[:frames + 1], estimate="fit", max_frames=frames)
    tol = 1e-6 if frames == 20 else 1e-5         # the integrators' own error at 32 rad/s
    np.testing.assert_allclose(om, w_world, rtol=tol, atol=tol)
    assert pose.rotation_angle(jnp.asarray(q), jnp.asarray(q0)) < tol
    np.testing.assert_allclose(v, [0.6, 0.1, 1.0], atol=1e-9)
    if frames != 20:
        return
    # the integrator alone: the same frames from the exact start, and its invariants
    inertia = dp.rigid.inertia_diagonal(scene.bodies[0])
    wb = pose.rotmat(q0).T @ w_world
    qs = first_state_mod.torque_free(q0, wb, inertia, t[1:])
    np.testing.assert_allclose(np.abs(np.sum(qs * quat[1:], axis=-1)), 1.0, atol=1e-12)
    long = first_state_mod.torque_free(np.tile(q0, (2, 1)), np.stack([wb, 2 * wb]), inertia,
                                       np.linspace(0.05, 1.0, 20))
    assert long.shape == (2, 20, 4)
    # world angular momentum R I R^T w is constant: rebuild w from two close samples
    for j, w_start in enumerate([wb, 2 * wb]):
        L0 = pose.rotmat(q0) @ (inertia * w_start)
        qa, qm, qb = first_state_mod.torque_free(q0, w_start, inertia,
                                                 [0.5 - 1e-5, 0.5, 0.5 + 1e-5])
        w_w = pose.rotvec(pose.qmul(qb, pose.qconj(qa))) / 2e-5
        L = pose.rotmat(qm) @ (inertia * (pose.rotmat(qm).T @ w_w))
        np.testing.assert_allclose(L, L0, rtol=1e-5)
        assert long[j].shape == (20, 4)


def test_first_state_of_a_body_starting_on_a_plane_is_not_a_parabola(cube):
    """Regression: a body that starts on a plane (a box sliding on the ground) got the
    gravity parabola of free flight over 3 frames under the "fit" estimate, which lifted
    its start velocity by about g t / 2 per frame (+0.05 m/s at 200 Hz). Now it gets the
    quadratic of a body that is not in flight: on a slide decelerating at mu g, exact."""
    t = np.arange(12) / 200.0
    v0, a = np.array([1.0, 0.3, 0.0]), -0.2 * 9.81 * np.array([1.0, 0.3, 0.0]) / 1.044
    pos = np.array([0.0, 0.0, 0.048]) + v0 * t[:, None] + 0.5 * a * t[:, None] ** 2
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (12, 1))
    assert flight_frames(cube.scene, 0, pos, quat, 0.005) == 0
    p, v, q, om = tf.first_state(cube.scene, 0, t, pos, quat, estimate="fit")
    np.testing.assert_allclose(v, v0, atol=1e-9)
    np.testing.assert_allclose(p, pos[0], atol=1e-12)
    np.testing.assert_allclose(om, 0.0, atol=1e-12)


def test_first_state_of_a_fast_spin_does_not_wrap(cube):
    """Regression: the "fit" estimate fitted a line to the rotation vectors since row 0,
    which wrap past pi: a cube turning at 30 rad/s over 20 frames at 148 Hz (3.9 rad) came
    out at (-8.8, -11.8, 0) rad/s instead of (18, 24, 0). Now the rate comes from the turns
    between consecutive frames: exact, with sign-flipped quaternions too."""
    t = np.arange(20) / 148.0
    g = np.array(cube.scene.gravity)
    w = 30.0 * np.array([0.6, 0.8, 0.0])
    pos = np.array([0.0, 0.0, 3.0]) + np.array([0.3, 0.0, 1.0]) * t[:, None] + \
        0.5 * g * t[:, None] ** 2
    quat = np.array([pose.qmul(pose.exp_quat(w * s), np.array([1.0, 0, 0, 0])) for s in t])
    quat[::3] *= -1.0
    p, v, q, om = tf.first_state(cube.scene, 0, t, pos, quat, estimate="fit", max_frames=20)
    np.testing.assert_allclose(om, w, atol=1e-9)
    np.testing.assert_allclose(abs(q @ quat[0]), 1.0, atol=1e-12)




def test_a_noisy_record_without_velocities_starts_from_its_whole_first_flight(tmp_path):
    """Regression: the start state of a record without velocity columns came from its first
    20 frames only: a ball dropped from 1 m, recorded at 500 Hz with 1 mm noise (truth k 1e4,
    c 20), started from 0.04 s of its 0.43 s fall, and the fit ended at k 9375 +- 42, c 19.36
    (15 standard errors off). The whole first flight: within 1% and 3 standard errors."""
    from tuning.scene_fit import fit_files
    from tuning.sysid import synthetic_record
    t, z = synthetic_record(1e4, 20.0, duration=1.3, noise=1e-3)
    rec = tmp_path / "ball.csv"
    rec.write_text("t,x,y,z\n" + "".join(f"{float(a)!r},0,0,{float(b)!r}\n"
                                         for a, b in zip(t, z)))
    scene = tmp_path / "ball.toml"
    scene.write_text(BALL_FIT)
    out = fit_files(str(scene), [str(rec)])
    for leaf, truth in (("contact.rubber.k", 1e4), ("contact.rubber.c", 20.0)):
        value, err = out["fitted"][leaf], out["stderr"][leaf]
        assert abs(value / truth - 1) < 0.01 and abs(value - truth) < 3 * err, (leaf, value, err)


BALL_ON_FIXED_SPHERE = """
dt = 5e-4
[materials.rubber]
k = 7000.0
c = 15.0
[[spheres]]
name = "ball"
radius = 0.05
mass = 0.5
position = [0.02, 0.0, 0.5]
material = "rubber"
[[fixed_spheres]]
center = [0.0, 0.0, 0.0]
radius = 0.2
material = "rubber"
[fit]
params = ["contact.rubber.k", "contact.rubber.c"]
first_state = "fit"
"""


def test_the_first_flight_ends_at_a_fixed_sphere_too(tmp_path):
    """Regression: the first flight ended only near a plane, so in a scene whose ball lands
    on a fixed sphere (no planes) the whole-flight start fitted its parabola through the
    impact: evaluated at 2784%, k fitted 0.18 (truth 1e4). The flight now ends near fixed
    spheres too, and in a scene with other bodies to touch it keeps at most
    UNSEEN_CONTACT_FRAMES."""
    from tuning.records import write_record
    from tuning.scene_fit import fit_files
    scene = tmp_path / "ball.toml"
    scene.write_text(BALL_ON_FIXED_SPHERE)
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    rec = tf.synthetic_record(sim, tf.with_leaves(sf.params(sim), {
        "contact.rubber.k": 1e4, "contact.rubber.c": 20.0}), 1.0, 2e-3, {"ball": 0},
        noise=5e-4, velocities=False)
    path = tmp_path / "rec.csv"
    write_record(str(path), rec)
    pos = rec.bodies["ball"].position
    n = flight_frames(sf.scene, 0, pos, None, 0.005)
    gap = np.linalg.norm(pos[:n + 1], axis=1) - 0.25
    assert 20 < n < len(pos) and gap[n - 1] >= 0.005 > gap[n]
    out = fit_files(str(scene), [str(path)])
    assert abs(out["fitted"]["contact.rubber.k"] / 1e4 - 1) < 0.02, out["fitted"]
    two = dp.Scene()
    two.add_sphere(0.05, 0.5, (0.0, 0.0, 0.5))
    two.add_sphere(0.05, 0.5, (1.0, 0.0, 0.5))
    free = np.column_stack([np.zeros(100), np.zeros(100), 0.5 - 0.001 * np.arange(100)])
    assert flight_frames(two, 0, free, None, 0.005) == first_state_mod.UNSEEN_CONTACT_FRAMES
