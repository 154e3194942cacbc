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
