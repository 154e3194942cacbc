"""The trust reports' own arithmetic and the fit's target checks (regressions: each failed on
the code before its fix)."""
import jax.numpy as jnp
import numpy as np
import pytest

from tuning.errors import FitError
from tuning.problem import FreeLeaves, target_spec
from tuning.reports import accuracy as A
from tuning.reports import extreme as X
from tuning.reports.gradient_check import largest_agreeing_step

STEPS = tuple(10.0 ** -np.arange(1, 8.5, 0.5))      # 1e-5 comes out as 9.999999999999999e-06


def test_largest_agreeing_step_checks_down_to_1e_5_and_never_below():
    """The floor 1e-5, computed as 9.999999999999999e-06, was dropped from the check: a step
    was reported as agreeing while 1e-5 disagreed, and where no step agreed at all the
    first step below the floor was reported (all([]) is True)."""
    g = 2.0
    fds = np.full(len(STEPS), g)
    assert largest_agreeing_step(STEPS, fds, g) == pytest.approx(0.1)
    at_floor = int(np.argmin(np.abs(np.array(STEPS) - 1e-5)))
    bad_floor = fds.copy()
    bad_floor[at_floor] = -g                       # 1e-5 disagrees (opposite sign)
    assert largest_agreeing_step(STEPS, bad_floor, g) is None
    assert largest_agreeing_step(STEPS, np.full(len(STEPS), -g), g) is None
    coarse_bad = fds.copy()
    coarse_bad[:3] = 1.5 * g                       # 0.1 .. 1e-2 off; 3.2e-3 and below agree
    assert largest_agreeing_step(STEPS, coarse_bad, g) == pytest.approx(STEPS[3])
    below = fds.copy()
    below[at_floor + 1:] = -g                      # below the floor: not checked
    assert largest_agreeing_step(STEPS, below, g) == pytest.approx(0.1)


def test_accuracy_horizon_covers_the_apexes_and_a_short_one_is_refused():
    """A ball dropped from 3 m reached its third apex after the report's fixed 3 s: every
    ball error came out inf and --tol advised a smaller dt."""
    spec = A.BallSpec(height=3.0)
    T = A.horizon(spec)
    assert T > 3.0
    from tuning.reports.reference import ball_reference
    ref = ball_reference(k=spec.k, c=spec.c, m=spec.mass, r=spec.radius, z0=spec.height, T=T)
    assert len(ref.apexes) >= spec.n_apex
    assert A.horizon(A.BallSpec()) >= 3.0
    # an apex counts once its flight has ended: a ball that does not settle is simulated past
    # the landing after its last apex (the horizon stopped 0.05 s after that apex, and the
    # third apex came out NaN, the report's error inf)
    from tuning.reports.reference import apex_heights
    for s in (A.BallSpec(c=1.0, height=10.0), A.BallSpec(c=2.0, height=20.0)):
        T = A.horizon(s)
        r = ball_reference(k=s.k, c=s.c, m=s.mass, r=s.radius, z0=s.height, T=T)
        t = np.arange(0.0, T, 1e-4)
        ap = apex_heights(t, np.asarray(r.state(t)[0]), s.radius, s.n_apex)
        np.testing.assert_allclose(ap, r.apexes[:s.n_apex], rtol=1e-6)
    with pytest.raises(ValueError, match="comes after T = 3 s"):
        A.accuracy(ball=spec, integrators=("semi_implicit_euler",), n_dt=1,
                   problems=("ball",))
    with pytest.raises(ValueError, match="does not bounce 3 times"):
        A.horizon(A.BallSpec(c=400.0))


def test_substep_remedies_are_checked_on_every_inner_state():
    """A case re-run with substeps was checked on its outer states only: a k = 1e9 contact
    shorter than dt reported a negative penetration (never touched)."""
    case = X.Case(scene="ball", dtype="float64", integrator="verlet", k=1e4, label="k")
    sim1, steps1, _ = X._case_sim(case, 1)
    sim4, steps4, _ = X._case_sim(case, 4)
    assert sim4.dt == pytest.approx(case.dt / 4) and steps4 == 4 * steps1
    assert sim1.dt == pytest.approx(case.dt)


@pytest.mark.parametrize("kw, words", [
    (dict(rtol=-1.0), "rtol of target 'apex' must be a finite number > 0"),
    (dict(rtol=float("nan")), "rtol of target 'apex' must be a finite number > 0"),
    (dict(rtol={"apexx": 0.5}), "rtol names ['apexx'], which are not targets"),
    (dict(weights={"apexx": 2.0}), "weights names ['apexx'], which are not targets"),
    (dict(weights={"apex": float("inf")}), "weight of target 'apex' must be a finite"),
])
def test_target_tolerances_and_weights_are_checked(kw, words):
    """A negative or NaN rtol ran to maxiter, and a misspelt metric in rtol or weights was
    ignored."""
    args = dict(weights=None, rtol=1e-3) | kw
    with pytest.raises(FitError) as exc:
        target_spec({"apex": np.ones(2)}, args["weights"], args["rtol"])
    assert words in str(exc.value)
    assert target_spec({"apex": np.ones(2)}, {"apex": 2.0}, {"apex": 1e-2})[0].rtol == 1e-2


def test_bounds_of_a_leaf_that_is_not_fitted_are_refused():
    import diffpen as dp
    from tuning.scenes import ball_scene
    sim = dp.compile(ball_scene(), 1e-3, dtype=jnp.float64)
    p0 = sim.params(k=1e4, c=10.0)
    with pytest.raises(FitError, match="not fitted"):
        FreeLeaves.build(p0, ["contact.default.k"], {"contact.default.c": (1.0, 100.0)})
    FreeLeaves.build(p0, ["contact.default.k"], {"contact.default.k": (1e3, 1e5)})


def test_too_few_bounces_blames_the_damping_only_when_the_ball_is_damped():
    """At k 1e18 N/m (damping ratio 1e-8) the reference cannot resolve the 3e-9 s contact;
    the refusal said "lower the damping c", which cannot help. It names k there now."""
    assert "lower the damping c" in A._too_few_bounces(A.BallSpec(c=400.0))
    stiff = A._too_few_bounces(A.BallSpec(k=1e18, c=20.0))
    assert "lower k" in stiff and "damping c" not in stiff and "3.14e-09 s" in stiff
