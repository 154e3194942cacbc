"""tuning.lm: Levenberg-Marquardt recovers a known answer, stays in its box, refuses a start
where the residuals are not finite, and the extra stopping test ends it early."""
import numpy as np
import pytest

from tuning.errors import FitError
from tuning.lm import levenberg_marquardt

T = np.linspace(0.0, 4.0, 30)
Y = 2.0 * np.exp(-0.5 * T)            # exact data: a = 2, b = 0.5


def res_and_jac(x):
    a, b = np.asarray(x)
    e = np.exp(-b * T)
    return a * e - Y, np.stack([e, -a * T * e], axis=1)


def test_recovers_the_known_answer():
    out = levenberg_marquardt(res_and_jac, [1.0, 2.0], [0.1, 0.01], [10.0, 5.0], maxiter=100)
    assert out.converged
    np.testing.assert_allclose(out.x, [2.0, 0.5], rtol=1e-8)
    assert out.cost_history[-1] < 1e-16 and out.cost_history[0] > out.cost_history[-1]
    assert out.iterations < 30


def test_box_is_respected_and_stop_test_ends_early():
    out = levenberg_marquardt(res_and_jac, [1.0, 0.2], [0.1, 0.01], [10.0, 0.4], maxiter=100)
    assert out.x[1] == 0.4 and out.x[0] <= 10.0      # b held at its upper bound
    early = levenberg_marquardt(res_and_jac, [1.0, 2.0], [0.1, 0.01], [10.0, 5.0],
                                maxiter=100, stop=lambda r: float(r @ r) < 1e-2)
    assert early.message == "targets reached" and early.converged
    assert float(early.residuals @ early.residuals) < 1e-2 and early.cost_history[-1] < 1e-2


def test_non_finite_start_is_refused():
    with pytest.raises(FitError, match="not finite at the start"):
        levenberg_marquardt(lambda x: (np.full(3, np.nan), np.zeros((3, 2))), [1.0, 1.0],
                            [0.1, 0.1], [10.0, 10.0])


def _weak(eps, b_max=3.0):
    """r = a - 2 + eps b: b barely matters, and past b_max the residual is not finite (as a
    contact past its bounds)."""
    def res_and_jac(x):
        a, b = np.asarray(x)
        r = np.array([a - 2.0 + eps * b])
        return (r if b <= b_max else r * np.nan), np.array([[1.0, eps]])
    return res_and_jac


def _reached(r):
    return bool(np.all(np.abs(r) <= 1e-6))


def test_a_parameter_the_residuals_barely_depend_on_does_not_stall():
    """Regression: Marquardt's scaling diag(J^T J) was used as it was (only exact zeros
    floored), so the step in b was the one b would need alone (1e8 here): every trial left
    the finite region and LM stopped at its start as a "local minimum". The scaling is now
    floored at SCALE_FLOOR x its largest entry."""
    out = levenberg_marquardt(_weak(1e-8), [1.0, 1.0], [0.1, 0.1], [10.0, 10.0], maxiter=20,
                              stop=_reached)
    assert out.message == "targets reached" and out.iterations <= 3
    assert out.x[0] == pytest.approx(2.0, abs=1e-5)


def test_max_step_limits_each_parameter_of_a_trial_step():
    """A weak parameter just above the scaling floor still gets a step 100x the others';
    max_step cuts it (entry by entry, halving after a rejected trial it cut) so the others
    can move."""
    seen = []

    def rj(x):
        seen.append(np.asarray(x, float))
        return _weak(1e-4)(x)
    out = levenberg_marquardt(rj, [1.0, 1.0], [0.1, 0.1], [10.0, 10.0], maxiter=20,
                              stop=_reached, max_step=0.5)
    assert out.message == "targets reached" and out.iterations <= 5
    assert out.x[1] <= 3.0
    # every trial point lies within 0.5 of a point evaluated before it (the current one)
    for i in range(1, len(seen)):
        assert min(np.max(np.abs(seen[i] - x)) for x in seen[:i]) <= 0.5 + 1e-12


class _Bar:
    def __init__(self):
        self.counts = []

    def update(self, i, value=None):
        self.counts.append(i)


def test_progress_ends_at_the_iterations_run():
    """Regression: an iteration that found no decrease counted in ``iterations`` and in
    the history but not on the progress bar (a fit's bar ended one short)."""
    def res_and_jac(x):       # least squares minimum 2 at a = 0: ends without decrease
        a = float(np.asarray(x)[0])
        return np.array([a - 1.0, a + 1.0]), np.ones((2, 1))
    bar = _Bar()
    out = levenberg_marquardt(res_and_jac, [5.0], [-10.0], [10.0], maxiter=50, xtol=0.0,
                              ftol=0.0, progress=bar, offset=7)
    assert out.message == "no further decrease (local minimum)"
    assert bar.counts[-1] == 7 + out.iterations
    assert len(out.cost_history) == out.iterations + 1


def test_the_cost_tolerance_follows_the_residuals_precision():
    """Regression: ftol = 1e-12 is far below float32's resolution of a relative cost change
    (~1e-7), so a float32 fit went on past a decrease of 2.5e-7 and ended with 12 trial
    rollouts that rounding could not tell apart ("no further decrease"). The tolerance is
    now max(ftol, FTOL_EPS x eps of the residuals' dtype); float64 keeps 1e-12."""
    from tuning.lm import FTOL_EPS, precision_ftol
    assert precision_ftol(1e-12, np.float64) == 1e-12
    assert precision_ftol(1e-12, np.float32) == pytest.approx(FTOL_EPS * 1.1920929e-7)
    assert precision_ftol(1e-3, np.float32) == 1e-3

    def problem(dtype, calls):
        def rj(x):          # cost (x - 1)^2 + 1e6: the fit moves it by 2.5e-7 relative
            calls.append(1)
            x = np.asarray(x, dtype)
            return np.array([x[0] - 1.0, 1000.0], dtype), np.array([[1.0], [0.0]], dtype)
        return rj
    calls = []
    out = levenberg_marquardt(problem(np.float32, calls), [1.5], [0.0], [3.0])
    assert out.message == "step below tolerance" and out.iterations == 1 and len(calls) == 2
    calls = []
    out = levenberg_marquardt(problem(np.float64, calls), [1.5], [0.0], [3.0])
    assert out.message == "step below tolerance" and out.iterations == 2
    assert out.x[0] == pytest.approx(1.0, abs=1e-6)


def test_a_float32_record_fit_warns_to_enable_float64(ball_scene):
    """A cube record fit in float32 stopped 15% above the float64 cost (noisy float32
    Jacobians) with nothing said; a record fit in float32 now warns and names the switch."""
    import warnings

    import jax.numpy as jnp

    import diffpen as dp
    from tuning.trajfit import fit_records
    sim = dp.compile(ball_scene, 1e-3, dtype=jnp.float32)
    with pytest.warns(UserWarning, match=r"less reliable in float32.*jax_enable_x64"), \
            pytest.raises(FitError, match="nothing to fit"):
        fit_records(sim, sim.params(k=1e4, c=20.0), None, [])
    sim64 = dp.compile(ball_scene, 1e-3, dtype=jnp.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(FitError, match="nothing to fit"):
            fit_records(sim64, sim64.params(k=1e4, c=20.0), None, [])
