"""The `diffpen` command line: fit (JSON keys, flags, errors before compiling), simulate,
sweep with resume, scene files, trajectory fits from CSV."""
import json
import os

import numpy as np
import pytest

from tuning.cli import main


@pytest.fixture(autouse=True)
def no_disk_cache(monkeypatch):
    """Keep the command's persistent compilation cache out of the test session."""
    monkeypatch.setenv("DIFFPEN_CACHE", "0")


def run_json(capsys, argv):
    rc = main(argv + ["--json"])
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1, out            # exactly one JSON object on stdout
    return rc, json.loads(out[0])


def test_fit_defaults_json(capsys, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    png = str(tmp_path / "fit.png")
    rc, out = run_json(capsys, ["fit", "--plot", png])
    assert rc == 0 and out["reached"]
    assert os.path.getsize(png) > 1000
    for key in ("k", "c", "targets", "achieved", "iterations", "seconds"):
        assert key in out
    t, a = out["targets"], out["achieved"]
    assert t == {"apex_heights": [0.4], "settling_time": 2.6}
    assert out["zeta"] == pytest.approx(out["c"] / (2 * (out["k"] * 1.0) ** 0.5), rel=1e-12)
    assert abs(a["apex_heights"][0] / t["apex_heights"][0] - 1) < 5e-3
    assert abs(a["settling_time"] / t["settling_time"] - 1) < 1e-2
    # regression: a figure that could not be written (a full disk) ended the command with a
    # traceback before the fitted values were printed: they come first now, exit status 2
    from tuning import plots

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(plots, "fit_figure", full_disk)
    rc = main(["fit", "--plot", png, "--json"])
    captured = capsys.readouterr()
    again = json.loads(captured.out)
    assert rc == 2 and again["k"] == out["k"] and again["c"] == out["c"]
    assert "--plot " + png + " could not be written (OSError: [Errno 28] No space left" \
        in captured.err and "Traceback" not in captured.err


@pytest.mark.parametrize("argv, words", [
    (["fit", "--target-apex", "0.95"], "not below the drop height"),
    (["fit", "--target-settle", "0.1"], "shorter than the fall"),
    (["fit", "--drop", "0.05"], "must exceed --radius"),
    (["fit", "--data", "nope.csv"], "cannot read"),
    (["fit", "--data", "x.csv", "--target-apex", "0.3"], "drop the --target-"),
    (["simulate", "marble"], "unknown scene"),
    (["simulate", "ball", "--steps", "0"], "positive integer"),
    (["sweep", "--k", "1e5", "1e3"], "MIN < MAX"),
    (["sweep", "--k", "1e3", "1e8"], "stability limit"),
])
def test_bad_input_exits_2_with_a_message(capsys, argv, words, monkeypatch):
    import diffpen as dp

    def boom(*a, **k):
        raise AssertionError("compiled before checking the input")
    monkeypatch.setattr(dp, "compile", boom)
    assert main(argv) == 2
    assert words in capsys.readouterr().err


def test_bad_flag_value_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--radius", "-1"])
    assert exc.value.code == 2
    assert "--radius must be a finite number > 0" in capsys.readouterr().err


def test_simulate_ball_json_and_out(capsys, tmp_path):
    path = str(tmp_path / "traj.npz")
    rc, out = run_json(capsys, ["simulate", "ball", "--k", "1e4", "--c", "20", "--steps",
                                "1500", "--out", path])
    assert rc == 0
    for key in ("apex_heights", "settling_time", "max_penetration"):
        assert key in out
    with np.load(path) as f:
        assert f["position"].shape == (1501, 1, 3) and f["time"].shape == (1501,)
    # continuous (event-located reference): 0.46785; the plain step average at dt 1e-3 gave
    # 0.4665 (-0.29%), the centred damping this one-contact ball compiles with 0.4680
    assert out["apex_heights"][0] == pytest.approx(0.46785, rel=1e-3)
    assert out["settling_time"] is None      # 1.5 s is too short to settle: null, not a number


def test_sweep_writes_resumes_and_plots(capsys, tmp_path):
    pytest.importorskip("matplotlib")
    out = str(tmp_path / "sw.npz")
    argv = ["sweep", "--n", "6", "5", "--duration", "0.8", "--drop", "0.5", "--chunk", "8",
            "--k", "2e3", "2e4", "--c", "2", "40", "--out", out]
    rc, first = run_json(capsys, argv + ["--plot", str(tmp_path / "h.png"), "--target", "0.1"])
    assert rc == 0 and first["evaluated"] == 30
    assert os.path.getsize(str(tmp_path / "h.png")) > 1000
    assert os.path.exists(str(tmp_path / "sw.csv"))
    rc, again = run_json(capsys, argv)
    assert again["evaluated"] == 0             # everything read back from the .npz


def test_scene_file_fit_and_errors(capsys, tmp_path):
    toml = tmp_path / "s.toml"
    toml.write_text("""
dt = 1e-3
[materials.rubber]
k = 1e4
c = 10.0
[[spheres]]
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 0.6]
material = "rubber"
[[planes]]
material = "rubber"
[fit]
params = ["contact.rubber.c"]
[fit.targets]
apex_heights = [0.2]
""")
    rc, out = run_json(capsys, ["fit", str(toml)])
    assert rc == 0 and out["reached"]
    assert out["k"] == 1e4                   # only c is fitted, as the file says
    assert out["achieved"]["apex_heights"][0] == pytest.approx(0.2, rel=1e-3)
    bad = tmp_path / "bad.toml"
    bad.write_text("[[spheres]]\nradius = 0.1\nmass = -1.0\nposition = [0, 0, 1]\n[fit]\n"
                   "[fit.targets]\napex_heights = [0.2]\n")
    assert main(["fit", str(bad)]) == 2
    assert "spheres[0].mass must be > 0 (kg), got -1.0" in capsys.readouterr().err
    bad.write_text("[[sphere]]\nradius = 0.1\n")
    assert main(["fit", str(bad)]) == 2
    assert "unknown key(s) ['sphere']" in capsys.readouterr().err


def test_fit_data_csv(capsys, tmp_path):
    from tuning.sysid import save_csv, synthetic_record
    t, z = synthetic_record(1e4, 20.0, duration=1.3, noise=1e-3, dt=2e-5, seed=5)
    path = str(tmp_path / "rec.csv")
    save_csv(path, t, z)
    rc, out = run_json(capsys, ["fit", "--data", path])
    assert rc == 0
    assert out["k"] == pytest.approx(1e4, rel=0.02) and out["c"] == pytest.approx(20, rel=0.02)
    assert out["k_stderr"] > 0 and out["c_stderr"] > 0
    # the README's JSON keys for --data include zeta = c / (2 sqrt(k m)) (m = 1 kg here)
    assert out["zeta"] == pytest.approx(out["c"] / (2 * out["k"] ** 0.5), rel=1e-12)


def _fake_record_fit(monkeypatch, k=1e4, c=20.0):
    """Replace the --data fit by a fixed result (k N/m, c N s/m) so the output is checked
    without fitting."""
    from types import SimpleNamespace

    import tuning.sysid as sysid
    res = SimpleNamespace(k=k, c=c, k_stderr=1.0, c_stderr=0.1, k_lower_bound=None,
                          first_guess=(k, c), rms=1e-3, noise=1e-3, dt=1e-4, dt_error=0.0,
                          iterations=3, seconds=0.1, message="converged", notes=[],
                          horizons=[1.0], z_fit=None, history=None)
    monkeypatch.setattr(sysid, "fit_trajectory", lambda *a, **kw: res)


def test_fit_data_gives_the_damping_ratio_in_json_and_text(capsys, monkeypatch):
    """`fit --data` had no zeta in its JSON and printed no damping ratio; the README lists
    zeta for every fit (null for hunt_crossley)."""
    _fake_record_fit(monkeypatch, k=1e4, c=20.0)
    data = os.path.join(os.path.dirname(__file__), "..", "examples", "record.csv")
    rc, out = run_json(capsys, ["fit", "--data", data, "--mass", "0.5"])
    assert out["zeta"] == pytest.approx(20.0 / (2 * (1e4 * 0.5) ** 0.5), rel=1e-12)
    main(["fit", "--data", data, "--mass", "0.5"])
    assert f"damping ratio {out['zeta']:.4g}" in capsys.readouterr().out
    rc, out = run_json(capsys, ["fit", "--data", data, "--law", "hunt_crossley"])
    assert "zeta" in out and out["zeta"] is None
    main(["fit", "--data", data, "--law", "hunt_crossley"])
    assert "damping ratio" not in capsys.readouterr().out


def test_an_interrupted_command_says_so_without_a_traceback(monkeypatch, capsys):
    """Ctrl-C on a sweep printed a KeyboardInterrupt traceback; it now says how to resume
    and exits 130 (the sweep's file is written atomically after every chunk)."""
    from tuning.cli import sweep as sweep_cli

    def interrupted(args):
        raise KeyboardInterrupt
    monkeypatch.setattr(sweep_cli, "run", interrupted)
    from tuning.cli import main as cli_main
    assert cli_main(["sweep", "--n", "2"]) == 130
    assert "interrupted; rerun the same command to resume" in capsys.readouterr().err


def test_an_interrupted_command_ends_without_tearing_its_modules_down(monkeypatch):
    """The diffpen command after an interruption: the exit handlers run (a cluster's
    process tells the others it stopped), then the process ends with status 130 without
    the interpreter's teardown, where jaxlib crashed (exit 139) in about half the fits
    interrupted on a loaded machine. Other statuses exit as usual."""
    import atexit
    import os

    import tuning.cli as cli
    seen = []
    monkeypatch.setattr(atexit, "_run_exitfuncs", lambda: seen.append("handlers"))

    def ended(status):
        seen.append(status)
        raise SystemExit(status)
    monkeypatch.setattr(os, "_exit", ended)
    monkeypatch.setattr(cli, "main", lambda: 130)
    with pytest.raises(SystemExit):
        cli.entry()
    assert seen == ["handlers", 130]
    monkeypatch.setattr(cli, "main", lambda: 2)
    with pytest.raises(SystemExit) as exc:
        cli.entry()
    assert exc.value.code == 2 and seen == ["handlers", 130]


def test_a_dropped_ctrl_c_is_not_printed_and_stays_pending(monkeypatch, capsys):
    """Regression: a Ctrl-C in a command's first second landed in JAX's garbage-collection
    callback, where Python drops it and printed a 10-line "Exception ignored in:
    <function _xla_gc_callback ...>" traceback before "interrupted". The command's
    handlers (``install_handlers``) keep it quiet and pending; other exceptions Python
    drops are still printed."""
    import gc
    import signal
    import sys

    import tuning.cli as cli
    from tuning import progress
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)    # restored after
    monkeypatch.setattr(signal, "signal", lambda *a: None)
    cli.install_handlers()

    def callback(phase, info):
        gc.callbacks.remove(callback)
        cli._on_sigint(signal.SIGINT, None)          # raised inside the callback: dropped
    gc.callbacks.append(callback)
    capsys.readouterr()
    try:
        gc.collect()
        assert "Exception ignored" not in capsys.readouterr().err
        with pytest.raises(KeyboardInterrupt):
            progress.raise_pending()
    finally:
        progress.clear_pending()

    def failing(phase, info):
        gc.callbacks.remove(failing)
        raise ValueError("a real error")
    gc.callbacks.append(failing)
    gc.collect()
    assert "ValueError: a real error" in capsys.readouterr().err


def test_sweep_target_needs_a_plot(tmp_path, capsys):
    """--target (a contour on the heatmap) without --plot was ignored silently."""
    from tuning.cli import main as cli_main
    assert cli_main(["sweep", "--n", "2", "--target", "0.3",
                     "--out", str(tmp_path / "s.npz")]) == 2
    assert "--target marks a contour on the --plot heatmap" in capsys.readouterr().err
    assert not (tmp_path / "s.npz").exists()


def test_simulate_a_scene_file_keeps_each_materials_k_and_c(capsys, tmp_path):
    """Regression: `diffpen simulate SCENE.toml` passed the first material's k and c to every
    material: a foam ball (k 300) on a foam plane, in a file declaring steel (1e5) first,
    bounced as steel (contact 0.0099 s instead of 0.22 s). Now each material keeps its own;
    --k / --c set all of them."""
    path = tmp_path / "two.toml"
    path.write_text('dt = 1e-3\nduration = 1.0\n[materials.steel]\nk = 1e5\nc = 50.0\n'
                    '[materials.foam]\nk = 300.0\nc = 2.0\n[[spheres]]\nradius = 0.1\n'
                    'mass = 1.0\nposition = [0.0, 0.0, 0.3]\nmaterial = "foam"\n'
                    '[[planes]]\nmaterial = "foam"\n')
    rc, out = run_json(capsys, ["simulate", str(path)])
    assert rc == 0 and out["k"] == 300.0 and out["c"] == 2.0
    assert out["contact_durations"][0] == pytest.approx(0.2184, rel=0.01)
    rc, out = run_json(capsys, ["simulate", str(path), "--k", "1e5", "--c", "50"])
    assert out["contact_durations"][0] < 0.011
    assert main(["simulate", str(path)]) == 0          # the text output too
    assert "k=300 N/m, c=2 N s/m" in capsys.readouterr().out


def test_simulate_out_must_be_a_new_npz_not_the_scene_file(capsys, tmp_path, monkeypatch):
    """`diffpen simulate SCENE.toml --out SCENE.toml` wrote the trajectory over the scene
    file (exit 0); --out is now refused, before anything is loaded, when it is the scene
    file or does not end in .npz."""
    import diffpen as dp

    def boom(*a, **k):
        raise AssertionError("compiled before checking --out")
    monkeypatch.setattr(dp, "compile", boom)
    scene = tmp_path / "ball.toml"
    text = ("dt = 1e-3\nduration = 0.02\n[[spheres]]\nradius = 0.1\nmass = 1.0\n"
            "position = [0.0, 0.0, 0.5]\n[[planes]]\n")
    scene.write_text(text)
    assert main(["simulate", str(scene), "--out", str(scene)]) == 2
    assert "is one of the inputs" in capsys.readouterr().err
    assert scene.read_text() == text
    assert main(["simulate", str(scene), "--out", str(tmp_path / "traj.txt")]) == 2
    assert "must end in .npz" in capsys.readouterr().err
    assert not (tmp_path / "traj.txt").exists()


def test_sweep_refuses_a_csv_beside_out_that_is_not_its_table(capsys, tmp_path):
    """`diffpen sweep --out record.npz` overwrote an unrelated record.csv (a t,z record)
    with its table, while an unrelated record.npz was refused."""
    rec = tmp_path / "record.csv"
    rec.write_text("t,z\n0.0,1.0\n0.1,0.95\n")
    for fresh in ([], ["--fresh"]):
        assert main(["sweep", "--n", "2", "--duration", "0.3", "--out",
                     str(tmp_path / "record.npz")] + fresh) == 2
        err = capsys.readouterr().err
        assert "record.csv exists and is not the table of a sweep" in err
        assert "Move it, or choose another output path" in err
        assert rec.read_text() == "t,z\n0.0,1.0\n0.1,0.95\n"
        assert not (tmp_path / "record.npz").exists()


def test_sweep_counts_unsettled_points_apart_from_unstable_ones(capsys, tmp_path):
    """Points past the safe step kept the blown-up rollout's `settled` in the .npz and .csv,
    and "N points did not settle" counted them: they are settled False now and the count is
    over the points within the safe step, the unstable ones counted apart."""
    out = str(tmp_path / "u.npz")
    argv = ["sweep", "--n", "3", "--duration", "1", "--dt", "4e-3", "--chunk", "9", "--out",
            out]
    rc, js = run_json(capsys, argv)
    assert rc == 0
    with np.load(out) as f:
        unstable = f["metric:unstable"].astype(bool)
        settled = f["metric:settled"].astype(bool)
    table = np.genfromtxt(str(tmp_path / "u.csv"), delimiter=",", names=True)
    assert 0 < unstable.sum() < 9 and js["unstable"] == unstable.sum()
    assert not (settled & unstable).any()
    np.testing.assert_array_equal(table["settled"], settled.astype(float))
    assert js["unsettled"] == int(np.sum(~settled & ~unstable)) > 0
    assert main(argv) == 0                  # resumed: the text says the same
    text = capsys.readouterr().out
    assert (f"{js['unsettled']} points did not settle within 1 s: their settling_time is NaN "
            f"(besides the {js['unstable']} past the safe step)") in text


def test_fit_gives_a_damping_ratio_only_for_laws_that_have_one(capsys):
    """A Hunt-Crossley fit printed "(damping ratio 0.4184)" and stored zeta = c / (2 sqrt(k
    m)), meaningless in its units (k N/m^n, c N s/m^(n+1)): JSON null, nothing printed."""
    import argparse

    from tuning.cli import fit as fitcli
    rc, out = run_json(capsys, ["fit", "--target-contact", "0.05", "--law", "hunt_crossley",
                                "--maxiter", "2"])
    assert "zeta" in out and out["zeta"] is None
    fitcli._print(argparse.Namespace(json=False), out)
    text = capsys.readouterr().out
    assert "fitted:" in text and "damping ratio" not in text
    # and its c in its own units (F = k d - c vn d: N s/m^2), not N s/m as before
    assert " N s/m^2" in text, text
    assert fitcli.law_units("linear") == ("N/m", "N s/m")
    assert fitcli.law_units("no_tension") == ("N/m", "N s/m")
    fitcli._print(argparse.Namespace(json=False), dict(out, zeta=0.25, law="linear"))
    assert "(damping ratio 0.25)" in capsys.readouterr().out
    # an unsettled settling time's error is no number ("3.84 s (inf% off)", audit32)
    fitcli._print(argparse.Namespace(json=False), dict(
        out, achieved={"settling_time": 3.84}, rel_error={"settling_time": float("inf")}))
    text = capsys.readouterr().out
    assert "settling_time = 3.84 s (not settled within the rollout" in text and "inf%" not in text


def test_fit_takes_hunt_crossleys_exponent(capsys):
    """`diffpen fit --law hunt_crossley` had no way to say n: Hertz balls (n 1.5) could not be
    fitted from the command line. --exponent N: the Hertz ball's continuous bounces (apexes
    1-3 and the first contact's duration of the event-located reference) at dt 5e-4 are
    reached, k and c within 1.5% of the truth (1e6 N/m^1.5, 3e4 N s/m^2.5), printed in
    their units; with another law it is refused before anything runs."""
    import argparse

    from tuning.cli import fit as fitcli
    rc, out = run_json(capsys, ["fit", "--law", "hunt_crossley", "--exponent", "1.5",
                                "--dt", "5e-4", "--target-apex", "0.76342843", "0.65556042",
                                "0.5688891", "--target-contact", "0.00972831"])
    assert rc == 0 and out["reached"] and out["exponent"] == 1.5
    assert out["k"] == pytest.approx(1e6, rel=0.015) and out["c"] == pytest.approx(
        3e4, rel=0.015)
    assert "(n = 1.5)" in out["scene"]
    fitcli._print(argparse.Namespace(json=False), out)
    assert "N/m^1.5" in capsys.readouterr().out
    assert main(["fit", "--law", "linear", "--exponent", "1.5"]) == 2
    assert "give --law hunt_crossley" in capsys.readouterr().err


def test_simulate_past_the_safe_step_gives_advice_this_command_can_follow(capsys):
    """diffpen simulate has --dt but no substeps or integrator flag: the advice names --dt
    and, for a scene file, its keys (it named compile(substeps=...) and integrator='...')."""
    assert main(["simulate", "ball", "--dt", "0.05"]) == 2
    err = capsys.readouterr().err
    assert "Use --dt 0.005 or smaller" in err and "compile with" not in err
    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "ball.toml")
    assert main(["simulate", scene, "--dt", "0.05"]) == 2
    err = capsys.readouterr().err
    assert 'set substeps = 10 (or "auto") or integrator = "implicit_euler"' in err, err


def test_simulate_without_a_practical_step_names_the_scene_files_key(capsys, tmp_path):
    """Where no substep count is practical the advice kept the library's Python
    (integrator='implicit_euler') and named no file (audit33)."""
    scene = tmp_path / "tiny.toml"
    scene.write_text("[[spheres]]\nradius = 0.1\nmass = 1e-300\nposition = [0, 0, 1]\n"
                     "[[planes]]\n")
    assert main(["simulate", str(scene)]) == 2
    err = capsys.readouterr().err
    assert "no practical step" in err and "integrator='" not in err
    assert f'set integrator = "implicit_euler" at the top of {scene} (no step limit)' in err
    # the same where the file asks for substeps = "auto" (audit35)
    scene.write_text('substeps = "auto"\n' + scene.read_text())
    assert main(["simulate", str(scene)]) == 2
    err = capsys.readouterr().err
    assert "substeps='auto' would need" in err and "integrator='" not in err, err
    assert f'set integrator = "implicit_euler" at the top of {scene}' in err


def test_fit_with_event_exact_steps(capsys, tmp_path):
    """``diffpen fit --events`` fits the built-in ball with the law's event-exact record
    (diffpen.laws.linear(events=True)): the targets are reached, the JSON says so, and
    the k it finds differs from the default record's by that record's own step error (the
    same targets, k 11414 against 11403 N/m measured). It is refused with a scene file or a
    --data record, with errors that say what to change."""
    argv = ["fit", "--target-apex", "0.5", "--target-contact", "0.03"]
    rc, ev = run_json(capsys, argv + ["--events"])
    assert rc == 0 and ev["reached"] and ev["events"] is True, ev
    assert "event-exact steps" in ev["scene"]
    rc, plain = run_json(capsys, argv)
    assert rc == 0 and plain["events"] is False
    assert 1e-5 < abs(ev["k"] / plain["k"] - 1.0) < 0.01, (ev["k"], plain["k"])
    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "ball.toml")
    assert main(["fit", scene, "--events"]) == 2
    assert "--events set the built-in ball's fit" in capsys.readouterr().err
    data = tmp_path / "rec.csv"
    data.write_text("t,z\n0,1\n0.01,0.999\n0.02,0.998\n")
    assert main(["fit", "--data", str(data), "--events"]) == 2
    assert "does not read --events" in capsys.readouterr().err


def test_a_decay_time_target_from_the_flag_and_from_a_scene_file(capsys, tmp_path):
    """Regression: the energy-decay time (the settling measure smooth in k and c) was a target
    of tuning.bounce.fit_bounce only: a scene file's [fit.targets] refused decay_time and the
    command had no flag. --target-decay and decay_time = S now fit it, to the same values."""
    rc, flag = run_json(capsys, ["fit", "--target-decay", "0.5", "--k0", "1e4"])
    assert rc == 0 and flag["reached"], flag
    assert flag["achieved"]["decay_time"] == pytest.approx(0.5, rel=2e-3)
    scene = tmp_path / "ball.toml"
    scene.write_text("dt = 1e-3\n[[spheres]]\nradius = 0.1\nmass = 1.0\n"
                     "position = [0.0, 0.0, 1.0]\n[[planes]]\n[fit.targets]\n"
                     "decay_time = 0.5\n", encoding="utf-8")
    rc, toml = run_json(capsys, ["fit", str(scene)])
    assert rc == 0 and toml["reached"], toml
    assert toml["fitted"]["contact.default.k"] == pytest.approx(flag["k"], rel=1e-6)
    assert toml["fitted"]["contact.default.c"] == pytest.approx(flag["c"], rel=1e-6)


def test_simulate_takes_a_duration_as_fit_and_sweep_do(capsys):
    """Regression: `diffpen simulate` took the rollout's length as --steps only, where fit,
    sweep and scene files take a duration in seconds; --duration S is now the same rollout
    as --steps S / dt, and giving both is refused."""
    rc, by_duration = run_json(capsys, ["simulate", "ball", "--duration", "0.25"])
    rc2, by_steps = run_json(capsys, ["simulate", "ball", "--steps", "250"])
    assert rc == rc2 == 0 and by_duration["steps"] == 250
    assert by_duration["max_penetration"] == by_steps["max_penetration"]
    assert main(["simulate", "ball", "--duration", "0.25", "--steps", "3"]) == 2
    assert "give one" in capsys.readouterr().err


def test_simulate_takes_hunt_crossleys_exponent_as_fit_does(capsys):
    """Regression: `diffpen simulate` took --law hunt_crossley but not its exponent (fit took
    --exponent), so a Hertz ball could not be simulated from the command line."""
    argv = ["simulate", "ball", "--law", "hunt_crossley", "--duration", "0.6"]
    rc, hertz = run_json(capsys, argv + ["--exponent", "1.5", "--k", "1e6", "--c", "3e4"])
    rc1, n_one = run_json(capsys, argv + ["--k", "3e4", "--c", "3e3"])
    assert rc == rc1 == 0 and hertz["exponent"] == 1.5 and n_one["exponent"] == 1.0
    # Hertz at k 1e6 N/m^1.5 stores the 0.9 m fall's energy undamped at (5/2 m g h / k)^(2/5)
    # = 13.7 mm (the linear law at 1e6 N/m: 4.2 mm); its damping takes a little of it
    assert 0.010 < hertz["max_penetration"] < 0.0137, hertz["max_penetration"]
    assert main(["simulate", "ball", "--exponent", "1.5"]) == 2
    assert "is read by law='hunt_crossley' only" in capsys.readouterr().err
    # the text says the law's exponent and its units (k was printed in N/m for any law)
    assert main(argv + ["--exponent", "1.5", "--k", "1e6", "--c", "3e4"]) == 0
    text = capsys.readouterr().out
    assert "hunt_crossley (n 1.5) law" in text and "k=1e+06 N/m^1.5, c=30000 N s/m^2.5" in text


def test_simulate_takes_an_integrator(capsys):
    """Regression: no command chose the integrator (scene files and dp.compile did); `diffpen
    simulate --integrator NAME` now does and reports it, and an unknown name is refused with
    the list."""
    rc, out = run_json(capsys, ["simulate", "ball", "--integrator", "rk4", "--duration", "0.1"])
    assert rc == 0 and out["integrator"] == "rk4"
    assert main(["simulate", "ball", "--integrator", "euler"]) == 2
    assert "unknown integrator 'euler'; choose one of" in capsys.readouterr().err


@pytest.mark.parametrize("line, says", [
    ("velocity = [0, 0, -1e300]", "spheres[0].velocity = [0, 0, -1e+300] has a component beyond"
     " 1e+06 m/s"),
    ("mass = 1e300", "spheres[0].mass must be <= 1e+12 (kg), got 1e+300"),
])
def test_scene_files_refuse_speeds_and_masses_no_simulation_reports(tmp_path, capsys, line,
                                                                    says):
    """A scene file's velocity of 1e300 m/s or mass of 1e300 kg passed (positions beyond 1e6
    m were refused): `diffpen simulate` exited 0 reporting max_penetration null, or a decay
    time of 0 s marked valid (audit33). Refused naming the field; nothing is written."""
    scene = tmp_path / "big.toml"
    body = {"velocity": "mass = 1.0", "mass": "velocity = [0, 0, 0]"}[line.split(" ")[0]]
    scene.write_text(f"[[spheres]]\nradius = 0.1\n{body}\nposition = [0, 0, 1]\n{line}\n"
                     "[[planes]]\n")
    out = tmp_path / "t.npz"
    assert main(["simulate", str(scene), "--json", "--out", str(out)]) == 2
    assert says in capsys.readouterr().err
    assert not out.exists()


def test_fit_takes_the_built_in_balls_rollout_length(capsys, monkeypatch, tmp_path):
    """An unsettled fit advised "a longer rollout", which `diffpen fit` on the built-in ball
    could not give (audit32): --duration sets it; a record or scene file refuses it."""
    import tuning.bounce as bounce
    seen = {}

    def spy(scene, targets, **kw):
        seen.update(kw)
        raise SystemExit(0)
    monkeypatch.setattr(bounce, "fit_bounce", spy)
    with pytest.raises(SystemExit):
        main(["fit", "--duration", "8"])
    assert seen["duration"] == 8.0
    monkeypatch.undo()
    # one that ends before the ball lands is refused, naming the flag (it fitted nothing)
    assert main(["fit", "--target-apex", "0.4", "--duration", "0.2"]) == 2
    assert "ends before the ball first lands" in capsys.readouterr().err
    rec = tmp_path / "rec.csv"
    rec.write_text("t,z\n0,1\n0.01,0.9995\n")
    assert main(["fit", "--data", str(rec), "--duration", "8"]) == 2
    assert "does not read --duration" in capsys.readouterr().err
    scene = os.path.join(os.path.dirname(__file__), "..", "examples", "ball.toml")
    assert main(["fit", scene, "--duration", "8"]) == 2
    assert "--duration set the built-in ball's fit" in capsys.readouterr().err
