"""Sweeps of a scene file's parameters (tuning.scene_sweep, diffpen sweep SCENE.toml): the
values equal the evaluation and the metrics at each point, the record's own parameters are
the lowest point, signed leaves get linear axes, results resume and another sweep's file is
refused, and the command's bad input is refused before anything runs."""
import json
import os

import jax
import numpy as np
import pytest

from tuning import trajfit as tf
from tuning.cli import main
from tuning.errors import FitError
from tuning.evaluate import evaluate_batch, evaluator
from tuning.metrics import ball_metrics
from tuning.records import write_record
from tuning.scene_sweep import sweep_scene_file
from tuning.scenefile import load_scene_file
from tuning.sweep import SweepError, sweep

BOX = """
dt = 1e-3
[materials.board]
k = 3000.0
c = 30.0
friction = 0.2
[[boxes]]
name = "cube"
half_extents = [0.05, 0.05, 0.05]
mass = 0.37
position = [0.0, 0.0, 0.15]
orientation = [0.95, 0.2, 0.1, 0.2]
velocity = [0.4, 0.1, 0.0]
body_angular_velocity = [2.0, -1.0, 1.0]
material = "board"
[[planes]]
name = "ground"
offset = -0.001
material = "board"
[fit]
params = ["contact.board.k", "contact.board.c", "extra.plane_offset.ground"]
[fit.bounds]
"contact.board.k" = [1000.0, 9000.0]
"contact.board.c" = [10.0, 120.0]
"extra.plane_offset.ground" = [-0.003, 0.001]
"""


@pytest.fixture(scope="module")
def box_files(tmp_path_factory):
    """The box scene and a 0.4 s record of it made at k 3000, c 30 (its own values)."""
    d = tmp_path_factory.mktemp("scene_sweep")
    scene = d / "box.toml"
    scene.write_text(BOX)
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    rec = tf.synthetic_record(sim, sf.params(sim), 0.4, 5e-3, {"cube": 0})
    path = d / "box.csv"
    write_record(str(path), rec)
    return str(scene), str(path), d


def test_record_sweep_equals_the_evaluation_and_resumes(box_files):
    """Each point's errors equal tuning.evaluate at that point's parameters; the record's
    own (k, c) has error 0 and is the lowest; a rerun reads every point back; the same
    output with another record is refused."""
    scene, rec, d = box_files
    out = str(d / "kc.npz")
    axes = [("contact.board.k", 1000.0, 9000.0), ("contact.board.c", 20.0, 45.0)]
    res, info = sweep_scene_file(scene, [rec], axes, n=[3], out=out, chunk=4)
    np.testing.assert_allclose(info["axes"]["contact.board.k"], [1000.0, 3000.0, 9000.0])
    np.testing.assert_allclose(info["axes"]["contact.board.c"], [20.0, 30.0, 45.0])
    assert res.points.shape == (9, 2) and res.evaluated == 9
    sf = load_scene_file(scene)
    sim = sf.compile()
    records, bodies = tf.load_records(sf, [rec])
    batch = tf.prepare(sim, records, bodies=bodies, estimate="record")
    fn = evaluator(sim, batch)                  # one compile for the three points
    for i in (0, 4, 8):
        p = tf.with_leaves(sf.params(sim), dict(zip(res.names, res.points[i])))
        ev = evaluate_batch(sim, p, batch, fn=fn)
        np.testing.assert_allclose(res.metrics["position_error_pct"][i],
                                   ev.position_error_pct["mean"], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(res.metrics["rotation_error_deg"][i],
                                   ev.rotation_error_deg["mean"], rtol=1e-9, atol=1e-9)
    pe = res.metrics["position_error_pct"]
    # k = 9000 with this box's damping is past its safe step (0.9 of the damped limit):
    # those points are NaN, as every unstable point of a sweep
    assert np.isnan(pe[[2, 5, 8]]).all() and np.isfinite(np.delete(pe, [2, 5, 8])).all()
    assert int(np.nanargmin(pe)) == 4 and pe[4] < 1e-6 < np.nanmin(np.delete(pe, 4))
    again, _ = sweep_scene_file(scene, [rec], axes, n=[3], out=out, chunk=4)
    assert again.evaluated == 0
    np.testing.assert_array_equal(again.metrics["position_error_pct"], pe)
    other = d / "other.csv"
    text = open(rec).read().splitlines()
    other.write_text("\n".join(text[:-5]) + "\n")             # a shorter record
    with pytest.raises(SweepError, match="records"):
        sweep_scene_file(scene, [str(other)], axes, n=[3], out=out, chunk=4)


def test_axes_from_the_fit_table_and_signed_leaves(box_files):
    """Without --param the [fit] params are swept over [fit.bounds]: log-spaced k and c,
    a linear plane offset through negative values."""
    scene, rec, _ = box_files
    res, info = sweep_scene_file(scene, [rec], None, n=[2, 2, 3], chunk=16)
    np.testing.assert_allclose(info["axes"]["extra.plane_offset.ground"], [-0.003, -0.001,
                                                                          0.001])
    np.testing.assert_allclose(info["axes"]["contact.board.k"], [1000.0, 9000.0])
    assert res.points.shape == (12, 3)
    # c = 120 N s/m is past this box's safe step at 1 ms (about 52): NaN and counted
    past = res.points[:, 1] > 100.0
    assert res.unstable == int(past.sum()) == 6
    assert np.all(np.isnan(res.metrics["position_error_pct"][past]))
    assert np.all(np.isfinite(res.metrics["position_error_pct"][~past]))
    with pytest.raises(FitError, match="not a parameter"):
        sweep_scene_file(scene, [rec], [("contact.wood.k", 1.0, 2.0)], n=[2])
    with pytest.raises(FitError, match="LO > 0"):
        sweep_scene_file(scene, [rec], [("contact.board.c", -1.0, 2.0)], n=[2])
    with pytest.raises(FitError, match="one per axis"):
        sweep_scene_file(scene, [rec], None, n=[2, 3])
    sf = load_scene_file(scene)                 # the library sweep: only offsets may be < 0
    with pytest.raises(ValueError, match="contact.board.k must be >= 0"):
        sweep(lambda p: {}, sf.params(sf.compile()), [[-1.0]], ["contact.board.k"])


def test_bounce_sweep_equals_the_metrics(tmp_path):
    """Without records a scene file's sweep measures its [fit] body's bounce: each point's
    metrics equal tuning.metrics.ball_metrics of a rollout at that point."""
    text = open(os.path.join(os.path.dirname(__file__), "..", "examples", "ball.toml")).read()
    scene = tmp_path / "ball.toml"
    scene.write_text(text.replace("duration = 3.0", "duration = 1.0"))
    axes = [("contact.rubber.k", 5e3, 2e4), ("contact.rubber.c", 10.0, 40.0)]
    res, info = sweep_scene_file(str(scene), (), axes, n=[2], chunk=4)
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    # each point's rollout and its metrics in one compiled program (one compile for both)
    metrics = jax.jit(lambda q: ball_metrics(sim, sim.rollout(q, sf.setup.steps), q, n_apex=3))
    for i in (0, 3):
        p = tf.with_leaves(sf.params(sim), dict(zip(res.names, res.points[i])))
        m = metrics(p)
        np.testing.assert_allclose(res.metrics["apex_heights"][i], m.apex_heights,
                                   rtol=1e-9)
        np.testing.assert_allclose(res.metrics["contact_durations"][i], m.contact_durations,
                                   rtol=1e-9)


def test_cli_scene_sweep(box_files, capsys):
    """diffpen sweep SCENE.toml --param ... --data ... --json: one JSON object naming the
    lowest point; the ball's own flags and --param without a scene are refused (exit 2)."""
    scene, rec, d = box_files
    out = str(d / "cli.npz")
    capsys.readouterr()
    assert main(["sweep", scene, "--param", "contact.board.k", "1000", "9000", "--param",
                 "contact.board.c", "20", "45", "--n", "3", "--data", rec, "--out", out,
                 "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["grid"] == [3, 3] and got["records"] == 1
    assert got["lowest"]["point"] == pytest.approx({"contact.board.k": 3000.0,
                                                   "contact.board.c": 30.0})
    assert os.path.exists(out) and os.path.exists(out[:-4] + ".csv")
    assert main(["sweep", scene, "--k", "1", "2", "--data", rec, "--out", out]) == 2
    assert "--k" in capsys.readouterr().err
    assert main(["sweep", "--param", "contact.board.k", "1", "2"]) == 2
    assert "SCENE.toml" in capsys.readouterr().err
    assert main(["sweep", scene, "--param", "contact.board.k", "1", "x", "--data", rec,
                 "--out", out]) == 2
    assert "must be a number" in capsys.readouterr().err


def test_cli_bounce_sweep_counts_the_unsettled_points(tmp_path, capsys):
    """The scene file's bounce sweep reports how many points did not settle, as the
    ball's sweep does (their settling_time is NaN)."""
    text = open(os.path.join(os.path.dirname(__file__), "..", "examples", "ball.toml")).read()
    scene = tmp_path / "ball.toml"
    scene.write_text(text.replace("duration = 3.0", "duration = 0.6"))
    capsys.readouterr()
    assert main(["sweep", str(scene), "--param", "contact.rubber.k", "5e3", "2e4", "--param",
                 "contact.rubber.c", "10", "40", "--n", "2", "--metric", "apex_heights",
                 "--out", str(tmp_path / "b.npz"), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["unsettled"] == 4                  # 0.6 s: no ball settles


def test_a_damping_declared_zero_is_swept_in_log_steps(tmp_path):
    """Regression: the spacing followed the leaf's start value, so a damping declared 0 (a
    rope's bare `bend = 20.0`) was swept linearly (0.01, 0.505, 1) beside its log-spaced k.
    The kind of leaf decides now; LO = 0 for it asks for [fit.space] linear."""
    from tuning.scene_sweep import sweep_axes
    scene = tmp_path / "rope.toml"
    scene.write_text("dt = 1e-3\nduration = 0.1\n[[ropes]]\nn = 4\nstart = [0.0, 0.0, 1.0]\n"
                     "end = [0.3, 0.0, 1.0]\nmass = 0.1\nk = 200.0\nc = 0.2\nbend = 20.0\n"
                     "pinned = [0]\n")
    sf = load_scene_file(str(scene))
    params = sf.params(sf.compile())
    axes = sweep_axes(sf, params, [("springs.rope.bend.c", 0.01, 1.0)], [3])
    np.testing.assert_allclose(axes["springs.rope.bend.c"], [0.01, 0.1, 1.0])
    with pytest.raises(FitError, match="log steps and needs LO > 0"):
        sweep_axes(sf, params, [("springs.rope.bend.c", 0.0, 1.0)], [3])


NEAR = """
dt = 5e-4
[materials.board]
k = 3000.0
c = 25.0
friction = 0.5
[[boxes]]
name = "box"
half_extents = [0.05, 0.04, 0.03]
mass = 2.0
position = [0.0, 0.0, 0.032]
velocity = [1.2, 0.3, 0.0]
body_angular_velocity = [0.0, 0.0, 2.0]
material = "board"
[[planes]]
name = "ground"
offset = {off}
material = "board"
"""


def test_a_swept_plane_offset_starts_the_records_as_evaluate_does(tmp_path):
    """Regression: the records' start states were estimated once, against the scene file's
    plane offset, and reused at every swept offset; a box 2 mm above its ground is in
    contact at the file's offset and in free flight at -4 mm, which changes its start
    velocity. Each point now equals diffpen evaluate of the scene file with that offset."""
    from tuning.evaluate import evaluate_files
    scene = tmp_path / "near.toml"
    scene.write_text(NEAR.format(off=0.002))
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    rec = str(tmp_path / "near.csv")
    write_record(rec, tf.synthetic_record(sim, sf.params(sim), 0.1, 5e-3, {"box": 0},
                                          noise=2e-4, seed=1))
    res, _ = sweep_scene_file(str(scene), [rec], [("extra.plane_offset.ground", -0.004,
                                                   0.002), ("contact.board.c", 20.0, 25.0)],
                              n=[2], chunk=4)
    for i, (off, c) in enumerate(res.points):
        at = tmp_path / f"at{i}.toml"
        at.write_text(NEAR.format(off=repr(float(off))).replace("c = 25.0",
                                                                 f"c = {float(c)!r}"))
        ev = evaluate_files(str(at), [rec])
        for m in ("position_error_pct", "rotation_error_deg"):
            np.testing.assert_allclose(res.metrics[m][i], ev[m]["mean"], rtol=1e-9,
                                       atol=1e-12, err_msg=f"{m} at offset {off}, c {c}")
        assert res.metrics["unstable_records"][i] == ev["unstable"] == 0


SPIN = """
dt = {dt}
duration = 0.05
[materials.board]
k = 500.0
c = 10.0
friction = 0.3
[[boxes]]
name = "box"
half_extents = [0.1, 0.05, 0.01]
mass = 1.0
position = [0.0, 0.0, 0.5]
material = "board"
[[planes]]
name = "ground"
material = "board"
"""


@pytest.fixture(scope="module")
def spin_records(tmp_path_factory):
    """The spinning box's scene at dt 5e-4 and two records made at dt 5e-5: a slow one and
    one spinning at 150 rad/s, past the spin limit at 5e-4 (its rollout goes unstable).
    Shared: the tests read the files and write only under their own tmp_path."""
    tmp_path = tmp_path_factory.mktemp("spin")
    fine, scene = tmp_path / "fine.toml", tmp_path / "spin.toml"
    fine.write_text(SPIN.format(dt=5e-5))
    scene.write_text(SPIN.format(dt=5e-4))
    sf = load_scene_file(str(fine))
    sim = sf.compile()
    recs = []
    for name, w in (("slow", (0.0, 0.0, 2.0)), ("fast", (3.0, 2.0, 150.0))):
        s = sim.state_from(body=0, position=(0.0, 0.0, 0.5), angular_velocity=w, frame="body")
        recs.append(str(tmp_path / f"{name}.csv"))
        write_record(recs[-1], tf.synthetic_record(sim, sf.params(sim), 0.05, 5e-3,
                                                   {"box": 0}, state=s))
    return scene, recs


def test_an_unstable_record_is_left_out_of_each_point_as_evaluate_does(tmp_path,
                                                                       spin_records):
    """Regression: one record past the safe step (a flat box spinning at 150 rad/s, past
    the spin limit at dt 5e-4) made every point NaN and counted it unstable, whatever k.
    Each point now equals tuning.evaluate: that record is left out of the mean and median
    and counted per point (unstable_records); the point is a result."""
    scene, recs = spin_records
    out = str(tmp_path / "spin.npz")
    res, _ = sweep_scene_file(str(scene), recs, [("contact.board.k", 300.0, 800.0)], n=[2],
                              out=out, chunk=2)
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    records, bodies = tf.load_records(sf, recs)
    batch = tf.prepare(sim, records, bodies=bodies, estimate="record")
    assert res.unstable == 0
    fn = evaluator(sim, batch)                  # one compile for both points
    for i in range(2):
        ev = evaluate_batch(sim, tf.with_leaves(sf.params(sim), {"contact.board.k":
                                                                 res.points[i, 0]}), batch,
                            fn=fn)
        assert ev.unstable == 1 and res.metrics["unstable_records"][i] == 1
        for m, s in (("position_error_pct", ev.position_error_pct),
                     ("rotation_error_deg", ev.rotation_error_deg)):
            np.testing.assert_allclose(res.metrics[m][i], s["mean"], rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(res.metrics[m.replace("pct", "median").replace(
                "deg", "median")][i], s["median"], rtol=1e-9, atol=1e-12)
    with open(out[:-4] + ".csv") as fh:             # the count is in the table too
        assert "unstable_records" in fh.readline().split(",")


def test_the_sweep_command_says_how_many_points_left_records_out(tmp_path, capsys,
                                                                 spin_records):
    """The command says when points left records out (past the safe step), in words and
    in its JSON, instead of leaving the count to the table alone. The JSON run resumes the
    text run's sweep (nothing evaluated again): the count is the results', however they
    were obtained."""
    scene, recs = spin_records
    argv = ["sweep", str(scene), "--param", "contact.board.k", "300", "800", "--n", "2",
            "--data", *recs, "--out", str(tmp_path / "a.npz")]
    assert main(argv) == 0
    assert "2 points left out records" in capsys.readouterr().out
    assert main(argv + ["--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["evaluated"] == 0 and got["points_with_unstable_records"] == 2


def test_points_with_unstable_records_leave_out_the_points_where_all_were(tmp_path, capsys,
                                                                          monkeypatch):
    """Points where every record went past the safe step (NaN, counted as unstable points)
    were counted again as points that "left out records ... their errors are over the other
    records", though they have no errors. Only points with some but not all records left
    out are counted there, in words and in the JSON."""
    import tuning.scene_sweep as SS
    from tuning.sweep import SweepResult
    left = np.array([0, 1, 2, 2])                # of 2 records; the last two: all left out
    res = SweepResult(["contact.board.k"], np.array([[1e3], [2e3], [3e3], [4e3]]),
                      {"position_error_pct": np.array([1.0, 2.0, np.nan, np.nan]),
                       "unstable_records": left, "unstable": left == 2},
                      np.ones(4, bool), (4,), unstable=2)
    info = {"axes": {"contact.board.k": res.points[:, 0]},
            "metrics": ["position_error_pct"], "records": 2}
    monkeypatch.setattr(SS, "sweep_scene_file", lambda *a, **k: (res, info))
    argv = ["sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "s.npz")]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "2 points are past the scene's safe step" in text
    assert "1 points left out records whose rollouts went past the safe step (up to 1 of " \
           "2;" in text
    assert main(argv + ["--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["points_with_unstable_records"] == 1 and got["unstable"] == 2
