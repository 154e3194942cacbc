"""The command line refuses bad input with exit 2 and a message before computing, measures
`reached`, marks what it cannot trust, and reports progress off a terminal."""
import io
import json
import os

import numpy as np
import pytest

from tuning.cli import main


@pytest.fixture(autouse=True)
def no_disk_cache(monkeypatch):
    monkeypatch.setenv("DIFFPEN_CACHE", "0")


@pytest.fixture
def no_compile(monkeypatch):
    import diffpen as dp

    def boom(*a, **k):
        raise AssertionError("compiled before checking the input")
    monkeypatch.setattr(dp, "compile", boom)


def err_of(capsys, argv):
    try:
        rc = main(argv)
    except SystemExit as exc:          # argparse errors
        rc = exc.code
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("argv, words", [
    (["fit", "--plot", "/proc/nope/x.png"], "--plot /proc/nope/x.png: the folder /proc/nope"),
    (["sweep", "--n", "100000"], "TiB for the results alone"),
    (["sweep", "--n", "100000"], "lower --n"),
    (["sweep", "--dt", "1e-12"], "or raise --dt"),        # the cause was not among the advice
    (["sweep", "--duration", "1e-6"], "--duration 1e-06 s is only 0 step(s)"),
    (["sweep", "--target", "nan"], "--target must be a finite number"),
    (["sweep", "--n", "1.5"], "--n must be an integer, got '1.5'"),
    (["sweep", "--out", "/proc/nope/s.npz"], "does not exist"),
    (["sweep", "--out", "."], "is a directory"),
    (["sweep", "--plot", "/proc/nope/h.png"], "--plot"),
    (["simulate", "ball", "--steps", "1e9"], "--steps 1000000000 keeps 1000000000 states"),
    (["simulate", "ball", "--steps", "1000000000"], "GiB, more than half"),
    # --n 0 said ">= 1", and --n 1 was then refused for another reason
    (["sweep", "--n", "1"], "--n must be an integer >= 2, got '1'"),
    # a tiny --dt: the step count follows from it (the message blamed --steps, which was not
    # given, and printed a 300-digit count twice)
    (["simulate", "ball", "--dt", "1e-300"], "--dt 1e-300 over the scene's 3 s keeps 3e+300 "
                                             "states"),
    (["simulate", "ball", "--out", "/proc/nope/t.npz"], "does not exist"),
    (["simulate", "ball", "--c", "nan"], "--c must be a finite number"),
    (["fit", "--maxiter", "many"], "--maxiter must be an integer"),
    (["report", "accuracy", "--plot", "/proc/nope/a.png"], "does not exist"),
    (["simulate", "nope.TOML"], "cannot read nope.TOML"),      # a file, not a scene name
    # a figure type matplotlib cannot write failed after the whole sweep or report, and a
    # name without one was written with .png added, another file than the one reported
    (["sweep", "--plot", "heat.pngg"], "must end in one of .png"),
    (["sweep", "--plot", "heat"], "must end in one of .png"),
    (["fit", "--plot", "fit.npz"], "must end in one of .png"),
    (["report", "accuracy", "--plot", "acc.pngg"], "must end in one of .png"),
    # flags a report does not read were accepted and ignored
    (["report", "stability", "--plot", "s.png"], "--plot is not read by the stability"),
    (["report", "stability", "--k", "1e6", "--tol", "1e-3"], "--tol, --k are not read"),
    (["report", "accuracy", "--scenes", "ball"], "--scenes is not read by the accuracy"),
    (["report", "gradients", "--integrators", "rk4"], "--integrators is not read"),
    # c = 0 crashed with a ZeroDivisionError (its central differences step c both ways)
    (["report", "gradients", "--c", "0"], "--c must be > 0 for the gradients report"),
    # dt 1e-7 (38 million steps a rollout) ran for days; dt 1e-300 ended on an OverflowError
    # traceback; a 1e-300 kg ball on "math domain error"
    (["fit", "--dt", "1e-7"], "needs about 3.84e+07 steps for the 3.84 s rollout"),
    (["fit", "--dt", "1e-300"], "at most 1000000 steps a rollout. Give dt >= 3.84e-06 s"),
    (["fit", "--mass", "1e-300"], "the ball's mass 1e-300 kg is outside 1e-100..1e+100 kg"),
    # read by nothing, accepted without a word
    (["fit", "--lr", "0.1"], "--lr is the learning rate of the optax optimisers"),
    (["fit", "--loss", "l1"], "--loss are options of fits to position records"),
    (["fit", "--no-step-check"], "--no-step-check and --loss are options of fits to position"),
])
def test_bad_input_exits_2_before_computing(capsys, no_compile, argv, words):
    rc, err = err_of(capsys, argv)
    assert rc == 2, err
    assert words in err and "Traceback" not in err


def test_report_help_lists_gradients(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    line = [x for x in capsys.readouterr().out.splitlines() if x.strip().startswith("report")]
    assert line and "gradient" in line[0]
    with pytest.raises(SystemExit):
        main(["report", "--help"])
    assert "gradient" in capsys.readouterr().out.split("\n\n")[1]


def test_matplotlib_hint_names_an_installable_spec(monkeypatch):
    import sys

    from tuning.plots import require_matplotlib
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ImportError) as exc:
        require_matplotlib()
    assert "pip install 'matplotlib>=3.7'" in str(exc.value)
    assert "pip install -e '.[plot]'" in str(exc.value)


def test_stability_message_names_the_limit_that_applies():
    """c h / m past 1 at a tiny k: the message must not claim w h = 0.5 > 0.5."""
    import diffpen as dp
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3)
    with pytest.raises(dp.StabilityError) as exc:
        sim.rollout(sim.params(k=1.0, c=1100.0), 10)
    msg = str(exc.value)
    assert "c h / m = 1.1" in msg and "w h = 0.001" in msg
    assert "0.5 > 0.5" not in msg and "must be at most 0.00090909 s" in msg


def test_tiny_mass_gets_valid_bounds_and_a_huge_k0_consistent_notes(monkeypatch):
    """fit --mass 1e-12 (bounds lo > hi before) and fit --k0 1e9 --target-apex 0.4 (c guessed
    for k = 1e9 and pinned at its bound; notes said k held at 1e9 and lowered)."""
    import diffpen as dp
    from tuning import bounce

    seen = {}

    class Fake:
        notes = []

    def fake_fit(mfn, params0, targets, *, free, bounds, **kw):
        seen.update(params0=params0, bounds=bounds, free=free)
        out = Fake()
        out.params = params0            # the fit's step-error check reads the fitted point
        return out
    monkeypatch.setattr(bounce, "fit", fake_fit)

    def scene(m):
        s = dp.Scene()
        s.add_sphere(0.1, m, (0.0, 0.0, 1.0))
        s.add_plane()
        return s
    bounce.fit_bounce(scene(1e-12), {"apex_heights": [0.4], "settling_time": 2.6})
    for lo, hi in seen["bounds"].values():
        assert 0.0 < lo < hi
    res = bounce.fit_bounce(scene(1.0), {"apex_heights": [0.4]}, k0=1e9)
    kmax = (0.25 / 1e-3) ** 2
    k = float(seen["params0"].contact["default"].k)
    c = float(seen["params0"].contact["default"].c)
    assert k == pytest.approx(kmax)
    assert c < 0.5 * seen["bounds"]["contact.default.c"][1]     # not pinned at its bound
    assert c == pytest.approx(2 * 0.128 * np.sqrt(kmax), rel=0.05)
    text = " ".join(res.notes)
    assert "held at 6.25e+04" in text and "1e+09 N/m lowered to 6.25e+04" in text
    assert "held at 1e+09" not in text


def test_data_fit_reached_comes_from_the_residuals(capsys, monkeypatch, tmp_path):
    from tuning import sysid
    from tuning.fit import residual_reached
    assert residual_reached(1.0e-3, 1.0e-3) and not residual_reached(15.7e3, 1e-3)
    assert not residual_reached(float("nan"), 1e-3)
    t, z = sysid.load_csv(os.path.join(os.path.dirname(__file__), "..", "examples",
                                       "record.csv"))
    path = str(tmp_path / "rec_ms.csv")          # times in milliseconds
    sysid.save_csv(path, t * 1e3, z)
    rc = main(["fit", "--data", path, "--json"])
    captured = capsys.readouterr()
    if rc == 2:                                  # the record reader catches the units itself
        assert "milliseconds" in captured.err
    else:
        out = json.loads(captured.out)
        assert rc == 1 and out["reached"] is False and "units" in out["message"]
    # the fit itself refuses a record whose first flight is no fall under gravity
    with pytest.raises(sysid.FitError, match="check the units"):
        sysid.fit_trajectory(t * 1e3, z, radius=0.1, mass=1.0)

    def fake(rms):
        def fit_trajectory(t, z, **kw):
            return sysid.TrajectoryFit(
                k=1.0, c=1.0, k_stderr=0.1, c_stderr=0.1, first_guess=(1.0, 1.0), rms=rms,
                noise=1e-3, dt=1e-4, dt_error=1e-5, iterations=3, seconds=0.1, horizons=[1.0],
                history=[1.0], z_fit=z, events=None, converged=True, message="ok", notes=[])
        return fit_trajectory
    rec = os.path.join(os.path.dirname(__file__), "..", "examples", "record.csv")
    for rms, code in ((1.1e-3, 0), (9.3e-3, 1)):
        monkeypatch.setattr(sysid, "fit_trajectory", fake(rms))
        rc = main(["fit", "--data", rec, "--json"])
        out = json.loads(capsys.readouterr().out)
        assert rc == code and out["reached"] is (code == 0)
    rc = main(["fit", "--data", rec])
    assert rc == 1 and "RECORD NOT EXPLAINED" in capsys.readouterr().out


def test_progress_prints_lines_off_a_terminal():
    from tuning.progress import Progress
    buf = io.StringIO()
    bar = Progress(4, "sweep chunks", None, value="done", every=0.0, stream=buf)
    bar.update(1, 0.25)
    bar.update(2, 0.5)
    bar.close()
    lines = buf.getvalue().splitlines()
    assert lines[0].startswith("sweep chunks 1/4 25.0% done") and len(lines) == 2
    quiet = io.StringIO()
    Progress(4, "fit", None, stream=quiet).update(1, 0.5)       # within the first 5 s
    assert quiet.getvalue() == ""
    off = io.StringIO()
    Progress(4, "fit", False, every=0.0, stream=off).update(1, 0.5)
    assert off.getvalue() == ""


def test_cli_sweep_keys_nan_for_unsettled_and_locks(capsys, tmp_path):
    from tuning.io import OutputLock
    out = str(tmp_path / "sw.npz")
    argv = ["sweep", "--n", "3", "2", "--duration", "0.5", "--drop", "0.3", "--chunk", "8",
            "--k", "2e3", "2e4", "--c", "2", "40", "--out", out, "--json"]
    assert main(argv) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["evaluated"] == 6 and first["unsettled"] > 0 and first["unstable"] == 0
    with np.load(out) as f:
        settled = f["metric:settled"].astype(bool)
        ts = f["metric:settling_time"]
    assert (~settled).any() and np.isnan(ts[~settled]).all() and np.isfinite(ts[settled]).all()
    table = np.genfromtxt(str(tmp_path / "sw.csv"), delimiter=",", names=True)
    assert np.isnan(table["settling_time"][~settled]).all()
    assert main(argv) == 0                             # the same settings: resumed
    assert json.loads(capsys.readouterr().out)["evaluated"] == 0
    # other physics on the same --out: refused, naming what differs (--fresh overwrites:
    # resume=False, tested in test_safety_io)
    other = [a if a != "0.3" else "0.35" for a in argv]
    assert main(other) == 2
    err = capsys.readouterr().err
    assert "drop: file has 0.3, this run has 0.35" in err and "--fresh" in err
    with OutputLock(out):
        assert main(other) == 2
    assert "being written by another process" in capsys.readouterr().err
    # a corrupt member (its key intact): a raw BadZipFile traceback, exit 1; now exit 2
    import zipfile
    with zipfile.ZipFile(out) as z:
        info = z.getinfo("metric:apex_heights.npy")
    data = bytearray(open(out, "rb").read())
    data[info.header_offset + 30 + len(info.filename) + info.compress_size // 2] ^= 0xFF
    open(out, "wb").write(bytes(data))
    rc, err = err_of(capsys, argv)
    assert rc == 2 and "sw.npz cannot be read" in err and "--fresh" in err, err
    assert "Traceback" not in err


def test_a_table_path_that_is_a_folder_says_to_move_it_or_change_out(capsys, no_compile,
                                                                     tmp_path):
    """--out h.npz beside a folder h.csv was refused with "give a file name inside it, e.g.
    h.csv/result.npz": the table's name follows from --out and cannot be given."""
    (tmp_path / "h.csv").mkdir()
    rc, err = err_of(capsys, ["sweep", "--n", "4", "--out", str(tmp_path / "h.npz")])
    assert rc == 2, err
    assert "is a directory: its name follows from --out, so move or remove that folder, or " \
           "choose another --out" in err
    assert "file name inside it" not in err


def test_a_sweep_never_writes_over_its_inputs(capsys, no_compile, tmp_path):
    """`diffpen sweep SCENE.toml --data REC.csv --out REC.npz` wrote its table to REC.csv,
    over the measured record, with exit 0."""
    import shutil
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    scene = shutil.copy(os.path.join(here, "examples", "cube_toss.toml"), tmp_path)
    rec = shutil.copy(os.path.join(here, "examples", "data", "cube-toss", "toss_003.csv"),
                      tmp_path / "toss.csv")
    before = open(rec, "rb").read()
    rc, err = err_of(capsys, ["sweep", str(scene), "--data", str(rec), "--param",
                              "contact.board.k", "1e3", "1e4", "--n", "2", "--out",
                              str(tmp_path / "toss.npz")])
    assert rc == 2 and "is one of the inputs" in err, err
    assert open(rec, "rb").read() == before
    rc, err = err_of(capsys, ["sweep", "--out", str(tmp_path / "s.npz"), "--plot",
                              str(tmp_path / "s.csv")])
    assert rc == 2 and "must end in one of" in err, err


def test_negative_numbers_in_exponent_notation_are_values():
    """Regression: argparse read -1e-2 as an option, so `diffpen sweep SCENE --param
    extra.plane_offset.ground -1e-2 1e-2` failed with 'expected 3 arguments' while -0.01
    worked."""
    from tuning.cli import build_parser
    args = build_parser({"sweep"}).parse_args(
        ["sweep", "s.toml", "--param", "extra.plane_offset.ground", "-1e-2", "1e-2"])
    assert args.param == [["extra.plane_offset.ground", "-1e-2", "1e-2"]]


def test_a_record_starting_inside_the_ground_is_refused_naming_the_file(capsys, tmp_path):
    """Regression: a record whose first pose is 0.6 m inside the plane started the rollout
    there (diffpen evaluate exited 0 with a 10801% error); now the scene's overlap rule
    refuses it, naming the file and the body."""
    scene = tmp_path / "ball.toml"
    scene.write_text('dt = 1e-3\nduration = 0.1\n[materials.rubber]\nk = 8000.0\nc = 15.0\n'
                     '[[spheres]]\nname = "ball"\nradius = 0.1\nmass = 1.0\n'
                     'position = [0.0, 0.0, 0.6]\nmaterial = "rubber"\n'
                     '[[planes]]\nmaterial = "rubber"\n')
    rec = tmp_path / "under.csv"
    rec.write_text("t,x,y,z\n" + "".join(f"{0.005 * i},0,0,-0.5\n" for i in range(10)))
    rc, err = err_of(capsys, ["evaluate", str(scene), "--data", str(rec), "--json"])
    assert rc == 2
    assert "under.csv, body 'ball', first state" in err and "overlap by 0.6 m" in err


def test_terminal_bar_ends_on_the_last_update_and_keeps_its_label_whole():
    """Regression: on a terminal, updates within 50 ms of the last drawn one were skipped and
    close() drew nothing, so a fit's bar stayed at e.g. 222/300 after 300 iterations; and
    the label was split around the bar ("diffpen [###...] fit 222/300")."""
    from tuning.progress import Progress

    class Tty(io.StringIO):
        def isatty(self):
            return True
    out = Tty()
    bar = Progress(300, "diffpen fit", None, stream=out)
    for i in range(1, 301):
        bar.update(i, 1.0 / i)
    bar.close()
    last = out.getvalue().rstrip("\n").split("\r")[-1]
    assert last.startswith("diffpen fit [########################] 300/300")


def test_an_output_folder_that_takes_no_files_gets_a_clear_error(capsys, tmp_path):
    """Regression: `diffpen sweep --out /proc/x.npz` passed the path checks (the folder reads
    as writable) and then failed with a raw "[Errno 2] ... '/proc/.x.npz.lock'"."""
    from tuning.io import OutputError, OutputLock
    with pytest.raises(OutputError, match="cannot create a file in /proc"):
        OutputLock("/proc/x.npz", what="--out").acquire()


def test_plot_with_a_scene_file_fit_is_refused_before_fitting(capsys, tmp_path):
    """Regression: `diffpen fit SCENE.toml --plot y.png` with [fit.targets] fitted, printed a
    note and wrote no file (exit 0); now it is refused up front, pointing to evaluate."""
    scene = tmp_path / "ball.toml"
    scene.write_text("[materials.rubber]\nk = 1e4\nc = 10.0\n[[spheres]]\nradius = 0.1\n"
                     "mass = 1.0\nposition = [0.0, 0.0, 1.0]\nmaterial = \"rubber\"\n"
                     "[[planes]]\nmaterial = \"rubber\"\n[fit]\n"
                     "params = [\"contact.rubber.k\"]\n[fit.targets]\napex_heights = [0.3]\n")
    rc, err = err_of(capsys, ["fit", str(scene), "--plot", str(tmp_path / "y.png")])
    assert rc == 2 and "fit prints its fitted values" in err
    assert not (tmp_path / "y.png").exists()
    # regression: --out on this target fit said "--out ... need a scene file" (one was given)
    rc, err = err_of(capsys, ["fit", str(scene), "--out", str(tmp_path / "f.toml")])
    assert rc == 2 and "need a scene file" not in err
    assert "is fitted to its [fit] targets or a t,z record" in err
