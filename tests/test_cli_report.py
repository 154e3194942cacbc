"""diffpen report and diffpen bench (tuning.cli.report, tuning.cli.bench): bad input is refused
before anything runs."""
from tuning.cli import main


def test_cli_refuses_bad_input(capsys):
    assert main(["report", "stability", "--integrators", "euler"]) == 2
    assert "unknown integrator" in capsys.readouterr().err
    assert main(["report", "accuracy", "--height", "0.05"]) == 2
    # the drop height takes fit's and sweep's name too (report had --height only)
    assert main(["report", "accuracy", "--drop", "0.05"]) == 2
    assert "--drop (--height) must be above --radius" in capsys.readouterr().err


def test_cli_bench_refuses_bad_input(capsys):
    assert main(["bench", "--repeats", "0"]) == 2
    assert "--repeats must be >= 1" in capsys.readouterr().err
    assert main(["bench", "ball_b2"]) == 2
    assert "unknown case(s) ['ball_b2']" in capsys.readouterr().err


def test_gradients_report_refuses_a_ball_that_does_not_land_twice(capsys):
    """Regression: `diffpen report gradients --height 5` (or a large c) crashed with an
    IndexError from the reference's contact list; now a clear error, exit status 2."""
    assert main(["report", "gradients", "--quick", "--height", "5"]) == 2
    assert "does not land twice within 2 s" in capsys.readouterr().err


def test_accuracy_report_records_refused_width_and_default_rows():
    """Regression: `diffpen report accuracy --k 1e6` ended in a StabilityError traceback
    from the smoothing-width and default rows (rolled out without the dt ladder's try); now
    they are refused points, as the ladder's are."""
    import math

    from tuning.reports.accuracy import BallSpec, accuracy
    res = accuracy(ball=BallSpec(k=1e6), integrators=("rk4",), dts=(2.5e-4,), widths=(0.0,),
                   width_dt=1e-3, repeats=1, problems=("ball",),
                   default_dtypes=("float64",))
    for row in (res["widths"][0], res["default"][0]):
        assert row["note"] == "StabilityError" and math.isinf(row["error"])


def test_gradients_report_refuses_a_rollout_past_the_safe_step(capsys):
    """Regression: `diffpen report gradients --k 1e7 --quick` reported jax.grad of an
    unstable rollout (relative errors ~1e6) with exit status 0."""
    assert main(["report", "gradients", "--quick", "--k", "1e7"]) == 2
    err = capsys.readouterr().err
    assert "past the safe step" in err and "lower --k or --c" in err


def test_stability_report_progress_is_lines_off_a_terminal(capsys, monkeypatch):
    """`diffpen report stability` wrote `\\r{i}/{n} cases` itself: off a terminal a log got
    one 4 kB line (audit32). It reports through tuning.progress: a line every 5 s there (a
    short run none), a bar on a terminal."""
    import tuning.progress as progress
    import tuning.reports.extreme as extreme
    cases = ["a", "b", "c"]

    def matrix(cs, progress=None):
        for i, _ in enumerate(cs):
            progress(i + 1, len(cs), {})
        return []
    monkeypatch.setattr(extreme, "extreme_cases", lambda **kw: cases)
    monkeypatch.setattr(extreme, "stability_matrix", matrix)
    monkeypatch.setattr(extreme, "summarize_matrix", lambda rows: {"ok": 3})
    assert main(["report", "stability", "--quick"]) == 0
    assert "\r" not in capsys.readouterr().err
    # each update a line when they are 5 s apart
    monkeypatch.setattr(progress.Progress, "__init__", _every(progress.Progress.__init__))
    assert main(["report", "stability", "--quick"]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert [ln.split(" (")[0] for ln in lines] == [
        f"diffpen report stability {i}/3 {100 * i / 3:.1f}% done" for i in (1, 2, 3)]


def _every(init):
    def patched(self, *a, **kw):
        init(self, *a, **{**kw, "every": 0.0})
    return patched
