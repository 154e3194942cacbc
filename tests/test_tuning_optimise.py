"""tuning.optimise: the optax loop run from the host (fit) and inside a while_loop (batch)
follow the same rule: a row never stops at, nor reports, a point past the safe step while a
stable one exists."""
import numpy as np
import optax
import pytest

import diffpen as dp
from diffpen.state import ContactParams
from tuning import fit as F
from tuning.batch_fit import fit_batch
from tuning.optimise import LIMIT, MESSAGES

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
    assert int(row.status[0]) == LIMIT and row.messages[0] == MESSAGES[LIMIT]
    assert not row.converged[0] and not row.reached[0]
    assert int(row.iterations[0]) == single.iterations
    assert row.values[0, 0] == pytest.approx(single.values[FREE[0]], rel=1e-10)
    np.testing.assert_allclose(row.loss_history[0], single.loss_history, rtol=1e-10)
