"""Precision limits and the step's gate: scenes a dtype cannot resolve (far from the origin,
past float32's range, rigid bodies too small), steps too short for float32 (also for the
event-exact records' rebuilt force), and ``sim.step`` refusing and picking substeps as a
rollout does."""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp


def test_a_scene_far_from_the_origin_is_refused_where_the_dtype_cannot_resolve_it():
    """Regression: in float32 a ball resting on a plane at z = 1e4 m froze (one distinct
    height in 20000 steps, reading vz = -0.3 m/s) and a box sliding at x = 1e4 m never moved
    while friction stopped it, with no error: a step's displacement rounds away there. Now
    compile refuses it and says to move the scene or use float64; near the origin, at 100 m,
    and in float64 it compiles."""
    def scene(z):
        s = dp.Scene()
        s.add_material("m", k=1e4, c=20.0)
        s.add_plane(offset=z, material="m")
        s.add_sphere(0.1, 1.0, (0.0, 0.0, z + 0.099), material="m")
        return s
    with pytest.raises(dp.SceneError, match="1e\\+04 m from the origin.*float32.*dtype=float64"):
        dp.compile(scene(1e4), 1e-3, dtype=jnp.float32)
    box = dp.Scene()
    box.add_material("rough", k=1e4, c=20.0, friction=0.4)
    box.add_plane(material="rough")
    box.add_box((0.05,) * 3, 1.0, (1e4, 0.0, 0.0495), velocity=(2.0, 0.0, 0.0),
                material="rough")
    with pytest.raises(dp.SceneError, match="from the origin"):
        dp.compile(box, 1e-3, dtype=jnp.float32)
    for z in (0.0, 100.0):
        dp.compile(scene(z), 1e-3, dtype=jnp.float32)
    dp.compile(scene(1e4), 1e-3, dtype=jnp.float64)
    # regression: a rope of particles (no body size, its k given to sim.params only) passed
    # at x = 1e4 m in float32 and ran 1.9 cm (2% of its swing) off in 1 s, unwarned; its
    # shortest spring (0.11 m) is the size float32 must resolve there
    from diffpen import builders

    def rope(x):
        s = dp.Scene()
        builders.add_rope(s, 10, (x, 0.0, 1.0), (x + 1.0, 0.0, 1.0), 1.0, 500.0, 0.5)
        return s
    with pytest.raises(dp.SceneError, match=r"1e\+04 m from the origin.*float32.*1e-4 of its "
                                            r"shortest spring \(0\.111 m\)"):
        dp.compile(rope(1e4), 2e-3, dtype=jnp.float32)
    for x, dtype in ((0.0, jnp.float32), (100.0, jnp.float32), (1e4, jnp.float64)):
        dp.compile(rope(x), 2e-3, dtype=dtype)
    chain = dp.Scene()                  # springs of rest length 0: their start length counts
    for i in range(3):
        chain.add_particle(1.0, (1e4 + 0.1 * i, 0.0, 1.0), pinned=i == 0)
    chain.add_spring(0, 1, k=500.0, c=0.5, rest_length=0.0)
    chain.add_spring(1, 2, rest_length=0.0)
    with pytest.raises(dp.SceneError, match=r"shortest spring \(0\.1 m\)"):
        dp.compile(chain, 2e-3, dtype=jnp.float32)


def test_numbers_past_float32s_range_are_refused_by_name(ball_scene):
    """In float32 a sphere at x = 1e39 m compiled with an inf start state (its rollout then
    stopped on NaN blaming the time step), and sim.params(k=1e300) became inf (the rollout
    then said k must be finite, of a value given finite)."""
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (1e39, 0.0, 1.0))
    s.add_plane()
    with pytest.raises(dp.SceneError, match=r"bodies\[0\]\.position = 1e\+39 is past "
                                            "float32's largest number"):
        dp.compile(s, 1e-3, dtype=jnp.float32)
    s = dp.Scene()
    s.add_material("hard", k=1e300, c=1.0)
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    s.add_plane(material="hard")
    with pytest.raises(dp.SceneError, match=r"materials\['hard'\]\.k = 1e\+300 is past"):
        dp.compile(s, 1e-3, dtype=jnp.float32)
    sim = dp.compile(ball_scene, 1e-3, dtype=jnp.float32)
    with pytest.raises(dp.SceneError, match=r"contact k of material 'default' \(N/m\) = "
                                            r"1e\+300 is past float32's largest number"):
        sim.params(k=1e300, c=1.0)
    assert np.isfinite(sim.params(k=1e30, c=1.0).contact["default"].k)


def test_a_step_too_short_for_float32_warns(ball_scene):
    """Regression: in float32 a 10 cm ball dropped from 1 m at dt = 1e-7 s stood still while
    its velocity grew (its displacement per step rounded away) and fell 1.9% short in 0.2 s,
    without a word (the far-from-origin check looked at coordinates only); a stiff bead's
    substeps="auto" picked such a step too. Now a PrecisionWarning naming float64 and the
    shortest step resolved (6.0e-7 s here); float64 and ordinary steps stay silent."""
    import warnings
    scene = ball_scene
    for dtype, dt, warns in ((jnp.float32, 1e-7, True), (jnp.float32, 1e-5, False),
                             (jnp.float64, 1e-7, False)):
        s = dp.compile(scene, dt, dtype=dtype)
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            s.rollout(s.params(k=1e4, c=20.0), 5, save_every=5)
        hits = [w for w in got if issubclass(w.category, dp.PrecisionWarning)]
        assert bool(hits) == warns, (dtype, dt, [str(w.message) for w in got])
        if warns:
            assert "dtype=float64" in str(hits[0].message) and "6e-07 s" in str(hits[0].message)
            assert hits[0].filename == __file__          # points at the caller's rollout
            with warnings.catch_warnings(record=True) as got:
                warnings.simplefilter("always")
                s.step(s.params(k=1e4, c=20.0), s.init_state())
            # and at the caller's step (it pointed at diffpen/compile.py: a hand-counted
            # stacklevel one frame short)
            assert [w.filename for w in got] == [__file__], [(w.filename, w.lineno) for w in got]
    # a 1 mm ball dropped from 5 mm near the origin, where float32 resolves ~250x finer than
    # at 1 m: dt 2e-6 s agrees with float64 to 6e-5 of the radius and does not warn (the
    # spacing was taken at 1 m at least)
    small = dp.Scene()
    small.add_sphere(0.001, 3.3e-5, (0.0, 0.0, 0.005))
    small.add_plane()
    assert dp.precision.min_resolved_step(small, np.float32) < 2e-6


def test_a_step_loop_gets_the_rollouts_verdict_through_a_bounce_and_auto_substeps(ball_scene):
    """Regression: sim.step's gate counted the energy of each state it was given, so a Hertz
    ball (k 1e6 N/m^1.5, dt 1e-3 s) that its rollout steps safely was refused mid-bounce
    (a touching state has no energy bound: the radius's stiffer bound), and it ran the gate
    on every call; with substeps="auto" it stepped one substep and told the user to compile
    with substeps='auto'. Now one verdict per params kept through the contact, and "auto"
    steps with the count it picks, as a rollout does."""
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.4))
    scene.add_plane()
    hertz = dp.compile(scene, 1e-3, law="hunt_crossley", exponent=1.5)
    p = hertz.params(k=1e6, c=0.0)
    state, low = hertz.init_state(), 1.0
    for _ in range(400):                                 # falls, bounces, flies again
        state = hertz.step(p, state)
        low = min(low, float(state.position[0, 2]))
    assert low < 0.1 < float(state.position[0, 2])
    np.testing.assert_allclose(state.position, hertz.rollout(p, 400).position[-1], rtol=1e-12)
    auto = dp.compile(ball_scene, 1e-3, substeps="auto")
    q = auto.params(k=1e7, c=20.0)
    one = auto.step(q, auto.init_state())
    np.testing.assert_allclose(one.position, auto.rollout(q, 1).position[-1], rtol=1e-12)


def test_a_rigid_body_too_small_for_the_dtype_is_refused_at_compile():
    """Regression: a box of half extent 1e-20 m in float32 (moments 7e-41 kg m^2, below
    float32's smallest normal) compiled, ran to NaN at its first step, and the rollout
    blamed the time step; at 1e-170 m in float64 a raw LinAlgError came out of compile."""
    for half, dtype, ok in ((1e-20, jnp.float32, False), (1e-170, jnp.float64, False),
                            (1e-3, jnp.float32, True)):
        s = dp.Scene()
        s.add_box((half, half, half), 1.0, (0.0, 0.0, 1.0))
        s.add_plane()
        if ok:
            dp.compile(s, 1e-3, dtype=dtype)
            continue
        with pytest.raises(dp.SceneError, match="(moments of inertia reach|size) .* "
                                                "smallest normal"):
            dp.compile(s, 1e-3, dtype=dtype)


def test_a_sphere_too_small_for_the_dtype_is_refused_at_compile():
    """Regression (audit17): a sphere of radius 5e-324 m (float64) ended in a raw
    ZeroDivisionError from the step-length check (its fall time rounds to 0), and one of
    1e-50 m in float32 (0 there) compiled with a PrecisionWarning asking for an inner step
    of at least 1.9e+148 s. Both are refused, naming the size."""
    for radius, dtype in ((5e-324, jnp.float64), (1e-50, jnp.float32)):
        s = dp.Scene()
        with warnings.catch_warnings():     # the overlap grid's cells: no overflow warning
            warnings.simplefilter("error", RuntimeWarning)
            s.add_sphere(radius, 1.0, (0.0, 0.0, 1.0))
            s.add_plane()
        with pytest.raises(dp.SceneError, match=r"body 0's size \(.* m\) is below the square "
                                                "root of .* smallest normal number"):
            dp.compile(s, 1e-3, dtype=dtype)
    # a float32 slip speed of 1e-20 m/s: s^2 underflowed, friction was 0 / 0 at rest and the
    # NaN's message blamed the time step
    s = dp.Scene()
    s.add_material("rough", friction=1e-30, slip_speed=1e-20)
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.1))
    s.add_plane(material="rough")
    with pytest.raises(dp.SceneError, match="slip_speed .* rounds to 0 for a body at rest"):
        dp.compile(s, 1e-3, dtype=jnp.float32)


def test_an_event_exact_record_whose_step_float32_cannot_resolve_warns():
    """Regression (audit17): the event-exact records rebuild each step's force from a second
    difference of positions over h^2, whose float32 rounding grows as spacing / h^2: a ball
    at dt 5e-5 s had derivatives off by up to 13x (1e-4 s: 64%) with no word, where the
    default record stayed within 0.4%. A rollout (or step) whose inner step, substeps
    included, is past the step float32 resolves to 1e-3 of g warns, naming float64;
    float64, and float32 at a long enough step, do not."""
    from diffpen.precision import events_min_step
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.2))
    scene.add_plane()
    rec = dp.laws.linear(events=True)
    least = events_min_step(scene, jnp.float32)
    assert 1e-3 < least < 3e-3 and events_min_step(scene, jnp.float64) < 1e-7

    def run(dt, dtype, law=rec, **kw):
        sim = dp.compile(scene, dt, law=law, dtype=dtype)
        sim.rollout(sim.params(k=1e4, c=20.0), 2, **kw)
    with pytest.warns(dp.PrecisionWarning, match="event-exact contact record at an inner "
                                                 "step of 0.0001 s in float32.*float64"):
        run(1e-4, jnp.float32)
    with pytest.warns(dp.PrecisionWarning, match="inner step of 0.0005 s in float32"):
        run(2.5e-3, jnp.float32, substeps=5)                  # the step the rollout takes
    sim = dp.compile(scene, 1e-4, law=rec, dtype=jnp.float32)  # steps (audit19): unchecked,
    with pytest.warns(dp.PrecisionWarning, match="event-exact"):    # and traced
        sim.step(sim.params(k=1e4, c=20.0), sim.init_state(), check_stability=False)
    with pytest.warns(dp.PrecisionWarning, match="event-exact"):
        jax.jit(lambda k: sim.step(sim.params(k=k, c=20.0), sim.init_state()).time)(1e4)
    with warnings.catch_warnings():
        warnings.simplefilter("error", dp.PrecisionWarning)
        run(1e-4, jnp.float64)
        run(2.5e-3, jnp.float32)
        run(1e-4, jnp.float32, law="linear")                  # the default record


def test_a_rest_float32_cannot_resolve_warns_under_an_explicit_integrator():
    """A 1 g ball resting on k 1e7 N/m sags 1e-9 m, below float32's resolution of its
    position: implicit Euler refused it, the explicit integrators returned d z / dk 17x too
    small with no word (audit33). They warn now; the value is right to a rounding; float64
    and a resolvable sag stay quiet."""
    k, m = 1e7, 1e-3

    def sim_of(dtype, mass):
        s = dp.Scene(gravity=(0.0, 0.0, -9.81))
        s.add_sphere(0.1, mass, (0.0, 0.0, 0.1 - mass * 9.81 / k))
        s.add_plane()
        return dp.compile(s, dt=1e-3, substeps="auto", dtype=dtype)
    sim = sim_of(jnp.float32, m)
    with pytest.warns(dp.PrecisionWarning, match=r"static deflection .* 9.8e-10 m.*derivatives"
                      r" w.r.t. the stiffness"):
        z = sim.rollout(sim.params(k=k, c=100.0), 50, save_every=50).position[-1, 0, 2]
    assert abs(float(z) - 0.1) < 1e-7
    for dtype, mass in ((jnp.float64, m), (jnp.float32, 1.0)):
        quiet = sim_of(dtype, mass)
        with warnings.catch_warnings():
            warnings.simplefilter("error", dp.PrecisionWarning)
            quiet.rollout(quiet.params(k=k, c=100.0), 5)


def test_the_unresolved_rest_warning_is_given_once_per_simulator():
    """Its text carries the values, so Python's filter kept none of the repeats: a loop over
    12 stiffnesses warned 12 times (audit35)."""
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    s.add_sphere(0.1, 1e-3, (0.0, 0.0, 0.1))
    s.add_plane()
    sim = dp.compile(s, dt=1e-3, substeps="auto", dtype=jnp.float32)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        for k in (1e7, 2e7, 4e7):
            sim.rollout(sim.params(k=k, c=100.0), 2)
    assert sum(issubclass(w.category, dp.PrecisionWarning) for w in seen) == 1
