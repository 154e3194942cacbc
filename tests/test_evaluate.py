"""Open-loop evaluation against records (tuning.evaluate, diffpen evaluate)."""
import json
import os
import shutil

import jax.numpy as jnp
import numpy as np
import pytest

from tuning import evaluate as ev
from tuning import pose
from tuning import trajfit as tf
from tuning.cli import main
from tuning.records import write_record
from tuning.scenefile import load_scene_file

CUBE = """
dt = 1e-3
[materials.board]
k = 3000.0
c = 30.0
friction = 0.2
[[boxes]]
name = "cube"
half_extents = [0.05, 0.05, 0.05]
mass = 0.37
inertia = [8e-4, 8e-4, 8e-4]
position = [0.0, 0.0, 0.2]
material = "board"
[[planes]]
name = "ground"
material = "board"
[fit]
params = ["contact.board.k", "contact.board.c"]
"""


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("cube")
    scene = d / "cube.toml"
    scene.write_text(CUBE)
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    params = sf.params(sim)
    paths = []
    for i, (v, w, dur) in enumerate([((0.5, 0.0, 0.0), (3.0, 1.0, 0.0), 0.4),
                                     ((0.0, -0.3, 0.5), (0.0, 2.0, 5.0), 0.24)]):
        s = sim.state_from(body=0, position=(0.0, 0.0, 0.15), velocity=v,
                           orientation=(0.9, 0.2, 0.3, 0.1), angular_velocity=w,
                           frame="body")
        rec = tf.synthetic_record(sim, params, dur, 4e-3, {"cube": 0}, state=s)
        p = d / f"toss_{i}.csv"
        write_record(str(p), rec)
        paths.append(str(p))
    return str(scene), paths, sf, sim, params


def test_errors_of_known_offsets():
    """Position error = mean |dp| / size in %, rotation error = mean angle in degrees,
    over measured samples only."""
    class B:
        size = np.array([0.1])
        pos = np.zeros((1, 3, 1, 3))
        pos_mask = np.array([[[1.0], [1.0], [0.0]]])
        quat = np.tile([1.0, 0, 0, 0], (1, 3, 1, 1))
        quat_mask = np.array([[[1.0], [1.0], [1.0]]])
        has_rotation = True
    pos = np.zeros((1, 3, 1, 3))
    pos[0, 1, 0] = [0.003, 0.004, 0.0]          # 5 mm = 5% of 0.1 m at one of two samples
    pos[0, 2, 0] = [1.0, 0.0, 0.0]              # not measured: ignored
    ang = np.radians(30.0)
    quat = np.tile([1.0, 0, 0, 0], (1, 3, 1, 1))
    quat[0, 2, 0] = [np.cos(ang / 2), 0.0, 0.0, np.sin(ang / 2)]
    pe, re = ev._errors(jnp.asarray(pos), jnp.asarray(quat), B)
    assert float(pe[0]) == pytest.approx(2.5)
    assert float(re[0]) == pytest.approx(10.0)


def test_a_batch_of_a_layout_evaluated_before_compiles_nothing(setup, caplog):
    """Regression: evaluator(sim, batch) closed over the batch's arrays, so every batch (the
    held-out split, a record alone, the evaluation after a fitted plane offset) compiled
    its program anew. The program takes the arrays as arguments now: the same two records
    in the other order (another batch of the same layout) compile nothing and give each
    record's own errors."""
    import logging

    import jax
    scene, paths, sf, sim, params = setup
    recs, bodies = tf.load_records(sf, paths)
    ab = ev.evaluate_batch(sim, params, tf.prepare(sim, recs, bodies=bodies, estimate="record"))
    ba = tf.prepare(sim, recs[::-1], bodies=bodies, estimate="record")
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        out = ev.evaluate_batch(sim, params, ba)
    compiled = [r.getMessage() for r in caplog.records if "XLA compilation" in r.getMessage()]
    assert compiled == [], compiled
    assert [r["path"] for r in out.records] == paths[::-1]
    for mine, theirs in zip(out.records, ab.records[::-1]):
        assert mine == theirs


def test_records_of_the_same_model_evaluate_to_zero(setup):
    """A record made by the same simulator and parameters, started from its row 0 with its
    velocity columns, is reproduced exactly; other parameters are not."""
    scene, paths, sf, sim, params = setup
    recs, bodies = tf.load_records(sf, paths)
    batch = tf.prepare(sim, recs, bodies=bodies, estimate="record")
    fn = ev.evaluator(sim, batch)                      # one compile for both evaluations
    e = ev.evaluate_batch(sim, params, batch, fn=fn)
    assert e.position_error_pct["mean"] < 1e-6
    assert e.rotation_error_deg["mean"] < 1e-4
    # float64 arrays like params' leaves (python floats would be new input types: a recompile)
    other = tf.with_leaves(params, {"contact.board.c": jnp.asarray(5.0, jnp.float64),
                                    "contact.board.k": jnp.asarray(1e4, jnp.float64)})
    e2 = ev.evaluate_batch(sim, other, batch, fn=fn)
    assert e2.position_error_pct["mean"] > 0.5
    # the records are simulated once per evaluation: compiled ahead (lower/compile, shared
    # with fn's cache), then run and timed once (it ran once to compile and once to time)
    calls = []

    class Spy:
        def lower(self, *a):
            calls.append("lower")
            return fn.lower(*a)

        def __call__(self, *a):
            calls.append("call")
            return fn(*a)
    again = ev.evaluate_batch(sim, other, batch, fn=Spy())
    assert calls == ["lower"]
    assert again.records == e2.records
    # the batched evaluation equals one record at a time
    for r, rec in enumerate(recs):
        one = ev.evaluate_batch(sim, other, tf.prepare(sim, [rec], bodies=bodies,
                                                       estimate="record"))
        assert one.records[0]["position_error_pct"] == pytest.approx(
            e2.records[r]["position_error_pct"], rel=1e-9)
        assert one.records[0]["rotation_error_deg"] == pytest.approx(
            e2.records[r]["rotation_error_deg"], rel=1e-9)


def test_cli_evaluate_json_and_plots(setup, tmp_path, capsys):
    """diffpen evaluate --json --plot DIR: the errors' mean and median, one entry per record,
    PNG pictures; a missing record is a clear error (status 2); records of one file name in
    different folders get a picture each, under names no other record has.

    The plot folder holds this run's plots only: a second run into a --plot folder left the
    first run's pictures of other records (or another scene) beside its own, looking
    current. Each run lists its plots with the scene in DIR/plots.json, and the next run
    removes those listed that it does not redraw (and no file the index does not list)."""
    pytest.importorskip("matplotlib")
    scene, paths, *_ = setup
    plots = tmp_path / "plots"
    capsys.readouterr()
    rc = main(["evaluate", scene, "--data", *paths, "--json", "--plot", str(plots)])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["position_error_pct"]) == {"mean", "median"}
    assert set(out["rotation_error_deg"]) == {"mean", "median"}
    assert len(out["records"]) == 2
    assert out["records"][1]["frames"] == 61
    assert out["position_error_pct"]["mean"] < 1e-6
    for p in out["plots"]:
        with open(p, "rb") as fh:
            assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
    # the folder: this run's plots and their index
    assert sorted(os.listdir(plots)) == ["plots.json", "toss_0.png", "toss_1.png"]
    index = json.loads((plots / "plots.json").read_text())
    assert index == {"scene": os.path.abspath(scene), "files": ["toss_0.png", "toss_1.png"],
                     "records": [os.path.abspath(p) for p in paths],
                     "written_by": "diffpen evaluate"}
    (plots / "mine.png").write_bytes(b"not listed")          # never touched
    outside = tmp_path / "outside.png"
    outside.write_bytes(b"not in the folder")
    index["files"].append("../outside.png")                  # only plain names are removed
    (plots / "plots.json").write_text(json.dumps(index))
    assert main(["evaluate", scene, "--data", paths[0], "--json", "--plot", str(plots)]) == 0
    assert json.loads(capsys.readouterr().out)["plots"] == [str(plots / "toss_0.png")]
    assert sorted(os.listdir(plots)) == ["mine.png", "plots.json", "toss_0.png"]
    assert outside.exists()
    assert json.loads((plots / "plots.json").read_text())["files"] == ["toss_0.png"]
    # regression: a NAME.png no run of ours listed was drawn over (a user's own figure)
    (plots / "toss_1.png").write_bytes(b"my own figure")
    assert main(["evaluate", scene, "--data", *paths, "--json", "--plot", str(plots)]) == 0
    assert json.loads(capsys.readouterr().out)["plots"] == [
        str(plots / "toss_0.png"), str(plots / "001_toss_1.png")]
    assert (plots / "toss_1.png").read_bytes() == b"my own figure"
    # regression: another program's plots.json had the figures it lists removed
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "figure1.png").write_bytes(b"precious")
    (foreign / "plots.json").write_text('{"files": ["figure1.png"]}')
    assert main(["evaluate", scene, "--data", paths[0], "--json", "--plot", str(foreign)]) == 0
    capsys.readouterr()
    assert (foreign / "figure1.png").read_bytes() == b"precious"
    assert sorted(os.listdir(foreign)) == ["figure1.png", "plots.json", "toss_0.png"]
    # bad input: a clear error, exit status 2
    assert main(["evaluate", scene, "--data", str(tmp_path / "missing.csv")]) == 2
    assert "missing.csv" in capsys.readouterr().err
    # regression: two records with the same file name in different folders wrote one plot
    # (the second over the first) while "plots" listed the same path twice
    same = []
    for i, sub in enumerate(("a", "b")):
        os.makedirs(tmp_path / sub, exist_ok=True)
        same.append(str(tmp_path / sub / "toss.csv"))
        shutil.copy(paths[i], same[-1])
    # regression: with a third record named 001_toss.csv, the second's numbered name
    # 001_toss.png was that record's own: one picture overwrote the other
    same.append(str(tmp_path / "001_toss.csv"))
    with open(paths[0]) as fh:              # the first record less its last row (not a twin,
        lines = fh.readlines()              # which evaluate refuses)
    with open(same[-1], "w") as fh:
        fh.writelines(lines[:-1])
    plots = tmp_path / "same"
    assert main(["evaluate", scene, "--data", *same, "--json", "--plot", str(plots)]) == 0
    listed = json.loads(capsys.readouterr().out)["plots"]
    assert len(set(listed)) == 3 and all(os.path.exists(p) for p in listed)
    assert sorted(os.listdir(plots)) == sorted([os.path.basename(p) for p in listed]
                                               + ["plots.json"])
    assert ev._plot_names(["a/x.csv", "b/X.csv", "001_x.csv", "001_x.csv"]) == [
        "x.png", "001_X.png", "002_001_x.png", "003_001_x.png"]      # no two alike, any case


TWO = """
dt = 1e-3
[[boxes]]
name = "a"
half_extents = [0.05, 0.05, 0.05]
mass = 0.37
position = [0.0, 0.0, 0.3]
velocity = [0.5, 0.0, 0.0]
body_angular_velocity = [1.0, 2.0, 0.0]
[[boxes]]
name = "b"
half_extents = [0.04, 0.06, 0.03]
mass = 0.5
position = [1.0, 0.0, 0.3]
[[planes]]
"""


def test_plots_show_every_observed_body(tmp_path, monkeypatch):
    """Regression: with several observed bodies the plot drew the first body only, under a
    title giving the error of all of them. Now each record gets a row per body (up to 3),
    titled with the body's name and its own errors."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt
    scene = tmp_path / "two.toml"
    scene.write_text(TWO)
    sf = load_scene_file(str(scene))
    sim = sf.compile()
    rec = tf.synthetic_record(sim, sf.params(sim), 0.3, 5e-3, {"a": 0, "b": 1})
    batch = tf.prepare(sim, [rec], bodies={"a": 0, "b": 1}, estimate="record")
    result = ev.evaluate_batch(sim, sf.params(sim), batch)
    figs, subplots = [], plt.subplots

    def spy(*a, **k):
        fig, axes = subplots(*a, **k)
        figs.append(fig)
        return fig, axes
    monkeypatch.setattr(plt, "subplots", spy)
    path = ev.plot_records(str(tmp_path / "two.png"), batch, result)
    titles = [ax.get_title() for ax in figs[0].axes]
    assert len(figs[0].axes) == 4                              # 2 bodies x (position, rotation)
    assert any(", a: position error" in s for s in titles)
    assert any(", b: position error" in s for s in titles)
    assert any("rotation error, b" in s for s in titles)
    with open(path, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"


def _no_rollout(monkeypatch, why: str) -> None:
    """Make any rollout of the evaluation fail the test: the refusal must come first."""
    def boom(*a, **k):
        raise AssertionError(why)
    monkeypatch.setattr(ev, "evaluator", boom)


def test_cli_evaluate_refuses_a_plot_folder_it_cannot_write_before_rolling_out(
        setup, tmp_path, capsys, monkeypatch):
    """--plot DIR, an existing folder that takes no files: the records were rolled out, then
    saving the first picture failed with a traceback and exit status 1 (the status of records
    past the safe step). Now refused with status 2 before anything is compiled."""
    scene, paths, *_ = setup

    _no_rollout(monkeypatch, "rolled out before checking --plot")
    folder = tmp_path / "plots"
    folder.mkdir()
    real = os.access

    def access(path, mode, *a, **k):        # a read-only folder, even for root
        if os.path.abspath(path) == str(folder) and mode & os.W_OK:
            return False
        return real(path, mode, *a, **k)
    monkeypatch.setattr(os, "access", access)
    capsys.readouterr()
    assert main(["evaluate", scene, "--data", *paths, "--plot", str(folder)]) == 2
    err = capsys.readouterr().err
    assert f"--plot {folder}: the folder {folder} is not writable" in err
    assert "Traceback" not in err


def test_cli_evaluate_refuses_a_plot_path_that_is_a_folder_before_rolling_out(
        setup, tmp_path, capsys, monkeypatch):
    """--plot DIR where DIR/NAME.png (a record's picture) is a folder: the records were
    compiled and rolled out, then saving failed ("Is a directory"), the JSON lost and the
    index listing the picture. Now refused with status 2 before anything is compiled (a
    name an earlier run listed; a folder or file no run listed is someone else's, and the
    picture takes another name)."""
    pytest.importorskip("matplotlib")
    scene, paths, *_ = setup

    _no_rollout(monkeypatch, "rolled out before checking the pictures' paths")
    (tmp_path / "plots" / "toss_1.png").mkdir(parents=True)
    (tmp_path / "plots" / "plots.json").write_text(json.dumps(
        {"files": ["toss_1.png"], "written_by": "diffpen evaluate"}))
    capsys.readouterr()
    assert main(["evaluate", scene, "--data", *paths, "--plot", str(tmp_path / "plots")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'plots' / 'toss_1.png'} is a folder" in err
    assert "move or remove it, or choose another --plot folder" in err
    assert sorted(os.listdir(tmp_path / "plots")) == ["plots.json", "toss_1.png"]


def test_cli_evaluate_refuses_a_plot_folder_another_run_is_writing(
        setup, tmp_path, capsys, monkeypatch):
    """Two runs with --plot into one folder mixed their pictures and index (the index
    naming one scene, a picture drawn by the other). A run holds a lock on DIR/plots.json;
    a second run is refused with status 2 before anything is compiled."""
    pytest.importorskip("matplotlib")
    from tuning.io import OutputLock
    scene, paths, *_ = setup

    _no_rollout(monkeypatch, "rolled out into a folder another run is writing")
    plots = tmp_path / "plots"
    plots.mkdir()
    capsys.readouterr()
    with OutputLock(str(plots / "plots.json")):              # the first run, still drawing
        assert main(["evaluate", scene, "--data", *paths, "--plot", str(plots)]) == 2
    err = capsys.readouterr().err
    assert "being written by another process" in err and "Traceback" not in err
    assert os.listdir(plots) == []


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


def test_a_scene_file_past_its_safe_step_is_named_in_the_refusal(setup, tmp_path, capsys,
                                                                 monkeypatch):
    """Regression: `diffpen evaluate` (and fit) of a scene file whose start parameters are
    past the safe step said "the scene's integrator ... is unstable" without naming the
    file, unlike every other scene-file error."""
    _, paths, *_ = setup
    stiff = tmp_path / "stiff.toml"
    stiff.write_text(CUBE.replace("k = 3000.0", "k = 3e9"), encoding="utf-8")
    _no_rollout(monkeypatch, "rolled out past the safe step")
    capsys.readouterr()
    assert main(["evaluate", str(stiff), "--data", *paths]) == 2
    err = capsys.readouterr().err
    assert f"{stiff}: the scene's integrator 'semi_implicit_euler' is unstable" in err, err
