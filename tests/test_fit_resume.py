"""Record fits resume after an interruption (tuning.fit_checkpoint): fit_records(checkpoint=)
and diffpen fit SCENE.toml --data ... --out F.toml keep their progress after every LM
iteration and a rerun ends with the result of a fit never interrupted, bit for bit."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tuning import fit_checkpoint
from tuning import trajfit as tf
from tuning.fitted_scene import FITTED_MARK
from tuning.cli import main
from tuning.io import OutputLock
from tuning.records import write_record
from tuning.scenefile import load_scene_file

from record_scenes import DRAG


@pytest.fixture(scope="module")
def drag(tmp_path_factory):
    """(scene path, record path, simulator, start params, batch, free leaves): a thrown
    particle with air drag, its record made with drag 0.08 by rk4 at a finer step."""
    folder = tmp_path_factory.mktemp("resume")
    scene = folder / "p.toml"
    scene.write_text(DRAG)
    sf = load_scene_file(str(scene))
    truth = sf.compile(integrator="rk4", dt=2.5e-4)
    rec = tf.synthetic_record(truth, tf.with_leaves(sf.params(truth), {"extra.drag.air": 0.08}),
                              0.3, 5e-3, {"p": 0}, noise=1e-4, seed=3)
    path = folder / "p.csv"
    write_record(str(path), rec)
    sim = sf.compile()
    batch = tf.prepare(sim, [rec], estimate="record")
    return str(scene), str(path), sim, sf.params(sim), batch, tf.free_from_spec(sf.spec)


#: a fit with every part a checkpoint holds: a multi-start screen, two LM runs (one ended
#: before the other starts) and two horizon stages each
OPTIONS = dict(horizons=(0.1, None), maxiter=3, starts=[{"extra.drag.air": 0.03}], keep=2,
               progress=False)


def _same(a, b):
    assert a.values == b.values and a.history == b.history
    assert a.iterations == b.iterations and a.cost == b.cost and a.message == b.message
    assert a.starts == b.starts and a.cost_start == b.cost_start
    np.testing.assert_array_equal(a.correlation, b.correlation)


class Interrupt(BaseException):
    pass


def _interrupt_after(monkeypatch, n):
    """Make the n-th checkpoint save (and no other) end the fit right after writing."""
    saves = {"n": 0}
    real = fit_checkpoint.FitCheckpoint.save

    def save(self):
        real(self)
        saves["n"] += 1
        if saves["n"] == n:
            raise Interrupt
    monkeypatch.setattr(fit_checkpoint.FitCheckpoint, "save", save)
    return saves


def test_an_interrupted_record_fit_resumes_to_the_same_result(drag, tmp_path, monkeypatch):
    """Interrupted after each save in turn (the screen, every LM iteration of both runs and
    stages, each run's end), the rerun returns the uninterrupted fit's values, cost history,
    iterations, starts and correlations exactly, and counts the iterations it took over."""
    _, _, sim, params, batch, free = drag
    whole = tf.fit_records(sim, params, batch, free, **OPTIONS)
    counted = _interrupt_after(monkeypatch, 0)
    path = str(tmp_path / "progress.json")
    tf.fit_records(sim, params, batch, free, checkpoint=path, **OPTIONS)
    total = counted["n"]
    assert total == 1 + whole.iterations + 2          # the screen, every iteration, 2 runs
    os.unlink(path)
    taken = []
    for n in range(1, total + 1):
        _interrupt_after(monkeypatch, n)
        with pytest.raises(Interrupt):
            tf.fit_records(sim, params, batch, free, checkpoint=path, **OPTIONS)
        monkeypatch.undo()
        again = tf.fit_records(sim, params, batch, free, checkpoint=path, **OPTIONS)
        _same(again, whole)
        taken.append(again.resumed)
        os.unlink(path)
    assert taken[0] == 0 and taken[-1] == whole.iterations
    assert taken == sorted(taken)                      # each later save holds more


def test_a_checkpoint_of_another_fit_is_refused(drag, tmp_path, monkeypatch):
    """Other settings (here the iteration limit) never resume from a fit's progress: refused,
    naming what differs; ``fresh`` starts over. A file that is not a checkpoint is refused."""
    _, _, sim, params, batch, free = drag
    path = str(tmp_path / "progress.json")
    _interrupt_after(monkeypatch, 3)
    with pytest.raises(Interrupt):
        tf.fit_records(sim, params, batch, free, checkpoint=path, **OPTIONS)
    monkeypatch.undo()
    other = {**OPTIONS, "maxiter": 4}
    with pytest.raises(tf.FitError, match=r"another fit.*maxiter: file has 3, this run has 4"):
        tf.fit_records(sim, params, batch, free, checkpoint=path, **other)
    res = tf.fit_records(sim, params, batch, free, checkpoint=path, fresh=True, **other)
    assert res.resumed == 0
    _same(res, tf.fit_records(sim, params, batch, free, **other))
    with open(path, "w") as fh:
        fh.write("{not json")
    with pytest.raises(tf.FitError, match="not a readable fit checkpoint"):
        tf.fit_records(sim, params, batch, free, checkpoint=path, **OPTIONS)
    # a path that cannot be written is refused before anything is fitted
    for where, words in ((tmp_path, "is a directory"),
                         (tmp_path / "no" / "p.json", "does not exist")):
        with pytest.raises(tf.FitError, match=words):
            tf.fit_records(sim, params, batch, free, checkpoint=str(where), **OPTIONS)


def test_diffpen_fit_out_resumes_an_interrupted_fit(drag, tmp_path, capsys, monkeypatch):
    """diffpen fit SCENE --data REC --out F.toml interrupted (exit 130) says to rerun the same
    command and keeps F.toml.fit-progress.json (F.toml not written); a rerun with another
    --first-state is refused, naming it; the same command resumes, writes the values of a
    run never interrupted and removes the progress file."""
    scene, rec, *_ = drag
    argv = ["fit", scene, "--data", rec, "--horizon", "0.1", "--maxiter", "3", "--json"]
    capsys.readouterr()
    assert main(argv + ["--out", str(tmp_path / "whole.toml")]) == 0
    whole = json.loads(capsys.readouterr().out)
    out = tmp_path / "f.toml"
    progress = tmp_path / ("f.toml" + fit_checkpoint.SUFFIX)
    _interrupt_after(monkeypatch, 3)
    monkeypatch.setattr(tf, "_run_stages", _raising_keyboard(tf._run_stages))
    assert main(argv + ["--out", str(out)]) == 130
    io = capsys.readouterr()
    assert "rerun the same command to resume the fit" in io.err
    assert progress.exists() and not out.exists()
    monkeypatch.undo()
    # the same fit with another start-state estimate is refused, naming the option
    assert main(argv + ["--out", str(out), "--first-state", "fit"]) == 2
    assert 'first_state: file has "record", this run has "fit"' in capsys.readouterr().err
    assert main(argv + ["--out", str(out)]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["resumed"] > 0 and whole["resumed"] == 0
    assert again["fitted"] == whole["fitted"] and again["cost"] == whole["cost"]
    assert out.exists() and not progress.exists()
    assert main(argv + ["--fresh"]) == 2                   # --fresh needs --out
    assert "--fresh restarts a fit that --out keeps" in capsys.readouterr().err


def _raising_keyboard(run_stages):
    """``_run_stages`` with the tests' interruption turned into the KeyboardInterrupt of a
    Ctrl-C (what the command catches)."""
    def wrapped(*a, **k):
        try:
            return run_stages(*a, **k)
        except Interrupt:
            raise KeyboardInterrupt from None
    return wrapped


def test_a_second_fit_into_the_same_out_is_refused(drag, tmp_path):
    """Two fits into one --out would write one progress file: the second is refused at
    once, naming the first one's lock."""
    scene, rec, *_ = drag
    out = tmp_path / "f.toml"
    with OutputLock(str(out)):
        with pytest.raises(tf.FitError, match="being written by another process"):
            tf.fit_files(scene, [rec], out=str(out), maxiter=1)


def test_diffpen_fit_out_audit_cases(drag, tmp_path, capsys, monkeypatch):
    """What an audit of the command met, each fixed:
    - a symbolic link as --out was replaced by a plain file, its target left as it was: the
      target is written, the link kept, the progress kept beside the target;
    - a Ctrl-C after FITTED.toml was written but before the summary was printed said to
      rerun, yet the progress was gone and the rerun fitted again: the progress now goes only
      after the summary, and that rerun takes every iteration over;
    - interrupted with --fresh, the advice to rerun the same command started over: it says
      to rerun without --fresh;
    - a progress file that cannot be saved (a full disk) ended in a traceback: a one-line
      error, exit status 2, saying the saved progress resumes;
    - a folder where the progress file goes is named as following from --out."""
    scene, rec, *_ = drag
    argv = ["fit", scene, "--data", rec, "--horizon", "0.1", "--maxiter", "3", "--json"]
    capsys.readouterr()
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "fitted.toml"
    target.write_text(FITTED_MARK + " p.toml\n")       # an earlier fit's output
    link = tmp_path / "link.toml"
    link.symlink_to(target)
    assert main(argv + ["--out", str(link)]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert link.is_symlink() and "extra" in target.read_text()
    assert not (tmp_path / "real" / ("fitted.toml" + fit_checkpoint.SUFFIX)).exists()

    out = tmp_path / "f.toml"
    progress = tmp_path / ("f.toml" + fit_checkpoint.SUFFIX)
    from tuning.cli import record_fit_report

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(record_fit_report, "dump_json", interrupted)  # after f.toml is written
    assert main(argv + ["--out", str(out)]) == 130
    assert "rerun the same command to resume the fit" in capsys.readouterr().err
    assert out.exists() and progress.exists()
    monkeypatch.undo()
    assert main(argv + ["--out", str(out)]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["resumed"] == again["iterations"] == whole["iterations"]
    assert again["fitted"] == whole["fitted"] and not progress.exists()

    _interrupt_after(monkeypatch, 3)
    monkeypatch.setattr(tf, "_run_stages", _raising_keyboard(tf._run_stages))
    assert main(argv + ["--out", str(out), "--fresh"]) == 130
    assert "rerun the same command without --fresh to resume" in capsys.readouterr().err
    monkeypatch.undo()

    real = fit_checkpoint.FitCheckpoint.save
    calls = {"n": 0}

    def full_disk(self):
        calls["n"] += 1
        if calls["n"] > 2:
            raise OSError(28, "No space left on device", self.path)
        real(self)
    monkeypatch.setattr(fit_checkpoint.FitCheckpoint, "save", full_disk)
    assert main(argv + ["--out", str(out), "--fresh"]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "rerun the same command" in err
    assert "Traceback" not in err
    monkeypatch.undo()
    assert main(argv + ["--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["resumed"] == 1

    (tmp_path / ("g.toml" + fit_checkpoint.SUFFIX)).mkdir()
    assert main(argv + ["--out", str(tmp_path / "g.toml")]) == 2
    assert "its name follows from --out" in capsys.readouterr().err


def test_a_refusal_names_what_changed(drag, tmp_path, capsys, monkeypatch):
    """A rerun against another fit's progress names the changed entry itself: the record file
    whose contents changed, a start value, the bounds as the scene file gives them (their
    values were cut to 120 characters, the same on both sides); the same records and scene
    copied to another folder resume (they were refused by their paths); and a fit whose
    records the scene file names ([fit] data) is told how to resume too."""
    scene, rec, *_ = drag
    copy = tmp_path / "p.csv"
    copy.write_text(open(rec).read())
    text = open(scene).read()
    sfile = tmp_path / "p.toml"
    sfile.write_text(text + 'data = ["p.csv"]\nmaxiter = 3\n')
    out = tmp_path / "f.toml"
    argv = ["fit", str(sfile), "--out", str(out), "--json"]
    _interrupt_after(monkeypatch, 3)
    monkeypatch.setattr(tf, "_run_stages", _raising_keyboard(tf._run_stages))
    capsys.readouterr()
    assert main(argv) == 130
    assert "rerun the same command to resume the fit" in capsys.readouterr().err
    monkeypatch.undo()
    lines = copy.read_text().splitlines()
    cells = lines[5].split(",")
    cells[-1] = repr(float(cells[-1]) + 1e-4)         # one sample 0.1 mm higher
    lines[5] = ",".join(cells)
    copy.write_text("\n".join(lines) + "\n")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "data.1:p.csv: file has" in err
    # the same records from another folder resume (the key holds names and contents)
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "p.csv").write_text(open(rec).read())
    (moved / "p.toml").write_text(sfile.read_text())
    copy.write_text(open(rec).read())
    assert main(["fit", str(moved / "p.toml"), "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["resumed"] > 0
    _interrupt_after(monkeypatch, 3)
    monkeypatch.setattr(tf, "_run_stages", _raising_keyboard(tf._run_stages))
    assert main(argv) == 130
    monkeypatch.undo()
    capsys.readouterr()
    copy.write_text(open(rec).read())
    sfile.write_text(text.replace("c = 0.05", "c = 0.06") + 'data = ["p.csv"]\nmaxiter = 3\n'
                     + "[fit.bounds]\n\"extra.drag.air\" = [0.001, 1.0]\n")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "params.extra.drag.air: file has 0.05, this run has 0.06" in err
    assert "fitted.extra.drag.air.bounds: file has" in err and "[0.001, 1.0]" in err


def test_sigterm_ends_a_fit_as_ctrl_c_does(drag, tmp_path):
    """A batch scheduler's time limit sends SIGTERM: the command killed silently (the progress
    was kept, but nothing said so). Now it ends as a Ctrl-C does, with exit status 143 and
    the hint to resume, the progress file in place."""
    scene, rec, *_ = drag
    out = tmp_path / "f.toml"
    progress = tmp_path / ("f.toml" + fit_checkpoint.SUFFIX)
    env = {**os.environ, "JAX_ENABLE_X64": "1"}
    p = subprocess.Popen([sys.executable, "-m", "tuning.cli", "fit", scene, "--data", rec,
                          "--out", str(out), "--json"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.time() + 120
        while not progress.exists() and p.poll() is None and time.time() < deadline:
            time.sleep(0.01)          # the screen's save: the LM program compiles next
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 143, err[-2000:]
    assert "diffpen fit: terminated; rerun the same command to resume the fit" in err
    assert progress.exists() and not out.exists()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_ctrl_c_python_dropped_still_interrupts(drag, tmp_path, capsys):
    """A Ctrl-C in the command's first second was lost: it landed in JAX's
    garbage-collection callback, where Python prints an exception and drops it ("Exception
    ignored in: <function _xla_gc_callback ...>"), and the fit ran to its end. The handler
    remembers the interrupt (tuning.progress.interrupt) and the next progress report raises
    it again: here the fit stops at its first LM iteration with exit status 130."""
    import gc
    from tuning import cli, progress

    def callback(phase, info):
        gc.callbacks.remove(callback)
        cli._on_sigint(signal.SIGINT, None)          # raised inside the callback: dropped
    gc.callbacks.append(callback)
    gc.collect()
    assert callback not in gc.callbacks
    scene, rec, *_ = drag
    out = tmp_path / "f.toml"
    capsys.readouterr()
    assert main(["fit", scene, "--data", rec, "--out", str(out), "--json"]) == 130
    assert "diffpen fit: interrupted" in capsys.readouterr().err and not out.exists()
    progress.Progress(3, enabled=False).update(1)    # nothing pending after the command


def test_a_ctrl_c_while_the_command_starts_ends_it_cleanly(capsys, monkeypatch):
    """A Ctrl-C while the command imported its subcommand or read its arguments escaped as a
    KeyboardInterrupt traceback: it ends with "interrupted" and exit status 130 too."""
    import tuning.cli as cli

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli, "build_parser", interrupted)
    capsys.readouterr()
    assert main(["fit", "scene.toml"]) == 130
    assert capsys.readouterr().err.strip() == "diffpen fit: interrupted"
