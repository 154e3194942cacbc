"""Gradients through contact events against the continuous system: an event-located DOP853
reference (tuning.reports.reference), derivatives by central differences of it."""
import functools

import jax
import numpy as np
import pytest

from tuning.reports.gradient_check import (EVENT_CASES, EVENT_METRICS, event_metrics_fn,
                                           event_reference)

pytest.importorskip("scipy")

QUICK = EVENT_CASES[0]._replace(T=2.2)       # quick-start ball, three bounces
HEAVY = EVENT_CASES[2]._replace(T=2.2)       # 2 kg ball, no_tension, k 5e4, c 60
#: relative steps of the landscape's central differences, each with its tolerance
LANDSCAPE_STEPS = ((1e-2, 0.15), (1e-4, 1e-3), (1e-6, 1e-3))

#: the continuous reference of a case, computed once per module (a DOP853 solve per case)
reference = functools.lru_cache(maxsize=None)(event_reference)


@pytest.fixture(scope="module", params=[QUICK, HEAVY], ids=["linear", "no_tension"])
def at_default_dt(request):
    """The case, its jax derivatives at (k, c), the metrics at k +- s k and at c +- s c for
    each landscape step s (``{s: (f(k + h), f(k - h), f(c + h), f(c - h))}``), and the
    continuous reference. One compiled program gives the derivatives and, beside them, the
    values at every point."""
    case = request.param
    f, _ = event_metrics_fn(case, 1e-3)
    jac = jax.jit(jax.jacfwd(lambda k, c: (lambda y: (y, y))(f(k, c)), (0, 1), has_aux=True))

    def value(k, c):
        return np.asarray(jac(k, c)[1])
    k, c = case.k, case.c
    landscape = {s: (value(k + s * k, c), value(k - s * k, c),
                     value(k, c + s * c), value(k, c - s * c)) for s, _ in LANDSCAPE_STEPS}
    derivs, at = jac(k, c)
    return case, landscape, [np.asarray(a) for a in derivs], reference(case), np.asarray(at)


def _err(got, want):
    return np.abs(got - want) / np.abs(want)


def test_event_gradients_match_the_continuous_derivative_at_the_default_dt(at_default_dt):
    """dt = 1e-3, default smoothing, the law as named (centred damping on this one-contact
    ball): d apex1 / dk, dc within 2.5%, d duration / dk and d penetration / dk within 2.5%
    (6% for no_tension's durations) of the continuous derivative, every apex derivative of
    the right sign (before, d apex1 / dk had the wrong sign: -1.01e-5 against +1.61e-5 on
    the quick-start ball). The derivatives of apexes 2-3 ripple with where the impacts fall
    in the step (docs/gradients.txt, "Impact phase in the step": up to 11% / 13% over six
    phases with either damping), so they are held to 15% here (measured at this phase: the
    quick-start ball 2.9% / 6.3% on dk; the plain average was 2.2% / 0.1% at this phase
    and up to 9.4% over phases)."""
    case, _, (dk, dc), ref, _ = at_default_dt
    idx = {m: i for i, m in enumerate(EVENT_METRICS)}
    apex = [idx["apex1"], idx["apex2"], idx["apex3"]]
    dur = [idx["duration1"], idx["duration2"], idx["duration3"]]
    assert _err(dk[0], ref["dk"][0]) < 0.025 and _err(dc[0], ref["dc"][0]) < 0.025
    assert np.all(_err(dk[apex], ref["dk"][apex]) < 0.15)
    assert np.all(_err(dc[apex], ref["dc"][apex]) < 0.15)
    assert np.all(_err(dk[dur], ref["dk"][dur]) < (0.025 if case.law == "linear" else 0.06))
    i = idx["penetration"]
    assert _err(dk[i], ref["dk"][i]) < 0.01 and _err(dc[i], ref["dc"][i]) < 0.07
    assert np.all(np.sign(dk[apex]) == np.sign(ref["dk"][apex]))


def test_a_named_law_on_one_contact_gives_apexes_within_half_a_percent(at_default_dt):
    """Regression: ``dp.compile(ball, 1e-3)`` with the law named (the default "linear", or
    "no_tension") took the plain step average, whose damper acts on semi-implicit Euler's
    half-step-old velocity: apexes 1-3 of the quick-start ball -0.29/-0.59/-0.91% and of the
    2 kg no_tension ball -0.35/-0.70/-1.05% off the continuous ones at dt 1e-3. On a scene
    of one contact a named law now takes the centred damping (exact there): within 0.5%
    (measured +0.03/+0.05/+0.06% and +0.03/+0.07/+0.09%), and so are the durations."""
    case, _, _, ref, value = at_default_dt
    assert np.all(_err(value[:3], ref["value"][:3]) < 0.005), value[:3] / ref["value"][:3]
    assert np.all(_err(value[3:6], ref["value"][3:6]) < 0.005)


@pytest.mark.parametrize("case", [QUICK, HEAVY], ids=["linear", "no_tension"])
def test_centred_damping_values_within_half_a_percent(case):
    """Laws with the damping at the step window's centre speed (``linear(centred=True)``,
    ``no_tension(centred=True)``), dt = 1e-3: apex heights 1-3 within 0.5% of the continuous
    ones (measured +0.03/+0.08/+0.13% and +0.05/+0.10/+0.16%; the default records
    -0.29/-0.59/-0.91% and -0.35/-0.70/-1.05%), d duration1 / dc within 2% (measured 0.4%
    and 1.3%; default 37% and 76%), d penetration / dc within 0.5% (0.1%, 0.3%; default 3.8%
    and 6.0%), d apex1 / dk, dc within 1%."""
    f, _ = event_metrics_fn(case, 1e-3, centred=True)
    # the values come with the derivatives, from one compiled program
    (dk, dc), val = jax.tree_util.tree_map(np.asarray, jax.jit(jax.jacfwd(
        lambda k, c: (lambda y: (y, y))(f(k, c)), (0, 1), has_aux=True))(case.k, case.c))
    ref = reference(case)
    idx = {m: i for i, m in enumerate(EVENT_METRICS)}
    assert np.all(_err(val[:3], ref["value"][:3]) < 0.005)
    assert _err(dc[idx["duration1"]], ref["dc"][idx["duration1"]]) < 0.02
    assert _err(dc[idx["penetration"]], ref["dc"][idx["penetration"]]) < 0.005
    assert _err(dk[0], ref["dk"][0]) < 0.01 and _err(dc[0], ref["dc"][0]) < 0.01


def _record_derivatives(case, law, fd_steps=()):
    """Values and derivatives w.r.t. k and c of ``case``'s apexes 1-3 and contact durations
    1-3 with the contact record ``law`` at dt = 1e-3 (float64, :func:`event_metrics_fn`);
    with ``fd_steps``, also ``{step: (fk, fc)}``, their central differences at those relative
    steps of k and c (the values the same compiled program gives: nothing more compiles)."""
    f, _ = event_metrics_fn(case, 1e-3, record=law)
    jac = jax.jit(jax.jacfwd(lambda k, c: (lambda y: (y, y))(f(k, c)), (0, 1), has_aux=True))
    (dk, dc), val = jax.tree_util.tree_map(np.asarray, jac(case.k, case.c))

    def value(k, c):
        return np.asarray(jac(k, c)[1])[:6]
    fd = {s: ((value(case.k * (1 + s), case.c) - value(case.k * (1 - s), case.c))
              / (2 * s * case.k),
              (value(case.k, case.c * (1 + s)) - value(case.k, case.c * (1 - s)))
              / (2 * s * case.c)) for s in fd_steps}
    return (val[:6], dk[:6], dc[:6]) + ((fd,) if fd_steps else ())


def test_exact_record_derivatives_match_the_continuous_ones():
    """``linear(exact=True)`` on the quick-start ball at dt = 1e-3: d apex1 / dk, dc and d
    duration / dk, dc of contacts 1-3 within 2% of the continuous system's (the event-located
    reference; measured <= 0.8% on apex 1, <= 0.2% on the durations except d duration2-3 /
    dc, up to 6.7% over impact phases), contact durations within 0.01% (the centred record
    0.04% short)."""
    from diffpen import laws
    case = QUICK
    val, dk, dc = _record_derivatives(case, laws.linear(exact=True))
    ref = reference(case)
    assert _err(dk[0], ref["dk"][0]) < 0.02 and _err(dc[0], ref["dc"][0]) < 0.02
    assert np.all(_err(dk[3:6], ref["dk"][3:6]) < 0.02)
    assert _err(dc[3], ref["dc"][3]) < 0.02
    assert np.all(_err(val[3:6], ref["value"][3:6]) < 1e-4)


def test_the_landscape_has_no_jumps(at_default_dt):
    """The library's own central differences of the apexes agree with its jax derivative
    within 0.1% at relative steps 1e-4 ... 1e-6, and within 15% at 1e-2 (measured: <= 6%;
    what is left there is the smooth ripple of the apex 2-3 derivatives with the contact's
    phase in the step, up to 11-13% over phases, which +-1% of k averages out). Before, the
    apexes jumped every ~0.1% of k."""
    case, landscape, (dk, dc), _, _ = at_default_dt
    for s, tol in LANDSCAPE_STEPS:
        hk, hc = s * case.k, s * case.c
        k_up, k_down, c_up, c_down = landscape[s]
        fk = (k_up - k_down) / (2 * hk)
        fc = (c_up - c_down) / (2 * hc)
        assert np.all(_err(fk[:3], dk[:3]) <= tol), s
        assert np.all(_err(fc[:3], dc[:3]) <= tol), s


def test_gradient_converges_to_the_continuous_one():
    """Hertz ball (hunt_crossley n = 1.5): at dt = 2.5e-4 the derivatives of the first two
    apexes are within 0.2% of the continuous ones (measured 0.06-0.1%; 1-7% at 1e-3)."""
    case = EVENT_CASES[3]._replace(T=2.0)
    f, _ = event_metrics_fn(case, 2.5e-4)
    dk, dc = (np.asarray(a) for a in jax.jit(jax.jacfwd(f, (0, 1)))(case.k, case.c))
    ref = reference(case)
    assert np.all(_err(dk[:2], ref["dk"][:2]) < 2e-3)
    assert np.all(_err(dc[:2], ref["dc"][:2]) < 2e-3)
    # reverse mode too (it was NaN for a fractional exponent: the window's masked branch)
    rk, rc = (np.asarray(a) for a in jax.jit(jax.jacrev(f, (0, 1)))(case.k, case.c))
    assert np.all(_err(rk[:2], ref["dk"][:2]) < 2e-3)
    assert np.all(_err(rc[:2], ref["dc"][:2]) < 2e-3)


def test_hertz_ball_apexes_within_half_a_percent_at_the_default_dt():
    """Regression: the Hertz ball (hunt_crossley n = 1.5, k 1e6, c 3e4; named, so centred on
    this one contact) at dt = 1e-3 lost apex height at every bounce: -0.74 / -1.36 / -1.90%
    off the continuous apexes, and -0.42 / -0.83 / -1.24% undamped (c = 0, where the
    continuous ball keeps its height), because the window's mean of d^1.5 was taken along
    the path through the lagging speed and the damper's speed was held constant inside the
    window. Now within 0.5% (measured +0.02 / +0.04 / +0.05%), 0.05% undamped (measured
    0.00 / -0.01 / -0.00%), and d apex1 / dk, dc within 2% (measured 0.02% and 0.15%)."""
    case = EVENT_CASES[3]._replace(T=2.8)
    f, _ = event_metrics_fn(case, 1e-3)
    jac = jax.jit(jax.jacfwd(lambda k, c: (lambda y: (y, y))(f(k, c)), (0, 1), has_aux=True))
    (dk, dc), val = jax.tree_util.tree_map(np.asarray, jac(case.k, case.c))
    ref = reference(case)
    assert np.all(_err(val[:3], ref["value"][:3]) < 5e-3), val[:3] / ref["value"][:3] - 1
    assert _err(dk[0], ref["dk"][0]) < 0.02 and _err(dc[0], ref["dc"][0]) < 0.02
    undamped = case._replace(c=0.0)
    _, val0 = jax.tree_util.tree_map(np.asarray, jac(undamped.k, 0.0))
    ref0 = reference(undamped)["value"]
    assert np.all(_err(val0[:3], ref0[:3]) < 5e-4), val0[:3] / ref0[:3] - 1


def _band_settling(c, k=1e4, tol=1e-3, T=3.5):
    """Continuous settling time (last exit from |z - rest| <= tol) of the quick-start ball."""
    from scipy.optimize import brentq
    from tuning.reports.reference import ball_reference
    ref = ball_reference(k=k, c=c, m=1.0, r=0.1, z0=1.0, T=T)
    rest = 0.1 - 9.81 / k
    t = np.linspace(0.0, T, 70001)
    z, _ = ref.state(t)
    i = np.flatnonzero(np.abs(z - rest) > tol)[-1]
    return brentq(lambda s: abs(ref.state([s])[0][0] - rest) - tol, t[i], t[i + 1],
                  xtol=1e-14)


def test_settling_time_derivative_is_the_continuous_one():
    """Band-exit settling time (tol 1 mm) of the quick-start ball at dt = 1e-4: d/dc within
    2% of the continuous derivative (measured -0.1120 against -0.1106; before -180)."""
    import jax.numpy as jnp

    import diffpen as dp
    from tuning.metrics import ball_metrics
    from tuning.scenes import ball
    sim = dp.compile(ball().scene, 1e-4, dtype=jnp.float64)

    def settle(c):
        p = sim.params(k=1e4, c=c)
        return ball_metrics(sim, sim.rollout(p, 35000, save_every=2), p).settling_time
    g = float(jax.jit(jax.grad(settle))(20.0))
    want = (_band_settling(20.0 + 2e-3) - _band_settling(20.0 - 2e-3)) / 4e-3
    assert abs(g - want) <= 0.02 * abs(want)


def test_lm_fit_from_the_generic_start_without_the_scan():
    """fit_bounce with method="lm" from k = 1e4, c = 20 (first_guess=False: no scan or
    bisection start) reaches the continuous first apex and contact time of the ball at
    k = 2.2e3, c = 11 (measured: 4 iterations; before 25)."""
    from tuning.bounce import fit_bounce
    from tuning.reports.reference import ball_reference
    from tuning.scenes import ball
    ref = ball_reference(k=2.2e3, c=11.0, m=1.0, r=0.1, z0=1.0, T=1.5)
    targets = {"apex_heights": [ref.apexes[0] - 0.1],
               "contact_durations": [ref.contacts[0][1] - ref.contacts[0][0]]}
    res = fit_bounce(ball().scene, targets, dt=1e-3, k0=1e4, c0=20.0, first_guess=False,
                     method="lm", maxiter=10)
    assert res.reached and res.iterations <= 6
    assert res.values["contact.default.k"] == pytest.approx(2.2e3, rel=0.02)
    assert res.values["contact.default.c"] == pytest.approx(11.0, rel=0.02)


@pytest.mark.parametrize("case, tol", [(EVENT_CASES[1]._replace(T=2.2), 5e-4), (HEAVY, 5e-4),
                                       (EVENT_CASES[3]._replace(T=2.5), 5e-3)],
                         ids=["linear", "no_tension", "hertz"])
def test_event_exact_record_derivatives_equal_the_continuous_ones(case, tol):
    """``events=True`` (diffpen.event_step) on the 0.3 kg ball (linear, k 3e4, c 15, w h
    0.32: about ten steps per contact), the 2 kg no_tension ball (k 5e4, c 60) and the Hertz
    ball (hunt_crossley n 1.5, k 1e6, c 3e4) at dt = 1e-3: apexes 1-3 and contact durations
    1-3, their values and their derivatives w.r.t. k and c within 0.05% of the continuous
    system's, 0.5% for the Hertz ball, whose contact motion is a Runge-Kutta flow (measured:
    linear and no_tension under 2e-6 at six impact phases; at this phase the exact record is
    37% off on d apex 3 / dc and 52% on d duration 2 / dc; over eight phases the exact record
    up to 87% and 246%, the centred record 161% and 573%; no_tension: under 2e-6, the exact
    record up to 8.8% on d duration 3 / dc at this phase; Hertz: up to 0.16% over six phases,
    the centred record up to 3% and 6%). Their own central differences at relative steps 1e-2
    and 1e-3 of k and c agree with their derivatives within 2% (issue 12's item 4, which the
    default record does not meet there: up to 7% on the quick-start ball's apexes, 52% on the
    0.3 kg ball's; measured with these records: <= 0.1%)."""
    from diffpen import laws
    val, dk, dc, fd = _record_derivatives(case, laws.get(case.law, case.exponent, events=True),
                                          fd_steps=(1e-2, 1e-3))
    ref = reference(case)
    assert np.all(_err(val, ref["value"][:6]) < tol), val / ref["value"][:6] - 1
    assert np.all(_err(dk, ref["dk"][:6]) < tol), dk / ref["dk"][:6] - 1
    assert np.all(_err(dc, ref["dc"][:6]) < tol), dc / ref["dc"][:6] - 1
    for s, (fk, fc) in fd.items():
        assert np.all(_err(fk, dk) < 0.02) and np.all(_err(fc, dc) < 0.02), (s, fk / dk - 1,
                                                                             fc / dc - 1)


def test_gradient_report_rows_of_the_event_exact_records_beside_the_default():
    """``event_gradient_rows(..., events=True)`` (what `diffpen report gradients` prints
    beside the default record's rows, as "before") takes each case's event-exact record: on
    the 0.3 kg ball's first bounce d apex1 / dk is within 1e-4 of the continuous derivative
    (the default record: 5.8% off at this phase), and the table puts both side by side."""
    from tuning.reports.gradient_check import event_gradient_rows, event_gradient_table
    case = EVENT_CASES[1]._replace(T=0.9)
    after = event_gradient_rows([case], events=True)
    before = event_gradient_rows([case])

    def apex1_dk(rows):
        return next(r for r in rows if r["metric"] == "apex1" and r["param"] == "k")
    assert apex1_dk(after)["rel_error"] < 1e-4
    assert apex1_dk(before)["rel_error"] > 0.02
    table = event_gradient_table(after, before=before)
    assert "before: d/dk" in table and table.count("0.3 kg ball") == len(EVENT_METRICS)
