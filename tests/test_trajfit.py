"""Fitting scenes to measured motion (tuning.trajfit, diffpen fit SCENE.toml --data FILES):
recovery of known parameters from records made by another integrator and time step plus
noise, the first-state estimate, masks for records of unequal length, and the library pieces
it needs (named planes with a fitted offset, Simulator.state_from)."""
import json
import logging
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from tuning import pose
from tuning import trajfit as tf
from tuning.cli import main
from tuning import first_state as first_state_mod
from tuning.first_state import flight_frames
from tuning.records import write_record
from tuning.scenefile import load_scene_file

from record_scenes import BOX, DRAG

ROPE = """
dt = 1e-3
[[ropes]]
n = 4
start = [0.0, 0.0, 1.0]
end = [0.3, 0.0, 1.0]
mass = 0.3
k = {k}
c = {c}
pinned = [0]
[fit]
params = ["springs.rope.stretch.k", "springs.rope.stretch.c"]
"""



def _record_file(tmp_path, text, truth, bodies, name, *, integrator, dt, every, duration,
                 noise, seed):
    """Write the scene (start values) and a record of the truth made by ``integrator`` at
    ``dt``; returns (scene path, record path)."""
    scene = tmp_path / f"{name}.toml"
    scene.write_text(text)
    sf = load_scene_file(str(scene))
    sim = sf.compile(integrator=integrator, dt=dt)
    params = tf.with_leaves(sf.params(sim), truth)
    ids = {b: sf.names[b] for b in bodies}
    rec = tf.synthetic_record(sim, params, duration, every, ids, noise=noise, seed=seed)
    path = tmp_path / f"{name}.csv"
    write_record(str(path), rec)
    return str(scene), str(path)


def _fit_cli(capsys, argv):
    capsys.readouterr()
    assert main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


#: the rope's spring values in the record of ``rope_record``
ROPE_TRUTH = {"springs.rope.stretch.k": 300.0, "springs.rope.stretch.c": 0.5}


@pytest.fixture(scope="module")
def rope_record(tmp_path_factory):
    """The path of a record of the ROPE scene's nodes 1-3 at ROPE_TRUTH, made by rk4 at 0.25
    ms: 0.6 s at 5 ms, 0.1 mm of noise. Shared: the tests read it, or copy it beside their
    own scene file."""
    return _record_file(tmp_path_factory.mktemp("rope"), ROPE.format(k=200.0, c=0.3),
                        ROPE_TRUTH, ["rope[1]", "rope[2]", "rope[3]"], "rope",
                        integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.6, noise=1e-4,
                        seed=1)[1]


@pytest.mark.parametrize("case", ["rope", "box_springs"])
def test_record_fit_recovers_parameters(tmp_path, capsys, request, case):
    """diffpen fit SCENE.toml --data REC.csv recovers spring k and c within 2% from a record
    made by rk4 at a quarter of the fit's step (semi-implicit Euler), with noise; the box's
    c within 3%: the fit integrator's own step error moves it by +1.25% on the noise-free
    record (+0.6% at half the step), this record's noise by another +1.1%."""
    if case == "rope":
        truth = ROPE_TRUTH
        scene = tmp_path / "rope.toml"
        scene.write_text(ROPE.format(k=200.0, c=0.3))
        scene, rec = str(scene), request.getfixturevalue("rope_record")
    else:
        truth = {"springs.hang.k": 400.0, "springs.hang.c": 2.0}
        scene, rec = _record_file(tmp_path, BOX.format(k=250.0, c=1.0), truth, ["box"], case,
                                  integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.6,
                                  noise=2e-4, seed=1)
    out_toml = tmp_path / "fitted.toml"
    out = _fit_cli(capsys, ["fit", scene, "--data", rec, "--out", str(out_toml)])
    for name, v in truth.items():
        rel = 0.03 if name == "springs.hang.c" else 0.02
        assert out["fitted"][name] == pytest.approx(v, rel=rel), (name, out["fitted"])
        assert 0 < out["stderr"][name] < 0.05 * v
    assert out["after"]["position_error_pct"]["mean"] < out["before"]["position_error_pct"][
        "mean"]
    assert out["undetermined"] == []
    # the written scene holds the fitted values
    sf = load_scene_file(str(out_toml))
    got = sf.params(sf.compile())
    leaves = tf.leaf_names(got)
    for name in truth:
        assert float(tf.get_leaf(got, name)) == pytest.approx(out["fitted"][name], rel=1e-12)
    assert set(truth) <= set(leaves)


def test_standard_errors_take_in_the_records_start_state_noise(tmp_path):
    """Regression: the standard errors of a record fit were s^2 (J^T J)^-1 alone, blind to
    the noise of each record's first frame, which fixes its start state: over 8 noise seeds
    of the rope example the truth lay 13-41 reported errors away. They now take the larger of
    that and the records-as-clusters sandwich. Here four rope records, exact but for 0.5 mm /
    5 mm/s of noise on their first frame (pose and velocity columns), same integrator and
    step as the fit: the truth is within 3 reported errors (before: 6.0 for k). The records
    start the rope's free nodes at 0, 0.5, -1 and 0.8 m/s in y (one simulator, its start
    state's velocities set: the state a scene file with that rope velocity starts from)."""
    from tuning.scene_fit import fit_files
    text = ROPE.format(k=200.0, c=0.3) + 'observe = ["rope[1]", "rope[2]", "rope[3]"]\n'
    truth = {"springs.rope.stretch.k": 300.0, "springs.rope.stretch.c": 0.5}
    scene = tmp_path / "rope.toml"
    scene.write_text(text)
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    params = tf.with_leaves(sf.params(sim), truth)
    ids = {b: sf.names[b] for b in sf.spec.observe}
    free = [i for i, b in enumerate(sim.scene.bodies) if not b.pinned]
    paths = []
    for i, vy in enumerate((0.0, 0.5, -1.0, 0.8)):
        s = sim.state_from(body=free, velocity=np.tile([0.0, vy, 0.0], (len(free), 1)))
        rec = tf.synthetic_record(sim, params, 0.4, 5e-3, ids, state=s)
        noisy = tf.synthetic_record(sim, params, 0.4, 5e-3, ids, state=s, noise=5e-4, seed=i)
        for name in rec.bodies:
            rec.bodies[name].position[0] = noisy.bodies[name].position[0]
            rec.bodies[name].velocity[0] = noisy.bodies[name].velocity[0]
        paths.append(str(tmp_path / f"s{i}.csv"))
        write_record(paths[-1], rec)
    out = fit_files(str(scene), paths)
    for name, v in truth.items():
        z = (out["fitted"][name] - v) / out["stderr"][name]
        assert abs(z) < 3.0, (name, out["fitted"][name], out["stderr"][name])


# --------------------------------------------------------------------------- pieces
@pytest.fixture(scope="module")
def cube():
    scene = dp.Scene()
    scene.add_material("board", k=3e3, c=30.0, friction=0.2)
    scene.add_box((0.05, 0.05, 0.05), 0.37, (0.0, 0.0, 0.3), inertia=(8e-4,) * 3)
    scene.add_plane(material="board", name="ground", offset=-0.002)
    return dp.compile(scene, 1e-3)


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


def test_host_rotation_matrices_are_float64_without_x64():
    """Regression: tuning.pose.rotmat (first states, body-frame velocities) went through JAX
    asking for float64; with x64 off JAX warned and truncated it to float32. It now
    computes on the host, in float64 either way, and equals diffpen's own matrices."""
    import warnings
    q = np.array([[0.9, 0.3, 0.1, 0.0], [0.1, -0.7, 0.2, 0.6]])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    with jax.enable_x64(False), warnings.catch_warnings():
        warnings.simplefilter("error")
        R = pose.rotmat(q)
    assert R.dtype == np.float64
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-15)
    np.testing.assert_allclose(R, np.asarray(dp.rigid.quat_to_matrix(jnp.asarray(q))),
                               atol=1e-15)


def test_unequal_lengths_are_masked(cube, caplog):
    """Records of different lengths in one batch give each record the residuals it gives
    alone (padding weighs nothing)."""
    params = cube.params()
    s = cube.state_from(body=0, position=(0, 0, 0.2), velocity=(0.4, 0, 0),
                        orientation=(0.9, 0.3, 0.1, 0.0), angular_velocity=(2, 0, 1))
    long = tf.synthetic_record(cube, params, 0.3, 5e-3, {"cube": 0}, state=s, noise=1e-3)
    short = tf.synthetic_record(cube, params, 0.12, 5e-3, {"cube": 0}, noise=1e-3, seed=3)
    both = tf.prepare(cube, [long, short], estimate="record")
    alone = [tf.prepare(cube, [r], estimate="record") for r in (long, short)]
    p2 = tf.with_leaves(params, {"contact.board.c": 20.0})

    def residuals(b):        # jitted: one compile per batch instead of one per eager op
        return np.asarray(jax.jit(lambda p: tf.pose_residuals(*tf.simulate(cube, p, b), b))(p2))
    r_both = residuals(both)
    # called eagerly, the same batch again reuses its compiled rollout (simulate's observe
    # function is one object per set of bodies, and the rollout program is keyed by it)
    first = tf.simulate(cube, p2, both)[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        again = tf.simulate(cube, p2, both)[0]
    assert not [r for r in caplog.records if r.getMessage().startswith("Compiling")]
    np.testing.assert_array_equal(np.asarray(again), np.asarray(first))
    cost_alone = [float(np.sum(residuals(b) ** 2)) for b in alone]
    # each record weighs 1/R in the batch: the batch cost is the mean of the costs alone
    assert float(np.sum(r_both ** 2)) == pytest.approx(np.mean(cost_alone), rel=1e-10)
    assert both.pos_mask[1, len(short.t):].sum() == 0
    # buckets of similar length give the same loss as one padded batch
    buckets = tf.prepare_buckets(cube, [long, short], buckets=2, estimate="record")
    assert [len(b.paths) for b in buckets] == [1, 1] and buckets[0].steps < both.steps
    r_buckets = np.concatenate([residuals(b) for b in buckets])
    assert float(np.sum(r_buckets ** 2)) == pytest.approx(float(np.sum(r_both ** 2)),
                                                          rel=1e-10)


def test_plane_offset_is_a_differentiable_parameter(cube):
    """A named plane's offset is params.extra["plane_offset"][name]: moving it moves the
    resting box by the same amount, and its gradient matches central differences."""
    params = cube.params()
    assert float(params.extra["plane_offset"]["ground"]) == -0.002
    s = cube.state_from(body=0, position=(0, 0, 0.1))

    def rest_z(off):
        p = tf.with_leaves(params, {"extra.plane_offset.ground": off})
        return cube.rollout(p, 400, s).position[-1, 0, 2]
    z0, z1 = float(rest_z(-0.002)), float(rest_z(0.003))
    assert z1 - z0 == pytest.approx(0.005, rel=1e-3)
    g = float(jax.grad(rest_z)(jnp.asarray(0.0)))
    h = 1e-6
    fd = (float(rest_z(h)) - float(rest_z(-h))) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-5)
    with pytest.raises(dp.SceneError, match="finite"):
        cube.params(extra={"plane_offset": {"ground": float("nan")}})
    with pytest.raises(dp.SceneError, match="exists already"):
        cube.scene.add_plane(name="ground")


def test_state_from_under_vmap_matches_a_loop(cube):
    """state_from sets pose, velocity and BODY-frame angular velocity; vmapped over start
    states it equals one call per state, and the world angular velocity is R w_body."""
    q = jnp.array([[1.0, 0, 0, 0], [0.0, 0, 0, 1.0]])
    wb = jnp.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    pos = jnp.array([[0, 0, 0.2], [0.1, 0, 0.3]])
    many = jax.vmap(lambda p, qq, w: cube.state_from(body=0, position=p, orientation=qq,
                                                     angular_velocity=w))(pos, q, wb)
    for i in range(2):
        one = cube.state_from(body=0, position=pos[i], orientation=q[i],
                              angular_velocity=wb[i])
        np.testing.assert_allclose(many.angular_velocity[i], one.angular_velocity)
    # a half turn about z maps body (1, 2, 3) to world (-1, -2, 3)
    np.testing.assert_allclose(many.angular_velocity[1, 0], [-1.0, -2.0, 3.0], atol=1e-12)
    with pytest.raises(dp.SceneError, match="body"):
        cube.state_from(body=3, position=(0, 0, 0))


def test_leaf_names_accept_keystr():
    assert tf._normalise(".contact['board'].k") == "contact.board.k"
    assert tf._normalise("springs.rope.stretch.c") == "springs.rope.stretch.c"
    assert tf.Free("extra.plane_offset.ground", -0.01, 0.01).resolved().log is False
    assert tf.Free("contact.board.k", 1.0, 1e5).resolved().log is True
    with pytest.raises(ValueError, match="lo >= 0"):
        tf.Free("contact.board.k", -1.0, 1.0, log=True).resolved()
    assert math.isclose(tf.ROT_WEIGHT, 0.5729577951308232)


def test_bad_records_fail_before_compiling(tmp_path, capsys):
    scene = tmp_path / "rope.toml"
    scene.write_text(ROPE.format(k=200.0, c=0.3))
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y\n0,1,2\n")
    assert main(["fit", str(scene), "--data", str(bad), "--json"]) == 2
    assert "bad.csv" in capsys.readouterr().err
    assert main(["fit", str(scene), "--data", str(tmp_path / "none.csv")]) == 2
    capsys.readouterr()
    # without a scene file --data is the ball's one t,z record
    assert main(["fit", "--data", str(bad), str(bad)]) == 2
    assert "one t,z record" in capsys.readouterr().err
    assert main(["fit", "--out", str(tmp_path / "x.toml")]) == 2


def test_a_record_without_a_first_pose_names_its_file_and_body(tmp_path, cube):
    """The rollout starts from row 0: a record whose first row lacks the position or the
    orientation is refused with the file, the body and what to do (it said neither)."""
    from tuning.records import read_record
    for cells, what in (("0,,,,1,0,0,0", "position (x, y, z)"),
                        ("0,0,0,0.3,,,,", "orientation (qw, qx, qy, qz)")):
        path = tmp_path / "late_start.csv"
        path.write_text("t,x,y,z,qw,qx,qy,qz\n" + cells + "\n0.01,0,0,0.3,1,0,0,0\n"
                        "0.02,0,0,0.299,1,0,0,0\n")
        rec = read_record(str(path), ["cube"])
        with pytest.raises(tf.FitError) as err:
            tf.prepare(cube, [rec], bodies={"cube": 0}, estimate="record")
        msg = str(err.value)
        assert "late_start.csv" in msg and "'cube'" in msg and what in msg, msg
        assert "Trim the record" in msg


def test_readme_snippet_runs_as_written():
    """The README's vmapped start states with a fitted plane offset run as written."""
    import pathlib
    import re
    text = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"## Fitting measured motion.*?```python\n(.*?)```", text, re.S).group(1)
    env: dict = {}
    exec(compile(block, "README fitting measured motion", "exec"), env)
    np.testing.assert_allclose(np.asarray(env["dz"]), 1.0, rtol=1e-3)
    assert np.all(np.abs(np.asarray(env["z"]) - 0.05) < 1e-3)


def test_write_fitted_places_every_kind_of_leaf(tmp_path):
    """Materials (k, c, friction), a named plane's offset, a cloth's spring groups and drag
    are written where the file declares them and read back equal."""
    from tuning.fitted_scene import write_fitted
    src = tmp_path / "s.toml"
    src.write_text("""
[materials.board]
k = 1e4
c = 100.0
friction = 0.2
[[boxes]]
name = "cube"
half_extents = [0.05, 0.05, 0.05]
mass = 0.37
position = [0.0, 0.0, 0.5]
material = "board"
[[planes]]
name = "ground"
material = "board"
[[cloths]]
nx = 3
ny = 3
spacing = 0.1
mass = 0.1
origin = [1.0, 0.0, 1.0]
structural = [100.0, 0.1]
shear = 50.0
drag = 0.01
""")
    values = {"contact.board.k": 2024.5, "contact.board.c": 25.25,
              "extra.friction.board": 0.175, "extra.plane_offset.ground": -0.001,
              "springs.cloth.structural.k": 123.0, "springs.cloth.shear.c": 0.5,
              "extra.drag.cloth.drag": 0.02}
    out = tmp_path / "out.toml"
    write_fitted(str(src), values, str(out))
    sf = load_scene_file(str(out))
    params = sf.params(sf.compile())
    for name, v in values.items():
        assert float(tf.get_leaf(params, name)) == v
    assert float(tf.get_leaf(params, "springs.cloth.structural.c")) == 0.1


def test_directions_a_record_cannot_determine_are_reported(cube):
    """A toss that never reaches the ground says nothing about the contact: both contact
    parameters come back unchanged and reported as undetermined directions."""
    params = cube.params()
    s = cube.state_from(body=0, position=(0, 0, 0.5), velocity=(0.2, 0, 1.0),
                        orientation=(1.0, 0, 0, 0), angular_velocity=(1.0, 2.0, 0.0))
    rec = tf.synthetic_record(cube, params, 0.1, 5e-3, {"cube": 0}, state=s, noise=1e-4)
    batch = tf.prepare(cube, [rec])
    res = tf.fit_records(cube, params, batch, [tf.Free("contact.board.k", 1.0, 1e6),
                                               tf.Free("contact.board.c", 0.1, 1e3)],
                         maxiter=3, progress=False)
    assert res.values == pytest.approx({"contact.board.k": 3e3, "contact.board.c": 30.0},
                                       rel=1e-12)
    assert len(res.undetermined) == 2
    assert res.stderr == {"contact.board.k": math.inf, "contact.board.c": math.inf}


def test_parameters_of_an_undetermined_direction_get_no_standard_error():
    """Regression: with two drag groups on one ball only their sum acts; the fit listed the
    undetermined direction (0.71, -0.71) yet reported 0.0744 +- 0.0017 and 0.0247 +- 0.0017
    (truth 0.05 each) with a correlation of +1: the pseudo-inverse kept only the determined
    direction. Both now get an infinite standard error and NaN correlations."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=0.05, mass=0.2, position=(0.0, 0.0, 2.0), velocity=(3.0, 0.0, 2.0))
    scene.add_drag(0, 0.05, group="g1")
    scene.add_drag(0, 0.05, group="g2")
    sim = dp.compile(scene, 1e-3)
    truth = sim.params()
    recs = [tf.synthetic_record(sim, truth, 0.3, 5e-3, {"ball": 0}, noise=1e-4, seed=s,
                                velocities=False) for s in range(2)]
    batch = tf.prepare(sim, recs, bodies={"ball": 0})
    start = tf.with_leaves(truth, {"extra.drag.g1": 0.08, "extra.drag.g2": 0.03})
    res = tf.fit_records(sim, start, batch, [tf.Free("extra.drag.g1", 1e-4, 1.0),
                                             tf.Free("extra.drag.g2", 1e-4, 1.0)],
                         horizons=(None,), maxiter=10, progress=False)
    assert len(res.undetermined) == 1
    assert sum(res.values.values()) == pytest.approx(0.1, rel=0.05)
    assert res.stderr == {"extra.drag.g1": math.inf, "extra.drag.g2": math.inf}
    assert np.all(np.isnan(res.correlation))


def test_records_named_in_the_scene_file_and_horizons(tmp_path, capsys, rope_record):
    """[fit] data = [...] in a scene file of a rope is fitted like --data records, here over
    a growing horizon; the file's [fit] first_state and flight_frames are used, its horizon
    gives way to --horizon."""
    import shutil
    truth = ROPE_TRUTH
    shutil.copy(rope_record, tmp_path / "rope.csv")         # named relative to the scene
    scene = str(tmp_path / "rope.toml")
    with open(scene, "w") as fh:
        fh.write(ROPE.format(k=250.0, c=0.4) + 'data = ["rope.csv"]\nfirst_state = "record"\n'
                 'flight_frames = 4\nhorizon = [0.3]\n')
    spec = load_scene_file(scene).spec
    assert (spec.first_state, spec.flight_frames, spec.horizon) == ("record", 4, [0.3])
    out = _fit_cli(capsys, ["fit", scene, "--horizon", "0.2"])
    assert out["horizons"] == [0.2, None] and out["records"] == 1
    assert out["estimate"] == "record" and out["flight_frames"] == 4
    for name, v in truth.items():
        assert out["fitted"][name] == pytest.approx(v, rel=0.02)


def test_past_the_safe_step_is_marked_not_reported(cube):
    """Regression: the batched rollouts of fit_records and evaluate_batch ignored
    State.aux['unstable'], so a fit/evaluation past the safe step (here k = 2e5 N/m, w h =
    0.74 > 0.5 at dt = 1 ms: finite but untrustworthy poses) was reported as a result."""
    from tuning import evaluate as ev
    from tuning.stable import safe_contact_bounds
    params = cube.params()
    rec = tf.synthetic_record(cube, params, 0.12, 5e-3, {"cube": 0}, noise=1e-3, seed=3)
    batch = tf.prepare(cube, [rec, rec], estimate="record")
    k_bad = 2e5
    assert k_bad > safe_contact_bounds(cube)[0]
    bad = tf.with_leaves(params, {"contact.board.k": k_bad})
    fn = ev.evaluator(cube, batch)                      # one compile for both evaluations
    good = ev.evaluate_batch(cube, params, batch, fn=fn)
    assert good.unstable == 0 and np.isfinite(good.position_error_pct["mean"])
    out = ev.evaluate_batch(cube, bad, batch, fn=fn)
    assert np.all(np.isfinite(out.pos))     # finite poses: only the flag tells
    assert out.unstable == 2 and "safe step" in out.message
    assert all(r["unstable"] and np.isnan(r["position_error_pct"]) for r in out.records)
    assert np.isnan(out.position_error_pct["mean"]) and out.as_dict()["unstable"] == 2
    # a fit never starts past the safe step: a clear error instead of a number
    with pytest.raises(tf.FitError, match="past the safe step"):
        tf.fit_records(cube, bad, batch, [tf.Free("contact.board.c", 1.0, 1e3)], maxiter=1)


@pytest.fixture(scope="module")
def damping_past_the_safe_step(cube):
    """(batch, fit): a record of the cube whose damping (150 N s/m, made at a quarter of the
    step) is past its safe step at dt = 1 ms, and the fit of c to it from the cube's own
    c = 30 (6 iterations). Shared: never mutate them."""
    fine = dp.compile(cube.scene, 2.5e-4)
    truth = tf.with_leaves(fine.params(), {"contact.board.c": 150.0})
    s = fine.state_from(body=0, position=(0, 0, 0.12), velocity=(0.3, 0, -0.5),
                        orientation=(0.9, 0.3, 0.1, 0.0), angular_velocity=(2, 0, 1))
    rec = tf.synthetic_record(fine, truth, 0.15, 5e-3, {"cube": 0}, state=s)
    batch = tf.prepare(cube, [rec], estimate="record")
    res = tf.fit_records(cube, cube.params(), batch, [tf.Free("contact.board.c", 1.0, 1e3)],
                         maxiter=6)
    return batch, res


def test_record_fit_never_steps_past_the_safe_step(cube, damping_past_the_safe_step):
    """Regression: Levenberg-Marquardt accepted trial points past the safe step when the
    bounds' caps (one contact on the lightest body, tuning.stable) were looser than the
    scene's own limit (a box: four corners and rotation). Here the record's damping (150
    N s/m, made at a quarter of the step) is past the cube's safe step at dt = 1 ms (about
    88 N s/m) though under the cap (366): the fit ran to c = 104 and ended 'NOT a result';
    now every accepted point is stable and the fit ends at the limit (88.3)."""
    from tuning.stable import safe_contact_bounds
    _, res = damping_past_the_safe_step
    assert not cube.stability(cube.params()).margin < 1.0
    assert cube.stability(tf.with_leaves(cube.params(), {"contact.board.c": 150.0})).margin < 1
    assert 150.0 < safe_contact_bounds(cube)[1]
    assert res.unstable == 0 and np.isfinite(res.cost), res.message
    c = res.values["contact.board.c"]
    assert 30.0 < c and cube.stability(tf.with_leaves(cube.params(),
                                                      {"contact.board.c": c})).margin >= 1.0


def test_a_record_fit_of_a_layout_fitted_before_compiles_nothing(cube,
                                                                  damping_past_the_safe_step,
                                                                  caplog, monkeypatch):
    """Regression: every fit_records call built its residual and Jacobian program anew (a
    closure over the call's params and records) and compiled it again, 3-7 s for one cube
    record, so a script fitting record after record, or from start after start, paid it at
    every call. The programs now take the params and the records' arrays as arguments: a fit
    of another record of the same layout (here the damping fixture's: 0.15 s at 5 ms, the
    cube, c free), from another start, compiles nothing, and gives what a program compiled
    afresh gives."""
    from tuning.record_batch import ProgramCache
    s = cube.state_from(body=0, position=(0.0, 0.0, 0.08), velocity=(-0.2, 0.1, -0.4),
                        orientation=(0.9, 0.1, 0.3, 0.2), angular_velocity=(-1.0, 2.0, 0.5))
    rec = tf.synthetic_record(cube, cube.params(), 0.15, 5e-3, {"cube": 0}, state=s,
                              noise=1e-4)
    batch = tf.prepare(cube, [rec], estimate="record")
    start = tf.with_leaves(cube.params(), {"contact.board.c": 12.0})
    free = [tf.Free("contact.board.c", 1.0, 1e3)]
    # the fixture's layout fitted here once more (its programs may have left the cache of
    # the last few layouts since the fixture ran; placed next to the fixture's first user,
    # this test seldom compiles them again)
    tf.fit_records(cube, cube.params(), damping_past_the_safe_step[0], free, maxiter=1)
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        again = tf.fit_records(cube, start, batch, free, maxiter=3)
    compiled = [r.getMessage() for r in caplog.records if "XLA compilation" in r.getMessage()]
    assert compiled == [], compiled
    monkeypatch.setattr(tf, "_PROGRAMS", ProgramCache())      # compiled afresh
    fresh = tf.fit_records(cube, start, batch, free, maxiter=3)
    assert again.values == fresh.values and again.cost == fresh.cost
    assert again.cost_start == fresh.cost_start and again.iterations == fresh.iterations


def test_a_fit_held_by_the_safe_step_says_so(cube, damping_past_the_safe_step, monkeypatch):
    """Regression: a record that wants a contact k or c past what the fit's dt allows ended
    at the safe step with only LM's word ('iteration limit reached'; a cube whose record
    wanted k = 3e5 crept to k = 128368, 57% low) or, at the cap itself, with 'widen
    [fit.bounds]', which does nothing. Both now say the leaf is held by the safe step and
    that a smaller dt helps. Here: the scene's own limit on a box's damping (about 88 N s/m,
    below the one-contact cap), and a cap lowered to 20 N s/m (the record wants 30)."""
    import tuning.stable as st
    batch, res = damping_past_the_safe_step
    free = [tf.Free("contact.board.c", 1.0, 1e3)]
    assert res.unstable == 0 and res.values["contact.board.c"] < 100.0
    assert res.message.startswith("held by the safe step"), res.message
    assert "contact.board.c" in res.message and "smaller dt" in res.message
    assert "widen" not in res.message
    k_max, _ = st.safe_contact_bounds(cube)
    monkeypatch.setattr(st, "safe_contact_bounds", lambda sim: (k_max, 20.0))
    res = tf.fit_records(cube, tf.with_leaves(cube.params(), {"contact.board.c": 10.0}),
                         batch, free, maxiter=6)
    assert res.values["contact.board.c"] == pytest.approx(20.0, rel=1e-9)
    assert res.message.startswith("held by the safe step"), res.message
    assert "widen" not in res.message and "at a bound" not in res.message


def test_record_fit_bounds_stay_inside_the_safe_step(cube, monkeypatch):
    """Regression: fit_records let Levenberg-Marquardt walk contact k and c past the safe
    step (only the final result was judged); their upper bounds are now capped at it.
    (The record, 0.1 s of the cube with k and c free, has the layout of
    test_directions_a_record_cannot_determine_are_reported's record: the program that gives
    the start's cost may be compiled already.)"""
    from tuning.stable import safe_contact_bounds
    seen = {}

    def fake_lm(fun, x, lo, hi, **kw):
        seen["hi"] = np.asarray(hi, dtype=float)
        raise RuntimeError("stop")
    monkeypatch.setattr(tf, "levenberg_marquardt", fake_lm)
    params = cube.params()
    rec = tf.synthetic_record(cube, params, 0.1, 5e-3, {"cube": 0})
    batch = tf.prepare(cube, [rec], estimate="record")
    k_max, c_max = safe_contact_bounds(cube)
    free = [tf.Free("contact.board.k", 1.0, 1e12), tf.Free("contact.board.c", 0.1, 1e9)]
    with pytest.raises(RuntimeError, match="stop"):
        tf.fit_records(cube, params, batch, free, maxiter=1)
    assert np.allclose(np.exp(seen["hi"]), [k_max, c_max], rtol=1e-12)
    too_stiff = tf.with_leaves(params, {"contact.board.k": 2.0 * k_max})
    with pytest.raises(tf.FitError, match="largest safe value"):
        tf.fit_records(cube, too_stiff, batch, free, maxiter=1)


def test_multi_start_keeps_the_fit_of_lowest_cost(cube):
    """fit_records(starts=...): every start is screened by its cost, LM runs from the `keep`
    cheapest and the fit of lowest final cost is returned. From a far start (c = 8) with
    one LM iteration, the start list holding the truth (c = 30) wins and is kept; drawn
    starts stay inside the bounds, within the spread around the start value."""
    truth = cube.params()                                    # c = 30 N s/m
    s = cube.state_from(body=0, position=(0, 0, 0.07), velocity=(0.3, 0, -0.5),
                        orientation=(0.95, 0.2, 0.2, 0.1), angular_velocity=(2, -1, 0))
    rec = tf.synthetic_record(cube, truth, 0.15, 5e-3, {"cube": 0}, state=s, noise=1e-4)
    batch = tf.prepare(cube, [rec], estimate="record")
    far = tf.with_leaves(truth, {"contact.board.c": 8.0})
    free = [tf.Free("contact.board.c", 1.0, 60.0)]
    res = tf.fit_records(cube, far, batch, free, maxiter=1, progress=False,
                         starts=[{"contact.board.c": 30.0}, {"contact.board.c": 15.0}],
                         keep=2)
    assert [round(u["values"]["contact.board.c"], 6) for u in res.starts] == [8, 30, 15]
    screen = [u["screen_cost"] for u in res.starts]
    assert screen[1] < screen[2] < screen[0]
    ran = [u for u in res.starts if u["cost"] is not None]
    assert len(ran) == 2 and res.starts[0]["cost"] is None      # the far start is dropped
    chosen = [u for u in res.starts if u["chosen"]]
    assert len(chosen) == 1 and chosen[0]["cost"] == min(u["cost"] for u in ran)
    assert chosen[0]["cost"] == pytest.approx(res.cost, rel=1e-12)
    assert res.values["contact.board.c"] == pytest.approx(30.0, rel=0.02)
    # cost_start is at the given values (c = 8), as without multi-start (it was the chosen
    # start's); the chosen start's is cost_chosen_start (screened on the whole records here)
    assert res.cost_start == pytest.approx(screen[0], rel=1e-9)
    assert res.cost_chosen_start == pytest.approx(screen[1], rel=1e-9)
    assert res.as_dict()["cost_start"] == res.cost_start
    # drawn starts: inside the bounds and within a factor `spread` of the start value
    pts = tf._start_points([tf.Free("contact.board.c", 1.0, 400.0).resolved(),
                            tf.Free("extra.plane_offset.ground", -0.02, 0.02).resolved()],
                           np.array([math.log(300.0), -0.002]), np.array([0.0, -0.02]),
                           np.array([math.log(400.0), 0.02]), 20, 0, 3.0)
    c = np.exp([p[0] for p in pts])
    off = np.array([p[1] for p in pts])
    assert len(pts) == 20 and np.all((c >= 100.0 - 1e-9) & (c <= 400.0 + 1e-9))
    assert np.all(np.abs(off + 0.002) <= 0.004 + 1e-12)
    with pytest.raises(tf.FitError, match="not a fitted parameter"):
        tf.fit_records(cube, far, batch, free, starts=[{"contact.board.k": 1.0}])


def test_decay_weighs_early_frames(cube):
    """pose_residuals(decay=tau) scales each frame's residuals by exp(-t / (2 tau)), so its
    cost by exp(-t / tau); decay=None leaves them as they are."""
    from tuning.records import BodyRecord, Record
    t = np.arange(21) * 5e-3
    z = 0.3 - 0.5 * 9.81 * t ** 2
    rec = Record(path="<free fall>", t=t, bodies={"cube": BodyRecord(
        position=np.stack([0.1 * t, 0 * t, z], axis=1),
        quaternion=np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1)))})
    batch = tf.prepare(cube, [rec], estimate="record")
    rng = np.random.default_rng(0)                     # poses off the record's (no rollout)
    pos = jnp.asarray(batch.pos + 1e-3 * rng.standard_normal(batch.pos.shape))
    dq = np.concatenate([np.ones(batch.quat.shape[:-1] + (1,)),
                         0.01 * rng.standard_normal(batch.quat.shape[:-1] + (3,))], axis=-1)
    quat = pose.qmul(batch.quat, dq)
    quat = jnp.asarray(quat / np.linalg.norm(quat, axis=-1, keepdims=True))
    plain = np.asarray(tf.pose_residuals(pos, quat, batch))
    tau = 0.05
    weighted = np.asarray(tf.pose_residuals(pos, quat, batch, decay=tau))
    T = batch.pos.shape[1]
    w = np.exp(-batch.time[0] / (2 * tau))                    # (T,) per frame
    n_pos = T * 3
    np.testing.assert_allclose(weighted[:n_pos].reshape(T, 3),
                               plain[:n_pos].reshape(T, 3) * w[:, None], rtol=1e-12)
    np.testing.assert_allclose(weighted[n_pos:].reshape(T, 3),
                               plain[n_pos:].reshape(T, 3) * w[:, None], rtol=1e-12)


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


def test_a_leaf_the_records_want_at_zero_stops_at_its_span(tmp_path):
    """Regression: a log-space leaf whose best value is 0 (a drag fitted to a record made
    without drag) took Gauss-Newton steps that grow as 1 / value, walked off to 0 and the
    fit crashed in the covariance ("SVD did not converge"). Now a leaf without bounds moves
    at most a factor LOG_SPAN from its start, and the message says it ended at a bound."""
    scene, rec = _record_file(tmp_path, DRAG, {"extra.drag.air": 0.0}, ["p"], "p",
                              integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.5,
                              noise=0.0, seed=1)
    out = tf.fit_files(scene, [rec], maxiter=30)
    assert out["fitted"]["extra.drag.air"] == pytest.approx(0.05 / tf.LOG_SPAN, rel=1e-6)
    assert "at a bound" in out["message"] and "extra.drag.air" in out["message"]
    assert math.isfinite(out["stderr"]["extra.drag.air"])


CLOTH = """
dt = 1e-3
[[cloths]]
nx = 5
ny = 5
spacing = 0.05
mass = 0.2
origin = [0.0, 0.0, 1.0]
structural = [{k}, {c}]
shear = [50.0, 0.05]
bend = false
pinned = [[0, 0], [4, 0]]
[fit]
params = ["springs.cloth.structural.k", "springs.cloth.structural.c"]
"""


def test_default_growing_horizon_escapes_a_swing_minimum(tmp_path):
    """Regression: without [fit] horizon a record fit fitted the whole records at once; a 5 x
    5 cloth pinned at two corners, swinging for 0.8 s, fitted from half its structural k
    and c, stopped in a local minimum (k 37% low, 5.6% position error). The default now
    fits 1/8, 1/4 and 1/2 of the longest record first (AUTO_HORIZON): k within 2%.
    ``horizon = []`` keeps the whole records only."""
    truth = {"springs.cloth.structural.k": 400.0, "springs.cloth.structural.c": 0.4}
    scene, rec = _record_file(tmp_path, CLOTH.format(k=200.0, c=0.2), truth,
                              ["cloth[2,4]", "cloth[4,4]", "cloth[0,4]", "cloth[2,2]"],
                              "cloth", integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.8,
                              noise=1e-4, seed=1)
    out = tf.fit_files(scene, [rec])
    assert out["horizons"] == pytest.approx([0.1, 0.2, 0.4, None])
    assert out["fitted"]["springs.cloth.structural.k"] == pytest.approx(400.0, rel=0.02)
    assert out["after"]["position_error_pct"]["mean"] < 0.5
    whole = tmp_path / "whole.toml"
    whole.write_text(CLOTH.format(k=200.0, c=0.2) + "horizon = []\n")
    out = tf.fit_files(str(whole), [rec], maxiter=1)
    assert out["horizons"] == [None]


def test_a_growing_horizon_never_ends_worse_than_its_start(tmp_path):
    """Regression: the shorter horizons can move parameters the early frames do not fix; on
    records of a swinging rope observed at three of its five free nodes (the other two
    started as the scene file says, not as the record's swing), the first stage drove k
    to its bound and the fit ended at 315% position error against 38% at the start (now
    17%, the whole-record fit's own answer for these inconsistent records). Now
    the whole-record stage starts from the start point when that is better there, so a fit
    never ends above its start. The records (rk4 at 0.25 ms, k 400 N/m, c 0.6 N s/m) start
    the free nodes at 0.5 and -1 m/s in y: one simulator, its start state's velocities set
    (the state a scene file with that rope velocity starts from)."""
    start = tmp_path / "rope.toml"
    start.write_text("dt = 1e-3\n[[ropes]]\nn = 6\nstart = [0.0, 0.0, 1.0]\n"
                     "end = [0.5, 0.0, 1.0]\nmass = 0.3\nk = 150.0\nc = 0.1\npinned = [0]\n"
                     "[fit]\nparams = [\"springs.rope.stretch.k\", \"springs.rope.stretch.c\"]\n"
                     "observe = [\"rope[2]\", \"rope[4]\", \"rope[5]\"]\n")
    sf = load_scene_file(str(start))
    sim = sf.compile(integrator="rk4", dt=2.5e-4)
    truth = tf.with_leaves(sf.params(sim), {"springs.rope.stretch.k": 400.0,
                                            "springs.rope.stretch.c": 0.6})
    ids = {b: sf.names[b] for b in sf.spec.observe}
    free = [j for j, b in enumerate(sim.scene.bodies) if not b.pinned]
    recs = []
    for i, vy in enumerate((0.5, -1.0)):
        s = sim.state_from(body=free, velocity=np.tile([0.0, vy, 0.0], (len(free), 1)))
        recs.append(str(tmp_path / f"swing{i}.csv"))
        write_record(recs[-1], tf.synthetic_record(sim, truth, 1.0, 5e-3, ids, state=s,
                                                   noise=2e-4, seed=i))
    out = tf.fit_files(str(start), recs)
    assert out["horizons"][-1] is None and len(out["horizons"]) == 4
    assert (out["after"]["position_error_pct"]["mean"]
            <= out["before"]["position_error_pct"]["mean"])


def test_first_states_are_computed_once_per_fit(tmp_path, monkeypatch):
    """prepare(cache=...) keeps each record's first states, so a fit's evaluation batch and
    its length buckets estimate them once (a tumbling box's torque-free fit costs 25-110 ms
    a record)."""
    from tuning import record_batch
    scene, rec = _record_file(tmp_path, BOX.format(k=400.0, c=2.0), {}, ["box"], "box",
                              integrator="rk4", dt=5e-4, every=5e-3, duration=0.1,
                              noise=0.0, seed=0)
    sf = load_scene_file(scene)
    sim = sf.compile()
    records, bodies = tf.load_records(sf, [rec, rec])
    calls = []
    real = record_batch.first_state
    monkeypatch.setattr(record_batch, "first_state", lambda *a, **k: calls.append(1) or
                        real(*a, **k))
    cache = {}
    one = tf.prepare(sim, records, bodies=bodies, cache=cache)
    tf.prepare_buckets(sim, records, bodies=bodies, cache=cache)
    assert len(calls) == 2                         # two records, one body each
    again = tf.prepare(sim, records, bodies=bodies)
    assert len(calls) == 4                         # without the cache: estimated again
    np.testing.assert_array_equal(np.asarray(one.start.position),
                                  np.asarray(again.start.position))


# --------------------------------------------------------------------------- CLI probes
@pytest.fixture(scope="module")
def drag_record(tmp_path_factory):
    """(scene, record) of a particle with air drag 0.08 (rk4, 0.3 s). Shared: the tests
    read both files and write only under their own tmp_path."""
    return _record_file(tmp_path_factory.mktemp("drag"), DRAG, {"extra.drag.air": 0.08}, ["p"], "p",
                        integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.3, noise=0.0,
                        seed=1)


def test_fit_out_is_checked_before_anything_is_fitted(tmp_path, drag_record, monkeypatch):
    """``--out`` naming a record (it was overwritten with TOML after the fit), a folder (a
    traceback after the fit) or the scene file itself is refused before compiling."""
    scene, rec = drag_record
    before = open(rec).read()
    monkeypatch.setattr(tf, "levenberg_marquardt", lambda *a, **k: pytest.fail("fitted"))
    for out, words in [(rec, "ending in .toml"), (str(tmp_path), "is a directory"),
                       (scene, "is one of the inputs"),
                       (str(tmp_path / "no" / "f.toml"), "does not exist")]:
        with pytest.raises(tf.FitError, match=words):
            tf.fit_files(scene, [rec], out=out, maxiter=1)
    assert open(rec).read() == before


def test_a_fit_whose_scene_cannot_be_written_keeps_its_values(tmp_path, drag_record, capsys,
                                                              monkeypatch):
    """A fitted value the writer cannot place used to end the command with an error after
    the whole fit, the values lost; now the JSON carries them and the exit status is 2."""
    from tuning import fitted_scene

    def refuse(*a, **k):
        raise tf.FitError("cannot place the fitted extra.drag.air")
    monkeypatch.setattr(fitted_scene, "write_fitted", refuse)
    scene, rec = drag_record
    capsys.readouterr()
    assert main(["fit", scene, "--data", rec, "--out", str(tmp_path / "f.toml"),
                 "--maxiter", "3", "--json"]) == 2
    io = capsys.readouterr()
    out = json.loads(io.out)
    assert out["fitted"]["extra.drag.air"] == pytest.approx(0.08, rel=0.05)
    assert out["out"] is None and "cannot place" in out["out_error"]
    assert "cannot place" in io.err
    assert not (tmp_path / "f.toml").exists()


def test_cost_start_is_on_the_whole_records(drag_record):
    """``cost_start`` was the first stage's cost (a growing horizon's first seconds) while
    ``cost`` is on the whole records: a fit looked worse than its start."""
    scene, rec = drag_record
    grow = tf.fit_files(scene, [rec], horizons=(0.05, None), maxiter=1)
    whole = tf.fit_files(scene, [rec], horizons=(None,), maxiter=1)
    assert grow["cost_start"] == pytest.approx(whole["cost_start"], rel=1e-12)
    assert grow["cost"] <= grow["cost_start"]


def test_ball_flags_with_a_scene_file_are_refused(capsys):
    """--dt, --target-apex, --law, --mass... were ignored silently with a scene file."""
    import os
    ball = os.path.join(os.path.dirname(__file__), "..", "examples", "ball.toml")
    assert main(["fit", ball, "--target-apex", "0.5", "--dt", "5e-4"]) == 2
    err = capsys.readouterr().err
    assert "--dt --target-apex set the built-in ball's fit" in err


def test_fit_with_a_plane_offset_reports_what_evaluate_gives(tmp_path):
    """With first_state = "fit" the flight frames are counted against the planes; the fit
    estimated them at the start offset and reported errors the written scene did not give
    (8.897% against diffpen evaluate's 8.925% on two cube tosses). Now "after" is evaluated
    as the fitted scene file is. Here the cube's lowest corner is 4 cm up: 16 flight frames
    clear the plane by 5 mm at the start offset, 17 at the fitted one (with noise the two
    parabolas differ)."""
    from tuning.evaluate import evaluate_files
    text = ("dt = 1e-3\n[materials.board]\nk = 3000.0\nc = 30.0\nfriction = 0.2\n"
            "[[boxes]]\nname = \"cube\"\nhalf_extents = [0.05, 0.05, 0.05]\nmass = 0.37\n"
            "position = [0.0, 0.0, 0.09]\nvelocity = [0.4, 0.0, 0.0]\n"
            "angular_velocity = [0.0, 1.0, 0.0]\nmaterial = \"board\"\n"
            "[[planes]]\nname = \"ground\"\noffset = 0.0\nmaterial = \"board\"\n[fit]\n"
            "params = [\"extra.plane_offset.ground\"]\n"
            "first_state = \"fit\"\n")
    scene, rec = _record_file(tmp_path, text, {"extra.plane_offset.ground": -0.004},
                              ["cube"], "cube", integrator="semi_implicit_euler", dt=1e-3,
                              every=5e-3, duration=0.4, noise=2e-4, seed=1)
    out = tf.fit_files(scene, [rec], out=str(tmp_path / "f.toml"), horizons=(None,),
                       maxiter=10)
    assert out["fitted"]["extra.plane_offset.ground"] == pytest.approx(-0.004, abs=5e-4)
    ev = evaluate_files(str(tmp_path / "f.toml"), [rec])
    assert ev["position_error_pct"]["mean"] == pytest.approx(
        out["after"]["position_error_pct"]["mean"], rel=1e-9)
    assert ev["rotation_error_deg"]["mean"] == pytest.approx(
        out["after"]["rotation_error_deg"]["mean"], rel=1e-9)


def test_fit_with_a_plane_offset_and_record_starts_reports_what_evaluate_gives(tmp_path):
    """Regression: with first_state = "record" the start's lag also depends on the planes
    (free flight's gravity, or the frames' slope for a body near a plane), but "after" was
    re-estimated at the fitted offset only for "fit": a box sliding on the ground, the start
    offset leaving it 6 mm up and the fitted one on the plane, reported 0.50071% / 0.10887
    deg where diffpen evaluate of the written scene gave 0.51923% / 0.10786 deg."""
    from tuning.evaluate import evaluate_files
    text = ("dt = 5e-4\n[materials.board]\nk = 3000.0\nc = 25.0\nfriction = 0.5\n"
            "[[boxes]]\nname = \"box\"\nhalf_extents = [0.05, 0.04, 0.03]\nmass = 2.0\n"
            "position = [0.0, 0.0, 0.032]\nvelocity = [1.2, 0.3, 0.0]\n"
            "body_angular_velocity = [0.0, 0.0, 2.0]\nmaterial = \"board\"\n"
            "[[planes]]\nname = \"ground\"\noffset = -0.004\nmaterial = \"board\"\n[fit]\n"
            "params = [\"extra.plane_offset.ground\"]\nfirst_state = \"record\"\n"
            "[fit.bounds]\n\"extra.plane_offset.ground\" = [-0.01, 0.01]\n")
    scene, rec = _record_file(tmp_path, text, {"extra.plane_offset.ground": 0.002}, ["box"],
                              "box", integrator="semi_implicit_euler", dt=5e-4, every=5e-3,
                              duration=0.4, noise=2e-4, seed=1)
    out = tf.fit_files(scene, [rec], out=str(tmp_path / "f.toml"), horizons=(None,),
                       maxiter=10)
    assert out["fitted"]["extra.plane_offset.ground"] == pytest.approx(0.002, abs=5e-4)
    ev = evaluate_files(str(tmp_path / "f.toml"), [rec])
    for key in ("position_error_pct", "rotation_error_deg"):
        assert ev[key]["mean"] == pytest.approx(out["after"][key]["mean"], rel=1e-9), key


def test_scene_sweep_checks_metric_and_plot_before_computing(tmp_path, drag_record, capsys):
    scene, rec = drag_record
    out = tmp_path / "s.npz"
    assert main(["sweep", scene, "--param", "extra.drag.air", "0.01", "0.1", "--n", "3",
                 "--data", rec, "--metric", "settling_time", "--out", str(out)]) == 2
    assert "is not measured by this sweep" in capsys.readouterr().err
    assert main(["sweep", scene, "--param", "extra.drag.air", "0.01", "0.1", "--n", "3",
                 "--data", rec, "--plot", str(tmp_path / "p.png"), "--out", str(out)]) == 2
    assert "over two parameters" in capsys.readouterr().err
    assert not out.exists()


def test_evaluate_plot_must_be_a_folder(tmp_path, drag_record, capsys):
    scene, rec = drag_record
    f = tmp_path / "taken.png"
    f.write_text("x")
    assert main(["evaluate", scene, "--data", rec, "--plot", str(f)]) == 2
    assert "is a file" in capsys.readouterr().err


ROLLING = """
dt = 1.25e-4
[materials.rubber]
k = 5183.0
c = 3.045
friction = 0.598
[[rigid_spheres]]
name = "ball"
radius = 0.05
mass = 0.3
position = [0.0, 0.0, 0.3]
velocity = [1.0, 0.05, 0.5]
angular_velocity = [0.0, -10.0, 0.0]
material = "rubber"
[[planes]]
name = "ground"
material = "rubber"
[fit]
params = ["extra.friction.rubber"]
"""


def test_a_fit_whose_derivatives_blow_up_is_not_a_result(tmp_path):
    """A sphere that lands rolling without slip: during the impact its viscous friction
    (mu f_n / slip_speed, bounded by the safe step at the static load m g only) is past the
    explicit step's limit for the tangents, so d position / d mu grows to 1e64 while the
    motion stays bounded. The fit reported standard errors of 1e-128, correlations of
    +-1 and "reached": true. Now it says the derivatives blew up and is not a result."""
    scene, rec = _record_file(tmp_path, ROLLING, {}, ["ball"], "ball",
                              integrator="semi_implicit_euler", dt=1.25e-4, every=5e-3,
                              duration=0.8, noise=0.0, seed=0)
    out = tf.fit_files(scene, [rec], horizons=(None,), maxiter=1)
    assert out["diverged"] and not out["reached"]
    assert "derivatives blew up" in out["message"]
    assert math.isnan(out["stderr"]["extra.friction.rubber"])


def test_a_rigid_body_without_orientation_columns_is_warned_about(tmp_path, cube):
    """A record with positions only of a box started it silently from the scene file's
    orientation with no spin (31.9% position error against 1.40% with quaternions)."""
    from tuning.records import BodyRecord, Record
    t = np.arange(12) * 5e-3
    pos = np.stack([np.zeros(12), np.zeros(12), 0.3 - 4.9 * t ** 2], axis=1)
    rec = Record(path=str(tmp_path / "posonly.csv"), t=t, bodies={"0": BodyRecord(pos)})
    with pytest.warns(UserWarning, match="no orientation columns .* posonly.csv"):
        tf.prepare(cube, [rec])


def test_a_record_of_a_pinned_body_prepares(tmp_path):
    """A record that also tracks a rope's pinned end failed ("body 0 is pinned ... takes
    no velocity"): its estimated velocity went to state_from. A pinned body keeps zero
    velocity; a zero velocity is accepted."""
    text = ROPE.format(k=200.0, c=0.3)
    scene, rec = _record_file(tmp_path, text, {}, ["rope[0]", "rope[2]"], "rope",
                              integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.1,
                              noise=1e-4, seed=1)
    sf = load_scene_file(scene)
    sim = sf.compile()
    records, bodies = tf.load_records(sf, [rec])
    for est in ("record", "fit"):
        batch = tf.prepare(sim, records, bodies=bodies, estimate=est)
        assert np.all(np.asarray(batch.start.velocity)[0, sf.names["rope[0]"]] == 0.0)
    sim.state_from(body=sf.names["rope[0]"], velocity=(0.0, 0.0, 0.0))


def test_rotation_angle_is_accurate_near_zero_in_float32():
    """Regression: the angle was 2 arccos(|q_sim . q_data|), which reads identical float32
    orientations as up to 0.056 deg apart (mean 0.009 deg). Now 2 atan2(|v|, |w|) of the
    relative quaternion: 0 for identical ones, and right for small and large angles."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=(1000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q32 = jnp.asarray(q, jnp.float32)
    assert float(jnp.max(jnp.degrees(pose.rotation_angle(q32, q32)))) < 1e-3
    for angle in (1e-3, 0.3, 2.5):
        turn = np.array([np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0])
        other = np.asarray(pose.qmul(jnp.asarray(q), jnp.asarray(turn)))
        got = np.asarray(pose.rotation_angle(jnp.asarray(q), jnp.asarray(other)))
        np.testing.assert_allclose(got, angle, rtol=1e-6)


def test_records_may_observe_builder_nodes_beside_named_bodies(tmp_path):
    """Regression: with a named body in the scene, a record column of a builder's node
    (rope[3].x, the README's multi-body form) was refused as 'names body rope[3], which the
    scene does not have'; now it resolves to the node (a node outside the builder is still
    refused, naming the record)."""
    scene = tmp_path / "mixed.toml"
    scene.write_text('dt = 1e-3\nduration = 0.2\n[[boxes]]\nname = "cube"\n'
                     'half_extents = [0.05, 0.05, 0.05]\nmass = 0.4\n'
                     'position = [0.0, 0.0, 0.5]\n[[ropes]]\nn = 4\nstart = [0.0, 0.5, 1.0]\n'
                     'end = [0.3, 0.5, 1.0]\nmass = 0.1\nk = 200.0\nc = 0.2\n'
                     '[fit]\nparams = ["springs.rope.stretch.k"]\n')
    sf = load_scene_file(str(scene))
    good, bad = tmp_path / "good.csv", tmp_path / "bad.csv"
    for path, node in ((good, "rope[3]"), (bad, "rope[9]")):
        path.write_text(f"t,cube.x,cube.y,cube.z,{node}.x,{node}.y,{node}.z\n"
                        "0.0,0.0,0.0,0.5,0.3,0.5,1.0\n0.01,0.0,0.0,0.4995,0.3,0.5,0.9995\n")
    _, bodies = tf.load_records(sf, [str(good)])
    assert bodies == {"cube": sf.names["cube"], "rope[3]": sf.body_index("rope[3]")}
    with pytest.raises(tf.FitError, match="bad.csv: the columns of 'rope\\[9\\]'"):
        tf.load_records(sf, [str(bad)])


def test_a_record_fit_refuses_a_method_it_does_not_use(tmp_path):
    """Regression: [fit] method = "adam" in a scene file with records was silently ignored
    (the fit ran Levenberg-Marquardt), while --method adam was refused."""
    from tuning.scene_fit import fit_files
    scene = tmp_path / "rope.toml"
    scene.write_text(ROPE.format(k=200.0, c=0.3).replace("[fit]", '[fit]\nmethod = "adam"'))
    rec = tmp_path / "rope.csv"         # 50 ms of node 1 falling: a record the scene reads
    rec.write_text("t,rope[1].x,rope[1].y,rope[1].z\n" + "".join(
        f"{5e-3 * i!r},0.1,0.0,{1.0 - 4.905 * (5e-3 * i) ** 2!r}\n" for i in range(11)))
    assert tf.load_records(load_scene_file(str(scene)), [str(rec)])[1] == {"rope[1]": 1}
    with pytest.raises(tf.FitError, match="method = 'adam', but fits to records use"):
        fit_files(str(scene), [str(rec)])


SPHERE = ('dt = 1e-3\nduration = 0.1\n[[spheres]]\n{name}radius = 0.05\nmass = 0.2\n'
          'position = [0.0, 0.0, 0.5]\n')
ROPE_ONLY = ('dt = 1e-3\nduration = 0.1\n{pinned}[[ropes]]\nn = 4\nstart = [0.0, 0.0, 1.0]\n'
             'end = [0.3, 0.0, 1.0]\nmass = 0.4\nk = 300.0\n')
PINNED = ('[[spheres]]\nname = "s"\nradius = 0.05\nmass = 0.1\nposition = [5.0, 0.0, 1.0]\n'
          'pinned = true\n')


def _scene_and_records(tmp_path, text, *headers):
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    paths = []
    for k, header in enumerate(headers):
        n = header.count(".x") or 1
        path = tmp_path / f"rec{k}.csv"
        path.write_text(f"t,{header}\n" + "".join(
            f"{0.01 * i}" + ",0.3,0.0,1.0" * n + "\n" for i in range(3)))
        paths.append(str(path))
    return load_scene_file(str(scene)), paths


def test_record_columns_of_bodies_the_scene_lacks_are_refused(tmp_path):
    """Regression: in a scene without named bodies, columns a.x, b.x (bodies it does not
    have) were both mapped onto its only free body. They are refused with the file, line
    and column; plain x, y, z columns still belong to that body."""
    sf, (plain, ab) = _scene_and_records(tmp_path, SPHERE.format(name=""), "x,y,z",
                                         "a.x,a.y,a.z,b.x,b.y,b.z")
    assert tf.load_records(sf, [plain])[1] == {"body": 0}
    with pytest.raises(tf.FitError, match=r"rec1.csv, line 1, column 2: 'a.x' names body "
                                          r"'a', which the scene does not have; named "
                                          r"bodies: none"):
        tf.load_records(sf, [ab])


@pytest.mark.parametrize("pinned", ["", PINNED])
def test_node_columns_resolve_with_or_without_named_bodies(tmp_path, pinned):
    """Regression: rope[-1].x and rope[ 3 ].x (the README's node forms) were refused when the
    scene had no named body ("the columns name no body and the scene has 3 free bodies")."""
    sf, paths = _scene_and_records(tmp_path, ROPE_ONLY.format(pinned=pinned),
                                   *(f"{n}.x,{n}.y,{n}.z" for n in
                                     ("rope[3]", "rope[-1]", "rope[ 3 ]")))
    node = sf.body_index("rope[3]")
    for path, name in zip(paths, ("rope[3]", "rope[-1]", "rope[ 3 ]")):
        assert tf.load_records(sf, [path])[1] == {name: node}


def test_one_body_under_two_names_is_refused(tmp_path):
    """Regression: rope[3] and rope[-1] (the same node) with different data were accepted,
    the start state taken from the last. Two names of one body are refused, naming both,
    within a record and across records; prepare's own body map refuses it too."""
    sf, (both, three, last) = _scene_and_records(
        tmp_path, ROPE_ONLY.format(pinned=PINNED),
        "rope[3].x,rope[3].y,rope[3].z,rope[-1].x,rope[-1].y,rope[-1].z",
        "rope[3].x,rope[3].y,rope[3].z", "rope[-1].x,rope[-1].y,rope[-1].z")
    node = sf.body_index("rope[3]")
    with pytest.raises(tf.FitError, match=r"rec0.csv: the columns rope\[3\].x, ... and "
                                          rf"rope\[-1\].x, ... observe the same scene body "
                                          rf"{node}: name each body once"):
        tf.load_records(sf, [both])
    with pytest.raises(tf.FitError, match=r"rec2.csv: the columns rope\[-1\].x, ... observe "
                                          rf"the same scene body {node}, and .*rec1.csv names "
                                          r"it 'rope\[3\]'"):
        tf.load_records(sf, [three, last])
    from tuning.records import read_record
    rec = read_record(both)
    with pytest.raises(tf.FitError, match=r"record bodies 'rope\[3\]' and 'rope\[-1\]' both "
                                          rf"map to body {node}"):
        tf.prepare(sf.compile(), [rec], bodies={"rope[3]": node, "rope[-1]": node})


def test_columns_of_a_body_left_out_of_observe_say_so(tmp_path):
    """Regression: with [fit] observe = ["cube"], columns of the scene's body 'ball' were
    refused as a body 'the scene does not have'."""
    text = (SPHERE.format(name='name = "ball"\n') + SPHERE.format(name='name = "cube"\n')
            .replace("0.0, 0.0, 0.5", "1.0, 0.0, 0.5").split("duration = 0.1\n")[1]
            + '[fit]\nobserve = ["cube"]\nparams = ["contact.default.k"]\n')
    sf, (path,) = _scene_and_records(tmp_path, text, "cube.x,cube.y,cube.z,ball.x,ball.y,ball.z")
    with pytest.raises(tf.FitError, match=r"rec0.csv, line 1, column 5: 'ball.x' names body "
                                          r"'ball', which is not in \[fit\] observe \(cube\); "
                                          r"add 'ball' to observe or drop its columns"):
        tf.load_records(sf, [path])


def test_multi_start_screens_past_a_horizon_that_ties(cube):
    """Regression: every start's screen cost was 0 when the first horizon ended before the
    first contact, so LM ran from the first starts drawn instead of the cheapest. The
    screen now takes the next horizons while the costs are equal, and says so when they
    never differ. Both records last 0.3 s (one layout: one compile of the fit's programs):
    dropped from 0.2 m the cube lands after 0.17 s, past the first horizon (0.05 s);
    dropped from 0.6 m its lowest face is still 0.11 m above the plane at the end."""
    truth = cube.params()                                    # c = 30 N s/m

    def drop(z):
        s = cube.state_from(body=0, position=(0, 0, z), velocity=(0.3, 0, 0.0),
                            orientation=(1.0, 0, 0, 0), angular_velocity=(0, 0, 0))
        return tf.prepare(cube, [tf.synthetic_record(cube, truth, 0.3, 5e-3, {"cube": 0},
                                                     state=s)], estimate="record")
    batch = drop(0.2)
    far = tf.with_leaves(truth, {"contact.board.c": 8.0})
    free = [tf.Free("contact.board.c", 1.0, 60.0)]
    res = tf.fit_records(cube, far, batch, free, horizons=(0.05, None), maxiter=1,
                         starts=[{"contact.board.c": 30.0}], keep=1)
    assert res.starts[0]["cost"] is None and res.starts[1]["cost"] is not None
    assert res.starts[1]["screen_cost"] < res.starts[0]["screen_cost"]
    assert "first horizon were equal" in res.message, res.message
    flight = drop(0.6)
    assert np.min(flight.pos[..., 2]) > 0.05 + 0.1     # the lowest face 0.1 m above the plane
    res = tf.fit_records(cube, far, flight, free, maxiter=1,
                         starts=[{"contact.board.c": 30.0}], keep=1)
    assert "screen costs are equal up to the whole records" in res.message, res.message


def test_a_leaf_without_effect_on_a_noise_free_record_is_undetermined():
    """Regression: the damping of a ball resting on the ground all along has no effect on
    the record (only round-off in its Jacobian column), yet the fit reported it as
    determined with a standard error of 0 (J^T J normalised by its diagonal made the
    round-off a full direction). A column below BLIND_RATIO of the largest is now blind."""
    r, m, k = 0.05, 1.0, 2e4
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("m", k=k, c=20.0)
    scene.add_sphere(r, m, (0.0, 0.0, r - m * 9.81 / k), material="m")
    scene.add_plane(material="m")
    sim = dp.compile(scene, 1e-3)
    rec = tf.synthetic_record(sim, sim.params(), 0.2, 5e-3, {"ball": 0})
    batch = tf.prepare(sim, [rec], bodies={"ball": 0})
    start = tf.with_leaves(sim.params(), {"contact.m.k": 1e4})
    res = tf.fit_records(sim, start, batch, [tf.Free("contact.m.k", 1e3, 1e6),
                                             tf.Free("contact.m.c", 0.1, 1e3)],
                         horizons=(None,), maxiter=5)
    assert res.values["contact.m.k"] == pytest.approx(k, rel=1e-6)
    assert res.stderr["contact.m.c"] == math.inf and math.isfinite(res.stderr["contact.m.k"])
    assert [abs(u["direction"]["contact.m.c"]) for u in res.undetermined] == [
        pytest.approx(1.0)]


def test_commands_run_in_the_test_session_leave_the_compilation_cache_off():
    """Regression: the first in-process ``diffpen`` command (``tuning.cli.main``) turned on
    its persistent compilation cache in ~/.cache/diffpen for the rest of the pytest worker
    (every later test program was written there); tests/conftest.py sets DIFFPEN_CACHE=0 for
    the whole session, and ``setup_jax`` honours it."""
    import os

    import jax

    from tuning.cli._common import setup_jax
    assert os.environ.get("DIFFPEN_CACHE") == "0"
    before = jax.config.jax_compilation_cache_dir
    setup_jax()
    assert jax.config.jax_compilation_cache_dir == before


HERTZ_BALL = ('law = "hunt_crossley"\nexponent = 1.5\ndt = 1e-3\nduration = 1.0\n'
              '[materials.rubber]\nk = {k}\nc = {c}\n'
              '[[spheres]]\nname = "ball"\nradius = 0.1\nmass = 1.0\nposition = [0.0, 0.0, 1.0]\n'
              'material = "rubber"\n[[planes]]\nmaterial = "rubber"\nname = "ground"\n'
              '[fit]\nparams = ["contact.rubber.k", "contact.rubber.c"]\nobserve = ["ball"]\n'
              '[fit.bounds]\n"contact.rubber.k" = [3e5, 3e6]\n"contact.rubber.c" = [1e3, 1e5]\n')


def test_a_hertz_record_fit_counts_the_records_start_energy(tmp_path):
    """Regression: record fits capped Hunt-Crossley's k and c at the safe step with the
    contact taken at the ball's radius (10 cm), so the Hertz ball of the README (1 kg, k 1e6
    N/m^1.5, here c 4e4, dropped from 1 m onto a named, fittable floor) could not be fitted
    at dt 1 ms: both values lay past the caps (k 5.2e5, c 3.1e4). The caps now count the
    records' own start energy (the softest k of the bounds sinks deepest) and the floor's
    offset from the params, as a rollout from those starts does (k 1.26e6, c 1.85e5): the
    fit recovers k and c within 2% from a record made by rk4 at 0.25 ms."""
    from tuning.stable import safe_contact_bounds
    truth = {"contact.rubber.k": 1e6, "contact.rubber.c": 4e4}
    scene, rec = _record_file(tmp_path, HERTZ_BALL.format(k=5e5, c=2e4), truth, ["ball"],
                              "hertz", integrator="rk4", dt=2.5e-4, every=5e-3, duration=1.0,
                              noise=0.0, seed=0)
    sf = load_scene_file(scene)
    sim = sf.compile()
    radius_caps = safe_contact_bounds(sim)
    assert radius_caps[0] < 1e6 and radius_caps[1] < 4e4
    out = tf.fit_files(scene, [rec], horizons=[None])
    assert out["fitted"]["contact.rubber.k"] == pytest.approx(1e6, rel=0.02)
    assert out["fitted"]["contact.rubber.c"] == pytest.approx(4e4, rel=0.02)
