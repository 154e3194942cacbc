"""Result files: keyed resume (refused with what differs), one writer per output, orphan
temporary files removed, output paths checked before computing, temporary files beside the
output, points past the safe step and unsettled points NaN in the files."""
import os
import subprocess
import sys
import tempfile

import jax
import numpy as np
import pytest

import diffpen as dp
from diffpen.state import ContactParams
from tuning import io as IO
from tuning import sweep as S

NAMES = ["contact.default.k"]
PARAMS0 = dp.Params({"default": ContactParams(np.float64(1.0), np.float64(2.0))}, {}, {})
POINTS = np.arange(1.0, 11.0)[:, None]          # (10, 1)


def metrics_fn(p):
    k = p.contact["default"].k
    return {"twice": 2.0 * k, "settled": k < 8.0, "unstable": k > 9.0}


@pytest.fixture(scope="module")
def evaluate():
    return S.make_evaluator(metrics_fn, PARAMS0, NAMES, batch_map=lambda f: jax.jit(jax.vmap(f)))


def run(evaluate, out, key, **kw):
    return S.sweep(None, PARAMS0, POINTS, NAMES, chunk=4, out=out, key=key, evaluate=evaluate,
                   progress=False, **kw)


def test_resume_only_on_an_exact_key_else_refuse_naming_the_difference(evaluate, tmp_path):
    out = str(tmp_path / "s.npz")

    def stop(i, res):
        if i == 0:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):       # killed after the first chunk
        run(evaluate, out, {"dt": 1e-3, "drop": 1.0}, on_chunk=stop)
    assert S.load_sweep(out).done.sum() == 4
    # other physics: refused, the file is untouched (no mixing of old and new rows)
    before = open(out, "rb").read()
    with pytest.raises(S.SweepError) as exc:
        run(evaluate, out, {"dt": 1e-3, "drop": 2.0})
    msg = str(exc.value)
    assert "drop: file has 1.0, this run has 2.0" in msg and "--fresh" in msg
    assert "dt: file has" not in msg                       # only what differs is named
    assert open(out, "rb").read() == before
    # the same key resumes: only the missing points are computed
    res = run(evaluate, out, {"dt": 1e-3, "drop": 1.0})
    assert res.evaluated == 6 and res.done.all()
    # another grid over the same output: refused; resume=False overwrites
    with pytest.raises(S.SweepError, match="n_points"):
        S.sweep(None, PARAMS0, POINTS[:3], NAMES, chunk=4, out=out, evaluate=evaluate,
                key={"dt": 1e-3, "drop": 1.0}, progress=False)
    res = S.sweep(None, PARAMS0, POINTS[:3], NAMES, chunk=4, out=out, evaluate=evaluate,
                  key={"dt": 1e-3, "drop": 1.0}, resume=False, progress=False)
    assert res.evaluated == 3 and S.load_sweep(out).points.shape == (3, 1)
    # the key lives in the file and names the version and the dtype
    key = S.load_sweep(out).key
    assert key["drop"] == 1.0 and "version" in key and "dtype" in key


def test_a_second_writer_is_refused_and_a_killed_writer_does_not_block(evaluate, tmp_path):
    out = str(tmp_path / "s.npz")
    with IO.OutputLock(out):
        with pytest.raises(IO.OutputError, match=r"being written by another process \(pid"):
            run(evaluate, out, {})
    assert not os.path.exists(tmp_path / ".s.npz.lock")          # released and removed
    # a writer killed with SIGKILL leaves its lock file; the kernel dropped the lock
    code = ("import os, sys; sys.path.insert(0, %r); from tuning.io import OutputLock; "
            "OutputLock(%r).acquire(); os.kill(os.getpid(), 9)" % (os.getcwd(), out))
    subprocess.run([sys.executable, "-c", code], env=dict(os.environ))
    assert os.path.exists(tmp_path / ".s.npz.lock")
    assert run(evaluate, out, {}).done.all()


def test_orphans_of_a_killed_run_are_removed_and_temp_files_sit_beside_the_output(
        evaluate, tmp_path, monkeypatch):
    out = str(tmp_path / "s.npz")
    orphans = [tmp_path / ".tmp-abcd1234s.npz", tmp_path / ".tmp-wxyz9876s.csv"]
    other = tmp_path / ".tmp-abcd1234other.npz"                  # another output's: kept
    for f in orphans + [other]:
        f.write_bytes(b"half")
    dirs = []
    real = tempfile.mkstemp

    def spy(*a, **k):
        dirs.append(k.get("dir"))
        return real(*a, **k)
    monkeypatch.setattr(tempfile, "mkstemp", spy)
    run(evaluate, out, {})
    assert not any(f.exists() for f in orphans) and other.exists()
    assert dirs and set(dirs) == {str(tmp_path)}


@pytest.mark.parametrize("bad, words", [
    ("{tmp}/missing/s.npz", "does not exist"),
    ("{tmp}", "is a directory"),
    ("/proc/nope/s.npz", "does not exist"),
])
def test_output_paths_are_checked_before_computing(tmp_path, bad, words):
    def never(batch):
        raise AssertionError("computed before checking the output")
    with pytest.raises(IO.OutputError, match=words):
        S.sweep(None, PARAMS0, POINTS, NAMES, out=bad.format(tmp=tmp_path), evaluate=never,
                key={"case": "paths"})
    assert not any(f.startswith(".tmp-") for f in os.listdir(tmp_path))


def test_a_folder_that_takes_no_files_is_refused_before_computing(monkeypatch, capsys):
    """Regression: ``diffpen simulate --out /sys/s.npz`` ran the rollout, then failed with a raw
    ``[Errno 13] Permission denied: '/sys/.tmp-...npz'``: check_output trusted os.access,
    which passes for root in read-only folders and on filesystems that ignore it (/sys,
    NFS). Now the folder is probed by creating a file there; os.access is made to pass here
    as it does for root."""
    if not os.path.isdir("/sys") or os.access("/sys", os.W_OK) and _can_create("/sys"):
        pytest.skip("needs /sys, a folder that takes no new files")
    monkeypatch.setattr(IO.os, "access", lambda *a, **k: True)
    with pytest.raises(IO.OutputError, match=r"cannot create a file in /sys \("):
        IO.check_output("/sys/s.npz", what="--out")
    from tuning.cli import main
    monkeypatch.setattr(dp, "compile", lambda *a, **k: pytest.fail("compiled before checking"))
    assert main(["simulate", "ball", "--out", "/sys/s.npz"]) == 2
    assert "cannot create a file in /sys" in capsys.readouterr().err


def _can_create(folder: str) -> bool:
    try:
        fd, p = tempfile.mkstemp(dir=folder)
    except OSError:
        return False
    os.close(fd)
    os.unlink(p)
    return True


def test_points_past_the_safe_step_are_nan_and_counted_in_memory_and_files(evaluate, tmp_path):
    out = str(tmp_path / "s.npz")
    res = run(evaluate, out, {})
    bad = POINTS[:, 0] > 9.0
    assert res.unstable == int(bad.sum()) == 1
    assert np.isnan(res.metrics["twice"][bad]).all()
    np.testing.assert_array_equal(res.metrics["twice"][~bad], 2.0 * POINTS[~bad, 0])
    back = S.load_sweep(out)
    assert back.unstable == 1 and np.isnan(back.metrics["twice"][bad]).all()
    table = np.genfromtxt(str(tmp_path / "s.csv"), delimiter=",", names=True)
    assert np.isnan(table["twice"][bad]).all()


def test_finalize_marks_points_of_an_evaluator_without_the_flag(tmp_path):
    ev = S.make_evaluator(lambda p: {"twice": 2.0 * p.contact["default"].k}, PARAMS0, NAMES,
                          batch_map=lambda f: jax.jit(jax.vmap(f)))

    def finalize(m, pts):
        m["unstable"] = pts[:, 0] > 9.0
        return m
    res = S.sweep(None, PARAMS0, POINTS, NAMES, chunk=4, evaluate=ev, finalize=finalize,
                  out=str(tmp_path / "f.npz"), progress=False)
    assert res.unstable == 1 and np.isnan(res.metrics["twice"][-1])
    assert np.isfinite(res.metrics["twice"][:-1]).all()


def test_a_fully_resumed_sweep_writes_its_table_again(evaluate, tmp_path):
    """A run killed between replacing the .npz and its .csv left the table a chunk short,
    and every rerun found all points done and never wrote it again."""
    out = str(tmp_path / "s.npz")
    table = str(tmp_path / "s.csv")
    run(evaluate, out, {"dt": 1e-3})
    full = open(table).read()
    with open(table, "w") as fh:                 # the table of a run killed one chunk early
        fh.write("\n".join(full.splitlines()[:5]) + "\n")
    res = run(evaluate, out, {"dt": 1e-3})
    assert res.evaluated == 0 and res.done.all()
    assert open(table).read() == full


@pytest.mark.filterwarnings("ignore:the sweep's metrics hold no")
def test_a_sweep_to_a_file_without_key_is_keyed_by_its_function(tmp_path):
    """With out= and no key=, a rerun of another computation (another dt, scene, metric)
    resumed into the same file and mixed its rows with the old ones."""
    out = str(tmp_path / "s.npz")

    def twice(p):
        return {"m": 2.0 * p.contact["default"].k}

    def thrice(p):
        return {"m": 3.0 * p.contact["default"].k}
    def stop_first(i, res):
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        S.sweep(twice, PARAMS0, POINTS, NAMES, chunk=4, out=out, on_chunk=stop_first,
                batch_map=lambda f: jax.jit(jax.vmap(f)))
    with pytest.raises(S.SweepError, match="metrics_fn"):
        S.sweep(thrice, PARAMS0, POINTS, NAMES, chunk=4, out=out,
                batch_map=lambda f: jax.jit(jax.vmap(f)))
    res = S.sweep(twice, PARAMS0, POINTS, NAMES, chunk=4, out=out,
                  batch_map=lambda f: jax.jit(jax.vmap(f)))
    assert res.evaluated == 6
    np.testing.assert_allclose(res.metrics["m"], 2.0 * POINTS[:, 0])
    # an evaluator made by make_evaluator carries its function; any other needs a key
    ev = S.make_evaluator(thrice, PARAMS0, NAMES, batch_map=lambda f: jax.jit(jax.vmap(f)))
    with pytest.raises(S.SweepError, match="metrics_fn"):
        S.sweep(None, PARAMS0, POINTS, NAMES, chunk=4, out=out, evaluate=ev)
    with pytest.raises(S.SweepError, match="needs key="):
        S.sweep(None, PARAMS0, POINTS, NAMES, chunk=4, out=out,
                evaluate=lambda batch: {"m": batch[:, 0]})


@pytest.mark.parametrize("resume", [True, False])
def test_a_file_that_is_not_a_sweep_is_never_overwritten(tmp_path, resume):
    """Regression: a text file at the sweep's output was called "another sweep's results"
    and the message advised --fresh (resume=False), which then overwrote it; its table
    beside it was already protected. Now it is refused either way, before computing."""
    out = tmp_path / "x.npz"
    out.write_text("precious")

    def never(batch):
        raise AssertionError("computed before checking the output")
    with pytest.raises(S.SweepError, match="exists and is not a sweep's results file .* "
                                           "Move it, or choose another output path"):
        S.sweep(None, PARAMS0, POINTS, NAMES, out=str(out), evaluate=never,
                key={"case": "foreign"}, resume=resume)
    assert out.read_text() == "precious"


def test_outputs_that_are_inputs_or_each_other_are_refused(tmp_path):
    rec = tmp_path / "rec.csv"
    rec.write_text("t,z\n0,1\n")
    with pytest.raises(IO.OutputError, match="one of the inputs"):
        IO.check_distinct({"--out's table": str(rec)}, inputs=[str(rec)])
    with pytest.raises(IO.OutputError, match="same file as --out"):
        IO.check_distinct({"--out": str(tmp_path / "a.npz"), "--plot": str(tmp_path / "a.npz")})
    IO.check_distinct({"--out": str(tmp_path / "a.npz"), "--plot": None}, inputs=[str(rec)])
    for bad in ("heat.pngg", "heat", "heat.npz"):
        with pytest.raises(IO.OutputError, match="must end in one of"):
            IO.check_plot(str(tmp_path / bad))
    assert IO.check_plot(str(tmp_path / "heat.PDF")).endswith("heat.PDF")


def test_a_sweep_through_a_symbolic_link_resumes_and_finishes_the_file_it_names(
        evaluate, tmp_path):
    """``out`` a symbolic link to an interrupted sweep: the run resumed from the link's
    target, then ``os.replace`` onto the link turned it into a plain file beside the target,
    which kept the interrupted rows. Now the target is finished and the link kept; the lock
    of the link and of the file is one lock; the table's numbers read back exactly."""
    (tmp_path / "real").mkdir()
    real, link = str(tmp_path / "real" / "s.npz"), str(tmp_path / "link.npz")

    def stop(i, res):
        if i == 0:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        run(evaluate, real, {"dt": 1e-3}, on_chunk=stop)
    os.symlink(real, link)
    with IO.OutputLock(real):
        with pytest.raises(IO.OutputError, match="being written by another process"):
            run(evaluate, link, {"dt": 1e-3})
    res = run(evaluate, link, {"dt": 1e-3})
    assert res.evaluated == 6
    assert os.path.islink(link) and os.path.realpath(link) == os.path.realpath(real)
    assert S.load_sweep(real).done.all()
    assert not [f for f in os.listdir(tmp_path) if f.startswith(IO.TMP_PREFIX)]
    # the table: 17 significant digits (10 rounded most points of a log grid: a point read
    # from the table was not the point simulated)
    grid = np.geomspace(1.0, 10.0, 10)[:, None]
    S.sweep(None, PARAMS0, grid, NAMES, chunk=4, out=link, key={"dt": 1e-3, "log": True},
            evaluate=evaluate, resume=False, progress=False)
    csv = str(tmp_path / "link.csv")
    header = open(csv).readline().strip().split(",")
    table = np.loadtxt(csv, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table[:, 0], grid[:, 0])
    np.testing.assert_array_equal(table[:, header.index("twice")],
                                  np.where(grid[:, 0] > 9.0, np.nan, 2.0 * grid[:, 0]))


def test_figures_are_written_atomically(tmp_path):
    """A run stopped while drawing left an empty or half-written figure over a good one
    (``fig.savefig`` straight onto the path). Now the old figure stays until the new one is
    whole; the file type follows the extension."""
    plt = pytest.importorskip("matplotlib.pyplot")
    out = tmp_path / "f.png"
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    IO.save_figure_file(fig, str(out), dpi=50)
    good = out.read_bytes()
    assert good[:8] == b"\x89PNG\r\n\x1a\n"

    class Stop(Exception):
        pass

    def broken(fh, **kw):
        fh.write(b"\x89PNG half")
        raise Stop
    fig.savefig = broken
    with pytest.raises(Stop):
        IO.save_figure_file(fig, str(out))
    assert out.read_bytes() == good
    assert sorted(os.listdir(tmp_path)) == ["f.png"]
    plt.close(fig)
    fig, ax = plt.subplots()
    IO.save_figure_file(fig, str(tmp_path / "f.svg"))
    assert b"<svg" in (tmp_path / "f.svg").read_bytes()[:400]
    plt.close(fig)


def test_a_resume_with_another_chunk_is_refused(evaluate, tmp_path):
    """A chunk of 1 point runs unvectorised and rounds otherwise than larger chunks (~5e-10
    on a scene-file sweep): a resume with another --chunk mixed the two into a file equal to
    neither uninterrupted run. The chunk is part of the key now."""
    out = str(tmp_path / "s.npz")

    def stop(i, res):
        if i == 0:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        run(evaluate, out, {"dt": 1e-3}, on_chunk=stop)
    with pytest.raises(S.SweepError, match="chunk: file has 4, this run has 3"):
        S.sweep(None, PARAMS0, POINTS, NAMES, chunk=3, out=out, key={"dt": 1e-3},
                evaluate=evaluate, progress=False)
    assert run(evaluate, out, {"dt": 1e-3}).evaluated == 6
