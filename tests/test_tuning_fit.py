"""tuning.fit.fit: both methods reach an apex target, the loop compiles once, frozen
parameters stay put, bad arguments are refused, the safe step bounds the fit and a point past
it is never reached. (The bounce problem itself: test_tuning_bounce.py.)"""
import io
import logging
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import diffpen as dp
from diffpen.state import ContactParams
from tuning import bounce as B
from tuning import fit as F


def ball_scene(drop=1.0):
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, drop))
    scene.add_plane()
    return scene


@pytest.fixture(scope="module")
def short_problem():
    """Apex-only problem on a short rollout (c fitted, k frozen)."""
    sim = dp.compile(ball_scene(drop=0.6), 1e-3)
    mfn = B.bounce_metrics_fn(sim, 900, n_apex=1)
    return sim, mfn


class _Terminal(io.StringIO):
    """stderr as a terminal: it keeps what is written and says it is a tty."""

    def isatty(self):
        return True


def _fit_on_a_terminal(mfn, p0, targets, **kw):
    """``F.fit(mfn, p0, targets, **kw)`` with stderr a terminal: (result, what it drew)."""
    err, saved = _Terminal(), sys.stderr
    sys.stderr = err
    try:
        res = F.fit(mfn, p0, targets, **kw)
    finally:
        sys.stderr = saved
    return res, err.getvalue()


@pytest.fixture(scope="module")
def optax_apex_fit(short_problem):
    """The optax fit of the apex target (default optimizer, 300 iterations at most) on a
    terminal with ``progress=None`` (what the diffpen command passes: a bar on a terminal):
    (result, what the bar drew). Shared, never mutated."""
    sim, mfn = short_problem
    return _fit_on_a_terminal(mfn, sim.params(k=1e4, c=10.0), {"apex_heights": [0.2]},
                              free=["contact.default.c"], method="optax", maxiter=300,
                              progress=None, sim=sim)


@pytest.fixture(scope="module")
def lm_apex_fit(short_problem):
    """The LM fit of the apex target (20 iterations at most) with its progress bar on a
    terminal: (result, what the bar drew). Shared, never mutated."""
    sim, mfn = short_problem
    return _fit_on_a_terminal(mfn, sim.params(k=1e4, c=10.0), {"apex_heights": [0.2]},
                              free=["contact.default.c"], method="lm", maxiter=20,
                              progress=True, sim=sim)


def _compiles(caplog, name=""):
    return sum(r.getMessage().startswith(f"Compiling jit({name}") for r in caplog.records)


def test_optax_loop_compiles_once_and_frozen_params_stay(short_problem, caplog, monkeypatch):
    """The optax loop compiles its iteration function once per fit; the frozen stiffness
    stays at its start. These fits run on a terminal without ``progress``: by default the
    library prints nothing (printing belongs to the CLI)."""
    sim, mfn = short_problem
    p0 = sim.params(k=1e4, c=10.0)
    counts, traces = [], []
    # regression: the frozen leaves were differentiated too (one forward-mode tangent per
    # leaf of the params, 2 here for 1 free leaf), then zeroed by the optimiser
    tangents = []
    resolve = dp.autodiff.resolve_mode
    for maxiter in (3, 12):
        caplog.clear()
        err = _Terminal()
        monkeypatch.setattr(sys, "stderr", err)
        monkeypatch.setattr(dp.autodiff, "resolve_mode",
                            lambda mode, n, *a: (tangents.append(n), resolve(mode, n, *a))[1])
        with caplog.at_level(logging.WARNING), jax.log_compiles():
            res = F.fit(mfn, p0, {"apex_heights": [0.2]}, free=["contact.default.c"],
                        method="optax", optimizer=optax.adam(0.05), maxiter=maxiter,
                        rtol=1e-9)
        monkeypatch.undo()
        assert err.getvalue() == "", err.getvalue()       # progress not asked: no bar
        counts.append((_compiles(caplog), _compiles(caplog, "step)")))
        traces.append(res.traces)
        assert res.iterations == maxiter
        # the frozen stiffness is exactly the start value (optax partition: set_to_zero)
        assert float(res.params.contact["default"].k) == 1e4
        assert res.values["contact.default.c"] != 10.0
    assert traces[0] == traces[1] == 1
    assert tangents == [1, 1], tangents         # the free leaf only, traced once per fit
    # the iteration function compiles once per fit, however many iterations run; 4x the
    # iterations adds no compile at all (the second fit reuses the small helper programs)
    assert counts[0][1] == counts[1][1] == 1
    # ... and nothing else: a new maxiter compiles no helper program (the loss history of
    # the carry is built on the host, not by a broadcast compiled per length)
    assert counts[1][0] == 1
    assert res.loss_history[-1] < res.loss_history[0]


def test_lm_reaches_apex_in_few_iterations(lm_apex_fit):
    res, _ = lm_apex_fit
    assert res.reached and res.iterations <= 8
    assert res.achieved["apex_heights"][0] == pytest.approx(0.2, rel=1e-3)
    assert res.traces == 1                 # residual and Jacobian: one forward-mode trace


def test_optax_reaches_apex(optax_apex_fit):
    res, _ = optax_apex_fit
    assert res.reached, res.message
    assert res.achieved["apex_heights"][0] == pytest.approx(0.2, rel=1e-3)
    assert res.iterations > 8            # first order: more iterations than LM's <= 8 above


def test_bad_fit_arguments(ball_sim):
    sim = ball_sim                      # the drop-1 m ball at dt 1e-3 s (conftest)
    mfn = B.bounce_metrics_fn(sim, 10)
    p0 = sim.params(k=1e4, c=10.0)
    with pytest.raises(F.FitError, match="unknown parameter"):
        F.fit(mfn, p0, {"apex_heights": [0.2]}, free=["contact.rubber.k"])
    with pytest.raises(F.FitError, match="zero entry"):
        F.fit(mfn, p0, {"apex_heights": [0.0]})
    with pytest.raises(F.FitError, match="unknown method"):
        F.fit(mfn, p0, {"apex_heights": [0.2]}, method="newton")
    with pytest.raises(F.FitError, match="positive start"):
        F.fit(mfn, sim.params(k=1e4, c=0.0), {"apex_heights": [0.2]})


def test_fit_with_sim_stays_inside_the_safe_step(ball_sim):
    """Regression: fit() had no stability bounds, so a target that pulls k past the safe step
    was met and returned as reached. Given the simulator, k is capped at the safe step and the
    result is not reached (values never past the cap); batch fits share the bounds."""
    from tuning import batch_fit as BF
    from tuning.stable import contact_unstable, safe_contact_bounds
    sim = ball_sim                      # the drop-1 m ball at dt 1e-3 s (conftest)
    k_max, c_max = safe_contact_bounds(sim)
    p0 = sim.params(k=1e4, c=10.0)
    mfn = lambda p: {"stiffness": p.contact["default"].k}    # no rollout: fast
    targets = {"stiffness": 10.0 * k_max}
    free = ["contact.default.k"]
    opts = dict(free=free, method="optax", optimizer=optax.adam(0.5), maxiter=60, rtol=1e-2)
    # without the simulator the optimiser walks past the safe step (the old behaviour)
    loose = F.fit(mfn, p0, targets, **opts)
    assert loose.values["contact.default.k"] > k_max
    res = F.fit(mfn, p0, targets, sim=sim, **opts)
    assert not res.reached
    assert res.values["contact.default.k"] <= k_max * (1 + 1e-9)
    assert not bool(contact_unstable(sim, res.params))
    lm = F.fit(mfn, p0, targets, sim=sim, free=free, method="lm", maxiter=30, rtol=1e-2)
    assert not lm.reached and lm.values["contact.default.k"] <= k_max * (1 + 1e-9)
    lo, hi = F.safe_bounds(["contact.default.k", "contact.default.c"], [1e4, 10.0],
                           {"contact.default.c": (1e-3, 1e9)}, sim)
    assert hi[0] == k_max and hi[1] == c_max
    with pytest.raises(F.FitError, match="safe step"):
        F.safe_bounds(free, [1e4], {"contact.default.k": (2 * k_max, 3 * k_max)}, sim)
    # a point past the safe step is never reached, even when the user's bounds allow it
    # (metrics_fn without its own flag: the fit adds it from the simulator)
    far = F.fit(mfn, sim.params(k=2 * k_max, c=10.0), {"stiffness": 2 * k_max},
                free=["contact.default.c"], method="optax", maxiter=3, sim=sim)
    assert not far.reached and "safe step" in far.message
    bf = BF.BatchFitter(mfn, p0, free=free, sim=sim, maxiter=60, learning_rate=0.5,
                        rtol=1e-2)
    assert bf.hi[0] == k_max
    out = bf([targets])
    assert not out.reached[0]


def test_a_fit_that_meets_its_targets_only_past_the_safe_step_is_not_reached():
    params0 = dp.Params({"default": ContactParams(np.float64(1.0), np.float64(2.0))}, {}, {})

    def mfn(p):
        k = p.contact["default"].k
        return {"apex_heights": jnp.atleast_1d(k / 10.0), "unstable": k > 3.0}
    res = F.fit(mfn, params0, {"apex_heights": [0.5]}, free=["contact.default.k"],
                method="lm", maxiter=20, progress=False)
    # LM rejects trial points past the safe step (it used to walk to k = 5 and report a
    # result it then disowned): it stops at the stable side and says why
    assert res.values["contact.default.k"] <= 3.0
    assert res.achieved["apex_heights"][0] == pytest.approx(0.3, rel=1e-2)
    assert not res.reached and "safe step" in res.message
    with pytest.raises(F.FitError, match="past the simulator's safe step"):
        F.fit(mfn, params0._replace(contact={"default": ContactParams(4.0, 2.0)}),
              {"apex_heights": [0.5]}, free=["contact.default.k"], method="lm", maxiter=5,
              progress=False)


def test_library_fit_prints_nothing_unless_asked(optax_apex_fit):
    """Printing belongs to the CLI: on a terminal, fit draws its progress bar only when asked
    (progress=None or True, what the diffpen command passes); by default it writes nothing
    (the default is checked on the fits of test_optax_loop_compiles_once_and_frozen_params_stay,
    progress=True in test_iterations_history_and_progress_bar_agree)."""
    _, drawn = optax_apex_fit                  # progress=None on a terminal: a bar
    assert drawn and "/300 " in drawn, drawn


#: a first-apex target of the short problem met near c = 8 N s/m at k 1e4 N/m (its apex
#: there, computed once: the test only needs the target to lie much nearer the start at
#: c = 8.1 than the starts at 30 and 60)
APEX_AT_C8 = 0.3843990090648111


def test_optax_starts_from_the_cheapest_given_start(short_problem):
    """fit(method="optax", starts=[...]) checked the extra starts, then ignored them: the
    loop now runs from the start of lowest cost."""
    sim, mfn = short_problem
    target = {"apex_heights": [APEX_AT_C8]}
    p0 = sim.params(k=1e4, c=60.0)
    far = F.fit(mfn, p0, target, free=["contact.default.c"], method="optax", maxiter=1)
    near = F.fit(mfn, p0, target, free=["contact.default.c"], method="optax", maxiter=1,
                 starts=[{"contact.default.c": 8.1}, {"contact.default.c": 30.0}])
    assert near.start["contact.default.c"] == pytest.approx(8.1)
    assert near.rel_error["apex_heights"] < far.rel_error["apex_heights"]


def test_fit_refuses_bad_iteration_and_start_counts_and_duplicate_free(ball_sim):
    """Regression: maxiter <= 0 gave a misleading optax error ("the first iteration already
    failed") and an LM result at the start; n_starts = 0 was blamed on the safe step; a
    parameter named twice in free was fitted as two."""
    sim = ball_sim                      # the drop-1 m ball at dt 1e-3 s (conftest)
    mfn = B.bounce_metrics_fn(sim, 10)
    p0 = sim.params(k=1e4, c=10.0)
    tg, free = {"apex_heights": [0.2]}, ["contact.default.c"]
    for method in ("optax", "lm"):
        for maxiter in (0, -5, 2.5, True):
            with pytest.raises(F.FitError, match="maxiter must be a positive integer"):
                F.fit(mfn, p0, tg, free=free, method=method, maxiter=maxiter)
    with pytest.raises(F.FitError, match="n_starts must be a positive integer"):
        F.fit(mfn, p0, tg, free=free, method="lm", starts=[{"contact.default.c": 5.0}],
              n_starts=0)
    with pytest.raises(F.FitError, match=r"free names \['contact.default.c'\] more than once"):
        F.fit(mfn, p0, tg, free=["contact.default.c", "contact.default.k",
                                 "contact.default.c"], method="lm")


def test_iterations_history_and_progress_bar_agree(short_problem, optax_apex_fit,
                                                   lm_apex_fit):
    """Regression: an optax fit that reached its targets said iterations=39 while its bar
    ended at 40/300 and its history had 40 entries (at the limit: maxiter entries, maxiter
    iterations); an LM iteration that found no decrease was counted but not drawn. Now optax
    has one history entry per iteration, LM one more (the start), and the bar ends at the
    iterations reported. (The optax fit to its target with a 300-iteration bar and the LM fit
    of 20 iterations at most are the shared fits of the two apex tests above.)"""
    import re

    sim, mfn = short_problem
    p0 = sim.params(k=1e4, c=10.0)
    free = ["contact.default.c"]
    cases = [("optax", {"apex_heights": [0.2]}, {"maxiter": 300}, 0),
             ("optax", {"apex_heights": [0.2]}, {"maxiter": 5, "rtol": 1e-9}, 0),
             ("lm", {"apex_heights": [0.2]}, {"maxiter": 20}, 1),
             ("lm", {"apex_heights": [0.55]}, {"maxiter": 10, "starts": [
                 {"contact.default.c": 5.0}, {"contact.default.c": 50.0}]}, None)]
    shared = {0: optax_apex_fit, 2: lm_apex_fit}
    for i, (method, targets, kw, extra) in enumerate(cases):
        if i in shared:
            res, drawn = shared[i]
        else:
            res, drawn = _fit_on_a_terminal(mfn, p0, targets, free=free, method=method,
                                            progress=True, sim=sim, **kw)
        done, total = (int(v) for v in re.findall(r"(\d+)/(\d+) ", drawn)[-1])
        assert done == res.iterations, (method, kw, drawn[-200:])
        assert total == kw["maxiter"] * (3 if "starts" in kw else 1), (method, kw, total)
        if extra is not None:
            assert len(res.loss_history) == res.iterations + extra, (method, kw)
        if kw.get("maxiter") == 5:
            assert res.iterations == total == 5 and not res.converged
        if "starts" in kw:          # every run may take maxiter iterations
            assert res.iterations > kw["maxiter"] and total == 3 * kw["maxiter"]


def test_an_unsettled_settling_time_is_not_reached_and_the_message_says_why():
    """Regression: a settling time that is only the rollout's end (the motion never settled)
    but within 1e-3 of its target stopped the optax loop as converged, and the message read
    "targets NOT reached (targets reached)". Now the loop goes on and the message names the
    reason, for either method; LM no longer stops there as if the targets were met."""
    def mfn(p):         # a 1 s rollout: settles at 2 / c s, else reads the rollout's end
        t = 2.0 / p.contact["default"].c
        return {"settling_time": jnp.minimum(t, 1.0), "settled": t < 1.0}
    p0 = dp.Params({"default": ContactParams(np.float64(1.0), np.float64(1.5))}, {}, {})
    for method in ("optax", "lm"):
        res = F.fit(mfn, p0, {"settling_time": 0.9995}, free=["contact.default.c"],
                    method=method, maxiter=5)
        assert not res.reached and res.rel_error["settling_time"] == np.inf
        assert "has not settled within the rollout" in res.message, res.message
        assert "(targets reached)" not in res.message
        if method == "optax":
            assert not res.converged and res.iterations == 5
        else:       # LM did not stop as if the targets were met (it did, at iteration 0)
            assert "within its tolerance" not in res.message, res.message
            assert res.iterations >= 1
    # held at a bound it says so (`diffpen fit --law hunt_crossley` advised a longer rollout,
    # which the command cannot give, for targets out of the law's reach, audit32)
    res = F.fit(mfn, p0, {"settling_time": 0.9995}, free=["contact.default.c"], method="lm",
                maxiter=5, bounds={"contact.default.c": (1.5, 1.6)})
    assert "use a longer rollout (diffpen fit --duration" in res.message, res.message
    assert "parameters at their bounds: ['contact.default.c']" in res.message, res.message


def test_residuals_and_jacobian_trace_once_and_equal_separate_passes():
    """tuning.lm.residuals_and_jacobian: the residuals, forward-mode Jacobian and the
    function's other output from one trace of the function (record fits, LM and sysid all
    take theirs from it), equal to a value pass and a separate jax.jacfwd."""
    from tuning.lm import residuals_and_jacobian
    traces = []

    def fn(x):
        traces.append(1)
        r = jnp.stack([jnp.sin(x[0]) * x[1], x[0] ** 2 - jnp.exp(x[1]), x[0] * x[1]])
        return r, {"flag": r[0] > 0}
    x = jnp.asarray([0.3, -1.2])
    r, J, aux = jax.jit(lambda x: residuals_and_jacobian(fn, x))(x)
    assert len(traces) == 1
    # the separate passes: a value pass and jax.jacfwd (jitted together: one compile, not one
    # per eager operation)
    (r_value, aux_value), J_fwd = jax.jit(
        lambda x: (fn(x), jax.jacfwd(lambda x: fn(x)[0])(x)))(x)
    np.testing.assert_allclose(np.asarray(r), np.asarray(r_value), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(J), np.asarray(J_fwd), rtol=1e-15)
    assert bool(aux["flag"]) == bool(aux_value["flag"])


@pytest.mark.parametrize("method, program", [("lm", "rj"), ("optax", "step")])
def test_a_later_fit_of_an_equal_problem_compiles_nothing(short_problem, caplog, method,
                                                          program):
    """Regression: every fit built and compiled its residual program (LM) or loop (optax), and
    optax its ranking of extra starts, again (1.6-2.8 s a fit), even with the same metrics function, simulator and frozen leaves
    and only new targets or starts. A later fit of such a problem runs the compiled program
    with its own targets; a changed frozen leaf (k here) is a different program, never the
    old one."""
    sim, mfn = short_problem

    def run(k, apex):
        with caplog.at_level(logging.WARNING), jax.log_compiles():
            caplog.clear()
            res = F.fit(mfn, sim.params(k=k, c=10.0), {"apex_heights": [apex]},
                        free=["contact.default.c"], method=method, maxiter=150, sim=sim,
                        starts=[{"contact.default.c": 14.0}])
        return res, _compiles(caplog, program)
    first, _ = run(1.2e4, 0.2)
    again, compiled = run(1.2e4, 0.22)
    # nothing at all: neither the fit's program nor the ranking of the starts
    assert compiled == 0 and _compiles(caplog) == 0 and again.traces == 0
    assert again.reached and again.achieved["apex_heights"][0] == pytest.approx(0.22, rel=1e-3)
    other, compiled = run(1.5e4, 0.22)
    assert compiled == 1 and other.traces == 1 and other.reached
    assert float(other.params.contact["default"].k) == 1.5e4
    assert other.values["contact.default.c"] != pytest.approx(again.values["contact.default.c"],
                                                              rel=1e-3)


def test_a_float32_fit_returns_float32_params(short_problem):
    """Regression: the fitted leaves of a float32 simulator's fit were put back as the
    optimiser's float64 values (``FitResult.params``: k float32, c float64). An int leaf of
    a hand-built Params still takes the fit's floats (cast to int it never moved)."""
    sim = dp.compile(ball_scene(drop=0.6), 1e-3, dtype=jnp.float32)
    mfn = B.bounce_metrics_fn(sim, 300, n_apex=1)
    res = F.fit(mfn, sim.params(k=1e4, c=10.0), {"apex_heights": [0.2]},
                free=["contact.default.c"], method="lm", maxiter=1)
    assert {np.dtype(x.dtype) for x in jax.tree_util.tree_leaves(res.params)} == {
        np.dtype(np.float32)}
    sim, mfn = short_problem
    p_int = dp.Params(contact={"default": ContactParams(np.int64(10000), np.int64(10))},
                      springs={})
    res = F.fit(mfn, p_int, {"apex_heights": [0.2]}, free=["contact.default.c"], method="lm",
                maxiter=1)
    assert res.values["contact.default.c"] != pytest.approx(10.0, rel=1e-3)
    assert float(res.params.contact["default"].c) == pytest.approx(
        res.values["contact.default.c"], rel=1e-6)
