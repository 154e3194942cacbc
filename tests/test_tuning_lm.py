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
