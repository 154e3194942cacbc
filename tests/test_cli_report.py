"""diffpen report and diffpen bench (tuning.cli.report, tuning.cli.bench): bad input is refused
before anything runs."""
from tuning.cli import main


def test_cli_refuses_bad_input(capsys):
    assert main(["report", "stability", "--integrators", "euler"]) == 2
    assert "unknown integrator" in capsys.readouterr().err
    assert main(["report", "accuracy", "--height", "0.05"]) == 2


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
