"""The fit command's probes (diffpen fit / evaluate / sweep SCENE.toml --data FILES): what it
checks before fitting, what it reports, and the values it writes against what evaluate
gives."""
import json
import math

import pytest

from tuning import trajfit as tf
from tuning.cli import main
from tuning.scenefile import load_scene_file

from record_scenes import DRAG, ROPE, record_file


@pytest.fixture(scope="module")
def drag_record(tmp_path_factory):
    """(scene, record) of a particle with air drag 0.08 (rk4, 0.3 s). Shared: the tests
    read both files and write only under their own tmp_path."""
    return record_file(tmp_path_factory.mktemp("drag"), DRAG, {"extra.drag.air": 0.08}, ["p"], "p",
                        integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.3, noise=0.0,
                        seed=1)


def test_fit_out_is_checked_before_anything_is_fitted(tmp_path, drag_record, monkeypatch):
    """``--out`` naming a record (it was overwritten with TOML after the fit), a folder (a
    traceback after the fit) or the scene file itself is refused before compiling."""
    scene, rec = drag_record
    before = open(rec).read()
    monkeypatch.setattr(tf, "levenberg_marquardt", lambda *a, **k: pytest.fail("fitted"))
    # regression: an existing TOML file that no fit wrote was replaced without a word
    mine = tmp_path / "mine.toml"
    mine.write_text('description = "mine"\n')
    for out, words in [(rec, "ending in .toml"), (str(tmp_path), "is a directory"),
                       (scene, "is one of the inputs"),
                       (str(tmp_path / "no" / "f.toml"), "does not exist"),
                       (str(mine), "exists and is not a scene diffpen fit wrote")]:
        with pytest.raises(tf.FitError, match=words):
            tf.fit_files(scene, [rec], out=out, maxiter=1)
    assert open(rec).read() == before and mine.read_text() == 'description = "mine"\n'


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
    scene, rec = record_file(tmp_path, text, {"extra.plane_offset.ground": -0.004},
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
    scene, rec = record_file(tmp_path, text, {"extra.plane_offset.ground": 0.002}, ["box"],
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
    scene, rec = record_file(tmp_path, ROLLING, {}, ["ball"], "ball",
                              integrator="semi_implicit_euler", dt=1.25e-4, every=5e-3,
                              duration=0.8, noise=0.0, seed=0)
    out = tf.fit_files(scene, [rec], horizons=(None,), maxiter=1)
    assert out["diverged"] and not out["reached"]
    assert "derivatives blew up" in out["message"]
    assert math.isnan(out["stderr"]["extra.friction.rubber"])


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


def test_a_ball_scene_file_with_records_is_one_fit_with_or_without_out(tmp_path, capsys):
    """Regression: a bouncing ball's scene file naming an x,y,z record in [fit] data went to
    the ball's trajectory fit (its own step, other JSON keys) without --out and to the record
    fit with it: adding --out moved k by 7%. Now position records always go to the record
    fit, --out only writes; a t,z height record stays the trajectory fit's, and --out with
    it says why it cannot write."""
    from tuning.sysid import synthetic_record
    from record_scenes import BALL_FIT
    t, z = synthetic_record(1e4, 20.0, duration=1.3, noise=1e-3)
    (tmp_path / "xyz.csv").write_text("t,x,y,z\n" + "".join(
        f"{float(a)!r},0,0,{float(b)!r}\n" for a, b in zip(t, z)))
    (tmp_path / "tz.csv").write_text("t,z\n" + "".join(
        f"{float(a)!r},{float(b)!r}\n" for a, b in zip(t, z)))
    for name in ("xyz", "tz"):
        (tmp_path / f"{name}.toml").write_text(BALL_FIT + f'data = ["{name}.csv"]\n')
    plain = _fit_json(capsys, ["fit", str(tmp_path / "xyz.toml")])
    written = _fit_json(capsys, ["fit", str(tmp_path / "xyz.toml"),
                                 "--out", str(tmp_path / "f.toml")])
    assert plain["fitted"] == written["fitted"] and (tmp_path / "f.toml").exists()
    assert abs(plain["fitted"]["contact.rubber.k"] / 1e4 - 1) < 0.01
    height = _fit_json(capsys, ["fit", str(tmp_path / "tz.toml")])
    assert abs(height["k"] / 1e4 - 1) < 0.01
    # regression: its text summary crashed on the record's name ("Unknown format code 'g'")
    assert main(["fit", str(tmp_path / "tz.toml")]) == 0
    assert "targets:   data = tz.csv" in capsys.readouterr().out
    # regression: a record whose header follows a comment line went to the height fit
    (tmp_path / "noted.csv").write_text("# ball, 500 Hz\n" + (tmp_path / "xyz.csv").read_text())
    (tmp_path / "noted.toml").write_text(BALL_FIT + 'data = ["noted.csv"]\n')
    noted = _fit_json(capsys, ["fit", str(tmp_path / "noted.toml")])
    assert noted["fitted"] == plain["fitted"]
    assert main(["fit", str(tmp_path / "tz.toml"), "--out", str(tmp_path / "g.toml")]) == 2
    assert "names t,z height records, which the ball's trajectory fit reads" in \
        capsys.readouterr().err and not (tmp_path / "g.toml").exists()


def _fit_json(capsys, argv):
    capsys.readouterr()
    assert main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_cold_default_fit_compiles_its_sixteen_programs_and_no_more(tmp_path):
    """Regression: printing the damping ratio through dp.physical.damping_ratio's eager jax
    operations added programs to every cold start of `diffpen fit` (25 in its persistent
    cache instead of 16; each small program costs 5-70 ms to compile). The command, whole,
    in a fresh process with an empty cache folder."""
    import os
    import subprocess
    import sys
    env = dict(os.environ, DIFFPEN_CACHE="1", DIFFPEN_CACHE_DIR=str(tmp_path / "cache"),
               JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-m", "tuning.cli", "fit", "--json"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout)["reached"] is True
    assert len(os.listdir(tmp_path / "cache")) <= 16, sorted(os.listdir(tmp_path / "cache"))


def test_a_record_too_short_to_fit_is_refused_before_it_is_run(tmp_path, monkeypatch):
    """Regression: a 2-row record of a box on springs fitted k 65% and c 17x off, reported
    determined, exit 0 (its start velocity came from the same 2 frames; audit13)."""
    from tuning import scene_fit
    scene = tmp_path / "rope.toml"
    scene.write_text(ROPE.format(k=200.0, c=0.3))
    rec = tmp_path / "short.csv"
    rec.write_text("t,rope[1].x,rope[1].y,rope[1].z\n0.0,0.1,0.0,1.0\n0.005,0.1,0.0,0.9999\n")
    monkeypatch.setattr(scene_fit, "prepare", lambda *a, **k: pytest.fail("prepared"))
    with pytest.raises(tf.FitError, match=r"too short to fit: .*short.csv \(2 rows\).* at "
                                          r"least 6 rows"):
        scene_fit.fit_files(str(scene), [str(rec)])


def test_a_leaf_the_records_barely_see_is_named(tmp_path):
    """Regression (audit13): a leaf whose standard error exceeds its value (a cloth's
    structural k fitted 2.7 +- 11.8 from 120, truth 200) went unsaid. Here a drag of 0.002
    over 0.1 s under 1 mm of noise: the fit ends at its lower bound, and says both."""
    from tuning.scene_fit import fit_files
    scene, rec = record_file(tmp_path, DRAG, {"extra.drag.air": 0.002}, ["p"], "p",
                             integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.1,
                             noise=1e-3, seed=1)
    out = fit_files(scene, [rec])
    assert out["stderr"]["extra.drag.air"] > out["fitted"]["extra.drag.air"]
    assert "barely determined by the records" in out["message"]
    assert "extra.drag.air = 5e-08 +- 0.0052" in out["message"]
