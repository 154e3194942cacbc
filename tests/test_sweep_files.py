"""A sweep's files (audit16): what the key holds (the code and the runtime that computed
the rows, the values a finalize= reads), when the .npz is written, what a stopped or failing
write leaves, and sizes refused before anything runs."""
import errno
import functools
import os
import shutil
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp  # noqa: F401 - before any JAX computation
from tuning import io as tio
from tuning import sweep as S
from tuning.code_key import code_key

sys.path.insert(0, os.path.dirname(__file__))
from test_tuning_sweep import TOY_NAMES, TOY_POINTS, stop_first, toy_sweep  # noqa: E402


def test_a_sweep_written_by_other_code_or_another_jax_is_not_resumed(tmp_path, monkeypatch):
    """Regression: the key's "version" was the package's 0.1.0 through every change of the
    code, and a command's own key= held no digest of what computes the rows: a sweep
    interrupted under one version of the code resumed under another without a word, its
    rows mixing two physics (9464 of 16384 apexes 1% apart in the audit). The key now holds
    the source digest of diffpen and tuning, and jax, jaxlib and the backend."""
    out = str(tmp_path / "s.npz")
    with pytest.raises(KeyboardInterrupt):
        toy_sweep(out, on_chunk=stop_first, key={"metric": "twice"})
    monkeypatch.setattr(tio, "source_digest", lambda: "0123456789abcdef", raising=False)
    with pytest.raises(S.SweepError, match="source: file has .*the diffpen or tuning source "
                                           "changed since the file was written"):
        toy_sweep(out, key={"metric": "twice"})
    monkeypatch.undo()
    monkeypatch.setattr(tio, "runtime", lambda: {"jax": "0.0", "jaxlib": "0.0",
                                                 "backend": "gpu"}, raising=False)
    with pytest.raises(S.SweepError, match="runtime.backend: file has \"cpu\", this run has "
                                           "\"gpu\".*rounding differently"):
        toy_sweep(out, key={"metric": "twice"})
    monkeypatch.undo()
    import json                                        # a file from before keys held them
    key = dict(S.load_sweep(out).key)
    del key["source"], key["runtime"]
    data = dict(np.load(out))
    data["key"] = np.array(json.dumps(key))
    np.savez(out, **data)
    with pytest.raises(S.SweepError, match=r'runtime: file has "<absent>".*\(the file was '
                                           r'written before keys held it\)'):
        toy_sweep(out, key={"metric": "twice"})
    monkeypatch.undo()
    with pytest.raises(KeyboardInterrupt):
        toy_sweep(out, on_chunk=stop_first, key={"metric": "twice"}, resume=False)
    res = toy_sweep(out, key={"metric": "twice"})      # the same code and runtime resume
    assert res.evaluated == 4 and res.done.all()


def test_the_source_digest_follows_every_python_file_of_both_packages(tmp_path, monkeypatch):
    """A copy of both packages digests the same; an edit to any of their .py files changes
    the digest, a compiled cache file or another file type does not."""
    import diffpen
    import tuning
    for pkg in (diffpen, tuning):
        src = os.path.dirname(pkg.__file__)
        shutil.copytree(src, tmp_path / pkg.__name__,
                        ignore=shutil.ignore_patterns("__pycache__"))

    def digest():
        monkeypatch.setattr(diffpen, "__file__", str(tmp_path / "diffpen" / "__init__.py"))
        monkeypatch.setitem(sys.modules, "tuning", type(sys)("tuning"))
        sys.modules["tuning"].__file__ = str(tmp_path / "tuning" / "__init__.py")
        try:
            return tio.source_digest()
        finally:
            monkeypatch.undo()
    here = tio.source_digest()
    assert digest() == here
    (tmp_path / "tuning" / "__pycache__").mkdir()
    (tmp_path / "tuning" / "__pycache__" / "x.pyc").write_bytes(b"\0")
    (tmp_path / "diffpen" / "notes.txt").write_text("x")
    # audit18: an editor's lock file (a dangling link) made every sweep fail to open it
    os.symlink("user@host.1234:1700000000", tmp_path / "tuning" / ".#sweep.py")
    (tmp_path / "tuning" / ".ipynb_checkpoints").mkdir()
    (tmp_path / "tuning" / ".ipynb_checkpoints" / "sweep-checkpoint.py").write_text("x")
    assert digest() == here
    with open(tmp_path / "diffpen" / "window.py", "a") as fh:
        fh.write("\n# an edit\n")
    assert digest() != here
    assert tio.source_digest() == here


THRESHOLD = 0.5


def _helper(v):
    return v > THRESHOLD


def finalize_by_global(m, pts):
    m["high"] = _helper(m["twice"] / 10.0)
    return m


def test_a_finalize_is_keyed_by_the_globals_it_reads_and_the_helpers_it_calls(tmp_path,
                                                                             monkeypatch):
    """Regression: finalize='s key hashed its code, closure and defaults but not the values
    of the globals it reads nor the helpers it calls: a rerun with THRESHOLD changed from
    0.5 to 0.05 resumed into the same file, rows flagged both ways."""
    this = sys.modules[__name__]
    k0 = code_key(finalize_by_global)
    monkeypatch.setattr(this, "THRESHOLD", 0.05)
    k1 = code_key(finalize_by_global)
    monkeypatch.setattr(this, "_helper", lambda v: v >= THRESHOLD)
    k2 = code_key(finalize_by_global)
    assert len({k0, k1, k2}) == 3
    monkeypatch.undo()
    assert code_key(finalize_by_global) == k0
    out = str(tmp_path / "g.npz")
    with pytest.raises(KeyboardInterrupt):
        toy_sweep(out, finalize=finalize_by_global, on_chunk=stop_first)
    monkeypatch.setattr(this, "THRESHOLD", 0.05)
    with pytest.raises(S.SweepError, match="finalize: file has"):
        toy_sweep(out, finalize=finalize_by_global)
    monkeypatch.undo()
    res = toy_sweep(out, finalize=finalize_by_global)
    assert res.evaluated == 4
    k = TOY_POINTS[:, 0]                   # the toy's points above 6 are "unstable": False
    np.testing.assert_array_equal(res.metrics["high"], (0.2 * k > 0.5) & (k <= 6.0))


LIMIT = jnp.asarray(0.5)


@jax.jit
def _jitted(v):
    return v > LIMIT


_partial = functools.partial(np.greater, 0.5)


def finalize_by_arrays(m, pts):
    m["high"] = np.asarray(_jitted(m["twice"])) & _partial(m["twice"])
    return m


def test_a_finalize_is_keyed_by_jax_arrays_jitted_helpers_and_partials(monkeypatch):
    """Regression (audit18): a JAX array global, a helper under jax.jit and a
    functools.partial's arguments were keyed by their type only: changed, the digest stayed
    the same and a rerun resumed into the same file."""
    this = sys.modules[__name__]
    k0 = code_key(finalize_by_arrays)
    keys = []
    for name, value in (("LIMIT", jnp.asarray(0.05)),
                        ("_partial", functools.partial(np.greater, 0.05)),
                        ("_jitted", jax.jit(lambda v: v >= LIMIT))):
        monkeypatch.setattr(this, name, value)
        keys.append(code_key(finalize_by_arrays))
        monkeypatch.undo()
    assert len({k0, *keys}) == 4 and code_key(finalize_by_arrays) == k0

    def make(limits, table):           # audit19: a list of JAX arrays, a closed-over helper,
        def helper(v):                 # a dict's int key against its text
            return v > limits[0]

        def finalize(m, pts):
            return {"high": helper(m["twice"]) & (table.get(1, 0.0) > 0.0)}
        return finalize
    made = [code_key(make(*a)) for a in (([jnp.asarray(0.5)], {1: 0.5}),
                                         ([jnp.asarray(0.05)], {1: 0.5}),
                                         ([jnp.asarray(0.5)], {"1": 0.5}))]
    assert len(set(made)) == 3


def test_a_leaf_swept_twice_is_refused():
    """Regression: names with a leaf twice ran, the last column winning: a table then
    showed values that were not the ones simulated."""
    with pytest.raises(S.SweepError, match=r"names gives \['contact.default.k'\] more than "
                                           "once"):
        S.sweep(lambda p: {}, None, np.ones((3, 2)), TOY_NAMES * 2)


@pytest.mark.filterwarnings("ignore:the sweep's metrics hold no")
def test_a_costly_results_file_is_written_as_often_as_its_cost_allows(tmp_path, monkeypatch):
    """Regression: the whole .npz was rewritten after every chunk, so a sweep of many points
    spent most of its time writing (1e6 points: 0.18 s a chunk against 0.006 s of
    computing). Now it is rewritten once the chunks since took NPZ_COST_FACTOR times its
    write time, and always when the sweep ends or stops; a sweep whose table would take
    longer than CSV_ON_STOP_S to write leaves it when stopped and says so, and a rerun
    writes it."""
    import time

    import tuning.sweep_files as files
    written = []
    real = files._save_npz

    def slow(out, res):                  # a large file: every write costs 0.2 s
        time.sleep(0.2)
        written.append(int(res.done.sum()))
        real(out, res)
    monkeypatch.setattr(files, "_save_npz", slow)
    out = str(tmp_path / "c.npz")
    res = S.sweep(lambda p: {"k": p.contact["default"].k}, _toy_params(),
                  np.arange(1.0, 33.0)[:, None], TOY_NAMES, chunk=2, out=out, progress=False)
    assert res.done.all() and len(written) < 16        # 16 chunks: every one wrote before
    assert written[0] == 2 and written[-1] == 32
    back = S.load_sweep(out)
    assert back.done.all() and np.array_equal(back.metrics["k"], res.points[:, 0])
    # stopped, with a table too slow to write then: the .npz has every point done, the table
    # stays as it was, and a rerun (everything resumed) writes it
    monkeypatch.setattr(files, "CSV_ON_STOP_S", 0.0)
    out2 = str(tmp_path / "d.npz")

    def stop_third(i, r):
        if i == 2:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        S.sweep(lambda p: {"k": p.contact["default"].k}, _toy_params(),
                np.arange(1.0, 33.0)[:, None], TOY_NAMES, chunk=2, out=out2, progress=False,
                on_chunk=stop_third)
    assert S.load_sweep(out2).done.sum() == 6 and not os.path.exists(tmp_path / "d.csv")
    again = S.sweep(lambda p: {"k": p.contact["default"].k}, _toy_params(),
                    np.arange(1.0, 33.0)[:, None], TOY_NAMES, chunk=2, out=out2,
                    progress=False)
    assert again.evaluated == 26
    table = np.loadtxt(tmp_path / "d.csv", delimiter=",", skiprows=1)
    assert table.shape == (32, 3) and table[:, -1].all()


def test_a_full_disk_names_the_file_and_what_is_kept(tmp_path, monkeypatch):
    """Regression: a full disk while the table was written ended on a bare "[Errno 28] No
    space left on device", naming neither the file nor that the .npz beside it was
    complete."""
    import tuning.sweep_files as files
    real = files.atomic_write

    def full(path, fn):
        if path.endswith(".csv"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, fn)
    monkeypatch.setattr(files, "atomic_write", full)
    out = str(tmp_path / "e.npz")
    with pytest.raises(OSError, match=r"could not write .*e\.csv: No space left on device\. "
                                      r".*e\.npz holds the 8 points written before"):
        toy_sweep(out)
    assert S.load_sweep(out).done.all()
    # every point resumed: the pair is written again, through the same guard (audit18: a
    # bare "[Errno 28]" there)
    with pytest.raises(OSError, match=r"could not write .*e\.csv: No space left on device\. "
                                      r".*e\.npz holds the 8 points written before"):
        toy_sweep(out)


def _toy_params():
    from test_tuning_sweep import toy_params
    return toy_params()


def test_a_scene_file_sweep_too_large_is_refused_before_it_runs(tmp_path):
    """Regression: diffpen sweep SCENE.toml had no size check: --n 100000 ended in numpy's
    MemoryError making the grid, and --chunk 1000000 in XLA's RESOURCE_EXHAUSTED after
    compiling (the built-in ball's sweep refused both with an estimate)."""
    from tuning.scene_sweep import sweep_scene_file
    scene = tmp_path / "ball.toml"
    scene.write_text("dt = 1e-3\nduration = 3.0\n[[spheres]]\nradius = 0.1\nmass = 1.0\n"
                     "position = [0.0, 0.0, 0.3]\n[[planes]]\n[fit]\n"
                     "params = ['contact.default.k', 'contact.default.c']\n[fit.bounds]\n"
                     "'contact.default.k' = [2e3, 2e4]\n'contact.default.c' = [2.0, 20.0]\n")
    with pytest.raises(S.SweepError, match=r"10000000000 points need about .* for the "
                                           r"results alone .* lower n"):
        sweep_scene_file(str(scene), (), None, n=[100000], out=None)
    with pytest.raises(S.SweepError, match=r"a chunk of 1000000 points .* lower chunk"):
        sweep_scene_file(str(scene), (), None, n=[1000], chunk=10 ** 6, out=None)


def test_a_record_sweep_counts_the_points_where_a_crumple_member_collapsed(tmp_path, capsys):
    """audit18: the collapse flag (a plastic member crushed below 5% of its length, past
    what the model describes) reached no sweep: a scene-file sweep over a crumple bar
    returned inverted bars as ordinary errors. Its records sweep now keeps a
    collapsed_records column (per point, the records whose rollout collapsed) and the
    command counts those points."""
    import json

    from record_scenes import CRUMPLE, record_file

    from tuning.cli import main
    scene, rec = record_file(tmp_path, CRUMPLE, {"springs.bar.k": 2000.0},
                             ["bar[0]", "bar[5]"], "crumple", integrator="semi_implicit_euler",
                             dt=1e-4, every=0.005, duration=0.3, noise=0.0, seed=0)
    from tuning.scene_sweep import sweep_scene_file
    res, info = sweep_scene_file(scene, [rec], [("springs.bar.k", 200.0, 2000.0)], n=[2])
    crushed = np.asarray(res.metrics["collapsed_records"]).reshape(-1)
    assert list(crushed) == [1, 0]          # the soft bar (k 200 N/m) collapses at 1 m/s
    capsys.readouterr()
    assert main(["sweep", scene, "--data", rec, "--param", "springs.bar.k", "200", "2000",
                 "--n", "2", "--json", "--out", str(tmp_path / "c.npz")]) == 0
    assert json.loads(capsys.readouterr().out)["points_with_collapsed_records"] == 1
    # diffpen evaluate (and a scene fit's final evaluation) marks such a record too
    from tuning.evaluate import evaluate_files
    soft = tmp_path / "soft.toml"
    soft.write_text(CRUMPLE.replace("k = 2000.0", "k = 200.0"))
    out = evaluate_files(str(soft), [rec])
    assert out["records"][0]["collapsed"] and "crushed a plastic spring" in out["message"]
    assert not evaluate_files(scene, [rec])["records"][0]["collapsed"]
    from tuning.scene_fit import fit_files            # a fit held to soft members
    held = tmp_path / "held.toml"
    held.write_text(CRUMPLE.replace("k = 2000.0", "k = 200.0")
                    + "[fit.bounds]\n'springs.bar.k' = [150.0, 250.0]\n")
    fitted = fit_files(str(held), [rec], maxiter=2, step_check=False)
    assert fitted["collapsed_records"] == [rec]
    assert "crushed a plastic spring" in fitted["message"]
