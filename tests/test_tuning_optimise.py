"""tuning.optimise: the optax loop run from the host (fit) and inside a while_loop (batch)
follow the same rule: a row never stops at, nor reports, a point past the safe step while a
stable one exists, nor stops at a settling time that is only the rollout's end; a row's
reached, converged and message are the single fit's."""
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import diffpen as dp
from diffpen.state import ContactParams
from tuning import fit as F
from tuning.batch_fit import fit_batch
from tuning.optimise import LIMIT

PARAMS0 = dp.Params({"default": ContactParams(np.float64(1.0), np.float64(2.0))}, {}, {})
FREE = ["contact.default.k"]


def mfn(p):
    k = p.contact["default"].k
    return {"stiffness": k, "unstable": k > 2.0}       # the target 3 lies past the safe step


def test_batch_row_follows_the_fit_rule_past_the_safe_step():
    """Regression: a batch row ignored the flag: it reported its lowest-loss point although
    that point was past the safe step (k = 2.94 here), where the single fit reports the best
    stable point; a row could also stop there as converged."""
    opts = dict(free=FREE, optimizer=optax.adam(0.2), maxiter=25, rtol=1e-2)
    single = F.fit(mfn, PARAMS0, {"stiffness": 3.0}, method="optax", progress=False, **opts)
    assert not single.converged and single.iterations == 25
    assert single.values[FREE[0]] <= 2.0 and not single.reached
    row = fit_batch(mfn, PARAMS0, [{"stiffness": 3.0}], **opts)
    assert int(row.status[0]) == LIMIT and row.messages[0] == single.message
    assert not row.converged[0] and not row.reached[0]
    assert int(row.iterations[0]) == single.iterations
    assert row.values[0, 0] == pytest.approx(single.values[FREE[0]], rel=1e-10)
    np.testing.assert_allclose(row.loss_history[0], single.loss_history, rtol=1e-10)


def settling_mfn(p):
    """A 1 s rollout: the motion settles at 2 / c s, or its settling time is the rollout's
    end (1 s) with ``settled`` False."""
    t = 2.0 / p.contact["default"].c
    return {"settling_time": jnp.minimum(t, 1.0), "settled": t < 1.0}


def _same_as_single(row, i, single):
    assert bool(row.reached[i]) == single.reached
    assert bool(row.converged[i]) == single.converged
    assert row.messages[i] == single.message
    assert int(row.iterations[i]) == single.iterations
    assert row.values[i, 0] == pytest.approx(next(iter(single.values.values())), rel=1e-10)


def test_batch_row_that_never_settled_is_not_reached_as_in_the_single_fit():
    """Regression: a row whose motion never settled (settling_time = the rollout's end, 1 s,
    within 1e-3 of the target 0.9995 s) stopped as converged and was reported reached; the
    single fit of that row said "targets NOT reached (targets reached)"."""
    free = ["contact.default.c"]
    rows, starts = [{"settling_time": 0.5}, {"settling_time": 0.9995}], [3.0, 1.5]
    opts = dict(free=free, optimizer=optax.adam(0.01), maxiter=60, rtol=1e-3)
    res = fit_batch(settling_mfn, PARAMS0, rows, [{free[0]: c} for c in starts], **opts)
    for i, (tg, c) in enumerate(zip(rows, starts)):
        p0 = dp.Params({"default": ContactParams(np.float64(1.0), np.float64(c))}, {}, {})
        single = F.fit(settling_mfn, p0, tg, method="optax", progress=False, **opts)
        _same_as_single(res, i, single)
    assert res.reached[0] and res.converged[0]       # settled at 0.5 s: c = 4
    assert not res.reached[1] and not res.converged[1]
    assert int(res.status[1]) == LIMIT and res.rel_error["settling_time"][1] == np.inf
    assert "has not settled within the rollout" in res.messages[1]
    assert "(targets reached)" not in res.messages[1]


def test_batch_row_past_the_safe_step_everywhere_is_not_reached():
    """Regression: a row whose every point lay past the safe step (k = 3 meets its target
    there) was reported reached: the batch tested the targets without the "unstable" flag;
    the single fit of that row says NOT reached (past its safe step)."""
    opts = dict(free=FREE, optimizer=optax.adam(0.2), maxiter=5, rtol=1e-2)
    p0 = dp.Params({"default": ContactParams(np.float64(3.0), np.float64(2.0))}, {}, {})
    single = F.fit(mfn, p0, {"stiffness": 3.0}, method="optax", progress=False, **opts)
    row = fit_batch(mfn, p0, [{"stiffness": 3.0}], **opts)
    _same_as_single(row, 0, single)
    assert not row.reached[0] and not row.converged[0]
    assert "past its safe step" in row.messages[0]
