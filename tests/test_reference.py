"""tuning.reports.reference: the independent references are right (closed forms, an
independent ODE solver, the simulator at a small step) and the sampled metrics measure what
they claim."""
import math

import numpy as np
import pytest

import diffpen as dp
from tuning.reports.reference import (apex_heights, ball_reference, chain_reference,
                                      settling_time, spring_closed_form)


@pytest.mark.parametrize("zeta", [0.1, 0.3])
def test_ball_reference_matches_closed_form_restitution_and_contact_time(zeta):
    """No gravity: one contact of the linear law, e = exp(-pi z / sqrt(1 - z^2)) and
    t_c = pi / w_d (docs/physics-notes.md section 2)."""
    k, m = 1e4, 1.0
    c = 2 * zeta * math.sqrt(k * m)
    ref = ball_reference(k=k, c=c, m=m, r=0.1, z0=0.2, v0=-3.0, T=0.2, g=0.0)
    (t0, t1), = ref.contacts
    w_d = math.sqrt(k / m) * math.sqrt(1 - zeta ** 2)
    assert t0 == pytest.approx(0.1 / 3.0, rel=1e-10)
    assert t1 - t0 == pytest.approx(math.pi / w_d, rel=1e-9)
    _, v = ref.state([t1 + 1e-3])
    assert v[0] / 3.0 == pytest.approx(math.exp(-math.pi * zeta / math.sqrt(1 - zeta ** 2)),
                                       rel=1e-9)


def test_ball_reference_with_gravity_and_metrics():
    ref = ball_reference(k=1e4, c=20.0, m=1.0, r=0.1, z0=1.0, T=3.0)
    e0 = 0.729247614287671       # zeta = 0.1 without gravity; gravity lowers it slightly
    first = math.sqrt((ref.apexes[0] - 0.1) / 0.9)
    assert e0 - 0.02 < first < e0
    assert ref.apexes[0] > ref.apexes[1] > ref.apexes[2]
    ts = ref.settling_time(0.01)
    z, v = ref.state([ts])
    assert ref.energy(z, v)[0] == pytest.approx(0.01 * 9.81 * 0.9, rel=1e-8)
    # the sampled metrics recover the reference from its own dense samples
    t = np.linspace(1e-4, 3.0, 30000)
    z, v = ref.state(t)
    np.testing.assert_allclose(apex_heights(t, z, 0.1, 3), ref.apexes[:3], rtol=1e-7)
    e = ref.energy(z, v)
    assert settling_time(np.r_[0.0, t], np.r_[9.81 * 0.9, e]) == pytest.approx(ts, abs=2e-4)


def test_apex_heights_exact_on_parabolas():
    t = np.arange(0.0, 1.0, 1e-2) + 3e-3
    z = np.where(t < 0.2, 0.05, 0.1 + 2.0 * (t - 0.2) - 4.905 * (t - 0.2) ** 2)
    ap = apex_heights(t, z, 0.1, 2)
    assert ap[0] == pytest.approx(0.1 + 2.0 ** 2 / (2 * 9.81), rel=1e-12)
    assert math.isnan(ap[1])


def _pinned_chain(n, k, c, m, L):
    """``n`` particles of ``m`` kg in a row at spacing ``L`` m from a pinned one, joined by
    springs of ``k`` N/m and ``c`` N s/m at rest length ``L``, under gravity."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    prev = scene.add_particle(mass=m, position=(0.0, 0.0, 0.0), pinned=True)
    for i in range(1, n + 1):
        b = scene.add_particle(mass=m, position=(L * i, 0.0, 0.0))
        scene.add_spring(prev, b, k=k, c=c, rest_length=L)
        prev = b
    return scene


def test_chain_reference_agrees_with_simulator_at_small_dt():
    n, k, c, m, L = 3, 200.0, 0.5, 0.1, 0.2
    scene = _pinned_chain(n, k, c, m, L)
    sim = dp.compile(scene, 1e-4, integrator="rk4")
    traj = sim.rollout(sim.params(), 2000, save_every=100)
    ref = chain_reference(np.asarray(traj.time), x0=[[L * i, 0, 0] for i in range(n + 1)],
                          m=m, k=k, c=c, rest=L)
    np.testing.assert_allclose(traj.position, ref, atol=1e-9)


def test_spring_closed_form_solves_the_ode():
    from scipy.integrate import solve_ivp
    for c in (2.0, 20.0, 50.0):           # under-, critically and over-damped (k=100, m=1)
        t = np.linspace(0, 2, 50)
        sol = solve_ivp(lambda _, y: [y[1], -100 * y[0] - c * y[1]], (0, 2), [0.1, 0.0],
                        t_eval=t, method="DOP853", rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(spring_closed_form(t, k=100.0, c=c, m=1.0, x0=0.1),
                                   sol.y[0], atol=1e-11)


def test_reference_derivatives_at_zero_damping_are_one_sided_and_finite():
    """Regression: at c = 0 the relative step was 0, and d/dc came out 0 / 0 = NaN with a
    RuntimeWarning. Now a forward difference; for small damping e = 1 - pi zeta, so
    d apex1 / dc = -2 pi (z0 - r) / (2 sqrt(k m)) = -0.0283 (gravity during the short contact
    moves it by 3%)."""
    import warnings
    from tuning.reports.reference import ball_reference_derivatives
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ref = ball_reference_derivatives(k=1e4, c=0.0, m=1.0, r=0.1, z0=1.0, T=1.2, n=1)
    assert ref["dc"]["apex"][0] == pytest.approx(-math.pi * 0.9 / 100.0, rel=0.05)   # -0.0291
    assert ref["dk"]["apex"][0] == pytest.approx(0.0, abs=1e-6)     # undamped: k moves no height


def test_verlet_gives_the_continuous_spring_damping_derivative():
    """d positions / d (spring c) of a swinging chain against the continuous one (central
    differences of the DOP853 reference), dt 1e-3: velocity Verlet's damper reads a predicted
    end velocity and is second order (0.08% off); semi-implicit Euler's reads the velocity
    of the step that ended, half a step late (15% off). README: "Gradients outside the
    one-contact ball"."""
    import jax
    n, k, c, m, L, T, dt = 3, 200.0, 0.5, 0.1, 0.2, 0.3, 1e-3
    x0 = [[L * i, 0, 0] for i in range(n + 1)]

    def ref(cc):
        return chain_reference(np.array([T]), x0=x0, m=m, k=k, c=cc, rest=L)[-1, 1:].ravel()
    cont = (ref(c * (1 + 1e-5)) - ref(c * (1 - 1e-5))) / (2e-5 * c)
    scene = _pinned_chain(n, k, c, m, L)
    steps = int(round(T / dt))
    big = np.abs(cont) > 0.1 * np.abs(cont).max()
    errors = {}
    for integrator in ("verlet", "semi_implicit_euler"):
        sim = dp.compile(scene, dt, integrator=integrator)

        def end(cc):
            tr = sim.rollout(sim.params(springs={"default": (k, cc)}), steps, save_every=steps)
            return tr.position[-1, 1:].ravel()
        jac = np.asarray(jax.jacfwd(end)(np.float64(c)))
        errors[integrator] = np.max(np.abs(jac - cont)[big] / np.abs(cont)[big])
    assert errors["verlet"] < 0.005
    assert errors["semi_implicit_euler"] > 0.05
