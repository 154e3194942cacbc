"""Sweeps: vmapped chunks equal a point-by-point loop, interrupted sweeps resume, writes are
atomic."""
import os

import jax
import numpy as np
import pytest

import diffpen as dp
from tuning import bounce as B
from tuning import sweep as S

NAMES = ["contact.default.k", "contact.default.c"]


@pytest.fixture(scope="module")
def problem():
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.5))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3)
    mfn = B.bounce_metrics_fn(sim, 700, n_apex=1)
    points, shape = S.grid_points({NAMES[0]: np.geomspace(5e3, 2e4, 4),
                                   NAMES[1]: np.geomspace(5.0, 40.0, 4)})
    keys = ["apex_heights", "max_penetration", "settled"]
    ev = S.make_evaluator(mfn, sim.params(k=1e4, c=10.0), NAMES, keys)   # one compile
    full = S.sweep(None, sim.params(k=1e4, c=10.0), points, NAMES, chunk=5, keys=keys,
                   shape=shape, evaluate=ev)
    return sim, ev, points, shape, keys, full


def test_chunks_match_point_by_point(problem):
    sim, ev, points, shape, keys, full = problem
    assert full.done.all() and full.evaluated == 16
    assert full.grid("apex_heights", 0).shape == shape
    import jax
    mfn = B.bounce_metrics_fn(sim, 700, n_apex=1)
    f = jax.jit(mfn)
    for i in (0, 7, 15):                 # 15 sits in the padded last chunk
        m = f(sim.params(k=points[i, 0], c=points[i, 1]))
        assert float(m["apex_heights"][0]) == pytest.approx(full.metrics["apex_heights"][i, 0],
                                                           rel=1e-12)
    # more damping -> lower apex, along every row of the grid
    apex = full.grid("apex_heights", 0)
    assert np.all(np.diff(apex, axis=1) < 0)


def test_interrupted_sweep_resumes(problem, tmp_path):
    sim, ev, points, shape, keys, full = problem
    out = str(tmp_path / "s.npz")

    def stop_after_two(i, res):
        if i == 1:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        S.sweep(None, sim.params(k=1e4, c=10.0), points, NAMES, chunk=5, keys=keys, out=out,
                on_chunk=stop_after_two, evaluate=ev)
    part = S.load_sweep(out)
    assert part.done.sum() == 10 and not part.done[10:].any()
    res = S.sweep(None, sim.params(k=1e4, c=10.0), points, NAMES, chunk=5, keys=keys, out=out,
                  evaluate=ev)
    assert res.evaluated == 6            # only the two missing chunks
    np.testing.assert_array_equal(res.metrics["apex_heights"], full.metrics["apex_heights"])
    back = S.load_sweep(out)
    assert back.done.all()
    np.testing.assert_array_equal(back.metrics["max_penetration"],
                                  full.metrics["max_penetration"])
    header = open(str(tmp_path / "s.csv")).readline().strip().split(",")
    assert header == NAMES + ["apex_heights", "max_penetration", "settled", "unstable", "done"]
    assert np.loadtxt(str(tmp_path / "s.csv"), delimiter=",", skiprows=1).shape == (16, 7)
    # other points: refused (the file holds another sweep), overwritten only when asked
    with pytest.raises(S.SweepError, match="points"):
        S.sweep(None, sim.params(k=1e4, c=10.0), points[:3], NAMES, chunk=5, keys=keys,
                out=out, evaluate=ev)
    # another chunk size: refused, saying how to resume (before, only "chunk: file has 5")
    with pytest.raises(S.SweepError, match="to resume it, give its chunk size again"):
        S.sweep(None, sim.params(k=1e4, c=10.0), points, NAMES, chunk=4, keys=keys,
                out=out, evaluate=ev)
    res2 = S.sweep(None, sim.params(k=1e4, c=10.0), points[:3], NAMES, chunk=5, keys=keys,
                   out=out, evaluate=ev, resume=False)
    assert res2.evaluated == 3


def test_writes_are_atomic(problem, tmp_path, monkeypatch):
    sim, ev, points, shape, keys, full = problem
    out = str(tmp_path / "a.npz")
    S.sweep(None, sim.params(k=1e4, c=10.0), points[:5], NAMES, chunk=5, keys=keys, out=out,
                  evaluate=ev)
    before = open(out, "rb").read()
    real = os.replace

    def crash(src, dst):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError):
        S.sweep(None, sim.params(k=1e4, c=10.0), points[5:10], NAMES, chunk=5, keys=keys,
                out=out, evaluate=ev, resume=False)
    monkeypatch.setattr(os, "replace", real)
    assert open(out, "rb").read() == before            # the old file is intact
    assert S.load_sweep(out).done.all()
    assert [f for f in os.listdir(tmp_path) if f.startswith(".tmp-")] == []


def test_atomic_write_gives_a_plain_files_permissions(tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    S.atomic_write(str(tmp_path / "atomic.txt"), lambda fh: fh.write(b"x"))
    assert (os.stat(tmp_path / "atomic.txt").st_mode & 0o777
            == os.stat(plain).st_mode & 0o777)


def test_random_points_and_bad_input():
    pts = S.random_points({"a": (1.0, 100.0), "b": (0.1, 1.0)}, 500, seed=1)
    assert pts.shape == (500, 2)
    assert pts[:, 0].min() >= 1.0 and pts[:, 0].max() <= 100.0
    assert abs(np.median(np.log10(pts[:, 0])) - 1.0) < 0.15      # log-uniform
    # regression: a signed range (a plane offset) or a lower bound of 0 gave all-NaN columns
    # under the default log=True, with only numpy's RuntimeWarning
    for bad in ((-0.01, 0.01), (0.0, 1.0)):
        with pytest.raises(ValueError, match="log=False"):
            S.random_points({"extra.plane_offset.ground": bad}, 5)
    with pytest.raises(ValueError, match="lo < hi"):
        S.random_points({"a": (2.0, 1.0)}, 5)
    lin = S.random_points({"extra.plane_offset.ground": (-0.01, 0.01)}, 50, log=False)
    assert np.all(np.isfinite(lin)) and lin.min() >= -0.01 and lin.max() <= 0.01
    with pytest.raises(ValueError, match="shape"):
        S.sweep(lambda p: {}, None, np.ones((3, 3)), NAMES)
    with pytest.raises(ValueError, match=">= 0"):
        S.sweep(lambda p: {}, None, -np.ones((3, 2)), NAMES)


# a sweep of a few host-cheap metrics: resume keys, tables and flags without rollouts
TOY_NAMES = ["contact.default.k"]
TOY_POINTS = np.arange(1.0, 9.0)[:, None]          # (8, 1)


def toy_params():
    from diffpen.state import ContactParams
    return dp.Params({"default": ContactParams(np.float64(1.0), np.float64(2.0))}, {}, {})


def toy(p):
    k = p.contact["default"].k
    return {"twice": 2.0 * k, "settled": k > 2.0, "unstable": k > 6.0}


def toy_sweep(out, evaluate=None, **kw):
    import jax
    if evaluate is None:
        kw.setdefault("batch_map", lambda f: jax.jit(jax.vmap(f)))
    return S.sweep(None if evaluate is not None else toy, toy_params(), TOY_POINTS, TOY_NAMES,
                   chunk=4, out=out, evaluate=evaluate, progress=False, **kw)


def stop_first(i, res):
    raise KeyboardInterrupt


def test_a_sweep_without_key_is_keyed_by_its_finalize(tmp_path):
    """Without key=, the key was only the digest of metrics_fn: a run resumed with another
    finalize= mixed rows post-processed two ways."""
    out = str(tmp_path / "f.npz")

    def halve(th):
        def finalize(m, pts):
            m["twice"] = np.where(pts[:, 0] > th, 0.5 * m["twice"], m["twice"])
            return m
        return finalize
    with pytest.raises(KeyboardInterrupt):
        toy_sweep(out, on_chunk=stop_first)
    before = open(out, "rb").read()
    with pytest.raises(S.SweepError, match='finalize: file has "<absent>"'):
        toy_sweep(out, finalize=halve(2.0))
    assert open(out, "rb").read() == before                 # refused, nothing mixed in
    with pytest.raises(KeyboardInterrupt):
        toy_sweep(out, finalize=halve(2.0), resume=False, on_chunk=stop_first)
    with pytest.raises(S.SweepError, match="finalize: file has"):
        toy_sweep(out, finalize=halve(3.0))                 # the same code, another value
    res = toy_sweep(out, finalize=halve(2.0))               # the same finalize resumes
    assert res.evaluated == 4 and res.done.all()
    np.testing.assert_array_equal(res.metrics["twice"][:6],
                                  np.where(TOY_POINTS[:6, 0] > 2.0, 1.0, 2.0) * TOY_POINTS[:6, 0])


def test_a_sweep_without_key_is_keyed_by_the_metrics_its_evaluator_keeps(tmp_path):
    """A run resumed with a make_evaluator keeping other metrics ended with every point done
    and each metric NaN on half of them: refused now, naming the metrics."""
    import jax
    out = str(tmp_path / "e.npz")

    def ev(keys):
        return S.make_evaluator(toy, toy_params(), TOY_NAMES, keys=keys,
                                batch_map=lambda f: jax.jit(jax.vmap(f)))
    with pytest.raises(KeyboardInterrupt):
        toy_sweep(out, evaluate=ev(["twice"]), on_chunk=stop_first)
    with pytest.raises(S.SweepError, match=r'metrics: file has \["twice"\], this run has '
                                           r'\["settled"\]'):
        toy_sweep(out, evaluate=ev(["settled"]))
    res = toy_sweep(out, evaluate=ev(["twice"]))
    assert res.evaluated == 4 and np.isfinite(res.metrics["twice"][:6]).all()


def _jit_vmap(f):
    import jax
    return jax.jit(jax.vmap(f))


def test_a_later_sweep_of_the_same_problem_compiles_nothing(caplog):
    """A sweep without evaluate= built and compiled a new evaluator at every call (~2 s on
    the ball): a later sweep with equal arguments now runs the first one's program."""
    import logging
    import jax
    S.sweep(toy, toy_params(), TOY_POINTS, TOY_NAMES, chunk=4, batch_map=_jit_vmap)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        res = S.sweep(toy, toy_params(), 1.5 * TOY_POINTS, TOY_NAMES, chunk=4,
                      batch_map=_jit_vmap)
    assert [r for r in caplog.records if r.getMessage().startswith("Compiling")] == []
    np.testing.assert_array_equal(res.metrics["twice"][:4], 3.0 * TOY_POINTS[:4, 0])


def test_points_past_the_safe_step_are_not_settled(tmp_path):
    """Points past the safe step had their float metrics NaN but kept the bool 'settled' of
    the blown-up rollout, in memory, the .npz and the .csv."""
    out = str(tmp_path / "u.npz")
    res = toy_sweep(out)
    k = TOY_POINTS[:, 0]
    bad = k > 6.0                     # their rollouts' "settled" would say True
    assert res.unstable == 2
    assert np.isnan(res.metrics["twice"][bad]).all()
    np.testing.assert_array_equal(res.metrics["settled"], (k > 2.0) & ~bad)
    np.testing.assert_array_equal(S.load_sweep(out).metrics["settled"], (k > 2.0) & ~bad)
    table = np.genfromtxt(str(tmp_path / "u.csv"), delimiter=",", names=True)
    np.testing.assert_array_equal(table["settled"], ((k > 2.0) & ~bad).astype(float))


def test_a_csv_that_is_not_the_sweeps_table_is_refused(tmp_path):
    """The .csv beside out= was overwritten whatever it held (e.g. a t,z record) while an
    unrelated .npz at out= was refused."""
    rec = tmp_path / "record.csv"
    rec.write_text("t,z\n0.0,1.0\n0.1,0.95\n")
    for fresh in (False, True):
        with pytest.raises(S.SweepError, match="is not the table of a sweep in .*Move it, "
                                               "or choose another output path"):
            toy_sweep(str(tmp_path / "record.npz"), resume=not fresh)
        assert rec.read_text() == "t,z\n0.0,1.0\n0.1,0.95\n"
        assert not (tmp_path / "record.npz").exists()
    # beside a sweep file too: the table must be that sweep's
    out = str(tmp_path / "s.npz")
    toy_sweep(out)
    table = open(str(tmp_path / "s.csv")).read()
    assert toy_sweep(out).evaluated == 0                    # its own table: resumed
    assert toy_sweep(out, resume=False).evaluated == 8      # and overwritten when asked
    (tmp_path / "s.csv").write_text("t,z\n0.0,1.0\n")
    with pytest.raises(S.SweepError, match="not the table"):
        toy_sweep(out, resume=False)
    assert (tmp_path / "s.csv").read_text() == "t,z\n0.0,1.0\n"
    assert table.startswith("contact.default.k,") and table.splitlines()[0].endswith(",done")


def test_an_out_that_is_not_npz_is_refused(tmp_path):
    """sweep(out="res.csv") wrote its .npz to res.csv, then its table over it: the results
    were lost and load_sweep/resume failed. Refused before anything is written."""
    for bad in ("res.csv", "res", "res.npz.bak"):
        with pytest.raises(S.SweepError, match=r"must end in \.npz.*give NAME\.npz"):
            toy_sweep(str(tmp_path / bad))
    assert os.listdir(tmp_path) == []
    assert toy_sweep(str(tmp_path / "res.NPZ")).done.all()          # any case


def _corrupt_member(path, member):
    import zipfile
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(member)
    data = bytearray(open(path, "rb").read())
    data[info.header_offset + 30 + len(info.filename) + info.compress_size // 2] ^= 0xFF
    open(path, "wb").write(bytes(data))


def test_an_unreadable_sweep_file_is_refused_clearly_and_fresh_overwrites_it(tmp_path):
    """A sweep .npz with a corrupt member raised a raw BadZipFile; a truncated one beside
    its own table was refused as if the table were another file's ("not the table"), also
    with resume=False, which could never overwrite it. Both now: "cannot be read", and
    resume=False (--fresh) overwrites the file and its table."""
    out = str(tmp_path / "s.npz")
    toy_sweep(out)
    _corrupt_member(out, "metric:twice.npy")                 # its key is intact
    with pytest.raises(S.SweepError, match=r"s\.npz cannot be read \(BadZipFile.*resume="
                                           r"False \(diffpen sweep --fresh\)"):
        toy_sweep(out)
    with open(out, "rb") as fh:
        data = fh.read()
    with open(out, "wb") as fh:                             # truncated
        fh.write(data[:300])
    with pytest.raises(S.SweepError, match=r"cannot be read.*--fresh"):
        toy_sweep(out)
    res = toy_sweep(out, resume=False)
    assert res.evaluated == 8 and S.load_sweep(out).done.all()
    assert open(str(tmp_path / "s.csv")).readline().startswith("contact.default.k,")
    # an unreadable file does not make any .csv beside it its table
    with open(out, "wb") as fh:
        fh.write(data[:300])
    (tmp_path / "s.csv").write_text("t,z\n0.0,1.0\n")
    with pytest.raises(S.SweepError, match="not the table"):
        toy_sweep(out, resume=False)
    assert (tmp_path / "s.csv").read_text() == "t,z\n0.0,1.0\n"


def test_a_float64_batch_sets_float32_params_in_their_own_dtype():
    """A float32 simulator's sweep (x64 on) set the float64 points into its float32 params,
    so what the metrics computed from k (the settling time's resting height) came out
    float64, not bit for bit the single float32 rollout's."""
    import jax.numpy as jnp
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3, dtype=jnp.float32)
    p0 = sim.params(k=1e4, c=10.0)
    ev = S.make_evaluator(lambda p: {"kc": p.contact["default"][0] * p.contact["default"][1]},
                          p0, ["contact.default.k", "contact.default.c"],
                          batch_map=lambda f: jax.jit(jax.vmap(f)))
    out = ev(jnp.asarray([[1e4 + 0.1, 10.0]], jnp.float64))
    assert out["kc"].dtype == jnp.float32


def test_the_table_is_written_once_at_the_end_and_agrees_after_an_interrupt(tmp_path,
                                                                             monkeypatch):
    """Regression: the .csv (the whole table in text) was rewritten after every chunk, so a
    large sweep was quadratic (65536 points: 56 of its 61 s writing, the rollouts ~5 s), and
    a Ctrl-C nearly always landed inside that write, leaving the .csv a chunk behind the
    .npz. Now the .npz follows every chunk and the .csv is written when the sweep ends (or
    every CSV_EVERY_S), and an interrupt that arrives while the pair is written waits for
    both."""
    from tuning import progress
    out = str(tmp_path / "t.npz")
    csv = str(tmp_path / "t.csv")
    writes = []
    import tuning.sweep_files as files
    real = files.atomic_write
    monkeypatch.setattr(files, "atomic_write",
                        lambda path, fn: (writes.append(os.path.basename(path)), real(path, fn)))
    toy_sweep(out)                                   # 2 chunks
    assert writes.count("t.npz") == 2 and writes.count("t.csv") == 1
    table = np.loadtxt(csv, delimiter=",", skiprows=1)
    twice = open(csv).readline().strip().split(",").index("twice")
    k = TOY_POINTS[:, 0]
    np.testing.assert_array_equal(table[:, twice], np.where(k > 6.0, np.nan, 2.0 * k))
    # a signal while the first chunk's .npz is written: the .csv follows before it ends the
    # run, so the pair agrees (done: 4 of 8 rows in both)
    os.remove(out), os.remove(csv)
    count = []

    def signalled(path, fn):
        real(path, fn)
        count.append(path)
        if len(count) == 1:
            progress.interrupt(KeyboardInterrupt)   # what the command's SIGINT handler does
    monkeypatch.setattr(files, "atomic_write", signalled)
    try:
        with pytest.raises(KeyboardInterrupt):
            toy_sweep(out)
    finally:
        progress.clear_pending()
    part = S.load_sweep(out)
    assert part.done.sum() == 4
    table = np.loadtxt(csv, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table[:, -1], part.done.astype(float))


def test_grid_axes_and_point_counts_are_checked():
    """Regression: grid_points took NaN and empty axes (a NaN lane, a sweep of nothing),
    random_points(n=-1) said only "negative dimensions are not allowed"."""
    for axis in ([1e3, float("nan")], []):
        with pytest.raises(ValueError, match="axis 'k' must hold finite values"):
            S.grid_points({"k": axis})
    with pytest.raises(ValueError, match="n must be a whole number of points >= 0"):
        S.random_points({"k": (1.0, 10.0)}, -1)
    with pytest.raises(ValueError, match="at least one axis"):
        S.grid_points({})                       # "need at least one array to stack"
    with pytest.raises(ValueError, match="at least one"):
        S.random_points({}, 3)


def test_cache_keys_are_values_with_their_types():
    """The keys of the sweeps' and batched fits' caches (tuning.compiled.frozen_key): equal
    values give equal keys; values a program would treat differently do not (an int leaf
    casts the batch to int, -0.0 is not 0.0 to every operation); traced values give none."""
    import jax
    from tuning.compiled import frozen_key
    p = toy_params()
    assert frozen_key(p, ["a"], {"x": 1.0}) == frozen_key(toy_params(), ["a"], {"x": 1.0})
    assert frozen_key(1) != frozen_key(1.0) != frozen_key(True)
    assert frozen_key(-0.0) != frozen_key(0.0) and frozen_key(np.float32(1)) != frozen_key(1.0)
    assert frozen_key(["a"]) != frozen_key(("a",)) and frozen_key([1]) != frozen_key([[1]])
    assert frozen_key(np.zeros(2)) != frozen_key(np.zeros(3))
    assert frozen_key([{1, 2}]) is None                       # unhashable
    seen = []
    jax.jit(lambda x: seen.append(frozen_key(x)) or x)(1.0)
    assert seen == [None]


GAIN = {"value": 1.0}


def _gained(p):
    return {"twice": GAIN["value"] * p.contact["default"].k}


def test_the_function_key_sees_a_changed_global(monkeypatch):
    """Regression (audit15): JAX keeps the trace of a function it traced before, globals'
    values and all, so a sweep's key of its metrics (what a rerun into the same out= is
    checked against) stayed that of the first trace in a process after a global changed."""
    monkeypatch.setitem(GAIN, "value", 1.0)
    first = S.function_key(_gained, toy_params())
    monkeypatch.setitem(GAIN, "value", 2.0)
    assert S.function_key(_gained, toy_params()) != first
