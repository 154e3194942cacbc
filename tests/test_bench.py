"""Benchmarks measure what they name (not timed tests: no speed is asserted here)."""
import jax.numpy as jnp
import numpy as np

from tuning import bench


def test_checkpointed_gradient_memory_is_bounded_and_exact():
    out = bench.gradient_memory(6, 2000, 100, 10, dtype=jnp.float64, compare=True)
    assert out["checkpoint_over_forward"] <= 10.0
    assert out["grad_plain_bytes"] > 10 * out["grad_checkpoint_bytes"]
    assert out["max_rel_diff"] <= 1e-6


def test_ball_case_reports_every_figure():
    row = bench.run_case("ball_b1", quick=True, repeats=1)
    for key in ("compile_s", "forward_s", "grad_s", "floor_s", "numpy_s", "steps_per_s"):
        assert np.isfinite(row[key]) and row[key] > 0
    assert row["steps"] == 500 and row["batch"] == 1
    assert row["vs_floor"] == row["forward_s"] / row["floor_s"]
    assert row["stepping_vs_floor"] == row["stepping_s"] / row["floor_stepping_s"]
    assert row["stepping_per_s"] == row["steps"] / row["stepping_s"]


def test_floor_and_numpy_baselines_compute_the_same_physics():
    spec = bench.CASES["ball_b1"].build(jnp.float64, True)
    z = np.asarray(spec["forward"](*spec["args"]))
    zf = np.asarray(spec["floor"](*spec["args"]))
    zn = spec["numpy"]()
    # the floor has a pointwise hard contact, diffpen the step-averaged one: they differ by
    # up to 2.2e-4 m after the impacts (0.2 mm; the forward cost is what is compared)
    np.testing.assert_allclose(zf, z, atol=5e-4)
    np.testing.assert_allclose(zn, zf, rtol=1e-12)
    # the stepping workloads end where the recorded ones do
    np.testing.assert_allclose(np.asarray(spec["stepping"](*spec["args"]))[-1, 0, 2], z[-1],
                               rtol=1e-12)
    np.testing.assert_allclose(np.asarray(spec["floor_stepping"](*spec["args"]))[2], zf[-1],
                               rtol=1e-12)
    net = bench.CASES["cloth32"].build(jnp.float64, True)
    a = net["args"]
    np.testing.assert_allclose(net["floor"](*a), net["forward"](*a), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(net["numpy"](), net["floor"](*a), rtol=1e-9, atol=1e-12)
