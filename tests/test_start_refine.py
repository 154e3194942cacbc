"""Record fits that refine each record's start state with the parameters
(``diffpen fit --first-state refine``, :mod:`tuning.start_refine`): the projection against
the joint least-squares problem, the offsets against the bodies they move, and a rope fitted
from noisy marker positions alone, and a box on anchored springs within 2% where row 0's
pose moved its damping 3%."""
import json

import jax.numpy as jnp
import numpy as np
import pytest

from tuning import scene_fit
from tuning.cli import main
from tuning.start_refine import project_starts, start_steps

from record_scenes import BOX, ROPE, record_file


def test_the_projection_is_the_joint_problem_with_the_starts_eliminated():
    """Gauss-Newton on the projected residuals gives the parameters' step and covariance of
    the joint problem (parameters and every record's own start offsets): the Schur
    complement, record by record."""
    rng = np.random.default_rng(0)
    n_rec, rows, P, S = 3, 40, 2, 4
    record = np.repeat(np.arange(n_rec), rows)
    r = rng.standard_normal(n_rec * rows)
    jp = rng.standard_normal((n_rec * rows, P))
    js = rng.standard_normal((n_rec * rows, S))
    joint = np.zeros((n_rec * rows, P + n_rec * S))      # the dense joint Jacobian
    joint[:, :P] = jp
    for i in range(n_rec):
        joint[record == i, P + i * S:P + (i + 1) * S] = js[record == i]
    step = -np.linalg.lstsq(joint, r, rcond=None)[0]
    cov = np.linalg.inv(joint.T @ joint)[:P, :P]
    rp, jpp = (np.asarray(a) for a in project_starts(jnp.asarray(r), jnp.asarray(jp),
                                                     jnp.asarray(js), record, n_rec))
    np.testing.assert_allclose(-np.linalg.lstsq(jpp, rp, rcond=None)[0], step[:P], rtol=1e-9)
    np.testing.assert_allclose(np.linalg.inv(jpp.T @ jpp), cov, rtol=1e-9)
    # the standard errors: the joint problem's, its noise estimated with the starts' offsets
    # fitted too (audit15: m - p degrees of freedom, not m - p - the offsets)
    import types
    from tuning.fit_errors import parameter_errors
    free = [types.SimpleNamespace(name=n, log=False) for n in ("a", "b")]
    rp_cost = float(rp @ rp)
    se, _, _ = parameter_errors(jpp, rp, rp_cost, free, {"a": 1.0, "b": 1.0}, None,
                                nuisance=n_rec * S)
    s2 = rp_cost / (len(r) - P - n_rec * S)
    np.testing.assert_allclose([se["a"], se["b"]], np.sqrt(np.diag(cov) * s2), rtol=1e-9)
    # the starts' own steps at fixed parameters: each record's least squares
    got = np.asarray(start_steps(jnp.asarray(r), jnp.asarray(js), record, n_rec))
    for i in range(n_rec):
        m = record == i
        np.testing.assert_allclose(got[i], -np.linalg.lstsq(js[m], r[m], rcond=None)[0],
                                   rtol=1e-9)
    # an offset no row sees (a body observed only later) stays 0, the others as before
    js0 = js.copy()
    js0[:, 3] = 0.0
    got0 = np.asarray(start_steps(jnp.asarray(r), jnp.asarray(js0), record, n_rec))
    assert np.all(got0[:, 3] == 0.0) and np.all(np.isfinite(got0))


def test_a_rope_is_fitted_from_noisy_marker_positions_alone(tmp_path):
    """A rope's k and c from a record of 3 of its nodes' positions (no velocity columns;
    rk4 at a quarter of the fit's step, 0.2 mm of noise): started from the first frames'
    estimate the fit missed c by 70% and k by 12% (its start velocities a few cm/s off, the
    motion they start explained by the springs; `--first-state record`, measured on this
    record), refined with the start 0.3% and 0.1%, the truth within 3.5 reported errors
    (audit13: 9-22% and 13% off on other scenes). The whole record at once: the growing
    horizon's stages end at the same values."""
    from tuning.scene_fit import fit_files
    truth = {"springs.rope.stretch.k": 300.0, "springs.rope.stretch.c": 0.5}
    scene, rec = record_file(tmp_path, ROPE.format(k=200.0, c=0.3), truth,
                             ["rope[1]", "rope[2]", "rope[3]"], "rope", integrator="rk4",
                             dt=2.5e-4, every=5e-3, duration=0.6, noise=2e-4, seed=1,
                             velocities=False)
    out = fit_files(scene, [rec], estimate="refine", horizons=(None,))
    for name, v in truth.items():
        assert out["fitted"][name] == pytest.approx(v, rel=0.01), (name, out["fitted"])
        assert abs(out["fitted"][name] - v) < 3.5 * out["stderr"][name]
    assert out["estimate"] == "refine" and out["undetermined"] == []


def test_the_offsets_move_the_observed_unpinned_bodies_only():
    """A record's offsets move its bodies observed in its first frame that are not pinned;
    orientation offsets turn the bodies whose first frame has an orientation, shared offsets
    move every record alike, per-record ones each its own."""
    import types

    import jax
    import diffpen as dp
    from tuning.start_refine import active_offsets, offset_columns, with_start_offsets
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(0.05, 1.0, (0.0, 0.0, 1.0), pinned=True)
    scene.add_sphere(0.05, 1.0, (0.5, 0.0, 1.0))
    scene.add_box((0.1, 0.05, 0.03), 1.0, (1.0, 0.0, 1.0))
    sim = dp.compile(scene, 1e-3)
    s0 = sim.init_state()
    start = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), s0)
    seen = np.ones((2, 4, 3))
    seen[1, 0, 1] = 0.0                 # record 1 starts without body 1
    turned = np.zeros((2, 4, 3))
    turned[:, 0, 2] = 1.0               # the box's orientation is measured
    batch = types.SimpleNamespace(bodies=np.array([0, 1, 2]), pos_mask=seen,
                                  quat_mask=turned, has_rotation=True)
    assert offset_columns(batch, True) == 36
    assert active_offsets(sim, batch) == 6 * 3 + 6 * 2     # positions seen 3x, the box turned 2x
    u = jnp.asarray(np.arange(1.0, 37.0) * 1e-3)
    out = with_start_offsets(sim, start, batch, u, True)
    dpos = np.asarray(out.position - start.position)
    dvel = np.asarray(out.velocity - start.velocity)
    np.testing.assert_allclose(dpos[0], np.asarray(u[:9]).reshape(3, 3) * [[0], [1], [1]])
    np.testing.assert_allclose(dpos[1], np.asarray(u[:9]).reshape(3, 3) * [[0], [0], [1]])
    np.testing.assert_allclose(dvel[0, 2], np.asarray(u[15:18]))
    dw = np.asarray(out.angular_velocity - start.angular_velocity)
    assert np.all(dw[:, :2] == 0.0) and np.allclose(dw[:, 2], np.asarray(u[33:36]))
    q = np.asarray(out.orientation)
    assert np.all(q[:, :2] == np.asarray(start.orientation)[:, :2])
    assert not np.allclose(q[:, 2], np.asarray(start.orientation)[:, 2])
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=1e-12)
    # per record: each its own
    per = jnp.stack([u, 2.0 * u])
    out2 = with_start_offsets(sim, start, batch, per, True)
    np.testing.assert_allclose(np.asarray(out2.velocity - start.velocity)[1, 2],
                               2.0 * np.asarray(u[15:18]))


def test_a_refined_start_recovers_the_hung_box_within_two_percent(tmp_path, capsys,
                                                                 monkeypatch):
    """Issue 14's item 7 for the box on anchored springs: from row 0's noisy pose the
    damping is fitted to the oscillation that pose's error starts, c -4.9% ... +1.5% over
    noise seeds 1-5 (this record's seed 2: +1.49%, k -0.31%). ``--first-state refine`` fits
    each record's start with k and c: k -0.40 ... -0.45%, c -0.31 ... -0.41% over the same
    five seeds (the fit integrator's own step error: noise-free -0.42 / -0.33%, at half the
    step -0.21 / -0.16%; measured), held here to 2%."""
    truth = {"springs.hang.k": 400.0, "springs.hang.c": 2.0}
    scene, rec = record_file(tmp_path, BOX.format(k=250.0, c=1.0), truth, ["box"], "box2",
                             integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.6,
                             noise=2e-4, seed=2)
    monkeypatch.setattr(scene_fit, "STEP_CHECK", False)
    capsys.readouterr()
    assert main(["fit", scene, "--data", rec, "--first-state", "refine", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for name, v in truth.items():
        assert out["fitted"][name] == pytest.approx(v, rel=0.02), (name, out["fitted"])
