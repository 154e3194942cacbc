"""tuning.problem: targets -> residual layout and residuals (by hand), the achieved values
and the reached test, bounds (the safe step from diffpen.stability), the fitted leaves and
their checks, all before anything is traced."""
import math

import numpy as np
import pytest

import diffpen as dp
from diffpen.state import ContactParams, SpringParams
from tuning import problem as PB
from tuning.errors import FitError
from tuning.stable import safe_contact_limits

PARAMS0 = dp.Params({"rubber": ContactParams(np.float64(1e4), np.float64(10.0))},
                    {"rope": SpringParams(np.float64(50.0), np.float64(0.5))},
                    {"drag": {"rope": np.float64(0.2)}})


def test_target_layout_residuals_and_achieved_by_hand():
    tg = PB.normalise_targets({"a": [2.0, 4.0], "b": 0.5})
    spec = PB.target_spec(tg, {"a": 4.0}, {"a": 1e-2})
    assert spec == (("a", 2, 4.0, 1e-2), ("b", 1, 1.0, 1e-3))
    assert spec[0].name == "a" and spec[1].rtol == 1e-3
    np.testing.assert_allclose(PB.tolerances(spec), [0.02, 0.02, 1e-3], rtol=1e-15)
    assert PB.target_slices(spec) == {"a": slice(0, 2), "b": slice(2, 3)}
    metrics = {"a": np.array([3.0, np.nan, 9.0]), "b": np.float64(0.25)}
    # sqrt(4) (3 - 2) / 2, an absent event counts as sqrt(4) ABSENT_ERROR, (0.25 - 0.5) / 0.5
    np.testing.assert_allclose(PB.residuals(metrics, tg, spec),
                               [1.0, 2.0 * PB.ABSENT_ERROR, -0.5], rtol=1e-15)
    ach, rel, ok = PB.achieved(metrics, tg, spec)
    assert ach["b"] == 0.25 and ach["a"][0] == 3.0 and math.isnan(ach["a"][1])
    assert rel == {"a": math.inf, "b": 0.5} and not ok
    close = {"a": np.array([2.01, 4.0]), "b": 0.5}
    assert PB.achieved(close, tg, spec)[2]


def test_an_absent_event_never_scores_below_a_present_one():
    """An absent event (nan: no rebound) counted as a value of 0, a residual of -1: a point
    without a rebound scored below one whose apex was 2x its target or more, and it has no
    gradient either, so fits stopped there and reported nan. It now costs more than any
    present value a fit would keep, with no gradient of its own."""
    import jax
    import jax.numpy as jnp
    tg = PB.normalise_targets({"apex_heights": [0.01], "contact_durations": [0.08]})
    spec = PB.target_spec(tg, None, 1e-3)

    def cost(apex, dur):
        r = PB.residuals({"apex_heights": jnp.atleast_1d(apex),
                          "contact_durations": jnp.atleast_1d(dur)}, tg, spec)
        return float(r @ r)
    absent = cost(np.nan, np.nan)
    assert absent > cost(0.9, 0.5) > cost(0.03, 0.1) > 0.0      # even far off: 90x, 6x
    assert absent == pytest.approx(2 * PB.ABSENT_ERROR ** 2)
    g = jax.jacfwd(lambda a: PB.residuals({"apex_heights": a, "contact_durations": a}, tg,
                                          spec))(jnp.array([jnp.nan]))
    np.testing.assert_array_equal(g, 0.0)      # finite: no nan leaks into the Jacobian


def test_fit_is_not_reached_when_the_rollout_was_unstable():
    spec = (PB.TargetSpec("apex_heights", 1, 1.0, 1e-3),)
    tg = {"apex_heights": np.array([0.4])}
    assert PB.achieved({"apex_heights": np.array([0.4])}, tg, spec)[2]
    assert not PB.achieved({"apex_heights": np.array([0.4]), "unstable": np.array(True)}, tg,
                           spec)[2]


@pytest.mark.parametrize("call, words", [
    (lambda: PB.normalise_targets({}), "no targets"),
    (lambda: PB.normalise_targets({"a": []}), "empty"),
    (lambda: PB.normalise_targets({"a": [1.0, math.inf]}), "finite"),
    (lambda: PB.normalise_targets({"a": [0.0]}), "zero entry"),
    (lambda: PB.target_spec({"a": np.ones(1)}, {"a": 0.0}, 1e-3), "weight"),
    (lambda: PB.residuals({"b": 1.0}, {"a": np.ones(1)}, (("a", 1, 1.0, 1e-3),)),
     "not a metric"),
    (lambda: PB.residuals({"a": np.ones(1)}, {"a": np.ones(2)}, (("a", 2, 1.0, 1e-3),)),
     "only 1"),
])
def test_bad_targets_say_what_to_change(call, words):
    with pytest.raises(FitError, match=words):
        call()


def test_default_bounds_and_the_safe_step():
    assert PB.default_bounds("contact.x.k", 5.0) == (1e-2, 1e9)
    assert PB.default_bounds("springs.x.c", 5.0) == (1e-6, 1e6)
    assert PB.default_bounds("extra.drag.x", 5.0) == (5e-4, 5e4)
    # with dt and mass: capped at the safe explicit step of diffpen.stability
    k_max, c_max = safe_contact_limits(1e-3, 0.5)
    assert PB.default_bounds("contact.x.k", 5.0, dt=1e-3, mass=0.5) == (1e-2, k_max)
    assert PB.default_bounds("contact.x.c", 5.0, dt=1e-3, mass=0.5) == (1e-6, c_max)
    assert math.sqrt(k_max / 0.5) * 1e-3 < dp.stability.SAFE_WH
    assert c_max * 1e-3 / 0.5 < dp.stability.SAFE_CH


def test_free_leaves_check_and_map_log_values_to_params():
    leaves = PB.FreeLeaves.build(PARAMS0, None, {"contact.rubber.c": (1.0, 100.0)})
    assert leaves.free == ("contact.rubber.k", "contact.rubber.c")
    np.testing.assert_array_equal(leaves.lo, [1e-2, 1.0])
    np.testing.assert_array_equal(leaves.hi, [1e9, 100.0])
    p = leaves.params_of(np.log([3e4, 20.0]))
    assert float(p.contact["rubber"].c) == pytest.approx(20.0, rel=1e-14)
    assert float(p.contact["rubber"].k) == pytest.approx(3e4, rel=1e-14)
    assert p.springs == PARAMS0.springs and p.extra == PARAMS0.extra
    np.testing.assert_array_equal(leaves.start_values([{"contact.rubber.c": 500.0}, {}]),
                                  [[1e4, 100.0], [1e4, 10.0]])
    with pytest.raises(FitError, match="not fitted"):
        leaves.start_values([{"springs.rope.k": 1.0}])
    with pytest.raises(FitError, match="finite and > 0"):
        leaves.start_values([{"contact.rubber.k": -1.0}])
    for kw, words in [({"free": ["contact.steel.k"]}, "unknown parameter"),
                      ({"free": []}, "nothing to fit"),
                      ({"bounds": {"springs.steel.k": (1.0, 2.0)}}, "unknown parameter"),
                      ({"bounds": {"contact.rubber.k": (2.0, 1.0)}}, "0 < lo < hi")]:
        with pytest.raises(FitError, match=words):
            PB.FreeLeaves.build(PARAMS0, kw.get("free"), kw.get("bounds"))


def test_problem_clips_the_start_and_keeps_the_target_form():
    def mfn(p):
        return {"k": p.contact["rubber"].k, "pair": np.array([1.0, 2.0])}
    pb = PB.Problem.build(mfn, PARAMS0, {"k": 2e4, "pair": [1.0, 4.0]},
                          free=["contact.rubber.k"], bounds={"contact.rubber.k": (2e4, 1e5)})
    np.testing.assert_array_equal(pb.x0, [2e4])
    assert pb.target_values() == {"k": 2e4, "pair": [1.0, 4.0]}
    r, m = pb.evaluate(pb.theta0)
    np.testing.assert_allclose(r, [0.0, 0.0, -0.5], atol=1e-12)
    assert len(pb.start_points([{"contact.rubber.k": 5e4}])) == 2
    with pytest.raises(FitError, match="not fitted"):
        pb.start_points([{"contact.rubber.c": 5.0}])
    with pytest.raises(FitError, match="finite and > 0"):      # was clipped to lo silently
        pb.start_points([{"contact.rubber.k": -5.0}])
    zero = dp.Params({"rubber": ContactParams(np.float64(1e4), np.float64(0.0))}, {}, {})
    with pytest.raises(FitError, match="positive start"):
        PB.Problem.build(mfn, zero, {"k": 1.0})
