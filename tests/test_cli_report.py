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
