"""Fast spins of rigid bodies: the start spin's limit per integrator (refused concrete,
flagged traced, reported by sim.stability) and semi-implicit Euler's carried angular
momentum (diffpen.motion, diffpen.rigid.RigidDynamics.transport)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen.geometry import quat_to_matrix
from jaxpr_scopes import traced_scopes


def test_a_spin_too_fast_for_semi_implicit_euler_is_refused_or_caught():
    """A box spinning at 300 rad/s (0.3 rad per 1 ms step) under semi-implicit Euler came
    back with NaN orientations and no error (only positions were checked). It is refused
    past the spin limit, and stepped past it (check_stability=False) it stays finite with its
    angular momentum: the step carries it (it turned NaN with the gyroscopic term stepped
    explicitly, and so did the substeps and verlet the error offered, audit33)."""
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(300.0, 10.0, 10.0),
              inertia=(1.0, 2.0, 3.0))
    bsim = dp.compile(s, 1e-3)
    with pytest.raises(dp.StabilityError, match=r"spins at up to \|w\| = 300.8 rad/s.*kappa = 1.*"
                       r"spin limit 0.05.*Use dt <= 0.000166 s.*substeps=7") as refused:
        bsim.rollout(bsim.params(), 400)
    # every remedy it names steps it: the dt (it was rounded up: 0.000167 s, refused again,
    # audit34) and implicit Euler (rk4, offered before, can be refused for the contacts at
    # the same step, audit37)
    assert "integrator='implicit_euler' (no spin limit" in str(refused.value)
    at = dp.compile(s, 0.000166)
    assert np.isfinite(at.rollout(at.params(), 2).orientation).all()
    implicit = dp.compile(s, 1e-3, integrator="implicit_euler")
    assert np.isfinite(implicit.rollout(implicit.params(), 2).orientation).all()
    past = bsim.rollout(bsim.params(), 400, check_stability=False)
    inertia = np.array([1.0, 2.0, 3.0])

    def momentum(tr):
        rot = quat_to_matrix(np.asarray(tr.orientation)[:, 0], xp=np)
        w_body = np.einsum("tji,tj->ti", rot, np.asarray(tr.angular_velocity)[:, 0])
        return np.einsum("tij,tj->ti", rot, inertia * w_body)
    mom = momentum(past)
    assert np.isfinite(mom).all()
    np.testing.assert_allclose(mom, np.broadcast_to([300.0, 20.0, 30.0], mom.shape), rtol=1e-12)
    # the fix it names steps it: 7 substeps; "auto" picks them
    seven = bsim.rollout(bsim.params(), 400, substeps=7)
    auto = dp.compile(s, 1e-3, substeps="auto")
    np.testing.assert_array_equal(auto.rollout(auto.params(), 400).orientation,
                                  seven.orientation)
    # traced params never raise (the rollout's aux flag is the traced check)
    sp = dp.Scene(gravity=(0.0, 0.0, 0.0))
    sp.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(300.0, 10.0, 10.0),
               inertia=(1.0, 2.0, 3.0))
    sp.add_plane(offset=-10.0)
    psim = dp.compile(sp, 1e-3)
    with pytest.raises(dp.StabilityError):
        psim.rollout(psim.params(k=1e4, c=20.0), 5)
    jax.jit(lambda p: psim.rollout(p, 5).position)(psim.params(k=1e4, c=20.0))
    # verlet and rk4 step the gyroscopic term explicitly: refused past their own limits
    # (verlet's 0.05: this spin turned NaN; rk4's 0.2), and sim.stability says so
    for name, need in (("verlet", 7), ("rk4", 2)):
        other = dp.compile(s, 1e-3, integrator=name)
        with pytest.raises(dp.StabilityError, match=rf"{name}'s spin limit.*substeps={need}"):
            other.rollout(other.params(), 400)
        report = other.stability(other.params())
        assert report.substeps_needed == need and not report.safe
        assert "spin" in report.limiting
        assert np.isfinite(other.rollout(other.params(), 400, substeps=need).orientation).all()
    # equal moments (a cube) have no gyroscopic term: the same spin is stepped exactly
    c = dp.Scene(gravity=(0.0, 0.0, 0.0))
    c.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(300.0, 10.0, 10.0))
    csim = dp.compile(c, 1e-3)
    w = csim.rollout(csim.params(), 400).angular_velocity
    np.testing.assert_allclose(w[-1, 0], [300.0, 10.0, 10.0], rtol=1e-12)


def test_a_traced_sweep_over_start_spins_flags_the_rows_past_the_spin_limit():
    """Under jit(vmap) over start spins, rows past SPIN_LIMIT ended NaN with
    aux["unstable"] False (the traced flag had no spin term), while a concrete rollout of the
    same start refuses it."""
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    box = s.add_box((0.1, 0.2, 0.3), 1.0, (0.0, 0.0, 0.0), inertia=(1.0, 2.0, 3.0))
    s.add_plane(offset=-10.0)
    bsim = dp.compile(s, 1e-2)
    p = bsim.params(k=100.0, c=0.0)
    axis = jnp.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)

    def one(w):
        st = bsim.state_from(body=box, angular_velocity=w * axis, frame="body")
        tr = bsim.rollout(p, 300, state=st, save_every=300)
        return jnp.isfinite(tr.orientation[-1]).all(), tr.aux["unstable"][-1]

    # kappa = 1, h = 0.01, spin speed sqrt(2 E / I_min) = sqrt(2) |w| here: kappa |w| h =
    # 0.014, 0.042 (inside 0.05), 0.14, 0.57 (past it)
    finite, flag = jax.jit(jax.vmap(one))(jnp.array([1.0, 3.0, 10.0, 40.0]))
    np.testing.assert_array_equal(flag, [False, False, True, True])
    assert bool(np.all(finite))         # the step carries the angular momentum: no NaN
    # verlet and rk4 flag past their own limits (0.05 and 0.2)
    for name, flags in (("verlet", [False, True, True]), ("rk4", [False, False, True])):
        vsim = dp.compile(s, 1e-2, integrator=name)
        got = jax.vmap(lambda w: vsim.rollout(p, 2, state=vsim.state_from(
            body=box, angular_velocity=w * axis, frame="body")).aux["unstable"][-1])(
                jnp.array([1.0, 10.0, 40.0]))
        np.testing.assert_array_equal(got, flags)


def test_vmap_over_a_start_spin_alone_runs():
    """vmap over state_from(angular_velocity=...) of a free box crashed with a raw
    TracerBoolConversionError: its positions do not depend on the spin, so they came back
    concrete while the angular velocities were tracers, and the finite check tested only
    the positions for concreteness."""
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    box = s.add_box((0.1, 0.2, 0.3), 1.0, (0.0, 0.0, 1.0))
    bsim = dp.compile(s, 1e-3)
    p = bsim.params()

    def final_spin(w):
        st = bsim.state_from(body=box, angular_velocity=jnp.array([0.0, 0.0, 1.0]) * w,
                             frame="body")
        return bsim.rollout(p, 20, state=st, save_every=20).angular_velocity[-1, box]

    np.testing.assert_allclose(jax.vmap(final_spin)(jnp.array([1.0, 2.0])),
                               [[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]], atol=1e-12)


def test_auto_substeps_for_a_spin_are_capped_and_the_report_names_the_spin():
    """substeps="auto" took any count a spin asked for (a 1:2:3 box at 1e9 rad/s: 2e7 inner
    steps per step, a run that looks hung); the stiffness path refuses past
    MAX_AUTO_SUBSTEPS. sim.stability(params, state) printed "w_max <= 0 rad/s, set by body
    0's spin" and kept the contact's limiting body; its substep count and "auto"'s differed
    (audit35)."""
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(1e9, 0.0, 1e7),
              inertia=(1.0, 2.0, 3.0))
    auto = dp.compile(s, 1e-3, substeps="auto")
    with pytest.raises(dp.StabilityError, match=r"substeps='auto' would need about 2e\+07 "
                       r"substeps.*body 0's spin.*too slow.*a cube has no spin limit"):
        auto.rollout(auto.params(), 2)
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(300.0, 10.0, 10.0),
              inertia=(1.0, 2.0, 3.0))
    sim = dp.compile(s, 1e-3)
    report = sim.stability(sim.params())
    assert report.limiting_body == 0 and report.substeps_needed == 7
    assert "w_max" not in str(report) and "set by body 0's spin" in str(report)
    assert dp.compile(s, 1e-3, substeps="auto").rollout(sim.params(), 2) is not None


def test_the_transport_is_traced_only_where_a_body_needs_it():
    """The angular-momentum transport runs for bodies with unequal moments under
    semi-implicit and implicit Euler only: not for cubes and rigid spheres (no gyroscopic
    term), pinned
    boxes, other integrators or scenes without rigid bodies (audit35: nothing checked it)."""
    def traced(add, integrator="semi_implicit_euler"):
        s = dp.Scene(gravity=(0.0, 0.0, -9.81))
        add(s)
        sim = dp.compile(s, 1e-3, integrator=integrator)
        return "angular_momentum_transport" in " ".join(traced_scopes(sim, sim.params())[0])

    def flat(s):
        s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 1.0))
    assert traced(flat) and traced(flat, "implicit_euler")
    assert not traced(flat, "verlet") and not traced(flat, "rk4")
    assert not traced(lambda s: s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 1.0)))
    assert not traced(lambda s: s.add_rigid_sphere(0.1, 1.0, (0.0, 0.0, 1.0)))
    assert not traced(lambda s: s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 1.0), pinned=True)
                      or s.add_particle(1.0, (1.0, 0.0, 0.0), collide=False))
    assert not traced(lambda s: s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0)))


def test_a_spin_a_torque_builds_up_during_a_rollout_is_flagged_and_warned():
    """Only the start spin was checked: a box starting at rest on a stretched anchored
    spring, at half the safe step, spun up to kappa |w| h 2.3 (46x the limit) and ended
    with 3.25x its energy under semi-implicit Euler, finite, unflagged and silent (verlet:
    NaN under jit, unflagged; audit34). Each step now ors the spin into aux["unstable"], and
    a concrete rollout warns (dp.SpinWarning)."""
    import warnings
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    b = s.add_box((0.05, 0.1, 0.15), 1.0, (0.0, 0.0, 0.0))
    s.add_anchored_spring(b, None, (0.05, 0.1, 0.15), (0.6, 0.3, -0.4), k=2000.0, c=0.0,
                          rest_length=0.0)
    probe = dp.compile(s, 1e-3)
    dt = 0.5 * probe.stability(probe.params()).safe_dt
    sim = dp.compile(s, dt)
    n = int(2.0 / dt)
    traced = jax.jit(lambda k: sim.rollout(sim.params(spring_k=k), n, save_every=n))(2000.0)
    assert bool(traced.aux["unstable"][-1])
    with pytest.warns(dp.SpinWarning, match=r"spun past semi_implicit_euler's spin limit.*"
                      r"first by saved step \d+.*Use dt <= .* s \(an inner step\) or "
                      r"substeps >= \d+") as said:
        tr = sim.rollout(sim.params(), n, save_every=1)
    assert said and bool(tr.aux["unstable"][-1])
    # a start whose own flag is set keeps it, and there is no spin-up to report (it warned
    # "a torque spun it up" for a slow free box, audit36)
    slow = dp.Scene(gravity=(0.0, 0.0, 0.0))
    slow.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(1.0, 0.5, 0.2))
    free = dp.compile(slow, 1e-3)
    start = free.init_state()
    with warnings.catch_warnings():
        warnings.simplefilter("error", dp.SpinWarning)
        kept = free.rollout(free.params(), 2, start._replace(aux={"unstable": jnp.asarray(True)}))
    assert bool(kept.aux["unstable"][-1])
    # at a step that keeps it within the limit (|w| peaks near 550 rad/s): no flag, no word
    fine = dp.compile(s, 5e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", dp.SpinWarning)
        assert not bool(fine.rollout(fine.params(), 400, save_every=400).aux["unstable"][-1])


def test_a_free_spin_near_the_middle_axis_within_the_limit_is_not_flagged():
    """Without torque |w| of a body near its middle axis grows (1.16x for moments 1:2:3), so
    a free box started at 0.9 of the limit had aux["unstable"] set part-way and a SpinWarning
    blaming a torque, and fits and sweeps read it as no result (audit36). The checks judge
    the speed sqrt(2 E / I_min), which no torque-free motion exceeds: such a start is within
    the limit all the way, or refused at once."""
    import warnings
    from diffpen.motion import spin_speed
    inertia = np.array([1.0, 2.0, 3.0])
    axis = np.array([0.05, 1.0, 0.05]) / np.linalg.norm([0.05, 1.0, 0.05])
    speed = float(spin_speed(axis[None], np.array([[1.0, 0.0, 0.0, 0.0]]), inertia[None])[0])
    w = 0.9 * 0.05 / (speed * 1e-3)                    # kappa = 1, h = 1 ms: 0.9 of the limit
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=tuple(w * axis),
              inertia=tuple(inertia))
    sim = dp.compile(s, 1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", dp.SpinWarning)
        tr = sim.rollout(sim.params(), 5000, save_every=50)
    assert not np.any(np.asarray(tr.aux["unstable"]))
    grown = np.linalg.norm(np.asarray(tr.angular_velocity)[:, 0], axis=-1).max() / w
    assert grown > 1.1                                  # |w| did grow on the way
    # at 0.9 of the limit by its |w| it passed the start check and was flagged part-way;
    # it is refused at once now (its energy's speed is past the limit)
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=tuple(45.0 * axis),
              inertia=tuple(inertia))
    late = dp.compile(s, 1e-3)
    with pytest.raises(dp.StabilityError, match="spins at up to"):
        late.rollout(late.params(), 5000, save_every=50)



def test_fit_messages_name_the_spin_limit_as_a_cause_of_the_flag():
    """Fits read aux["unstable"] as "no result" and blamed the safe step and k / c; with a
    rigid body that has a spin limit, each step flags a spin past it too (audit36)."""
    from tuning.stable import solver_miss
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0))
    assert "spin limit" in solver_miss(dp.compile(s, 1e-3))
    c = dp.Scene(gravity=(0.0, 0.0, 0.0))
    c.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.0))
    assert solver_miss(dp.compile(c, 1e-3)) == ""


def test_implicit_euler_carries_the_angular_momentum_too():
    """Implicit Euler linearised the gyroscopic term: a free 1:2:3 box at kappa |w| h 0.04
    gained energy and lost angular momentum by tens of percent over 2000 steps, unflagged
    (+39% and 58% at 0.05 over 5000, audit34). It carries the angular momentum as
    semi-implicit Euler does: |L| to rounding, the energy within 0.05%; its start spin has
    no limit (it is taken for steps past the explicit limit, where a landing box turns 0.1 a
    step: the limit flagged 23 of 24 landings at dt 2e-2, audit37)."""
    inertia = np.array([1.0, 2.0, 3.0])
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=tuple(20.0 * axis),
              inertia=tuple(inertia))
    sim = dp.compile(s, 1e-3, integrator="implicit_euler")
    tr = sim.rollout(sim.params(), 2000, save_every=100)
    rot = quat_to_matrix(np.asarray(tr.orientation)[:, 0], xp=np)
    w_body = np.einsum("tji,tj->ti", rot, np.asarray(tr.angular_velocity)[:, 0])
    mom = np.einsum("tij,tj->ti", rot, inertia * w_body)
    energy = np.sum(inertia * w_body ** 2, axis=1)
    w0 = 20.0 * axis
    np.testing.assert_allclose(mom, np.broadcast_to(inertia * w0, mom.shape), atol=1e-10)
    assert np.abs(energy / np.sum(inertia * w0 ** 2) - 1.0).max() < 5e-4
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(300.0, 10.0, 10.0),
              inertia=tuple(inertia))
    fast = dp.compile(s, 1e-3, integrator="implicit_euler")
    assert np.isfinite(fast.rollout(fast.params(), 10).angular_velocity).all()
    assert fast.stability(fast.params()).safe
