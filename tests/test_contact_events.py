"""Contact laws and contact events: zero force apart (every contact kind, every law), the
step-averaged force against its definition, and the step's continuity through contact start
and end."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen import laws
from diffpen.window import window_moments

LAWS = ["linear", "no_tension", "hunt_crossley"]


# --------------------------------------------------------------------------- zero apart
def _apart_scene():
    """One body of every contact kind, each 0.3 m from whatever it could touch and moving
    towards it at 1 m/s: sphere-plane, particle-plane, sphere-sphere, sphere-box, box corners
    on the plane, sphere and box against a fixed sphere."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_plane()
    scene.add_fixed_sphere((20.0, 0.0, 1.0), 0.5)
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.4), velocity=(0.0, 0.0, -1.0))     # plane
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.9), velocity=(0.0, 0.0, -1.0))     # sphere
    scene.add_particle(1.0, (3.0, 0.0, 0.3), velocity=(0.0, 0.0, -1.0))        # plane
    scene.add_box((0.1, 0.1, 0.1), 1.0, (6.0, 0.0, 0.4), velocity=(0.0, 0.0, -1.0))
    scene.add_sphere(0.1, 1.0, (6.0, 0.0, 0.9), velocity=(0.0, 0.0, -1.0))     # box
    scene.add_sphere(0.1, 1.0, (20.0, 0.0, 1.9), velocity=(0.0, 0.0, -1.0))    # fixed sph.
    scene.add_box((0.1, 0.1, 0.1), 1.0, (20.0, 0.0, 0.1 + 0.3 + 0.4 - 0.5),
                  velocity=(0.0, 0.0, 1.0))                                     # fixed sph.
    return scene


@pytest.mark.parametrize("law,width,h", [("hunt_crossley", 0.05, None),
                                         ("linear", 0.0, 1e-3)],
                         ids=["hunt_crossley-smoothed", "linear-step-averaged"])
def test_zero_force_and_derivative_apart_every_contact_kind(law, width, h):
    """Bodies 0.3 m apart (more than the smoothing band, 2.5 cm, and the step window,
    1 mm): exactly zero force and torque, and exactly zero derivatives w.r.t. k, c and the
    state. (The force-space clamp of no_tension / hunt_crossley left k width^n / 8 acting at
    any distance: 1.25 N at k = 1e5, width = 1e-2.) Per pair, every law and both forms are
    checked by the next test; here every contact kind routes through the law."""
    sim = dp.compile(_apart_scene(), 1e-3, law=law, smoothing=width,
                     exponent=1.5 if law == "hunt_crossley" else 1.0)
    kinds = {"contact_plane", "contact_sphere_sphere", "contact_sphere_box",
             "contact_box_plane", "contact_fixed_sphere", "contact_box_fixed_sphere"}
    assert kinds <= set(sim.terms)
    state = sim.init_state()

    def total(k, c, x, v):
        f, tau = sim.forces(sim.params(k=k, c=c),
                            state._replace(position=x, velocity=v), h=h)
        return jnp.concatenate([f.ravel(), tau.ravel()])
    args = tuple(np.asarray(a, dtype=np.float64) for a in
                 (1e5, 30.0, state.position, state.velocity))
    # the Jacobian column by column: one compiled JVP (the tangent is an argument) fed each
    # unit tangent of (k, c, x, v), as jacfwd does in one batch (the batched program compiled
    # ~2x slower than the JVP)
    jvp = jax.jit(lambda a, t: jax.jvp(total, a, t))
    zero = tuple(np.zeros_like(a) for a in args)
    value, _ = jvp(args, zero)
    assert np.all(np.asarray(value) == 0.0)
    columns = 0
    for i, a in enumerate(args):
        for idx in np.ndindex(a.shape):
            t = list(zero)
            t[i] = np.zeros_like(a)
            t[i][idx] = 1.0
            _, col = jvp(args, tuple(t))
            assert np.all(np.asarray(col) == 0.0), (i, idx)
            columns += 1
    assert columns == 2 + 2 * state.position.size


@pytest.mark.parametrize("law", LAWS)
def test_pair_law_zero_just_outside_the_band(law):
    """Per pair: 0 and zero slope from ``d = -width / 2`` on (pointwise), and from
    ``d = -|vn| h`` on (step-averaged), for approaching, still and separating contacts."""
    rec = laws.get(law, 1.5 if law == "hunt_crossley" else 1.0)
    w, h = 1e-2, 1e-3
    d = jnp.array([-0.5 * w, -0.5 * w - 1e-9, -1.0, -1e3] * 3)
    vn = jnp.repeat(jnp.array([-2.0, 0.0, 3.0]), 4)
    da = jnp.array([-2.0 * h, -2.0 * h - 1e-9, -1.0, -1e-9, -1.0, -0.1, -3.0 * h,
                    -3.0 * h - 1e-9, -1.0])
    va = jnp.repeat(jnp.array([-2.0, 0.0, 3.0]), 3)

    @jax.jit
    def both(d, vn, da, va):
        f = jax.vmap(jax.value_and_grad(lambda d_, v_, k_, c_: rec(d_, v_, k_, c_, w),
                                        argnums=(0, 1, 2, 3)))
        g = jax.vmap(jax.value_and_grad(lambda d_, v_, k_, c_: rec.averaged(d_, v_, k_, c_, h),
                                        argnums=(0, 1, 2, 3)))
        one = jnp.ones_like(d)
        return f(d, vn, 1e5 * one, 40.0 * one), g(da, va, 1e5 * one[:9], 40.0 * one[:9])
    for val, grads in both(d, vn, da, va):
        assert np.all(np.asarray(val) == 0.0)
        assert all(np.all(np.asarray(x) == 0.0) for x in grads)


# --------------------------------------------------------------------------- the records
def _hat_mean_quadrature(force, d, vn, h, k, c, n=4001):
    """The definition of the step average, by quadrature: the hat-weighted mean of the exact
    pointwise force ``force(d, vn)`` over s in [-h, h] along d(s) = d - vn s (trapezoids
    on each piece between the force's breaks: contact start/end, the clamp, the hat's
    peak; the force is evaluated at each piece's n - 1 midpoints, so every call has the
    same shape)."""
    breaks = [-h, 0.0, h]
    if vn != 0.0:
        breaks += [d / vn, (d - c * vn / k) / vn]
    breaks = sorted(b for b in set(breaks) if -h <= b <= h)
    total = 0.0
    for a, b in zip(breaks, breaks[1:]):
        ss = np.linspace(a, b, n)
        ww = 1.0 - np.abs(ss) / h
        mid = 0.5 * (ss[1:] + ss[:-1])
        fm = np.asarray(force(jnp.asarray(d - vn * mid), jnp.asarray(np.full(mid.size, vn))))
        total += float(np.sum(fm * 0.5 * (ww[1:] + ww[:-1]) * np.diff(ss)))
    return total / h


@pytest.mark.parametrize("law", LAWS)
def test_step_average_matches_its_definition(law):
    """Closed forms against quadrature of the hat-weighted mean: window inside, apart,
    crossing at either end, approaching and separating (no_tension: where the clamp cuts
    inside the window too), still contacts; deep inside it is the pointwise force."""
    rec = laws.get(law, 1.5 if law == "hunt_crossley" else 1.0)
    k, c, h = 2e4, 300.0, 1e-3
    cases = [(d, vn) for vn in (-3.0, -0.2, 0.4, 5.0)
             for d in (-4e-3, -2e-3, -1e-4, 0.0, 1e-4, 2.5e-3, 6e-3, 2e-2)] + [(1e-3, 0.0)]
    deep = [(0.05, -0.3), (0.08, 0.2)]             # the window inside: the pointwise force
    # one compiled batch for the cases and the deep points
    got = np.asarray(jax.jit(jax.vmap(lambda d, v: rec.averaged(d, v, k, c, h)))(
        np.array([x[0] for x in cases + deep]), np.array([x[1] for x in cases + deep])))
    force = jax.jit(lambda d, v: rec.force(d, v, k, c, 0.0))     # one compile per law
    want = np.array([_hat_mean_quadrature(force, d, vn, h, k, c) for d, vn in cases])
    scale = k * 1e-3
    np.testing.assert_allclose(got[:len(cases)], want, atol=2e-6 * scale, rtol=1e-6)
    np.testing.assert_allclose(got[len(cases):], force(*np.array(deep).T),
                               rtol=5e-6 if law == "hunt_crossley" else 1e-13)  # d^n: curved


@pytest.mark.parametrize("n", [1.0, 1.5])
def test_window_moments_match_their_definition(n):
    """``window_moments``: the hat-weighted means of ``max(d - vn s, 0)^n`` and of
    ``s max(d - vn s, 0)^n`` over ``[-h, h]`` against trapezoids between their breaks
    (window crossing at either end, inside, apart, a still contact); the first the same as
    ``window_mean``'s; exactly 0 apart, ``-vn h^2 / 6`` for n = 1 inside; finite
    derivatives at the window's edges."""
    h = 1e-3
    cases = [(d, vn) for vn in (-3.0, -0.2, 0.4, 5.0)
             for d in (-4e-3, -1e-4, 0.0, 1e-4, 2.5e-3, 6e-3, 2e-2)] + [(1e-3, 0.0)]
    dd, vv = (np.array(x) for x in zip(*cases))
    both = jax.jit(jax.vmap(lambda d, v: (window_moments(d, v, h, n),
                                          laws.window_mean(d, v, h, n)[1])))
    (mean, moment), direct = (np.asarray(a) if not isinstance(a, tuple) else
                              tuple(np.asarray(b) for b in a) for a in both(dd, vv))
    want = {0: [], 1: []}
    for d, vn in cases:
        breaks = sorted({-h, 0.0, h} | ({d / vn} if vn and -h < d / vn < h else set()))
        for power in (0, 1):
            total = 0.0
            for a, b in zip(breaks, breaks[1:]):
                ss = np.linspace(a, b, 20001)
                f = ss ** power * np.maximum(d - vn * ss, 0.0) ** n * (1.0 - np.abs(ss) / h)
                total += float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(ss)))
            want[power].append(total / h)
    scale = 2e-2 ** n
    np.testing.assert_allclose(mean, want[0], atol=1e-8 * scale, rtol=1e-6)
    np.testing.assert_allclose(mean, direct, atol=1e-12 * scale, rtol=1e-9)
    np.testing.assert_allclose(moment, want[1], atol=1e-8 * scale * h, rtol=1e-6)
    apart = (dd + np.abs(vv) * h <= 0.0)
    assert np.all(moment[apart] == 0.0) and np.all(mean[apart] == 0.0)
    if n == 1.0:
        inside = dd - np.abs(vv) * h >= 0.0
        np.testing.assert_allclose(moment[inside], -vv[inside] * h * h / 6.0, rtol=1e-12)
    grads = jax.jit(jax.vmap(jax.grad(lambda d, v: sum(window_moments(d, v, h, n)),
                                      (0, 1))))(dd, vv)
    assert all(np.isfinite(np.asarray(g)).all() for g in grads)


def test_batched_linear_window_equals_the_unbatched_one():
    """Under vmap the closed-form window takes its division without the selects around it
    (a custom_vmap rule, faster batched stepping): the same numbers as one call per element,
    values and derivatives, forward and reverse mode, edge cases included."""
    h = 1e-3
    d = jnp.asarray([0.0, 0.0, 1e-4, -1e-4, 1e-3, -1e-3, 5e-4, -5e-4, 2e-5, -3e-4])
    vn = jnp.asarray([0.0, 1.0, 0.1, -0.1, 0.0, 1.0, 0.5, -0.5, 1e-14, 0.7])
    # values op by op (eager, as a caller's single evaluation runs): bit for bit
    one = [laws.window_mean(a, b, h) for a, b in zip(np.asarray(d), np.asarray(vn))]
    batched = jax.vmap(lambda a, b: laws.window_mean(a, b, h))(d, vn)
    for i in (0, 1):
        np.testing.assert_array_equal(np.asarray(batched[i]), np.asarray([o[i] for o in one]))

    # derivatives: one compiled program per element (scalar arguments: no batching rule
    # involved; compiled once, called per element) against the same program under vmap
    def derivatives(a, b):
        return [mode(lambda a, b, i=i: laws.window_mean(a, b, h)[i], argnums=(0, 1))(a, b)
                for i in (0, 1) for mode in (jax.grad, jax.jacfwd)]
    single = jax.jit(derivatives)
    got = jax.jit(jax.vmap(derivatives))(d, vn)
    want = [single(a, b) for a, b in zip(np.asarray(d), np.asarray(vn))]
    assert len(got) == 4
    for n, g in enumerate(got):
        for j in (0, 1):
            np.testing.assert_allclose(np.asarray(g[j]), np.asarray([w[n][j] for w in want]),
                                       rtol=1e-13, atol=0.0)
    # lanes whose d and vn differ in rank (a (3,) d against a scalar vn per lane): the rule
    # put the batch axis in front of both, so they no longer broadcast lane by lane
    d3 = jnp.reshape(d[:9], (3, 3))
    got = jax.vmap(lambda a, b: laws.window_mean(a, b, h))(d3, vn[:3])
    for i in (0, 1):
        want = [laws.window_mean(a, b, h)[i]
                for a, b in zip(np.asarray(d3), np.asarray(vn[:3]))]
        np.testing.assert_array_equal(np.asarray(got[i]), np.asarray(want))


def test_linear_window_closed_form_derivatives_equal_autodiff():
    """With a static step the linear window carries closed-form derivatives (a custom JVP,
    what makes reverse-mode rollout gradients cheap); they equal autodiff of the same
    window (an array step takes the plain path) to rounding, forward and reverse mode and
    second order, on random windows and on the edge cases (touching, still, at the
    boundary)."""
    rng = np.random.default_rng(3)
    h = 1e-3
    d = jnp.asarray(np.r_[rng.normal(0.0, 1e-3, 4000), 0.0, 0.0, 1e-4, -1e-4, 1e-3, -1e-3,
                          5e-4, -5e-4])
    vn = jnp.asarray(np.r_[rng.normal(0.0, 1.0, 4000), 0.0, 1.0, 0.1, -0.1, 0.0, 1.0, 0.5,
                           -0.5])
    # the closed-form path's primal (|d|, max(d, 0)) gives the same numbers, bit for bit
    # (both evaluated op by op)
    fast_values = laws.window_mean(d, vn, h)
    plain_values = laws.window_mean(d, vn, jnp.asarray(h))
    for i in (0, 1):                                    # frac, mean
        np.testing.assert_array_equal(fast_values[i], plain_values[i])

    @jax.jit
    def derivatives(d, vn):
        """Per output i: [grad, jacfwd] of the closed form and of autodiff over all windows,
        and the Hessians over the first 300 (one compiled program for all of them)."""
        out = []
        for i in (0, 1):
            def fast(a, b, i=i):
                return laws.window_mean(a, b, h)[i]

            def plain(a, b, i=i):
                return laws.window_mean(a, b, jnp.asarray(h))[i]      # an array step
            firsts = [(jax.vmap(mode(fast, argnums=(0, 1)))(d, vn),
                       jax.vmap(mode(plain, argnums=(0, 1)))(d, vn))
                      for mode in (jax.grad, jax.jacfwd)]
            hess = (jax.vmap(jax.hessian(fast, argnums=(0, 1)))(d[:300], vn[:300]),
                    jax.vmap(jax.hessian(plain, argnums=(0, 1)))(d[:300], vn[:300]))
            out.append((firsts, hess))
        return out
    for firsts, (hg, hw) in derivatives(d, vn):
        for got, want in firsts:
            for g, w in zip(got, want):
                g, w = np.asarray(g), np.asarray(w)
                assert np.all(np.isfinite(g))
                np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-12 * np.abs(w).max())
        for p in (0, 1):
            for q in (0, 1):
                w = np.asarray(hw[p][q])
                np.testing.assert_allclose(np.asarray(hg[p][q]), w, rtol=1e-9,
                                           atol=1e-12 * np.abs(w).max())


@pytest.mark.parametrize("law", LAWS)
def test_centred_damping_is_the_average_at_the_centre_speed(law):
    """Centred records: the step average with the damping at the centre speed
    ``vc = vn + lag (F / m + g_n)`` of the force ``F`` itself (semi-implicit Euler's velocity
    lags by h / 2): ``F = k mean - c frac vc`` (linear; no_tension while approaching) and
    ``F0 = max(k - c vc, 0) mean`` solved for, then the window along ``d - vc s`` and the speed
    ``vc + a s`` inside it, ``max(k mean - c (vc mean + a m1), 0)`` (Hunt-Crossley, ``a``
    the separating acceleration, ``m1`` the window's first moment); the window of the
    linear laws from ``vn``. Exactly 0 apart,
    the plain average for ``lag = 0`` and for the default records, continuous through
    contact start."""
    rec = {"linear": laws.linear, "no_tension": laws.no_tension,
           "hunt_crossley": lambda c: laws.hunt_crossley(1.5, c)}[law](True)
    n = 1.5 if law == "hunt_crossley" else 1.0
    plain = laws.get(law, n)                               # the default: not centred
    assert plain.centred is None and laws.get(law, n, centred=True).centred is not None
    k, c, h, m, g = 2e4, 300.0, 1e-3, 0.7, -9.81
    lag = 0.5 * h
    d = np.array([-4e-3, -1e-4, 0.0, 1e-4, 2.5e-3, 2e-2, 2e-2])
    vn = np.array([-3.0, -0.2, -0.2, 0.4, 5.0, -0.3, 0.2])
    eps = 1e-9
    starts = np.array([0.0, -2e-4, 2e-4])              # either side of each: continuity
    sides = np.stack([starts - eps, starts + eps])

    @jax.jit                                           # one compiled program per law
    def evaluate(d, vn, sides):
        f = rec.centred_force(d, vn, k, c, h, lag, 1.0 / m, g)
        vc = vn + lag * (f / m + g)
        frac, mean = laws.window_mean(d, vn, h, rec.exponent)
        assert_first_pass = jnp.zeros_like(f)
        if law == "hunt_crossley":
            pw = mean                                       # the window along d - vn s
            f0 = jnp.maximum(k - c * (vn + lag * g), 0.0) * pw / (1.0 + c * lag / m * pw)
        if law == "hunt_crossley":
            # the damping at the centre speed solved for (the first pass), then the window
            # along the centre's motion d - vc s with the speed vc + a s inside it
            a = f0 / m + g
            vc = vn + lag * a
            assert_first_pass = jnp.maximum(k - c * vc, 0.0) * pw - f0
            mean_c, m1 = window_moments(d, vc, h, rec.exponent)
            want = jnp.maximum(k * mean_c - c * (vc * mean_c + a * m1), 0.0)
        else:
            want = k * mean - c * frac * vc
            if law == "no_tension":
                want = jnp.where(vn < 0.0, want, f)
        slope = jax.grad(lambda x: rec.centred_force(x, -3.0, k, c, h, lag, 1.0 / m, g))(
            -4e-3)
        plains = [r.centred_force(d, vn, k, c, h, lg, 1.0 / m, g)
                  for r, lg in ((rec, 0.0), (plain, lag))]
        across = rec.centred_force(sides, -0.2, k, c, h, lag, 1.0 / m, g)
        return (f, want, slope, plains, rec.averaged(d, vn, k, c, h), across,
                assert_first_pass)
    f, want, slope, plains, averaged, across, first = evaluate(d, vn, sides)
    np.testing.assert_allclose(f, want, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(first, 0.0, atol=1e-9)      # f0 solves F = max(k - c vc) mean
    assert float(f[0]) == 0.0 and float(slope) == 0.0
    for got in plains:
        np.testing.assert_allclose(got, averaged, rtol=1e-14)
    assert np.abs(np.asarray(across[0] - across[1])).max() < 1e-3


@pytest.mark.parametrize("law", ["linear", "no_tension"])
def test_centred_damping_keeps_an_overdamped_ball_above_its_resting_depth(law):
    """Regression: the centred records estimated the centre speed in one explicit pass,
    ``F0 - c frac lag (g_n + F0 / m)``, which scales the whole force by ``1 - c h / (2 m)``:
    near the explicit damping limit (c h / (2 m) -> 1) the force nearly vanished and an
    overdamped ball (0.1 kg, k 100 N/m, c 150 N s/m, zeta 24) at 0.99 x the stable step sank
    to 28 mm, three times its resting depth of 9.8 mm. Solved for the force it creeps down towards the resting depth and never passes it, at every step
    up to the limit, as the plain step average does. (Hunt-Crossley's damping grows with
    depth: its ball is not overdamped at impact.)"""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("b", k=100.0, c=150.0)
    scene.add_sphere(radius=0.1, mass=0.1, position=(0.0, 0.0, 0.3), material="b")
    scene.add_plane(material="b")
    probe = dp.compile(scene, 1e-4, law=law)
    stable = float(probe.stability(probe.params()).stable_dt)
    rest = 0.1 - 0.1 * 9.81 / 100.0
    for frac in (0.5, 0.99):
        dt = frac * stable
        sim = dp.compile(scene, dt, law=laws.get(law, 1.0))
        z = np.asarray(sim.rollout(sim.params(), int(6.0 / dt), check_stability=False)
                       .position[:, 0, 2])
        assert np.isfinite(z).all()
        assert z.min() > rest - 1e-4, (frac, z.min(), rest)
        assert abs(z[-1] - rest) < 2e-3, (frac, z[-1], rest)


def test_centred_damping_on_sphere_pairs_and_fixed_spheres():
    """The centred linear law through the sphere-sphere term (effective mass 1/m1 + 1/m2, no
    relative gravity): two spheres (1 kg, 3 kg) at 1 m/s, zeta 0.2, dt = contact time / 20,
    restitution within 0.2% of the closed form (measured +0.10 ... +0.15% over impact phases;
    the default record -0.88 ... -0.91%); through the fixed-sphere term (normal and gravity
    along it per step): a ball dropped onto a large fixed sphere straight below follows the
    ball dropped onto the plane (same depth, normal and gravity) to 1e-12 m."""
    m1, m2, k = 1.0, 3.0, 1e4
    mu = m1 * m2 / (m1 + m2)
    c = 2.0 * 0.2 * np.sqrt(k * mu)
    tc = float(dp.physical.contact_time(k, c, mu))
    e_closed = float(dp.physical.restitution(k, c, mu))
    centred = laws.linear(centred=True)
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_sphere(0.1, m1, (0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
    scene.add_sphere(0.1, m2, (0.2 + 2.4 * tc / 20, 0.0, 0.0))
    sim = dp.compile(scene, tc / 20, law=centred)
    v = np.asarray(sim.rollout(sim.params(k=k, c=c), 60, save_every=60).velocity)[-1]
    assert abs(float(v[1, 0] - v[0, 0]) / e_closed - 1.0) < 2e-3
    z = []
    for kind in ("plane", "fixed"):
        scene = dp.Scene()
        if kind == "plane":
            scene.add_plane()
        else:
            scene.add_fixed_sphere((0.0, 0.0, -10.0), 10.0)
        scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
        sim = dp.compile(scene, 1e-3, law=centred)
        z.append(np.asarray(sim.rollout(sim.params(k=1e4, c=20.0), 1500).position[:, 0, 2]))
    assert np.abs(z[0] - z[1]).max() < 1e-12


@pytest.mark.parametrize("centred", [True, False])
def test_ball_fast_path_applies_the_simulators_law(centred):
    """tuning.ball_fast steps the simulator's own force, plain (the default) or centred (it
    declined centred laws before): its heights equal the rollout's bit for bit either way."""
    from tuning.ball_fast import ball_heights, supports
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    scene.add_plane()
    sim = dp.compile(scene, 1e-3, law=laws.linear(centred=centred))
    assert supports(sim) is None
    k, c = jnp.array([5e3, 1e4]), jnp.array([10.0, 30.0])
    z = np.asarray(ball_heights(sim, k, c, 900))
    for i in range(2):
        want = sim.rollout(sim.params(k=k[i], c=c[i]), 900).position[:, 0, 2]
        np.testing.assert_array_equal(z[:, i], np.asarray(want))


@pytest.mark.parametrize("law", LAWS)
def test_energy_and_resting_depth_are_the_static_force_integral_and_inverse(law):
    rec = laws.get(law, 1.5 if law == "hunt_crossley" else 1.0)
    loads = np.array([0.5, 20.0, 300.0])

    @jax.jit                                           # one compiled program per law
    def evaluate(d, loads):
        out = []
        for width in (0.0, 2e-3):
            static = jax.vmap(lambda x: rec.force(x, 0.0, 3e4, 50.0, width))(d)
            slope = jax.vmap(jax.grad(lambda x: rec.energy(x, 3e4, width)))(d)
            depth = rec.resting_depth(loads, 3e4, width)
            out.append((static, slope, rec.force(depth, 0.0, 3e4, 50.0, width)))
        return out
    for static, slope, rested in evaluate(jnp.linspace(-3e-3, 4e-3, 15), loads):
        np.testing.assert_allclose(slope, static, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(rested, loads, rtol=1e-10, atol=0.0)


def test_a_named_law_is_centred_only_where_no_body_can_feel_two_contacts():
    """A law named by a string takes the centred damping on scenes of one contact (one
    sphere or particle on one plane or fixed sphere, two free spheres), and the plain step
    average wherever a body could feel a second force (another collider, a box's corners, a
    spring, drag, a term from outside diffpen) or where the law is given as a record."""
    from diffpen.checks import one_contact_per_body

    def scene(*adds):
        s = dp.Scene()
        for add in adds:
            add(s)
        return s
    ball = lambda s: s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.5))
    ball2 = lambda s: s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    plane = lambda s: s.add_plane()
    wall = lambda s: s.add_plane(normal=(1.0, 0.0, 0.0), offset=-1.0)
    one = {"ball on a plane": scene(ball, plane),
           "particle on a fixed sphere": scene(
               lambda s: s.add_particle(1.0, (0.0, 0.0, 2.0)),
               lambda s: s.add_fixed_sphere((0.0, 0.0, 0.0), 1.0)),
           "two free spheres": scene(ball, ball2)}
    several = {"ball, floor and wall": scene(ball, plane, wall),
               "two balls on a plane": scene(ball, ball2, plane),
               "box on a plane": scene(lambda s: s.add_box((0.1, 0.1, 0.1), 1.0,
                                                           (0.0, 0.0, 0.5)), plane),
               "ball on a spring": scene(ball, plane, lambda s: s.add_spring(
                   0, (0.0, 0.0, 1.0), k=100.0))}
    for name, s in one.items():
        assert one_contact_per_body(s), name
        assert not one_contact_per_body(s, builtin_terms=False), name
    for name, s in several.items():
        assert not one_contact_per_body(s), name
    sim = dp.compile(one["ball on a plane"], 1e-3, law="no_tension")
    assert sim.contact_law.name == "no_tension" and sim.contact_law.centred is not None
    assert dp.compile(several["ball, floor and wall"], 1e-3).contact_law.centred is None
    assert dp.compile(one["ball on a plane"], 1e-3,
                      law=laws.linear()).contact_law.centred is None


def test_two_stacked_balls_rest_exactly_with_the_named_law():
    """Where a body rests on two contacts the named law keeps the plain step average, which
    rests exactly: two stacked 1 kg balls at c 20 N s/m, dt 1 ms, end at the static depths
    (plane contact 2 m g / k, the pair's m g / k; the centred form, which rebuilds the
    centre speed from each contact's own force, rests 0.5% and 2% off)."""
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.1))
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.3))
    s.add_plane()
    sim = dp.compile(s, 1e-3)
    k, g = 1e4, 9.81
    end = np.asarray(sim.rollout(sim.params(k=k, c=20.0), 3000, save_every=3000).position)
    z = end[-1, :, 2]
    # 3 s: settled to 1e-5 (the centred form ends 5e-3 and 2e-2 off)
    np.testing.assert_allclose(0.1 - z[0], 2.0 * g / k, rtol=1e-4)
    np.testing.assert_allclose(0.2 - (z[1] - z[0]), g / k, rtol=1e-4)


def test_compile_takes_a_record_or_a_name():
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.105))
    scene.add_plane()
    # a name on this one-contact scene takes the centred record; a record is used as given
    a = dp.compile(scene, 1e-3, law=laws.hunt_crossley(1.5, centred=True))
    b = dp.compile(scene, 1e-3, law="hunt_crossley", exponent=1.5)
    assert a.law == b.law == "hunt_crossley" and a.exponent == b.exponent == 1.5
    assert a.contact_law.name == "hunt_crossley" and b.contact_law.centred is not None
    plain = laws.hunt_crossley(1.5)
    assert dp.compile(scene, 1e-3, law=plain).contact_law is plain
    p = a.params(k=1e5, c=1e2)
    np.testing.assert_array_equal(a.rollout(p, 50).position, b.rollout(p, 50).position)
    with pytest.raises(dp.SceneError, match="unknown contact law"):
        dp.compile(scene, 1e-3, law="hertz")
    with pytest.raises(dp.SceneError, match="exponent"):
        dp.compile(scene, 1e-3, law="hunt_crossley", exponent=0.5)
    # an exponent with another law was ignored: law="linear", exponent=2.0 ran linear
    with pytest.raises(dp.SceneError, match="read by law='hunt_crossley' only"):
        dp.compile(scene, 1e-3, law="linear", exponent=2.0)
    with pytest.raises(dp.SceneError, match="differs from the contact law record's own"):
        dp.compile(scene, 1e-3, law=plain, exponent=2.0)
    assert dp.compile(scene, 1e-3, law=plain, exponent=1.5).contact_law is plain


# --------------------------------------------------------------------------- no length scale
def test_restitution_does_not_depend_on_the_stiffness_scale():
    """Two spheres (1 kg, 3 kg) colliding at 1 m/s, zeta 0.2, dt = contact time / 400: with
    no fixed smoothing length the dimensionless problem is the same for every k, so the
    restitution is the same from k = 1e2 to 1e9 N/m (the fixed 1e-4 m band moved it by
    +0.57% at 1e8 and +4.6% at 1e9; at this resolution +83% at 1e9), and within 0.1% of the
    closed form (measured -0.053% for every k)."""
    m1, m2 = 1.0, 3.0
    mu = m1 * m2 / (m1 + m2)
    es = []
    for k in (1e2, 1e9):
        c = 2.0 * 0.2 * np.sqrt(k * mu)
        tc = float(dp.physical.contact_time(k, c, mu))
        dt = tc / 400
        scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
        scene.add_sphere(0.1, m1, (0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
        scene.add_sphere(0.1, m2, (0.2 + 0.5 * dt, 0.0, 0.0))
        sim = dp.compile(scene, dt)
        v = np.asarray(sim.rollout(sim.params(k=k, c=c), 600, save_every=600).velocity)[-1]
        es.append(float((v[1, 0] - v[0, 0]) / 1.0))
    e_closed = float(dp.physical.restitution(1e4, 2.0 * 0.2 * np.sqrt(1e4 * mu), mu))
    assert abs(es[1] / es[0] - 1.0) < 1e-6
    assert abs(es[0] / e_closed - 1.0) < 1e-3          # measured -0.053%


# --------------------------------------------------------------------------- friction
@pytest.fixture(scope="module")
def sliding_box():
    """A 1 kg cube (0.2 m) set down with its face exactly on a rough plane (corner depths 0:
    the step windows have zero length) and sliding at 2 m/s; mu 0.4, slip speed 5 cm/s."""
    def build(dtype):
        scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
        scene.add_material("rough", k=1e5, c=200.0, friction=0.4, slip_speed=0.05)
        scene.add_plane(material="rough")
        scene.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.1), velocity=(2.0, 0.0, 0.0))
        sim = dp.compile(scene, 1e-3, dtype=dtype)

        def stop(mu):
            p = sim.params(extra={"friction": {"rough": mu}})
            return sim.rollout(p, 1000, save_every=1000).position[-1, 0, 0]
        return jax.jit(jax.value_and_grad(stop))
    return build


def test_sliding_box_stop_distance_gradient_float32_and_float64(sliding_box):
    """d (stop distance) / d mu against Coulomb's -v^2 / (2 mu^2 g) = -1.274 m (smooth
    Coulomb with a 5 cm/s slip speed: -1.278, 0.3% off), and float32 against float64 within
    0.5%: a contact starting exactly at d = 0 with vn = 0 (zero-length step window) has
    finite derivatives in float32 (a 1e-30 m^2 guard overflowed its square)."""
    x64, g64 = sliding_box(jnp.float64)(jnp.float64(0.4))
    x32, g32 = sliding_box(jnp.float32)(jnp.float32(0.4))
    coulomb = -2.0 ** 2 / (2.0 * 0.4 ** 2 * 9.81)
    assert float(x64) == pytest.approx(2.0 ** 2 / (2 * 0.4 * 9.81), rel=0.01)
    assert float(g64) == pytest.approx(coulomb, rel=0.01)
    assert np.isfinite(float(g32)) and float(g32) == pytest.approx(float(g64), rel=5e-3)


def test_rolling_sphere_spin_up_gradient_float32_and_float64():
    """A rigid sphere set sliding at 2 m/s without spin rolls from t_r = 2 v0 / (7 mu g) on
    at 5/7 v0: x(1 s) = 5/7 v0 + 2 v0^2 / (49 mu g), d/d mu = -2 v0^2 / (49 mu^2 g)
    = -0.10402 m. Measured -0.10393 (float64 and float32)."""
    out = {}
    for dtype in (jnp.float64, jnp.float32):
        scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
        scene.add_material("rough", k=1e5, c=200.0, friction=0.4, slip_speed=0.01)
        scene.add_plane(material="rough")
        scene.add_rigid_sphere(0.1, 1.0, (0.0, 0.0, 0.1), velocity=(2.0, 0.0, 0.0))
        sim = dp.compile(scene, 1e-3, dtype=dtype)

        def x(mu, sim=sim):
            p = sim.params(extra={"friction": {"rough": mu}})
            return sim.rollout(p, 1000, save_every=1000).position[-1, 0, 0]
        out[dtype] = float(jax.jit(jax.grad(x))(dtype(0.4)))
    want = -2 * 2.0 ** 2 / (49 * 0.4 ** 2 * 9.81)
    assert out[jnp.float64] == pytest.approx(want, rel=2e-3)
    assert out[jnp.float32] == pytest.approx(out[jnp.float64], rel=1e-3)


# --------------------------------------------------------------------------- box on a corner
def test_box_corner_reference_closed_forms():
    """tuning.reports.reference.BoxCornerReference against closed forms: a cube in free flight
    follows the gravity parabola and turns at its constant world angular velocity
    (q(t) = exp(w t / 2) q0); a flat box (principal moments all different) tumbling freely
    keeps its energy and angular momentum; a cube set on its face 1 mm up settles with each
    corner at the penalty depth m g / (4 k), without moving sideways."""
    from tuning.reports.reference import BoxCornerReference
    q0 = np.array([0.9, 0.2, -0.3, 0.25]) / np.linalg.norm([0.9, 0.2, -0.3, 0.25])
    w0, x0, v0, T = np.array([3.0, -5.0, 7.0]), np.array([0.1, 0.2, 5.0]), np.array(
        [0.3, -0.2, 1.0]), 0.2
    kw = dict(k=2e4, c=20.0, mu=0.4, slip_speed=0.01, mass=0.37, x0=x0, v0=v0, q0=q0, w0=w0,
              T=T)
    ref = BoxCornerReference(half=(0.025,) * 3, **kw)
    assert ref.events == []
    x, v, q, w = ref.state(T)
    np.testing.assert_allclose(x, x0 + v0 * T - [0.0, 0.0, 0.5 * 9.81 * T * T], atol=1e-12)
    a = np.linalg.norm(w0) * T
    p = np.r_[np.cos(a / 2), np.sin(a / 2) * w0 / np.linalg.norm(w0)]
    want = np.r_[p[0] * q0[0] - p[1:] @ q0[1:],
                 p[0] * q0[1:] + q0[0] * p[1:] + np.cross(p[1:], q0[1:])]
    np.testing.assert_allclose(q * np.sign(q[0] * want[0]), want, atol=1e-9)
    np.testing.assert_allclose(w, w0, atol=1e-12)
    flat = BoxCornerReference(half=(0.05, 0.02, 0.01), **kw)
    ts = np.linspace(0.0, T, 9)
    energy = np.array([flat.energy(t) for t in ts])
    mom = np.array([flat.angular_momentum(t) for t in ts])
    assert np.ptp(energy) < 1e-11 * abs(energy[0])
    assert np.abs(mom - mom[0]).max() < 1e-9 * np.linalg.norm(mom[0])
    assert np.abs(mom[0] - mom[-1]).max() < np.linalg.norm(mom[0])   # it does tumble:
    assert np.abs(flat.state(T)[3] - w0).max() > 1.0                 # w is not constant
    k, m = 2e4, 0.37
    rest = BoxCornerReference(half=(0.025,) * 3, **{**kw, "x0": (0.0, 0.0, 0.026),
                                                    "v0": (0.0, 0.0, 0.0), "w0": (0.0,) * 3,
                                                    "q0": (1.0, 0.0, 0.0, 0.0), "T": 0.4})
    x, v, q, w = rest.state(0.4)
    assert abs(x[2] - (0.025 - m * 9.81 / (4 * k))) < 1e-10
    assert np.abs(x[:2]).max() < 1e-15 and len(rest.contacts[0]) >= 1


def test_box_corner_reference_is_diffpen_model_in_the_limit():
    """The cube of the gradient check (k 5e3 N/m: one corner lands, a second lands while it
    is down, both have left by 0.095 s): diffpen's pose at 0.1 s converges to the reference at
    first order: the same model in continuous time. Measured: centre 9.0e-6 / 9.0e-7 m and
    rotation 1.19e-3 / 1.18e-4 rad off at dt 1e-4 / 1e-5."""
    from tuning.reports.box_gradients import BOX_CASES, box_corner_scene
    from tuning.reports.reference import BoxCornerReference, rotation_angle
    case = BOX_CASES[1]
    ref = BoxCornerReference(k=case.k, c=case.c, mu=case.mu, slip_speed=case.slip_speed,
                             mass=case.mass, half=(case.half,) * 3, x0=case.x0(), v0=case.v0,
                             q0=case.orientation(), w0=case.w0, T=0.1)
    first = case.first_corner()
    assert [(i, kind) for _, i, kind in ref.events] == [
        (first, "start"), (0, "start"), (first, "pull"), (first, "end"), (0, "pull"),
        (0, "end")]
    xr, _, qr, _ = ref.state(0.1)
    err = []
    for dt in (1e-4, 1e-5):
        sim = dp.compile(box_corner_scene(case), dt)
        n = int(round(0.1 / dt))
        traj = sim.rollout(sim.params(), n, save_every=n)
        err.append((np.abs(np.asarray(traj.position[-1, 0]) - xr).max(),
                    rotation_angle(np.asarray(traj.orientation[-1, 0]), qr)))
    assert err[1][0] < 1.5e-6 and err[1][1] < 2e-4
    for a, b in zip(*err):
        assert 8.0 < a / b < 12.0


@pytest.fixture(scope="module")
def box_corner_gradients():
    """d metrics / d (k, c, mu) of the cube landing on a corner (tuning.reports.gradient_check,
    case "k 5e3": 5 cm, 0.37 kg, k 5e3 N/m, c 10 N s/m, mu 0.18, slip speed 1 cm/s; 300
    steps of the default dt 1e-3, default settings) by jax.jacfwd in float64 and float32,
    and the continuous system's w.r.t. k and mu of the two metrics compared with it
    (BoxCornerReference, central differences; DOP853 at rtol 1e-10: within 1e-7 of rtol
    1e-12; solved up to T1: within 5e-9 of the solve to T2)."""
    from tuning.reports.box_gradients import BOX_CASES, box_corner_metrics_fn
    from tuning.reports.reference import BoxCornerReference
    case = BOX_CASES[1]
    t1 = case.times[0]

    def reference(**kcmu):
        """The continuous system's x@T1 and t_end1 (box_corner_reference_metrics' values),
        solved up to T1 only: both are decided by then (the settling after it took 95% of
        the full solve; the same values to ~1e-13 relative)."""
        ref = BoxCornerReference(**kcmu, slip_speed=case.slip_speed, mass=case.mass,
                                 half=(case.half,) * 3, x0=np.asarray(case.x0()), v0=case.v0,
                                 q0=case.orientation(), w0=case.w0, T=t1, rtol=1e-10)
        t_end = ref.contacts[case.first_corner()][0][1]
        assert t_end < t1
        return np.array([ref.state(t1)[0][0], t_end])

    # box_corner_reference(case, rtol=1e-10, params=("k", "mu")) for these two metrics: its
    # central differences at its relative step 1e-4 (4 solves; no solve at the centre)
    ref = {}
    base = {"k": case.k, "c": case.c, "mu": case.mu}
    for name in ("k", "mu"):
        step = 1e-4 * base[name]
        up, dn = (reference(**{**base, name: base[name] + s}) for s in (step, -step))
        ref["d" + name] = dict(zip(("x@T1", "t_end1"), (up - dn) / (2.0 * step)))
    out = {"ref": ref}
    for dtype in (jnp.float64, jnp.float32):
        f, _ = box_corner_metrics_fn(case, 1e-3, dtype=dtype)
        args = tuple(dtype(v) for v in (case.k, case.c, case.mu))
        # jacfwd's three columns from one compiled JVP (the tangent is an argument; the
        # batched program of jacfwd compiled slower)
        jvp = jax.jit(lambda a, t, f=f: jax.jvp(f, a, t)[1])
        out[dtype] = np.array([jvp(args, tuple(dtype(float(i == j)) for i in range(3)))
                               for j in range(3)], dtype=float)
    return out


def test_box_corner_gradients_float32_agrees_with_float64(box_corner_gradients):
    """All 30 derivatives (10 metrics: pose during the bounces and after the settling,
    distance travelled, end of the first contact; w.r.t. k, c, mu): float32 has float64's
    sign and is within 5% of it (measured: within 0.1%; within 2.9% on the stiffer k 2e4
    case, which is not run here)."""
    g64, g32 = box_corner_gradients[jnp.float64], box_corner_gradients[jnp.float32]
    assert np.all(np.isfinite(g32)) and np.all(np.sign(g32) == np.sign(g64))
    assert np.abs(g32 / g64 - 1.0).max() < 0.05


def test_box_corner_gradients_against_the_continuous_system(box_corner_gradients):
    """Where diffpen's derivative at the default dt is within 2% of the continuous one for
    every phase of the landing within the step
    (tuning.reports.box_gradients.box_corner_phase_errors, 6 phases): the end of the first corner's contact w.r.t. k (0.1-1.4%) and mu (0.1-1.1%),
    and the sliding x position during the bounces w.r.t. mu (0.2-1.2%). The other 27 are
    NOT within 2% at dt 1e-3 (median 19%, up to 370%; docs/gradients.txt has the table: the
    errors fall ~10x per 10x in dt, 20 of 30 within 2% at dt 1e-4, 28 at dt 1e-5)."""
    from tuning.reports.box_gradients import BOX_METRICS
    ref, g = box_corner_gradients["ref"], box_corner_gradients[jnp.float64]
    for metric, p in (("t_end1", "dk"), ("t_end1", "dmu"), ("x@T1", "dmu")):
        m, i = BOX_METRICS.index(metric), ("dk", "dc", "dmu").index(p)
        assert g[i, m] == pytest.approx(ref[p][metric], rel=0.02), (metric, p)


def test_reverse_mode_through_a_hertz_contact_is_finite():
    """Reverse mode through the Hunt-Crossley law with n = 1.5 was NaN: the window's masked
    branch raised a negative base to the power 3.5 (where() discards the value, not the
    NaN of its derivative). Now jax.grad equals jax.jacfwd."""
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.2))
    s.add_plane()
    sim = dp.compile(s, 1e-3, law="hunt_crossley", exponent=1.5)

    def loss(k, c):
        return sim.rollout(sim.params(k=k, c=c), 400, save_every=400).position[-1, 0, 2]
    # both modes (and the window's own reverse mode) in one compiled program
    from diffpen.window import window_mean
    rev, fwd, g = jax.jit(lambda k, c, d: (
        jax.grad(loss, (0, 1))(k, c), jax.jacfwd(loss, (0, 1))(k, c),
        jax.grad(lambda d: window_mean(d, 0.1, 1e-3, 1.5)[1])(d)))(1e5, 50.0, 0.01)
    assert np.all(np.isfinite(np.asarray(rev)))
    np.testing.assert_allclose(np.asarray(rev), np.asarray(fwd), rtol=1e-9)
    assert np.isfinite(float(g))


def test_centred_friction_takes_the_normal_force_contact_plane_applies():
    """With a centred law the rigid sphere's friction recomputed its normal force without the
    centred damping: it scaled mu by another force than the one applied."""
    scene = dp.Scene()
    scene.add_material("rough", k=1e4, c=20.0, friction=0.5, slip_speed=0.01)
    scene.add_plane(material="rough")
    scene.add_rigid_sphere(0.1, 1.0, (0.0, 0.0, 0.095), velocity=(2.0, 0.0, -0.3))
    sim = dp.compile(scene, 1e-3, law=laws.linear(centred=True))
    params, state = sim.params(), sim.init_state()
    h = sim.dt
    from diffpen.layout import rows

    def fz_ft(sim):
        # both terms' forces in one compiled program (params and state as its arguments)
        fz, ft = jax.jit(lambda p, s: (
            rows(sim.term("contact_plane").force(p, s, h=h)[0])[0, 2],
            sim.term("friction_sphere_plane").force(p, s, h=h)[0][0]))(params, state)
        return float(fz), np.asarray(ft)
    fz, ft = fz_ft(sim)
    u = 2.0                                         # slip speed of the contact point, m/s
    expect = 0.5 * fz * u / np.sqrt(u * u + 0.01 ** 2)
    assert fz > 0 and abs(-ft[0] / expect - 1.0) < 1e-12, (ft, expect)
    # and with the plain law both are its plain step average
    fz, ft = fz_ft(dp.compile(scene, 1e-3))
    assert abs(-ft[0] / (0.5 * fz * u / np.sqrt(u * u + 0.01 ** 2)) - 1.0) < 1e-12


def test_friction_at_a_touching_start_takes_the_contact_side_of_the_tie():
    """Regression: a box placed exactly on a rough named plane (depth 0, normal speed 0)
    starts at the tie of the friction's max(fn, 0), whose derivative JAX splits 0.5 / 0.5
    while the contact window takes the contact side: d (x + z + vy) / d plane offset after
    one step was -4.196 against -8.446 from above (300 steps: 8.02 against 0.607). Now it
    equals the one-sided difference from above."""
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    s.add_material("rough", k=2e4, c=20.0, friction=0.4, slip_speed=0.02)
    s.add_box((0.05, 0.05, 0.05), mass=0.37, position=(0.0, 0.0, 0.05),
              velocity=(1.0, 0.2, 0.0), material="rough")
    s.add_plane(material="rough", name="ground")
    sim = dp.compile(s, 5e-4)

    def f(o):
        tr = sim.rollout(sim.params(extra={"plane_offset": {"ground": o}}), 1, save_every=1)
        return tr.position[-1, 0, 0] + tr.position[-1, 0, 2] + tr.velocity[-1, 0, 1]
    vg = jax.jit(jax.value_and_grad(f))        # one program: the values and the derivative
    h = 1e-8
    (f0, grad), (fh, _) = vg(0.0), vg(h)
    above = (float(fh) - float(f0)) / h
    assert abs(above) > 1.0                    # the derivative the tie decides is not small
    assert float(grad) == pytest.approx(above, rel=1e-5)


def test_half_integer_powers_equal_pow_with_finite_derivatives():
    """The window's powers (``diffpen.window._power``: integer power times ``sqrt`` for
    half-integer exponents, several times cheaper than ``pow``) equal ``x ** p`` with the
    same first and second derivatives, finite at ``x = 0`` for ``p >= 2`` (where the
    product rule would have given 0 / 0)."""
    from diffpen.window import _power
    x = np.array([0.0, 1e-9, 3e-4, 0.2, 2.0])
    for p in (0.5, 1.0, 1.5, 1.7, 2.0, 2.5, 3.5, 4.5):
        got = jax.jit(jax.vmap(lambda v: (_power(v, p), jax.grad(_power)(v, p),
                                          jax.grad(jax.grad(_power))(v, p))))(x)
        want = jax.jit(jax.vmap(lambda v: (v ** p, jax.grad(lambda u: u ** p)(v),
                                           jax.grad(jax.grad(lambda u: u ** p))(v))))(x)
        keep = x > 0 if p < 2.0 else np.ones_like(x, bool)   # pow's own 0 * inf at 0
        for g, w in zip(got, want):
            np.testing.assert_allclose(np.asarray(g)[keep], np.asarray(w)[keep], rtol=1e-13,
                                       atol=0)
        if p >= 2.0:
            assert all(np.isfinite(np.asarray(g)).all() for g in got)


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
def test_exact_records_step_the_damped_spring_exactly(law, mass, k, c):
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
    make = {"linear": laws.linear, "no_tension": laws.no_tension}[law]
    off = []
    for rec in (make(exact=True), make(centred=True)):
        sim = dp.compile(s, h, law=rec, dtype=jnp.float64)
        z = np.asarray(sim.rollout(sim.params(k=k, c=c), steps, check_stability=False)
                       .position[:, 0, 2])
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
    r, q = (np.asarray(a) for a in jax.jit(laws.exact_step_factors, static_argnums=3)(
        k, c, im, h))
    for i, (kk, cc, ii) in enumerate(cases):
        s, w2 = 0.5 * cc * ii, kk * ii
        disc = cmath.sqrt(s * s - w2)
        e1, e2 = (cmath.exp((-s + sign * disc) * h) for sign in (1, -1))
        want_r = ((1 - e1) * (1 - e2)).real / (w2 * h * h)
        want_q = (1 - np.exp(-2 * s * h)) / (2 * s * h) if cc else 1.0
        assert r[i] == pytest.approx(want_r, rel=1e-9) and q[i] == pytest.approx(want_q, rel=1e-12)
    r0, q0 = laws.exact_step_factors(0.0, 20.0, 1.0, h)
    assert float(r0) == pytest.approx(float(q0), rel=1e-12)
    assert [float(a) for a in laws.exact_step_factors(1e4, 20.0, 0.0, h)] == [1.0, 1.0]
    grads = jax.jit(jax.vmap(jax.grad(lambda a, b: sum(laws.exact_step_factors(a, b, 1.0, h)),
                                      (0, 1))))(np.array([1e4, 1e4, 0.0, 0.0, 1e4]),
                                                np.array([200.0, 20.0, 0.0, 20.0, 0.0]))
    assert all(np.isfinite(np.asarray(g)).all() for g in grads)
    r32 = laws.exact_step_factors(jnp.float32(1e4), jnp.float32(20.0), jnp.float32(1.0), 1e-5)
    r64 = laws.exact_step_factors(1e4, 20.0, 1.0, 1e-5)
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
