"""The `diffpen` command line keeps its word: flags a mode does not read are refused, a
step too coarse for the rollout is refused with a message, and a fitted scene written by
--out evaluates as the fit that wrote it."""
import pathlib
import tomllib

import pytest

from tuning.cli import main

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"
CUBE = str(EXAMPLES / "cube_toss.toml")
TOSS = EXAMPLES / "data" / "cube-toss" / "toss_003.csv"
RECORD = str(EXAMPLES / "record.csv")


@pytest.fixture(autouse=True)
def no_disk_cache(monkeypatch):
    """Keep the command's persistent compilation cache out of the test session."""
    monkeypatch.setenv("DIFFPEN_CACHE", "0")


def test_fit_out_writes_the_start_state_overrides(tmp_path, capsys):
    """Regression: --first-state / --flight-frames were not written to --out's [fit] table
    (the input's first_state = "fit", flight_frames = 20 stayed), so diffpen evaluate of
    the fitted scene measured other errors than the fit reported."""
    rec = tmp_path / "toss.csv"
    rows = TOSS.read_text(encoding="utf-8").splitlines(True)[:40]
    rec.write_text("".join(rows), encoding="utf-8")
    out = tmp_path / "fitted.toml"
    rc = main(["fit", CUBE, "--data", str(rec), "--maxiter", "1", "--horizon", "0.1",
               "--first-state", "record", "--flight-frames", "5", "--out", str(out),
               "--json"])
    assert rc in (0, 1), capsys.readouterr().err
    fit = tomllib.loads(out.read_text(encoding="utf-8"))["fit"]
    assert fit["first_state"] == "record" and fit["flight_frames"] == 5


@pytest.mark.parametrize("dt", ["10", "0.1"])
def test_fit_refuses_a_dt_too_coarse_for_the_rollout(dt, capsys):
    """Regression: `diffpen fit --dt 10` ended in JAX's 'zero-size array to reduction
    operation min' (an empty trajectory reached the metrics)."""
    assert main(["fit", "--dt", dt]) == 2
    err = capsys.readouterr().err
    assert f"dt = {dt} s leaves" in err and "Give dt <=" in err and "zero-size" not in err


@pytest.mark.parametrize("flags", [["--method", "adam"], ["--lr", "5"], ["--drop", "7"],
                                   ["--settle-tol", "0.5"]])
def test_fit_data_refuses_flags_it_does_not_read(flags, capsys, monkeypatch):
    """Regression: `diffpen fit --data REC.csv` ignored --method, --lr, --drop and
    --settle-tol (exit 0, the same LM fit)."""
    import tuning.sysid as sysid

    def boom(*a, **k):
        raise AssertionError("fitted despite flags it does not read")
    monkeypatch.setattr(sysid, "fit_trajectory", boom)
    assert main(["fit", "--data", RECORD, *flags]) == 2
    assert f"does not read {flags[0]}" in capsys.readouterr().err


@pytest.mark.parametrize("scene, flags", [("chain", ["--k", "1"]), ("cloth", ["--c", "1000"])])
def test_simulate_refuses_k_and_c_without_contact_materials(scene, flags, capsys):
    """Regression: `diffpen simulate chain|cloth --k 1 --c 1000` silently ignored --k/--c."""
    assert main(["simulate", scene, "--steps", "5", *flags]) == 2
    assert f"{flags[0]} set contact materials, but {scene} has no contact materials" in \
        capsys.readouterr().err


def test_examples_refuse_a_bad_picture_name_and_step_count_before_running(capsys):
    """An example's --out with a type matplotlib cannot write failed with a traceback only
    after the whole simulation; a --steps of 0 failed with a SceneError traceback. Both are
    argparse errors (status 2) now, before anything is computed."""
    import runpy
    import sys
    sys.path.insert(0, str(EXAMPLES))
    try:
        for name, argv in (("rope_swing", ["--out", "a.txt"]), ("paper_chain", ["--steps", "0"])):
            mod = runpy.run_path(str(EXAMPLES / f"{name}.py"), run_name="example")
            with pytest.raises(SystemExit) as exc:
                mod["main"](argv)
            assert exc.value.code == 2
        err = capsys.readouterr().err
        assert "a figure's name must end in one of" in err and "integer >= 1" in err
    finally:
        sys.path.remove(str(EXAMPLES))


def test_every_example_answers_help_without_running(capsys):
    """``python examples/fit_event_exact.py --help`` ignored the flag and ran both fits
    (15 s); every example now prints its usage and exits 0."""
    import runpy
    import sys
    sys.path.insert(0, str(EXAMPLES))
    try:
        for path in sorted(EXAMPLES.glob("*.py")):
            if path.name.startswith("_"):
                continue
            mod = runpy.run_path(str(path), run_name="example")
            with pytest.raises(SystemExit) as exc:
                mod["main"](["--help"])
            assert exc.value.code == 0, path.name
            assert capsys.readouterr().out.startswith("usage:"), path.name
    finally:
        sys.path.remove(str(EXAMPLES))


def test_help_states_what_maxiter_bounds_and_the_defaults(capsys):
    """Regression: `fit --maxiter` bounds the whole fit, each horizon stage or each stage
    depending on the fit, and --help said only "iteration limit"; report and bench stated no
    defaults for --k, --c, --mass, --radius, --height, --repeats."""
    for argv, words in ((["fit", "--help"], ["whole fit for targets", "per horizon stage",
                                             "default 15", "default 30"]),
                        (["report", "--help"], ["(default 10000;", "(default 20)",
                                                "(default 1)", "(default 0.1)",
                                                "no recommendation"]),
                        (["bench", "--help"], ["default 5"])):
        with pytest.raises(SystemExit):
            main(argv)
        text = " ".join(capsys.readouterr().out.split())
        for w in words:
            assert w in text, (argv, w)


@pytest.mark.parametrize("flags", [["--keep", "3"], ["--starts", "2", "--keep", "5"]])
def test_fit_refuses_a_keep_beyond_its_starts(flags, capsys, monkeypatch):
    """Regression: --keep without enough --starts was clamped to the starts there are (3
    without --starts ran one LM fit, 5 with --starts 2 ran three) without a word."""
    import tuning.trajfit as trajfit
    monkeypatch.setattr(trajfit, "fit_records",
                        lambda *a, **k: pytest.fail("fitted despite the --keep"))
    assert main(["fit", CUBE, "--data", str(TOSS), *flags]) == 2
    assert "--keep" in capsys.readouterr().err
    # the library refuses it too, first thing (nothing is read or compiled)
    from tuning.fit import FitError
    monkeypatch.undo()
    with pytest.raises(FitError, match=r"keep = 3: LM runs from the best `keep` .* of the 1 "):
        trajfit.fit_records(None, None, None, [], keep=3)
    with pytest.raises(FitError, match=r"of the 3 start point"):
        trajfit.fit_records(None, None, None, [], starts=2, keep=5)
    with pytest.raises(FitError, match=r"starts = -1: give a count >= 0"):
        trajfit.fit_records(None, None, None, [], starts=-1, keep=2)
    with pytest.raises(FitError, match=r"a whole number"):
        trajfit.fit_records(None, None, None, [], keep=2.0)
