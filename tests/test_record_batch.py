"""The pieces fits to records stand on (tuning.record_batch, tuning.trajfit): records of
unequal length batched with masks, the start state under vmap, a plane's offset as a
differentiable parameter, leaf names, and records refused before anything compiles."""
import logging
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from tuning import pose
from tuning import trajfit as tf
from tuning.cli import main

from record_scenes import ROPE


def test_host_rotation_matrices_are_float64_without_x64():
    """Regression: tuning.pose.rotmat (first states, body-frame velocities) went through JAX
    asking for float64; with x64 off JAX warned and truncated it to float32. It now
    computes on the host, in float64 either way, and equals diffpen's own matrices."""
    import warnings
    q = np.array([[0.9, 0.3, 0.1, 0.0], [0.1, -0.7, 0.2, 0.6]])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    with jax.enable_x64(False), warnings.catch_warnings():
        warnings.simplefilter("error")
        R = pose.rotmat(q)
    assert R.dtype == np.float64
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-15)
    np.testing.assert_allclose(R, np.asarray(dp.rigid.quat_to_matrix(jnp.asarray(q))),
                               atol=1e-15)


def test_unequal_lengths_are_masked(cube, caplog):
    """Records of different lengths in one batch give each record the residuals it gives
    alone (padding weighs nothing)."""
    params = cube.params()
    s = cube.state_from(body=0, position=(0, 0, 0.2), velocity=(0.4, 0, 0),
                        orientation=(0.9, 0.3, 0.1, 0.0), angular_velocity=(2, 0, 1),
                        frame="body")
    long = tf.synthetic_record(cube, params, 0.3, 5e-3, {"cube": 0}, state=s, noise=1e-3)
    short = tf.synthetic_record(cube, params, 0.12, 5e-3, {"cube": 0}, noise=1e-3, seed=3)
    both = tf.prepare(cube, [long, short], estimate="record")
    alone = [tf.prepare(cube, [r], estimate="record") for r in (long, short)]
    p2 = tf.with_leaves(params, {"contact.board.c": 20.0})

    def residuals(b):        # jitted: one compile per batch instead of one per eager op
        return np.asarray(jax.jit(lambda p: tf.pose_residuals(*tf.simulate(cube, p, b), b))(p2))
    r_both = residuals(both)
    # called eagerly, the same batch again reuses its compiled rollout (simulate's observe
    # function is one object per set of bodies, and the rollout program is keyed by it)
    first = tf.simulate(cube, p2, both)[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        again = tf.simulate(cube, p2, both)[0]
    assert not [r for r in caplog.records if r.getMessage().startswith("Compiling")]
    np.testing.assert_array_equal(np.asarray(again), np.asarray(first))
    cost_alone = [float(np.sum(residuals(b) ** 2)) for b in alone]
    # each record weighs 1/R in the batch: the batch cost is the mean of the costs alone
    assert float(np.sum(r_both ** 2)) == pytest.approx(np.mean(cost_alone), rel=1e-10)
    assert both.pos_mask[1, len(short.t):].sum() == 0
    # buckets of similar length give the same loss as one padded batch
    buckets = tf.prepare_buckets(cube, [long, short], buckets=2, estimate="record")
    assert [len(b.paths) for b in buckets] == [1, 1] and buckets[0].steps < both.steps
    r_buckets = np.concatenate([residuals(b) for b in buckets])
    assert float(np.sum(r_buckets ** 2)) == pytest.approx(float(np.sum(r_both ** 2)),
                                                          rel=1e-10)


def test_plane_offset_is_a_differentiable_parameter(cube):
    """A named plane's offset is params.extra["plane_offset"][name]: moving it moves the
    resting box by the same amount, and its gradient matches central differences."""
    params = cube.params()
    assert float(params.extra["plane_offset"]["ground"]) == -0.002
    s = cube.state_from(body=0, position=(0, 0, 0.1))

    def rest_z(off):
        p = tf.with_leaves(params, {"extra.plane_offset.ground": off})
        return cube.rollout(p, 400, s).position[-1, 0, 2]
    z0, z1 = float(rest_z(-0.002)), float(rest_z(0.003))
    assert z1 - z0 == pytest.approx(0.005, rel=1e-3)
    g = float(jax.grad(rest_z)(jnp.asarray(0.0)))
    h = 1e-6
    fd = (float(rest_z(h)) - float(rest_z(-h))) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-5)
    with pytest.raises(dp.SceneError, match="finite"):
        cube.params(extra={"plane_offset": {"ground": float("nan")}})
    with pytest.raises(dp.SceneError, match="exists already"):
        cube.scene.add_plane(name="ground")


def test_state_from_under_vmap_matches_a_loop(cube):
    """state_from sets pose, velocity and BODY-frame angular velocity; vmapped over start
    states it equals one call per state, and the world angular velocity is R w_body."""
    q = jnp.array([[1.0, 0, 0, 0], [0.0, 0, 0, 1.0]])
    wb = jnp.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    pos = jnp.array([[0, 0, 0.2], [0.1, 0, 0.3]])
    many = jax.vmap(lambda p, qq, w: cube.state_from(body=0, position=p, orientation=qq,
                                                     angular_velocity=w,
                                                     frame="body"))(pos, q, wb)
    for i in range(2):
        one = cube.state_from(body=0, position=pos[i], orientation=q[i],
                              angular_velocity=wb[i], frame="body")
        np.testing.assert_allclose(many.angular_velocity[i], one.angular_velocity)
    # a half turn about z maps body (1, 2, 3) to world (-1, -2, 3)
    np.testing.assert_allclose(many.angular_velocity[1, 0], [-1.0, -2.0, 3.0], atol=1e-12)
    with pytest.raises(dp.SceneError, match="body"):
        cube.state_from(body=3, position=(0, 0, 0))


def test_leaf_names_accept_keystr():
    assert tf._normalise(".contact['board'].k") == "contact.board.k"
    assert tf._normalise("springs.rope.stretch.c") == "springs.rope.stretch.c"
    assert tf.Free("extra.plane_offset.ground", -0.01, 0.01).resolved().log is False
    assert tf.Free("contact.board.k", 1.0, 1e5).resolved().log is True
    with pytest.raises(ValueError, match="lo >= 0"):
        tf.Free("contact.board.k", -1.0, 1.0, log=True).resolved()
    assert math.isclose(tf.ROT_WEIGHT, 0.5729577951308232)


def test_bad_records_fail_before_compiling(tmp_path, capsys):
    scene = tmp_path / "rope.toml"
    scene.write_text(ROPE.format(k=200.0, c=0.3))
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y\n0,1,2\n")
    assert main(["fit", str(scene), "--data", str(bad), "--json"]) == 2
    assert "bad.csv" in capsys.readouterr().err
    assert main(["fit", str(scene), "--data", str(tmp_path / "none.csv")]) == 2
    capsys.readouterr()
    # without a scene file --data is the ball's one t,z record
    assert main(["fit", "--data", str(bad), str(bad)]) == 2
    assert "one t,z record" in capsys.readouterr().err
    assert main(["fit", "--out", str(tmp_path / "x.toml")]) == 2


def test_a_record_without_a_first_pose_names_its_file_and_body(tmp_path, cube):
    """The rollout starts from row 0: a record whose first row lacks the position or the
    orientation is refused with the file, the body and what to do (it said neither)."""
    from tuning.records import read_record
    for cells, what in (("0,,,,1,0,0,0", "position (x, y, z)"),
                        ("0,0,0,0.3,,,,", "orientation (qw, qx, qy, qz)")):
        path = tmp_path / "late_start.csv"
        path.write_text("t,x,y,z,qw,qx,qy,qz\n" + cells + "\n0.01,0,0,0.3,1,0,0,0\n"
                        "0.02,0,0,0.299,1,0,0,0\n")
        rec = read_record(str(path), ["cube"])
        with pytest.raises(tf.FitError) as err:
            tf.prepare(cube, [rec], bodies={"cube": 0}, estimate="record")
        msg = str(err.value)
        assert "late_start.csv" in msg and "'cube'" in msg and what in msg, msg
        assert "Trim the record" in msg


def test_readme_snippet_runs_as_written():
    """The README's vmapped start states with a fitted plane offset run as written."""
    import pathlib
    import re
    text = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"## Fitting measured motion.*?```python\n(.*?)```", text, re.S).group(1)
    env: dict = {}
    exec(compile(block, "README fitting measured motion", "exec"), env)
    np.testing.assert_allclose(np.asarray(env["dz"]), 1.0, rtol=1e-3)
    assert np.all(np.abs(np.asarray(env["z"]) - 0.05) < 1e-3)
