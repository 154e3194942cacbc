"""Sweeps: vmapped chunks equal a point-by-point loop, interrupted sweeps resume, writes are
atomic."""
import os

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
    with pytest.raises(ValueError, match="shape"):
        S.sweep(lambda p: {}, None, np.ones((3, 3)), NAMES)
    with pytest.raises(ValueError, match=">= 0"):
        S.sweep(lambda p: {}, None, -np.ones((3, 2)), NAMES)
