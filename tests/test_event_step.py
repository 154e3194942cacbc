"""The exact and event-exact one-contact records (diffpen.one_contact, diffpen.event_step,
``diffpen.laws.linear(events=True)``, ``no_tension(events=True)``, ``hunt_crossley(n,
events=True)``): the spring motion against the matrix exponential, the exact records'
factors against the damped spring, and rollouts' positions against the continuous motion
with its contact events located."""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen import laws
from diffpen.event_step import spring_flow

scipy = pytest.importorskip("scipy")
from scipy.integrate import solve_ivp  # noqa: E402
from scipy.linalg import expm  # noqa: E402

G = 9.81


def _height(state):
    """The first body's height: the rollouts' ``observe``, one function object for the
    module (a new one per call traced and compiled the rollout again)."""
    return state.position[0, 2]


@pytest.fixture(scope="module")
def compiled():
    """``get(scene, law, record, key=())``: ``scene`` compiled at dt = 1e-3, float64, with
    ``laws.<law>(<record>=True)``, once per (law, record, key) for the module and shared (a
    Simulator is frozen), so that the tests of one scene share its compiled rollouts. A key
    given a scene that differs from its first one in more than the bodies' start positions
    and velocities (which a caller passing its own start state may vary) is an error."""
    import dataclasses
    sims = {}

    def get(scene, law, record, key=()):
        bodies = ([dataclasses.replace(b, position=(0.0,) * 3, velocity=(0.0,) * 3)
                   for b in scene.bodies], scene.planes, scene.gravity)
        if (law, record, key) not in sims:
            sims[law, record, key] = (dp.compile(scene, 1e-3, law=getattr(laws, law)(
                **{record: True}), dtype=jnp.float64), bodies)
        assert sims[law, record, key][1] == bodies, f"{key!r} was compiled for another scene"
        return sims[law, record, key][0]
    return get


def _ball03(get, law, record):
    """The 0.3 kg ball (radius 0.1 m, 0.25 m up) over the plane, from ``get`` (above)."""
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=0.3, position=(0.0, 0.0, 0.25))
    scene.add_plane()
    return get(scene, law, record, "0.3 kg ball")


@pytest.mark.parametrize("w2, b", [(1e5, 50.0), (1e4, 20.0), (100.0, 1500.0)],
                         ids=["stiff", "quick-start", "overdamped"])
def test_spring_flow_is_the_matrix_exponential(w2, b):
    """``spring_flow(tau)`` against scipy's expm of the augmented matrix [[0, 1, 0], [-w2, -b,
    1], [0, 0, 0]] for steps back and ahead (w0 tau up to 0.95)."""
    for tau in (-2e-3, 1e-3, 3e-3):
        e = expm(np.array([[0.0, 1.0, 0.0], [-w2, -b, 1.0], [0.0, 0.0, 0.0]]) * tau)
        got = np.array(spring_flow(jnp.float64(tau), w2, b), dtype=float)
        want = np.array([e[0, 0], e[0, 1], e[1, 0], e[1, 1], e[0, 2], e[1, 2]])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15 * max(1.0, abs(tau) * w2))


def test_only_one_one_contact_record_at_a_time():
    for law in (laws.linear, laws.no_tension):
        with pytest.raises(ValueError, match="choose one"):
            law(exact=True, events=True)
    with pytest.raises(ValueError, match="choose one"):
        laws.hunt_crossley(1.5, centred=True, events=True)
    # laws.get builds a named law's event-exact record (what `diffpen fit --events` takes)
    from diffpen.event_step import linear_events, no_tension_events
    assert laws.get("linear", events=True).centred is linear_events
    assert laws.get("no_tension", events=True).centred is no_tension_events
    hc = laws.get("hunt_crossley", 1.5, events=True)
    assert hc.exponent == 1.5 and hc.centred.__name__ == "events"
    assert laws.get("hunt_crossley", 1.5).centred is None


def test_one_contact_records_refuse_what_they_do_not_step():
    """Regression: an exact or event-exact record given with another integrator, a smoothing
    band, or a scene where a body can feel two forces (a stack, a box) compiled and silently
    took the plain step average (or, for the stack, rebuilt each contact's motion as if it
    were the body's only one). Now ``diffpen.compile`` refuses it, saying what to change."""
    ball = dp.Scene()
    ball.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    ball.add_plane()
    stack = dp.Scene()
    stack.add_sphere(0.1, 1.0, (0.0, 0.0, 0.1))
    stack.add_sphere(0.1, 1.0, (0.0, 0.0, 0.3))
    stack.add_plane()
    box = dp.Scene()
    box.add_box((0.05, 0.05, 0.05), 0.4, (0.0, 0.0, 0.3))
    box.add_plane()
    for law in (laws.linear(events=True), laws.no_tension(exact=True),
                laws.hunt_crossley(1.5, events=True)):
        with pytest.raises(dp.SceneError, match="integrator='semi_implicit_euler'"):
            dp.compile(ball, 1e-3, law=law, integrator="rk4")
        with pytest.raises(dp.SceneError, match="smoothing='auto'"):
            dp.compile(ball, 1e-3, law=law, smoothing=1e-3)
        for scene in (stack, box):
            with pytest.raises(dp.SceneError, match="more than one force"):
                dp.compile(scene, 1e-3, law=law)
    dp.compile(stack, 1e-3, law="linear")        # the named law fits any scene


def _continuous(z0, v0, k, c, m, r, times, law="linear", n=1.0):
    """Heights at ``times`` of a ball started at (z0, v0): free flight and contact solved
    piece by piece with DOP853, the contact's start (the surface reached from outside) and
    end (the surface reached from inside for the linear law, which may pull, and for
    Hunt-Crossley, ``max(d^n (k + c d'), 0)``; the force reaching 0 for no_tension, which then
    flies free inside the surface) located as events."""
    def free(t, y):
        return [y[1], -G]

    def contact(t, y):
        d = r - y[0]
        if law == "hunt_crossley":
            return [y[1], -G + max(max(d, 0.0) ** n * (k - c * y[1]), 0.0) / m]
        return [y[1], -G + (k * d - c * y[1]) / m]

    def touch(t, y):
        return y[0] - r
    touch.terminal = True
    touch.direction = -1.0

    def release(t, y):
        return y[0] - r if law != "no_tension" else k * (r - y[0]) - c * y[1]
    release.terminal = True
    release.direction = 1.0 if law != "no_tension" else -1.0
    t, y, out, inside = 0.0, [z0, v0], [], False
    while t < times[-1]:
        sol = solve_ivp(contact if inside else free, (t, times[-1]), y, method="DOP853",
                        rtol=1e-13, atol=1e-15, events=release if inside else touch,
                        dense_output=True)
        end = sol.t_events[0][0] if sol.t_events[0].size else times[-1]
        sel = (times >= t) & (times <= end)
        out.append(sol.sol(times[sel])[0])
        times = times[~sel] if end < times[-1] else times[:0]
        if not times.size:
            break
        t, y, inside = end, sol.sol(end), not inside
    return np.concatenate(out)


@pytest.mark.parametrize("law, c", [("linear", 15.0), ("no_tension", 60.0)],
                         ids=["linear", "no_tension"])
def test_positions_are_samples_of_the_continuous_motion_through_contact_start_and_end(
        compiled, law, c):
    """The 0.3 kg ball (k 3e4, c 15 linear / 60 no_tension, w h 0.32) dropped onto the plane
    at dt = 1e-3: with ``events=True`` the positions of a rollout (semi-implicit Euler: its
    velocity is the secant of the last step, so the continuous motion starts at
    ``v0 - g h / 2``) are the continuous motion's at every step time, before, through and
    after the contact (for no_tension also through the release and the free flight inside
    the surface after it), within 1e-10 m; the exact record (exact only inside contact) is
    1e-6 m off or more after the bounce. The batched rollout equals the single ones."""
    m, r, k, h, steps = 0.3, 0.1, 3e4, 1e-3, 400
    times = np.arange(steps + 1) * h
    want = _continuous(0.25, -G * h / 2, k, c, m, r, times, law)

    def heights(sim, k_):
        return sim.rollout(sim.params(k=k_, c=c), steps, observe=_height).observed
    events, exact = _ball03(compiled, law, "events"), _ball03(compiled, law, "exact")
    # one compiled single rollout, for the check against the continuous motion and for the
    # batched rollout's lanes (a second, eager rollout compiled the same program again),
    # called with Python floats only (a jax scalar compiled it once more)
    single = jax.jit(lambda k_: heights(events, k_))
    got = np.asarray(single(k))
    assert np.min(got) < r - 1e-3                       # the ball did bounce
    np.testing.assert_allclose(got, want[1:], atol=1e-10, rtol=0)   # states after each step
    old = np.asarray(heights(exact, k))
    assert np.max(np.abs(old - want[1:])) > 1e-6
    ks = [k, 2 * k]
    batched = np.asarray(jax.jit(jax.vmap(lambda k_: heights(events, k_)))(jnp.asarray(ks)))
    for i, ki in enumerate(ks):
        np.testing.assert_allclose(batched[i], np.asarray(single(ki)), rtol=0, atol=1e-12)


def test_event_exact_records_take_steps_up_to_w_h_one():
    """The safe step's contact limit ``w h <= 0.5`` bounds the energy a force held over a
    step injects where a contact starts or ends inside it; the linear and no_tension
    event-exact records follow the continuous motion through those steps, so they are held to
    ``w h <= 1.0`` (``ContactLaw.safe_wh``) instead. The 0.3 kg ball (k 3e4, w h 0.95 at
    dt 3e-3): its event-exact rollout runs and is the continuous motion within 1e-10 m at
    every step time through the bounce; the default record is refused at that step, and so is
    the event-exact record past w h 1.0 (k 4e4)."""
    m, r, h, k, c, steps = 0.3, 0.1, 3e-3, 3e4, 15.0, 120
    scene = dp.Scene()
    scene.add_sphere(radius=r, mass=m, position=(0.0, 0.0, 0.25))
    scene.add_plane()
    want = _continuous(0.25, -G * h / 2, k, c, m, r, np.arange(steps + 1) * h)[1:]
    sim = dp.compile(scene, h, law=laws.linear(events=True), dtype=jnp.float64)
    assert sim.analysis.contact_wh == 1.0
    got = np.asarray(sim.rollout(sim.params(k=k, c=c), steps, observe=_height).observed)
    assert np.min(got) < r - 4e-3                       # the ball did bounce
    np.testing.assert_allclose(got, want, atol=1e-10, rtol=0)
    with pytest.raises(dp.StabilityError, match="w h <= 1"):
        sim.rollout(sim.params(k=4e4, c=c), 10)
    plain = dp.compile(scene, h, law="linear", dtype=jnp.float64)
    assert plain.analysis.contact_wh == 0.5
    with pytest.raises(dp.StabilityError, match="w h <= 0.5"):
        plain.rollout(plain.params(k=k, c=c), 10)
    assert laws.no_tension(events=True).safe_wh == 1.0
    assert laws.hunt_crossley(1.5, events=True).safe_wh is None


def test_hunt_crossley_positions_follow_the_continuous_motion():
    """A Hertz ball (1 kg, hunt_crossley n 1.5, k 1e6 N/m^1.5, c 3e4) dropped onto the plane
    at dt = 1e-3 with ``hunt_crossley(1.5, events=True)``: the positions are the continuous
    motion's at every step time within 1e-6 m (measured 8e-8 m: the contact motion is a
    graded Runge-Kutta flow, not a closed form), the centred record's 6.5e-5 m. Batched
    equals single."""
    m, r, h, steps, k, c = 1.0, 0.1, 1e-3, 400, 1e6, 3e4
    scene = dp.Scene()
    scene.add_sphere(radius=r, mass=m, position=(0.0, 0.0, 0.25))
    scene.add_plane()
    want = _continuous(0.25, -G * h / 2, k, c, m, r, np.arange(steps + 1) * h,
                       "hunt_crossley", 1.5)[1:]

    def heights(sim, k_):
        # the safe step counts the depth the start's energy bounds (w h 0.40), not the
        # radius (0.69; diffpen.stability.depth)
        return sim.rollout(sim.params(k=k_, c=c), steps, observe=_height).observed
    events = dp.compile(scene, h, law=laws.hunt_crossley(1.5, events=True),
                        dtype=jnp.float64)
    centred = dp.compile(scene, h, law=laws.hunt_crossley(1.5, centred=True),
                         dtype=jnp.float64)
    single = jax.jit(lambda k_: heights(events, k_))
    got = np.asarray(single(k))
    assert np.min(got) < r - 3e-3                       # the ball did bounce
    np.testing.assert_allclose(got, want, atol=1e-6, rtol=0)
    assert np.max(np.abs(np.asarray(heights(centred, k)) - want)) > 1e-5
    ks = [k, 2 * k]                 # Python floats, as single's first call: no recompile
    batched = np.asarray(jax.jit(jax.vmap(lambda k_: heights(events, k_)))(jnp.asarray(ks)))
    for i, ki in enumerate(ks):
        np.testing.assert_allclose(batched[i], np.asarray(single(ki)), rtol=0, atol=1e-12)


def test_two_free_spheres_bounce_apart_at_the_closed_form_restitution():
    """Two free spheres (1 and 3 kg, no gravity) meeting head on at 1.5 m/s, k 3e4, c 30,
    dt = 1e-3 (the pair's contact takes the record with its effective mass): the separation
    speed over the approach speed is the closed form ``exp(-pi zeta / sqrt(1 - zeta^2))``
    within 1e-12 (the exact record: 3.3e-4 off, the centred one 4.5e-4)."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
    scene.add_sphere(radius=0.1, mass=3.0, position=(0.2031, 0.0, 0.0),
                     velocity=(-0.5, 0.0, 0.0))
    sim = dp.compile(scene, 1e-3, law=laws.linear(events=True), dtype=jnp.float64)
    k, c, m_eff = 3e4, 30.0, 0.75
    v = np.asarray(sim.rollout(sim.params(k=k, c=c), 200, save_every=200).velocity)[-1, :, 0]
    zeta = c / (2.0 * np.sqrt(k * m_eff))
    e = np.exp(-np.pi * zeta / np.sqrt(1.0 - zeta ** 2))
    assert abs((v[1] - v[0]) / 1.5 / e - 1.0) < 1e-12


def test_two_free_hertz_spheres_leave_at_the_continuous_restitution():
    """The pair with ``hunt_crossley(1.5, events=True)`` (k 1e6 N/m^1.5, c 3e4): the
    separation speed over the approach speed is the continuous contact's (its relative
    motion ``m_eff d'' = -max(d^1.5 (k + c d'), 0)`` solved by DOP853, m_eff 0.75 kg) within
    5e-6 (measured 6.4e-7; the centred record 1.0e-5)."""
    k, c, m_eff = 1e6, 3e4, 0.75

    def rhs(t, y):
        return [y[1], -max(max(y[0], 0.0) ** 1.5 * (k + c * y[1]), 0.0) / m_eff]

    def apart(t, y):
        return y[0]
    apart.terminal, apart.direction = True, -1.0
    sol = solve_ivp(rhs, (0.0, 1.0), [1e-12, 1.5], method="DOP853", rtol=1e-13, atol=1e-16,
                    events=apart)
    e = -sol.y_events[0][0][1] / 1.5
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
    scene.add_sphere(radius=0.1, mass=3.0, position=(0.2031, 0.0, 0.0),
                     velocity=(-0.5, 0.0, 0.0))
    sim = dp.compile(scene, 1e-3, law=laws.hunt_crossley(1.5, events=True), dtype=jnp.float64)
    v = np.asarray(sim.rollout(sim.params(k=k, c=c), 200, save_every=200,
                               check_stability=False).velocity)[-1, :, 0]
    assert 0.5 < e < 0.99                          # damped: e 0.971
    assert abs((v[1] - v[0]) / 1.5 / e - 1.0) < 5e-6


@pytest.mark.parametrize("c", [30.0, 150.0])
def test_two_free_spheres_with_no_tension_leave_at_the_closed_form_restitution(compiled, c):
    """The same pair with ``no_tension(events=True)``: the release (the force reaching 0
    before the surfaces part) is located within the step, and the restitution is
    Schwager & Poschel's closed form (``dp.physical.restitution``) within 1e-12 (the exact
    record: 3.7e-6 at c 30, 2.7e-3 at c 150)."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
    scene.add_sphere(radius=0.1, mass=3.0, position=(0.2031, 0.0, 0.0),
                     velocity=(-0.5, 0.0, 0.0))
    sim = compiled(scene, "no_tension", "events", "pair")     # one for both dampings
    v = np.asarray(sim.rollout(sim.params(k=3e4, c=c), 300, save_every=300).velocity)[-1, :, 0]
    e = float(dp.physical.restitution(3e4, c, 0.75, law="no_tension"))
    assert abs((v[1] - v[0]) / 1.5 / e - 1.0) < 1e-12


def test_reverse_mode_equals_forward_mode_through_a_bounce(compiled):
    """Reverse-mode (``jax.grad``, the rollout's steps rematerialised, the Newton solve and
    ``lax.cond`` inside) and forward-mode (``jax.jacfwd``) gradients of a loss over a
    bouncing no_tension ball's heights agree to 1e-10 (measured 2e-14, linear too)."""
    sim = _ball03(compiled, "no_tension", "events")

    def loss(k, c):
        z = sim.rollout(sim.params(k=k, c=c), 400, observe=_height).observed
        return jnp.sum(z ** 2)
    rev = np.asarray(jax.jit(jax.grad(loss, (0, 1)))(3e4, 60.0))
    fwd = np.asarray(jax.jit(jax.jacfwd(loss, (0, 1)))(3e4, 60.0))
    assert np.all(np.isfinite(rev)) and np.all(np.abs(fwd) > 0)
    np.testing.assert_allclose(rev, fwd, rtol=1e-10)


def test_hunt_crossley_step_reverse_mode_derivatives_equal_differences():
    """The Hertz record's force (``hunt_crossley(1.5, events=True)``'s one-contact step, 1 kg,
    k 1e6, c 3e4, h 1e-3) at states of every case (apart and entering within the next step,
    entered, in contact, leaving, left, leaving within the next step): its derivatives
    w.r.t. depth, rate, k and c by reverse mode (the shooting's Newton steps, the
    Runge-Kutta flows and the ``lax.cond``s differentiated backwards; forward mode is what
    the derivative tests against the continuous system take) equal central differences to
    1e-5."""
    force = laws.hunt_crossley(1.5, events=True).centred
    h = 1e-3

    # the force and its reverse-mode gradient from one compiled program: the differences
    # take its values (a second program for the force alone traced the shooting again)
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda z: force(z[0], z[1], z[2], z[3], h, 0.5 * h, 1.0, -G)))

    def f(z):
        return value_and_grad(z)[0]
    states = [(-5e-4, -1.0), (1e-3, -2.0), (8e-3, -1.0), (1e-2, 0.5), (-1e-3, 1.5),
              (1e-3, 2.0)]
    for d, vn in states:
        z = np.array([d, vn, 1e6, 3e4])
        rev = np.asarray(value_and_grad(z)[1])
        steps = np.array([1e-7, 1e-6, 1e-2, 1e-2]) * np.abs(z)
        # the shifted points built on the host (eager .at[i].add compiled a program per index)
        fd = np.array([(f(z + s * e) - f(z - s * e)) / (2 * s)
                       for s, e in zip(steps, np.eye(4))])
        assert np.abs(rev).max() > 0.0
        np.testing.assert_allclose(rev, fd, rtol=1e-5, atol=1e-6 * np.abs(rev).max())


@pytest.mark.parametrize("law, k, c, flow", [
    (laws.linear(events=True), 3e4, 15.0, "spring_flow"),
    (laws.no_tension(events=True), 3e4, 15.0, "spring_flow"),
    (laws.hunt_crossley(1.5, events=True), 1e6, 3e4, "_hc_flow")],
    ids=["linear", "no_tension", "hertz"])
def test_batched_records_solve_only_the_lanes_at_a_crossing(monkeypatch, law, k, c, flow):
    """Under ``jax.vmap`` a ``lax.cond`` runs both branches on every lane, so every batched
    ball paid for the crossing's Newton solve (and a Hertz ball for its shooting) in every
    step: 1024 balls 85-95x the default record's time. The batched step now gathers the
    lanes that need the solve and solves those only (``diffpen.lanes.by_lanes``; here
    two lanes per pass, so that the passes repeat). Twelve 0.3 kg balls of different k,
    0.2 s (the first impact on every lane at once, then contact ends at different steps):
    the batched heights equal each ball's own rollout, and the solve's flows are traced on
    gathered lanes of the pass's width (on the old code only on whole batches)."""
    import diffpen.event_step as es
    import diffpen.lanes
    monkeypatch.setattr(diffpen.lanes, "LANES_PER_PASS", 2)
    seen, original = [], getattr(es, flow)

    def spying(x, *args):
        seen.append(jnp.shape(x))
        return original(x, *args)
    monkeypatch.setattr(es, flow, spying)
    # the 0.3 kg ball, compiled here (not shared: its programs are traced under the patches)
    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=0.3, position=(0.0, 0.0, 0.25))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3, law=law, dtype=jnp.float64)
    ks = k * np.geomspace(0.6, 1.6, 12)

    def heights(kk):
        return sim.rollout(sim.params(k=kk, c=c), 200, observe=_height).observed
    batched = np.asarray(jax.jit(jax.vmap(heights))(jnp.asarray(ks)))
    one = jax.jit(heights)
    single = np.stack([np.asarray(one(kk)) for kk in ks])
    assert np.ptp(single[:, -1]) > 1e-3                    # the balls part ways
    np.testing.assert_allclose(batched, single, rtol=0.0, atol=1e-12)
    assert (2,) in seen, seen


def test_batched_record_gradients_by_both_modes(compiled):
    """Derivatives of the gathered batched step (above) are the record's own: reverse mode
    of a batch's summed loss (``jax.grad`` outside ``jax.vmap``; a ``lax.cond``
    differentiated inside a ``custom_jvp`` rule does not transpose there, which broke the
    first form of this change) equals forward mode inside it, for twelve 0.3 kg linear
    balls through their first bounce."""
    sim = _ball03(compiled, "linear", "events")
    ks = 3e4 * np.geomspace(0.6, 1.6, 12)

    def loss(kk):
        z = sim.rollout(sim.params(k=kk, c=15.0), 200, observe=_height)
        return jnp.sum(z.observed ** 2)
    rev = float(jax.jit(jax.grad(lambda s: jnp.sum(jax.vmap(loss)(s * ks))))(1.0))
    fwd = np.asarray(jax.jit(jax.vmap(jax.jacfwd(loss)))(jnp.asarray(ks)))
    assert np.all(fwd != 0.0)
    np.testing.assert_allclose(rev, np.dot(fwd, ks), rtol=1e-9)


def test_crossing_solve_derivatives_are_implicit_and_equal_differences():
    """The crossing's Newton solve is differentiated implicitly (``jax.lax.custom_root``),
    not through its iterations: forward and reverse mode of the crossing's next depth equal
    central differences, in the entered, left and stayed cases (0.3 kg ball, k 3e4, c 15,
    dt 1 ms), and the solve's program holds a custom_root."""
    import diffpen.event_step as es
    h, im = 1e-3, 1.0 / 0.3
    k, c, a = 3e4, 15.0, 9.81
    # (depth m, secant rate of penetration m/s): entered, left, stayed and leaving ahead
    # numpy: the shifted points below are made on the host (eager jnp ops compiled each)
    x = np.array([1e-4, -2e-4, 2e-3, 4e-4])
    u = np.array([0.9, -0.8, 0.3, -0.7])

    @jax.jit
    def nxt(x, u, k, c):
        flows = es.event_step_factors(k, c, im, h)
        return es._crossing(x, u, k * im, c * im, a, h, flows)
    args = (x, u, k, c)
    fwd = jax.jit(jax.jacfwd(nxt, argnums=(0, 1, 2, 3)))(*args)
    rev = jax.jit(jax.grad(lambda *v: jnp.sum(nxt(*v)), argnums=(0, 1, 2, 3)))(*args)
    for i, e in enumerate((1e-8, 1e-6, 1e-2, 1e-5)):
        up = [w + e if j == i else w for j, w in enumerate(args)]
        dn = [w - e if j == i else w for j, w in enumerate(args)]
        fd = (np.asarray(nxt(*up)) - np.asarray(nxt(*dn))) / (2 * e)
        tol = dict(rtol=1e-5, atol=1e-9 * np.abs(fd).max())
        np.testing.assert_allclose(np.diag(fwd[i]) if i < 2 else fwd[i], fd, **tol)
        # reverse mode of the summed depths
        np.testing.assert_allclose(rev[i], fd if i < 2 else np.sum(fd), **tol)
    assert "custom_root" in str(jax.make_jaxpr(jax.grad(lambda k: jnp.sum(nxt(x, u, k, c))))(k))


def _oscillator_back(k, c, m, x0, h):
    """The damped oscillator's position at t = -h (released from x0 at rest at t = 0)."""
    w0 = np.sqrt(k / m)
    z = c / (2.0 * np.sqrt(k * m))
    r = np.roots([1.0, 2.0 * z * w0, w0 * w0]).astype(complex)
    # x = a e^{r1 t} + b e^{r2 t}, x(0) = x0, x'(0) = 0
    a = -x0 * r[1] / (r[0] - r[1])
    b = x0 * r[0] / (r[0] - r[1])
    return float(np.real(a * np.exp(-r[0] * h) + b * np.exp(-r[1] * h)))


@pytest.mark.parametrize("law", ["linear", "no_tension"])
@pytest.mark.parametrize("mass, k, c", [(1.0, 1e4, 20.0), (0.3, 3e4, 15.0), (1.0, 1e4, 300.0)],
                         ids=["quick-start", "w h 0.32", "overdamped"])
def test_exact_records_step_the_damped_spring_exactly(compiled, law, mass, k, c):
    """``linear(exact=True)`` / ``no_tension(exact=True)``: a ball that stays in contact (the
    window inside, force ``R k d - Q c vn + (1 - R) m g``) is stepped exactly: semi-implicit
    Euler's positions equal the continuous damped oscillation about the resting depth at
    every step time (closed form, tuning.reports.reference.spring_closed_form) to 1e-10 of
    the amplitude over 1500 steps, whatever ``w h`` (0.1, 0.32) or damping (zeta 0.1, 1.5).
    The centred records (damping at the window centre's speed) are off by O((w h)^2):
    1.6e-3, 2.1e-2 and 8.7e-4 of the amplitude."""
    from tuning.reports.reference import spring_closed_form
    h, g, steps = 1e-3, 9.81, 1500
    rest = mass * g / k
    amp = 0.4 * rest                                    # stays in contact, window inside
    y = spring_closed_form(np.arange(steps + 1) * h, k=k, c=c, m=mass, x0=amp)
    y = np.concatenate([[_oscillator_back(k, c, mass, amp, h)], y])     # t = -h, 0, h, ...
    s = dp.Scene(gravity=(0.0, 0.0, -g))
    s.add_sphere(radius=0.1, mass=mass, position=(0.0, 0.0, 0.1 - rest - amp),
                 velocity=(0.0, 0.0, -(y[1] - y[0]) / h))
    s.add_plane()
    # one simulator per mass: the cases of one mass differ only in the ball's start
    # position and velocity, which each rollout takes as its start state (this scene's)
    start = dp.compile(s, h, dtype=jnp.float64).init_state()
    off = []
    for record in ("exact", "centred"):
        sim = compiled(s, law, record, ("resting ball", mass))
        z = np.asarray(sim.rollout(sim.params(k=k, c=c), steps, start, check_stability=False)
                       .position)[:, 0, 2]
        off.append(np.abs(0.1 - z - rest - y[2:]).max() / amp)   # y at t = h, 2h, ...
    assert off[0] < 1e-10 and off[1] > 5e-4, off


def test_exact_step_factors_against_the_roots():
    """``exact_step_factors``: ``R = (1 - e^{r1 h})(1 - e^{r2 h}) / (w0 h)^2`` and
    ``Q = (1 - e^{-2 s h}) / (2 s h)`` against the roots of ``r^2 + 2 s r + w0^2`` (complex
    arithmetic in numpy) to 1e-12, under-, near-critically and over-damped; the limits
    ``k -> 0`` (``R -> Q``) and ``inv_mass = 0`` (1, 1); finite derivatives everywhere,
    critical damping included; float32 within 1e-6 of float64 at a small ``w0 h``."""
    import cmath
    h = 1e-3
    cases = [(1e4, 20.0, 1.0), (3e4, 15.0, 1 / 0.3), (100.0, 150.0, 10.0), (1e4, 200.0, 1.0),
             (1e4, 199.9999, 1.0), (1e4, 200.01, 1.0), (1e4, 0.0, 1.0), (1e8, 20.0, 1.0),
             (1e4, 2e4, 1.0), (1e9, 63245.0, 1.0)]
    k, c, im = (np.array(x) for x in zip(*cases))
    # one jitted function for every call below (op by op, each call compiled ~25 programs)
    factors = jax.jit(laws.exact_step_factors, static_argnums=3)
    r, q = (np.asarray(a) for a in factors(k, c, im, h))
    for i, (kk, cc, ii) in enumerate(cases):
        s, w2 = 0.5 * cc * ii, kk * ii
        disc = cmath.sqrt(s * s - w2)
        e1, e2 = (cmath.exp((-s + sign * disc) * h) for sign in (1, -1))
        want_r = ((1 - e1) * (1 - e2)).real / (w2 * h * h)
        want_q = (1 - np.exp(-2 * s * h)) / (2 * s * h) if cc else 1.0
        assert r[i] == pytest.approx(want_r, rel=1e-9) and q[i] == pytest.approx(want_q, rel=1e-12)
    r0, q0 = factors(0.0, 20.0, 1.0, h)
    assert float(r0) == pytest.approx(float(q0), rel=1e-12)
    assert [float(a) for a in factors(1e4, 20.0, 0.0, h)] == [1.0, 1.0]
    grads = jax.jit(jax.vmap(jax.grad(lambda a, b: sum(laws.exact_step_factors(a, b, 1.0, h)),
                                      (0, 1))))(np.array([1e4, 1e4, 0.0, 0.0, 1e4]),
                                                np.array([200.0, 20.0, 0.0, 20.0, 0.0]))
    assert all(np.isfinite(np.asarray(g)).all() for g in grads)
    r32 = factors(np.float32(1e4), np.float32(20.0), np.float32(1.0), 1e-5)
    r64 = factors(1e4, 20.0, 1.0, 1e-5)
    np.testing.assert_allclose(np.asarray(r32, float), np.asarray(r64), rtol=1e-6)


@pytest.mark.parametrize("record, module, name", [
    ("exact", "one_contact", "exact_step_factors"),
    ("events", "event_step", "event_step_factors")], ids=["exact", "events"])
def test_a_rollout_computes_the_exact_factors_once_outside_its_loop(monkeypatch, record,
                                                                    module, name):
    """Regression: the exact records' step constants (``exact_step_factors``) were computed
    inside the step, so a reverse-mode gradient (each step rematerialised) recomputed them
    and their derivatives at every step: 5.6x the centred record's time, against 0.96x now.
    A rollout now computes them once, before its loop (``Params.extra``), and the step reads
    them; ``sim.step`` alone still computes its own. Both give the same states. The same for
    the event-exact record's one-step-back and one-step-ahead spring flows
    (``event_step_factors``)."""
    import importlib
    calls = []
    mod = importlib.import_module(f"diffpen.{module}")
    real = getattr(mod, name)
    law = laws.linear(**{record: True})    # its step_factors field: the rollout's one call

    def counted(*args):
        calls.append(1)
        return real(*args)
    monkeypatch.setattr(mod, name, counted)     # what a step calls
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.3))
    s.add_plane()
    sim = dp.compile(s, 1e-3, law=law, dtype=jnp.float64)
    p = sim.params(k=1e4, c=20.0)
    jax.make_jaxpr(jax.grad(lambda k: sim.rollout(sim.params(k=k, c=20.0), 50,
                                                  save_every=50).position[-1, 0, 2]))(1e4)
    assert calls == []                  # none from the step
    state = sim.init_state()
    for _ in range(300):
        state = sim.step(p, state)
    assert calls                        # the step alone computes them
    traj = sim.rollout(p, 300, save_every=300)
    np.testing.assert_allclose(np.asarray(traj.position[-1]), np.asarray(state.position),
                               rtol=0, atol=1e-13)


@pytest.mark.parametrize("law", ["linear", "no_tension"])
def test_event_exact_records_run_in_a_float32_simulator_with_x64_on(law):
    """Regression: with jax_enable_x64 on (as in these tests) a float32 simulator's event-exact
    linear and no_tension records failed to trace ("cond branches must have equal output
    types": the spring's flow over a Python-float step, and the masses kept as numpy
    float64, made its constants float64). Now float32 throughout, and through a bounce the
    heights follow the float64 record's to float32's accuracy."""
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.2))
    scene.add_plane()
    rec = dp.laws.get(law, events=True)
    z = {}
    for dtype in (jnp.float32, jnp.float64):
        sim = dp.compile(scene, 1e-3, law=rec, dtype=dtype)
        with warnings.catch_warnings():     # float32 at 1 ms: the rounding warning (below)
            warnings.simplefilter("ignore", dp.PrecisionWarning)
            traj = sim.rollout(sim.params(k=1e4, c=20.0), 300)
        assert traj.position.dtype == dtype
        z[dtype] = np.asarray(traj.position, float)[:, 0, 2]
    np.testing.assert_allclose(z[jnp.float32], z[jnp.float64], atol=2e-5)


def test_event_records_called_directly_compile_once(caplog):
    """The event-exact record's force and its step factors, called outside a jit (a user
    checking one contact): each call compiled its Newton and Taylor loops again (0.7-1.3 s a
    call; audit12). A call with new values of the same shapes now compiles nothing, and gives
    what the rollout's record gives."""
    import logging
    law = laws.linear(events=True)
    d, vn = jnp.array([1e-3, -2e-3, 5e-4]), jnp.array([-1.0, -0.5, 0.3])

    def call(k):
        factors = law.step_factors(k, 20.0, 1.0, 1e-3)
        return law.centred_force(d, vn, k, 20.0, 1e-3, 5e-4, 1.0, G, factors=factors)
    first = call(1e4)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        again = call(1.1e4)
    compiled = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling")]
    assert compiled == [], compiled
    assert float(again[0]) > float(first[0]) > 0.0 and float(again[1]) == 0.0
