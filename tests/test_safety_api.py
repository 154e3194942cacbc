"""Library input checks: numbers are never coerced from strings or bools, params() refuses
vectors, rollout names a bad params pytree, state or size before anything is traced (start
overlaps: test_safety_overlaps.py)."""
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp


def ball_scene(**kw):
    scene = dp.Scene(**kw)
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    scene.add_plane()
    return scene


@pytest.fixture(scope="module")
def sim():
    return dp.compile(ball_scene(), 1e-3)


# --------------------------------------------------------------------------- numbers
@pytest.mark.parametrize("kw, words", [
    (dict(mass="1.0"), "mass (kg) must be a number, got '1.0': write it without quotes"),
    (dict(mass=True), "mass (kg) must be a number, got True"),
    (dict(radius="0.1"), "radius (m) must be a number"),
    (dict(mass=[1.0, 2.0]), "mass (kg) must be one number"),
    (dict(position="0 0 1"), "position (m) must be 3 numbers"),
    (dict(velocity=(1j, 0, 0)), "velocity (m/s) must be 3 numbers"),
    # regression: a bool among the numbers became 1.0, and a (1, 3) or (3, 1) array was
    # flattened into a position
    (dict(position=(True, 0.0, 1.0)), "position (m) must be 3 numbers (x, y, z), got (True"),
    (dict(position=[[0.0, 0.0, 1.0]]), "one flat sequence"),
    (dict(velocity=np.zeros((3, 1))), "shape (3, 1)"),
])
def test_scene_numbers_are_not_coerced(kw, words):
    args = dict(radius=0.1, mass=1.0, position=(0.0, 0.0, 1.0))
    args.update(kw)
    with pytest.raises(dp.SceneError) as exc:
        dp.Scene().add_sphere(**args)
    assert words in str(exc.value)


def test_dt_and_params_are_not_coerced_and_k_is_a_scalar(sim):
    with pytest.raises(dp.SceneError, match="dt must be a number of seconds, got '1e-3'"):
        dp.compile(ball_scene(), "1e-3")
    with pytest.raises(dp.SceneError, match="dt must be a number"):
        dp.compile(ball_scene(), True)
    # regression: a quoted exponent was read as a number, True as n = 1
    with pytest.raises(dp.SceneError, match="exponent must be a number, got '1.5': write it"):
        dp.compile(ball_scene(), 1e-3, law="hunt_crossley", exponent="1.5")
    with pytest.raises(dp.SceneError, match="exponent must be a number, got True"):
        dp.compile(ball_scene(), 1e-3, law="hunt_crossley", exponent=True)
    with pytest.raises(dp.SceneError, match="got '1e4': write it without quotes"):
        sim.params(k="1e4", c=1.0)
    with pytest.raises(dp.SceneError, match="must be a number, got True"):
        sim.params(k=1e4, c=True)
    with pytest.raises(dp.SceneError, match=r"must be a scalar, got an array of shape \(3,\)"
                                            r".*jax.vmap"):
        sim.params(k=np.array([1e3, 1e4, 1e5]), c=1.0)
    sim.params(k=np.float32(1e4), c=np.array(1.0))          # numpy scalars are numbers


def test_rollout_refuses_bad_params_state_and_sizes_before_tracing(sim, monkeypatch):
    from diffpen import checks
    monkeypatch.setattr(checks, "memory_bytes", lambda: 8.0 * 2 ** 30)
    p = sim.params(k=1e4, c=10.0)
    s0 = sim.init_state()
    with pytest.raises(dp.SceneError, match="rollout needs the params pytree from sim.params"):
        sim.rollout(None, 10)
    with pytest.raises(dp.SceneError, match=r"state.position has shape \(2, 3\), this "
                                            r"simulator needs \(1, 3\)"):
        sim.rollout(p, 10, s0._replace(position=jnp.zeros((2, 3))))
    with pytest.raises(dp.SceneError, match="state.velocity has dtype"):
        sim.rollout(p, 10, s0._replace(velocity=s0.velocity.astype(jnp.float32)))
    # regression: a Python float time read "state.time has dtype None"
    with pytest.raises(dp.SceneError, match=r"state.time has no dtype \(float\), this "
                                            r"simulator runs in float64: cast it"):
        sim.rollout(p, 10, s0._replace(time=0.5))
    with pytest.raises(dp.SceneError) as exc:            # names the state, not the time step
        sim.rollout(p, 10, s0._replace(position=s0.position.at[0, 2].set(jnp.nan)))
    assert "start state is not finite: state.position of body 0" in str(exc.value)
    assert "time step is not the cause" in str(exc.value)
    with pytest.raises(dp.SceneError) as exc:
        sim.rollout(p, 10 ** 12)
    assert "int32" in str(exc.value) and "TiB" in str(exc.value)
    with pytest.raises(dp.SceneError, match="would store .* GiB, more than half"):
        sim.rollout(p, 2 * 10 ** 8)
    with pytest.raises(dp.SceneError, match=r"use steps=10\)"):
        sim.rollout(p, 10.0)


def test_too_many_pairs_without_a_broad_phase_are_refused_before_compiling(monkeypatch):
    from diffpen import checks
    monkeypatch.setattr(checks, "MAX_PAIRS", 10)
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    for i in range(6):                                   # 15 pairs
        scene.add_sphere(0.1, 1.0, (0.3 * i, 0.0, 0.0))
    with pytest.raises(dp.SceneError, match=r"6 colliding spheres make 15 sphere-sphere pairs"
                                            r".*broadphase=diffpen.broadphase.Grid\(\)"):
        dp.compile(scene, 1e-3)
    dp.compile(scene, 1e-3, broadphase=dp.broadphase.Grid())


# --------------------------------------------------------------------------- probes
def test_rollout_checks_params_edited_with_replace(sim):
    """rollout re-checks the values of a params tree edited with ``_replace`` as
    ``sim.params`` does (a negative k sent a box 25 km below its plane; a NaN friction
    crashed in the stability gate with an int conversion)."""
    from diffpen.state import ContactParams
    p = sim.params(k=1e4, c=20.0)
    for pair, words in [((-1e4, 20.0), ["contact k", "'default'", ">= 0"]),
                        ((1e4, float("nan")), ["contact c", "finite"]),
                        ((np.array([1e4, 2e4]), 20.0), ["scalar", "shape (2,)"])]:
        bad = p._replace(contact={"default": ContactParams(*map(np.asarray, pair))})
        with pytest.raises(dp.SceneError) as e:
            sim.rollout(bad, 10)
        for w in words:
            assert w in str(e.value)
    with pytest.raises(dp.SceneError, match="params.contact has"):
        sim.rollout(p._replace(contact={}), 10)
    # regression: a plain (k, c) tuple failed inside the traced force ("'tuple' object has no
    # attribute 'k'"); and a concrete JAX array as steps was refused without saying why
    with pytest.raises(dp.SceneError, match=r"is a tuple; .*dp\.ContactParams\(k, c\)"):
        sim.rollout(dp.Params(contact={"default": (1e4, 20.0)}, springs={}), 10)
    with pytest.raises(dp.SceneError, match=r"static, the compiled loop.s length: pass a "
                                            r"Python int"):
        sim.rollout(p, jnp.asarray(10))


def test_unknown_extra_keys_are_refused():
    """A misspelt ``extra`` key was dropped silently: the box rested on the plane the
    user meant to move."""
    s = dp.Scene()
    s.add_material("ice", k=1e4, c=20.0, friction=0.2)
    s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.1))
    s.add_plane(material="ice", name="ground")
    bsim = dp.compile(s, 5e-4)
    with pytest.raises(dp.SceneError, match=r"plane_ofset.*known: \['friction', 'plane_offset'\]"):
        bsim.params(extra={"plane_ofset": {"ground": 0.05}})
    p = bsim.params()
    with pytest.raises(dp.SceneError, match="friction parameter of group 'ice' must be >= 0"):
        bsim.rollout(p._replace(extra={**p.extra, "friction": {"ice": -0.5}}), 10)
    # the message speaks of the value refused (it blamed "stiffness and damping" for a mu)
    with pytest.raises(dp.SceneError, match="got -0.1: it cannot be negative") as info:
        bsim.params(extra={"friction": {"ice": -0.1}})
    assert "stiffness" not in str(info.value)
    with pytest.raises(dp.SceneError, match="stiffness and damping cannot be negative"):
        bsim.params(k=-1.0)
    with pytest.raises(dp.SceneError, match=r"params.extra\['friction'\] has \[\]"):
        bsim.rollout(p._replace(extra={**p.extra, "friction": {}}), 10)


def test_a_pinned_body_takes_no_velocity():
    """A pinned particle given a velocity through ``state_from`` drifted 1 m in 1 s."""
    s = dp.Scene()
    a = s.add_particle(1.0, (0.0, 0.0, 1.0), pinned=True)
    b = s.add_particle(1.0, (0.0, 0.0, 0.5))
    s.add_spring(a, b, k=100.0, c=1.0)
    psim = dp.compile(s, 1e-3)
    with pytest.raises(dp.SceneError, match="body 0 is pinned"):
        psim.state_from(body=a, velocity=(1.0, 0.0, 0.0))
    st = psim.init_state()
    moved = st._replace(velocity=st.velocity.at[a].set(jnp.array([1.0, 0.0, 0.0])))
    with pytest.raises(dp.SceneError, match="body 0 is .*pinned"):
        psim.rollout(psim.params(), 10, moved)
    # placing the pin elsewhere is allowed, and it stays there
    placed = psim.state_from(body=a, position=(0.5, 0.0, 1.0))
    assert np.allclose(psim.rollout(psim.params(), 10, placed).position[-1, a], [0.5, 0.0, 1.0])


def test_start_state_orientation_and_time_are_checked():
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.3, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(0.5, 4.0, 0.3))
    bsim = dp.compile(s, 1e-3)
    st = bsim.init_state()
    with pytest.raises(dp.SceneError, match="norm 0: orientations are unit quaternions"):
        bsim.rollout(bsim.params(), 10, st._replace(orientation=jnp.zeros_like(st.orientation)))
    with pytest.raises(dp.SceneError, match="time is nan"):
        bsim.rollout(bsim.params(), 10, st._replace(time=jnp.asarray(np.nan)))


def test_state_from_refuses_a_zero_quaternion():
    """state_from normalised a zero orientation to NaN: sim.step returned NaN positions and
    rollout blamed "NaN/inf in" an orientation typed as zeros (add_box refuses it)."""
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    box = s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 1.0))
    bsim = dp.compile(s, 1e-3)
    with pytest.raises(dp.SceneError, match="orientation of body 0 has norm 0.*unit quaternion"):
        bsim.state_from(body=box, orientation=(0.0, 0.0, 0.0, 0.0))
    st = bsim.state_from(body=box, orientation=(2.0, 0.0, 0.0, 0.0))     # normalised
    np.testing.assert_allclose(st.orientation[box], [1.0, 0.0, 0.0, 0.0])


def test_anchored_spring_between_particles_equals_a_spring():
    """Zero anchors on two particles (accepted by the scene) crashed the rollout: the term
    read orientations a scene without rotating bodies does not have."""
    def scene(anchored):
        s = dp.Scene(gravity=(0.0, 0.0, 0.0))
        s.add_particle(1.0, (0.0, 0.0, 0.0))
        s.add_particle(2.0, (1.0, 0.0, 0.0), velocity=(0.3, 0.1, 0.0))
        if anchored:
            s.add_anchored_spring(0, 1, k=10.0, c=0.5, rest_length=0.5)
        else:
            s.add_spring(0, 1, k=10.0, c=0.5, rest_length=0.5)
        return dp.compile(s, 1e-3)
    a, b = scene(True), scene(False)
    ta, tb = a.rollout(a.params(), 300), b.rollout(b.params(), 300)
    assert np.allclose(ta.position, tb.position, rtol=0, atol=1e-12)


def test_redeclaring_a_material_or_group_with_other_values_is_refused():
    s = dp.Scene()
    s.add_material("rubber", k=3e3, c=10.0, friction=0.5)
    s.add_material("rubber", k=3e3, c=10.0, friction=0.5)         # the same: fine
    with pytest.raises(dp.SceneError, match="material 'rubber' is already declared"):
        s.add_material("rubber", k=3e3)
    s.add_material("default", k=1e4, c=20.0)                      # the blank default: fine
    s.add_spring_group("g", k=5.0, c=0.1)
    with pytest.raises(dp.SceneError, match="spring group 'g' is already declared"):
        s.add_spring_group("g", k=6.0, c=0.1)


def test_box_inertia_must_be_physical():
    s = dp.Scene()
    with pytest.raises(dp.SceneError, match="at most the sum of the other two"):
        s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 1.0), inertia=(1.0, 1.0, 3.0))
    s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 1.0), inertia=(1.0, 2.0, 3.0))   # a plate


def test_compile_unroll_must_be_an_int():
    for bad in (1.5, "x", 0, True):
        with pytest.raises(dp.SceneError, match="unroll must be a positive integer"):
            dp.compile(ball_scene(), 1e-3, unroll=bad)


def test_compile_dtype_must_be_float32_or_float64():
    """dtype=bfloat16 compiled and then refused its own params; int32 failed inside
    lax.scan."""
    for bad in (jnp.bfloat16, jnp.float16, jnp.int32, "nonsense"):
        with pytest.raises(dp.SceneError, match="dtype must be float32 or float64"):
            dp.compile(ball_scene(), 1e-3, dtype=bad)


def test_a_step_no_substep_count_can_save_says_so():
    """Friction 1e9 made the safe step 0 and the error read "Use dt < 0 s,
    substeps=100001"."""
    s = dp.Scene()
    s.add_material("ice", k=1e4, c=20.0, friction=1e9)
    s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.1))
    s.add_plane(material="ice")
    sim = dp.compile(s, 1e-3)
    with pytest.raises(dp.StabilityError, match="no practical step.*implicit_euler"):
        sim.rollout(sim.params(), 10)


@pytest.mark.parametrize("k, mass, count", [(1e300, 1.0, "about 2e+147 substeps"),
                                             (1e4, 1e-300, "about 1e+298 substeps"),
                                             (1e4, 1e-30, "about 1e+28 substeps")])
def test_an_absurd_stiffness_or_mass_is_refused_at_once(k, mass, count):
    """k = 1e300 N/m or a 1e-300 kg ball hung the rollout (and ``diffpen simulate ball --k
    1e300``): the substep count's search stepped n by one from ~1e150, where dt / n and
    dt / (n - 1) are one float, and never ended. Refused at once now, with the count in
    three digits (a mass of 1e-30 kg said "safe step 0 s, 100001 substeps"; its safe step,
    2 / C = 2e-31 s, is computed without cancelling since audit17, where it was 0)."""
    import signal

    def hung(*_):
        raise TimeoutError("the stability check hung")
    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(30)
    try:
        s = dp.Scene()
        s.add_sphere(0.1, mass, (0.0, 0.0, 1.0))
        s.add_plane()
        sim = dp.compile(s, 1e-3)
        with pytest.raises(dp.StabilityError, match=f"no practical step.*{re.escape(count)}"):
            sim.rollout(sim.params(k=k, c=10.0), 10)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_contact_pairs_may_be_arrays():
    sim = dp.compile(ball_scene(), 1e-3)
    p = sim.params(contact={"default": np.array([1e4, 20.0])})
    assert float(p.contact["default"].k) == 1e4 and float(p.contact["default"].c) == 20.0


def test_bad_params_under_jax_grad_are_refused_as_in_a_plain_rollout(sim):
    """Regression: sim.params checked values only when concrete, so under jax.grad (whose
    tracers carry the value) a NaN k raised "cannot convert float NaN to integer" from the
    stability gate, and a negative k or c ran and returned NaN or a gradient silently. Now
    the same SceneError as for the plain value."""
    def loss(k, c):
        return sim.rollout(sim.params(k=k, c=c), 50, save_every=50).position[-1, 0, 2]
    for args, argnum, words in (((float("nan"), 20.0), 0, "must be finite, got nan"),
                                ((1e4, float("inf")), 1, "must be finite, got inf"),
                                ((-1e4, 20.0), 0, "must be >= 0, got -10000.0"),
                                ((1e4, -50.0), 1, "must be >= 0, got -50.0")):
        with pytest.raises(dp.SceneError, match=words):
            loss(*args)
        with pytest.raises(dp.SceneError, match=words):
            jax.grad(loss, argnum)(*args)
        with pytest.raises(dp.SceneError, match=words):
            jax.jvp(loss, args, (1.0, 0.0))


def test_stability_report_refuses_non_finite_params(sim):
    """Regression: sim.stability with a NaN k (params edited with _replace) raised
    "cannot convert float NaN to integer"; now a SceneError that says what to fix."""
    p = sim.params(k=1e4, c=20.0)
    mat = next(iter(p.contact))
    bad = p._replace(contact={**p.contact, mat: p.contact[mat]._replace(k=float("nan"))})
    with pytest.raises(dp.SceneError, match=r"contact k of material '\w+' \(N/m\) must be "
                                            "finite, got nan"):
        sim.stability(bad)


def test_traced_stability_flag_marks_nan_and_negative_rows(sim):
    """Regression: under jit + vmap the rollout's aux["unstable"] flag compared the safe step
    with NaN (always False) and never saw a negative k: a batch row with k = NaN or -1e4
    ended NaN and was not flagged, so sweeps and fits counted it as a valid run."""
    run = jax.jit(jax.vmap(lambda k: sim.rollout(sim.params(k=k, c=20.0), 200,
                                                 save_every=200).aux["unstable"][-1]))
    flags = np.asarray(run(jnp.array([1e4, jnp.nan, -1e4, 2e4, 1e9])))
    assert flags.tolist() == [False, True, True, False, True]


def test_traced_flag_marks_bad_values_under_implicit_euler_and_in_extras():
    """Regression: the flag's NaN / negative test ran for explicit integrators only (an
    implicit_euler row with k = NaN or -1e4 ended NaN or 2e10 m into the plane, unflagged),
    and of the extras only finiteness was tested: a negative drag (a particle sped up from
    1 to 7.4 m/s) and a yield strain outside (0, 1) (a negative rest length) passed
    unflagged. Concrete values of all of these are refused by sim.params."""
    imp = dp.compile(ball_scene(), 1e-3, integrator="implicit_euler")
    run = jax.jit(jax.vmap(lambda k: imp.rollout(imp.params(k=k, c=20.0), 20,
                                                 save_every=20).aux["unstable"][-1]))
    assert np.asarray(run(jnp.array([1e4, jnp.nan, -1e4]))).tolist() == [False, True, True]
    free = dp.Scene(gravity=(0.0, 0.0, 0.0))
    a = free.add_particle(1.0, (0.0, 0.0, 0.0), pinned=True)
    b = free.add_particle(1.0, (0.4, 0.0, 0.0), (1.0, 0.0, 0.0))
    free.add_drag(b, 0.1)
    free.add_plastic_spring(a, b, k=1000.0, c=0.0, yield_strain=0.05)
    sim2 = dp.compile(free, 1e-4)

    def flag(drag, strain):
        p = sim2.params(extra={"drag": {"drag": drag}, "plastic": {"plastic": strain}})
        return sim2.rollout(p, 10, save_every=10).aux["unstable"][-1]
    rows = jax.jit(jax.vmap(flag))(jnp.array([0.1, -2.0, 0.1, 0.1, 0.1]),
                                   jnp.array([0.05, 0.05, 1.5, -0.2, 0.0]))
    assert np.asarray(rows).tolist() == [False, True, True, True, True]


def test_state_from_checks_shapes_duplicates_and_start_overlaps():
    """Regression: state_from broadcast whatever it got (raw JAX broadcasting errors for a
    (2,) position or a (3,) quaternion, 'could not convert string to float' for text),
    took body=[0, 0] with the last row silently winning, and started a body 0.6 m inside
    the ground without the scene's overlap check (diffpen evaluate then reported a
    10801% error)."""
    s = dp.Scene()
    b = s.add_box((0.05,) * 3, 0.37, (0.0, 0.0, 0.2))
    s.add_plane()
    box = dp.compile(s, 1e-3)
    for kw, words in ((dict(position=(0, 0)), r"position must have shape \(3,\), got shape "
                       r"\(2,\)"),
                      (dict(orientation=(1, 0, 0)), r"orientation must have shape \(4,\)"),
                      (dict(angular_velocity=(1, 0), frame="body"),
                       r"angular_velocity must have shape"),
                      (dict(angular_velocity=(0, 0, 1)), "needs frame='body' .* or "
                       "frame='world'"),
                      (dict(position="abc"), "position must be numbers, 3 per body"),
                      (dict(position=[[0, 0, 1], [0, 0, 2]]), r"got shape \(2, 3\)"),
                      (dict(position=(0, 0, -0.2)), "box 0 started at .* plane 0 .* raise "
                       "its start by 0.25 m")):
        with pytest.raises(dp.SceneError, match=words):
            box.state_from(body=b, **kw)
    box.state_from(body=b, position=(0.0, 0.0, 0.04))      # resting on a corner: fine
    ball = dp.compile(ball_scene(), 1e-3)
    with pytest.raises(dp.SceneError, match="more than once"):
        ball.state_from(body=[0, 0], position=[[0, 0, 1], [0, 0, 2]])
    with pytest.raises(dp.SceneError, match="sphere 0 at .* plane 0 .* overlap by 0.6 m"):
        ball.state_from(position=(0.0, 0.0, -0.5))
    free = dp.compile(ball_scene(allow_overlap=True), 1e-3)
    free.state_from(position=(0.0, 0.0, -0.5))              # the scene allows it
    # regression: a NaN or inf start value was taken, and only the rollout's NaN said so
    for kw in (dict(position=(0.0, 0.0, float("nan"))), dict(velocity=(float("inf"), 0, 0))):
        with pytest.raises(dp.SceneError, match="must be finite numbers"):
            ball.state_from(**kw)
    with pytest.raises(dp.SceneError, match="angular_velocity must be finite"):
        box.state_from(body=b, angular_velocity=(0, float("nan"), 0), frame="body")


def test_scene_flags_and_group_values_are_not_coerced():
    """Regression: pinned="no" and collide="no" became True (a pinned body), Scene(
    allow_overlap="no") True; a group's k="x" raised a bare ValueError; yield_strain="0.1"
    was read as 0.1 and [0.1] raised TypeError; sim.params(extra={"plastic": 0.1}) raised
    TypeError."""
    s = dp.Scene()
    with pytest.raises(dp.SceneError, match="pinned must be True or False, got 'no'"):
        s.add_particle(1.0, (0, 0, 1), pinned="no")
    with pytest.raises(dp.SceneError, match="collide must be True or False"):
        s.add_particle(1.0, (0, 0, 1), collide="no")
    with pytest.raises(dp.SceneError, match="allow_overlap must be True or False"):
        dp.Scene(allow_overlap="no")
    a, b = s.add_particle(1.0, (0, 0, 1)), s.add_particle(1.0, (1, 0, 1))
    s.add_spring(a, b, k=1.0, group="g")
    with pytest.raises(dp.SceneError, match="spring k must be a number, got 'x'"):
        s.add_spring(a, b, k="x", group="g")
    with pytest.raises(dp.SceneError, match="yield_strain must be a number, got '0.1'"):
        s.add_plastic_spring(a, b, k=1.0, yield_strain="0.1", group="p1")
    with pytest.raises(dp.SceneError, match="yield_strain must be one number"):
        s.add_plastic_spring(a, b, k=1.0, yield_strain=[0.1], group="p2")
    s.add_plastic_spring(a, b, k=1.0, yield_strain=0.1, group="p3")
    sim = dp.compile(s, 1e-3)
    with pytest.raises(dp.SceneError, match=r"params extra\['plastic'\] must be a dict"):
        sim.params(extra={"plastic": 0.1})


def test_a_refused_add_call_leaves_the_scene_unchanged():
    """Regression: a refused add_spring / add_plastic_spring / add_anchored_spring still
    declared its group, so the corrected retry failed with 'group already has k=...'."""
    s = dp.Scene()
    a, b = s.add_particle(1.0, (0, 0, 1)), s.add_particle(1.0, (1, 0, 1))
    with pytest.raises(dp.SceneError, match="rest_length"):
        s.add_spring(a, b, k=5.0, group="g", rest_length=-1.0)
    assert "g" not in s.spring_groups and not s.springs
    s.add_spring(a, b, k=6.0, group="g", rest_length=1.0)
    with pytest.raises(dp.SceneError, match="is new: give k="):
        s.add_plastic_spring(a, b, yield_strain=0.1, group="pl")
    assert "pl" not in s.plastic_groups
    with pytest.raises(dp.SceneError, match="rest_length"):
        s.add_anchored_spring(a, b, k=2.0, group="h", rest_length=-1.0)
    assert "h" not in s.spring_groups and not s.anchored_springs
    s.add_anchored_spring(a, b, k=3.0, group="h")


def test_huge_and_tiny_normals_and_quaternions_are_normalised():
    """A plane normal (1e200, 1e200, 0) and a box orientation (1e200, 1e200, 0, 0) became
    zeros (their norm overflowed to inf): the plane pushed nothing and the box's rollout
    failed blaming the time step. A normal of 1e-200 entries underflowed the same way."""
    s = dp.Scene()
    s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 1.0), orientation=(1e200, 1e200, 0.0, 0.0))
    s.add_plane((1e200, 1e200, 0.0), offset=-5.0)
    s.add_plane((1e-200, 0.0, 1e-200), offset=-5.0)
    h = np.sqrt(0.5)
    np.testing.assert_allclose(s.bodies[0].orientation, (h, h, 0.0, 0.0), rtol=1e-15)
    np.testing.assert_allclose(s.planes[0].normal, (h, h, 0.0), rtol=1e-15)
    np.testing.assert_allclose(s.planes[1].normal, (h, 0.0, h), rtol=1e-15)
    with pytest.raises(dp.SceneError, match="plane normal must be non-zero"):
        s.add_plane((0.0, 0.0, 0.0))
    # regression: an orientation of norm 1e-13 was refused as "zero" (normals of 5e-324 pass)
    s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 3.0), orientation=(1e-13, 1e-13, 0.0, 0.0))
    np.testing.assert_allclose(s.bodies[1].orientation, (h, h, 0.0, 0.0), rtol=1e-15)


def test_rollout_switches_take_true_or_false_only():
    """``rollout(check_stability=None)`` switched the stability check off and
    ``check_finite="no"`` left the finiteness check on, without a word."""
    sim = dp.compile(ball_scene(), 1e-3)
    p = sim.params(k=1e4, c=10.0)
    for name, bad in (("check_stability", None), ("check_finite", "no"),
                      ("check_stability", 1)):
        with pytest.raises(dp.SceneError, match=f"{name} must be True or False"):
            sim.rollout(p, 10, **{name: bad})


def test_params_stability_and_observe_arguments_of_the_wrong_kind_say_so():
    """Raw Python errors before: sim.params(contact=[1, 2]) a TypeError, extra="x" a
    ValueError, sim.stability(None) an AttributeError, rollout(observe="x") "'str' object is
    not callable", and an observe returning text a raw error of JAX's scan."""
    sim = dp.compile(ball_scene(), 1e-3)
    p = sim.params(k=1e4, c=10.0)
    cases = ((lambda: sim.params(contact=[1, 2]), r"sim.params\(contact=...\) takes a dict"),
             (lambda: sim.params(k=1.0, c=1.0, extra="x"), r"params\(extra=...\) takes a dict"),
             (lambda: sim.params(springs=[1]), r"sim.params\(springs=...\) takes a dict"),
             (lambda: sim.stability(None), "sim.stability needs the params pytree"),
             (lambda: sim.rollout(p, 10, observe="x"), "observe must be a function"),
             (lambda: sim.rollout(p, 10, observe=lambda s: "a"),
              "observe.state. must return arrays"))
    for call, words in cases:
        with pytest.raises(dp.SceneError, match=words):
            call()
    assert sim.rollout(p, 10, observe=lambda s: s.position[:, 2]).observed.shape == (10, 1)


def test_forces_checks_its_step_and_arguments():
    """sim.forces(p, s, h=nan) returned NaN forces and h=-1 was taken as given; its params
    are checked as a rollout's (the state may be any, e.g. a pinned body moving)."""
    sim = dp.compile(ball_scene(), 1e-3)
    p, s = sim.params(k=1e4, c=10.0), sim.init_state()
    for bad in (float("nan"), -1.0, 0.0, "1e-3", True):
        with pytest.raises(dp.SceneError, match="h must be a positive, finite inner step"):
            sim.forces(p, s, h=bad)
    with pytest.raises(dp.SceneError, match="needs the params pytree"):
        sim.forces(None, s)
    f, _ = sim.forces(p, s, h=1e-3)
    assert np.all(np.isfinite(np.asarray(f)))


def test_a_step_past_the_safe_step_is_refused_as_a_rollout_is(sim):
    """Regression: sim.step ran the params a rollout refuses (k 1e9 at dt 1e-3, safe step
    1.6e-5 s): 300 steps of a ball dropped from 0.12 m left it at 6 m and 24 m/s upward (50x
    its energy), a stiff spring reached 1e264 m, with no error and no flag. Now the same
    StabilityError, unless asked not to check."""
    p = sim.params(k=1e9, c=20.0)
    with pytest.raises(dp.StabilityError, match="substeps="):
        sim.step(p, sim.init_state())
    assert np.all(np.isfinite(sim.step(p, sim.init_state(), check_stability=False).position))
    ok = sim.step(sim.params(k=1e4, c=20.0), sim.init_state())
    assert float(ok.position[0, 2]) < 1.0
