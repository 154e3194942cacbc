"""Benchmarks measure what they name (not timed tests: no speed of diffpen is asserted here)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tuning.reports import bench, floors, timing


def test_checkpointed_gradient_memory_is_bounded_and_exact():
    out = bench.gradient_memory(6, 2000, 100, 10, dtype=jnp.float64, compare=True)
    assert out["checkpoint_over_forward"] <= 10.0
    assert out["grad_plain_bytes"] > 10 * out["grad_checkpoint_bytes"]
    assert out["max_rel_diff"] <= 1e-6


U = 0.02     # s: the unit of the known costs below


class _Clock:
    """A virtual clock: ``sleep`` advances it, ``perf_counter`` reads it. The bench reads time
    through it (see ``clock``), so the workloads below have exactly known costs whatever the
    machine's load (a real sleep overshoots on a loaded machine)."""

    def __init__(self):
        self.t = 0.0

    def perf_counter(self):
        return self.t

    def sleep(self, s):
        self.t += s


@pytest.fixture
def clock(monkeypatch):
    c = _Clock()
    monkeypatch.setattr(timing, "time", c)
    monkeypatch.setattr(bench, "time", c)
    return c


class _Sleeper:
    """A workload of known cost: each call takes ``units`` x U seconds of the virtual clock.
    It stands in for a jitted function (``lower(...).compile()`` gives an executable without
    memory analysis)."""

    def __init__(self, clock, units: float):
        self.clock, self.units = clock, units

    def __call__(self, *args):
        self.clock.sleep(self.units * U)
        return np.zeros(())

    def lower(self, *args):
        return self

    def compile(self):
        return self

    def memory_analysis(self):
        return None


@pytest.fixture
def known_case(monkeypatch, clock):
    """A case whose every workload has a known cost, so that each reported figure has a known
    value: forward 4 U, floor 1 U, gradient 6 U, floor gradient 2 U, reverse mode 8 U, the
    floor's reverse mode 5 U, the band-layout floor 7 U, stepping 3 U, the natural code 5 U,
    the floor's stepping 1 U, NumPy 2 U."""
    def build(dtype, quick):
        def s(units):
            return _Sleeper(clock, units)
        return dict(forward=s(4), floor=s(1), grad=s(6), floor_grad=s(2), grad_reverse=s(8),
                    floor_grad_reverse=s(5), grad_mode="forward", stepping=s(3), natural=s(5),
                    floor_stepping=s(1), band_floor=s(7),
                    numpy=lambda: clock.sleep(2 * U), args=(jnp.ones(()), jnp.ones(())),
                    work=1000, steps=10, batch=100)
    monkeypatch.setitem(bench.CASES, "known", bench.Case("known", build))


def test_ratios_are_those_of_the_workloads_they_name(known_case):
    row = bench.run_case("known", repeats=3)     # the median of 3 turns
    # each figure equals its known value (the virtual clock): a ratio of the wrong pair of
    # workloads (or of one workload with itself) is off by 1.5x at least
    expect = dict(forward_s=4 * U, floor_s=U, grad_s=6 * U, floor_grad_s=2 * U,
                  grad_reverse_s=8 * U, floor_grad_reverse_s=5 * U, reverse_vs_floor=1.6,
                  band_floor_s=7 * U, vs_band_floor=4 / 7,
                  stepping_s=3 * U, natural_s=5 * U,
                  floor_stepping_s=U, numpy_s=2 * U, vs_floor=4.0, grad_vs_floor=3.0,
                  grad_over_forward=1.5, reverse_over_forward=2.0, stepping_vs_floor=3.0,
                  natural_vs_floor=5.0, vs_numpy=2.0, steps_per_s=1000 / (4 * U),
                  stepping_per_s=1000 / (3 * U))
    for key, value in expect.items():
        assert row[key] == pytest.approx(value, rel=1e-9), key
    assert row["steps"] == 10 and row["batch"] == 100 and row["grad_mode"] == "forward"
    # regression: a --quick row (batch <= 256, fewer steps) kept only the full case's name
    assert row["quick"] is False and bench.run_case("known", repeats=1, quick=True)["quick"]


def test_interleaved_times_are_medians_of_turns(clock):
    """Calls are taken in turns, so a slow spell hits every function alike: a function whose
    every 5th call is slow still gets its typical time."""
    calls = {"a": 0}

    def a():
        calls["a"] += 1
        clock.sleep((3 if calls["a"] % 5 == 0 else 1) * U)
        return jnp.zeros(())

    def b():
        clock.sleep(2 * U)
        return jnp.zeros(())
    t = timing.interleaved_times({"a": a, "b": b, "none": None}, (), repeats=7)
    assert set(t) == {"a", "b"}
    assert t["a"] == pytest.approx(U, rel=1e-9) and t["b"] == pytest.approx(2 * U, rel=1e-9)
    assert calls["a"] >= 2 * 7                 # an untimed call before each timed one


def test_interleaved_times_time_each_call_after_itself(clock):
    """Each timed call follows a call of the same function: a function that is slow only
    right after another one ran (as a real program is, after a different program evicted
    its caches) is timed at its settled speed. Before, the second function of a turn was
    always timed right after the first: here 3x its time."""
    last = {"who": None}

    def make(name):
        def f():
            clock.sleep((3 if last["who"] not in (None, name) else 1) * U)
            last["who"] = name
            return jnp.zeros(())
        return f
    t = timing.interleaved_times({"a": make("a"), "b": make("b")}, (), repeats=7)
    assert t["a"] == pytest.approx(U, rel=1e-9) and t["b"] == pytest.approx(U, rel=1e-9)


def test_settled_time_times_a_call_after_itself(clock):
    """timing.settled_time (the unit of interleaved_times and benchmarks/step_cost.py, whose
    own copy of this logic had no test) times a call right after an untimed call of the same
    function, whatever ran before it."""
    last = {"who": None}

    def make(name):
        def f(x):
            clock.sleep((3 if last["who"] not in (None, name) else 1) * U)
            last["who"] = name
            return x
        return f
    a, b = make("a"), make("b")
    times = []
    for _ in range(5):
        b(0.0)                                   # another program ran just before
        times.append(timing.settled_time(a, (0.0,)))
    # settled: U exactly (the virtual clock); unsettled it would be 3 U
    assert times == pytest.approx([U] * 5, rel=1e-9), times


def test_floor_and_numpy_baselines_compute_the_same_physics():
    spec = bench.CASES["ball_b1"].build(jnp.float64, True)
    z = np.asarray(spec["forward"](*spec["args"]))
    zf = np.asarray(spec["floor"](*spec["args"]))
    zn = spec["numpy"]()
    # the floor has a pointwise hard contact, diffpen the step-averaged one with centred
    # damping: they differ by up to 5.9e-4 m after the impacts (0.6 mm; the forward cost is
    # what is compared)
    np.testing.assert_allclose(zf, z, atol=1e-3)
    np.testing.assert_allclose(zn, zf, rtol=1e-12)
    # the stepping workloads (and the natural user code) end where the recorded ones do
    np.testing.assert_allclose(np.asarray(spec["stepping"](*spec["args"]))[-1, 0, 2], z[-1],
                               rtol=1e-12)
    np.testing.assert_allclose(spec["natural"](*spec["args"]), z[-1], rtol=1e-12)
    np.testing.assert_allclose(spec["floor_stepping"](*spec["args"]), zf[-1], rtol=1e-12)
    net = bench.CASES["cloth32"].build(jnp.float64, True)
    a = net["args"]
    np.testing.assert_allclose(net["floor"](*a), net["forward"](*a), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(net["band_floor"](*a), net["floor"](*a), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(net["numpy"](), net["floor"](*a), rtol=1e-9, atol=1e-12)


def test_the_spring_networks_floor_is_plain():
    """Regression: the spring networks' floor was written in diffpen's own lattice layout
    (diffpen.terms.spring_bands: dense slices added in place), a baseline shaped like the
    code it measures. The floor is now a plain gather per spring and segment_sum per node,
    reading nothing of diffpen's layout; the band-layout form stays as a second reference
    (vs_band_floor). Checked on the traced floor: segment sums, no dynamic_update_slice."""
    net = bench.CASES["cloth32"].build(jnp.float64, True)
    text = str(jax.make_jaxpr(net["floor"])(*net["args"]))
    assert "scatter-add" in text and "dynamic_update_slice" not in text
    band = str(jax.make_jaxpr(net["band_floor"])(*net["args"]))
    assert "dynamic_update_slice" in band


def test_numpy_network_baseline_runs_in_the_cases_dtype():
    """Regression: the spring networks' NumPy baseline summed forces with np.bincount
    (float64) and kept float64 rest lengths, so a float32 case timed float64 NumPy."""
    net = bench.CASES["chain"].build(jnp.float32, True)
    assert net["numpy"]().dtype == np.float32


def test_plain_floor_is_batch_vectorisable_and_matches_its_scalar_runs():
    """The plain floor carries one scalar per component: vmapped, its carry is (B,) arrays
    (no (B, 3) minor axis), and each row equals the row run alone."""
    ks = jnp.asarray([5e3, 1e4, 2e4])
    cs = jnp.asarray([5.0, 20.0, 40.0])
    batched = jax.vmap(lambda k, c: floors.plain_ball_floor(k, c, steps=400))
    jaxpr = jax.make_jaxpr(batched)(ks, cs)
    scan = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == "scan"][0]
    assert all(v.aval.shape == (3,) for v in scan.outvars[:2])    # the carry: z and v
    out = batched(ks, cs)
    for i in range(3):
        np.testing.assert_array_equal(out[i], floors.plain_ball_floor(ks[i], cs[i], steps=400))


def test_bench_help_names_every_case():
    """``diffpen bench --help`` listed 9 of the 11 cases (the columns-layout ones missing)."""
    from tuning.cli.bench import KNOWN_CASES
    from tuning.reports.bench import CASES
    assert sorted(KNOWN_CASES) == sorted(CASES)
