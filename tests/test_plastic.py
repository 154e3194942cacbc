"""Crumple zones: plastic springs keep a permanent set after unloading, never grow back, and
have finite gradients that agree with finite differences.

Press test (1D bar, no gravity): a bar of N plastic springs (rest L0 each, stiffness k, yield
strain eps) with its first node pinned is pushed by a zero-rest "press" spring (k_p) towards
an anchor at x_a, overdamped by drag, then the press is released (k_p = 0). Closed form: the
crushed bar comes to rest where the press force equals the yield force k eps L0, so its end
sits at x_a + k eps L0 / k_p; releasing it, every spring springs back by eps L0:
final length = x_a + k eps L0 / k_p + N eps L0 (first node at 0).
"""
import math

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from jaxpr_scopes import traced_scopes
from diffpen.builders import add_crumple_bar
from diffpen.terms.plastic import AUX_KEY, rest_update

N, L0, K, EPS, KP, XA = 4, 0.1, 1000.0, 0.05, 100.0, 0.3
STEPS = 800


@pytest.fixture(scope="module")
def press():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    nodes = add_crumple_bar(scene, N + 1, (0.0, 0.0, 0.0), (N * L0, 0.0, 0.0), mass=0.05, k=K,
                            yield_strain=EPS, pinned=[0], drag=2.0)
    scene.add_spring(int(nodes[-1]), (XA, 0.0, 0.0), k=KP, rest_length=0.0, group="press")
    sim = dp.compile(scene, dt=1e-3)

    def run(eps=EPS, k=K, kp=KP):
        on = sim.params(springs={"bar": (k, 0.0), "press": (kp, 0.0)},
                        extra={"plastic": {"bar": eps}})
        off = sim.params(springs={"bar": (k, 0.0), "press": (0.0, 0.0)},
                         extra={"plastic": {"bar": eps}})
        crushed = sim.rollout(on, STEPS, save_every=10)
        released = sim.rollout(off, STEPS, state=crushed.final, save_every=10)
        return crushed, released
    return sim, nodes, run


def _length(traj):
    return np.asarray(traj.position[:, -1, 0] - traj.position[:, 0, 0])


def test_permanent_set_matches_closed_form(press):
    sim, nodes, run = press
    assert "plastic_springs" in sim.terms
    crushed, released = run()
    y = EPS * L0
    peak = _length(crushed)[-1]
    final = _length(released)[-1]
    assert peak == pytest.approx(XA + K * y / KP, abs=2e-4)
    assert final == pytest.approx(XA + K * y / KP + N * y, abs=3e-4)
    permanent_set = N * L0 - final
    assert permanent_set > 0.025                         # ~0.03 m of the 0.4 m bar for good
    # unloaded: the bar's length is the sum of its (shortened) rest lengths
    rest = np.asarray(released.aux[AUX_KEY][-1])
    assert final == pytest.approx(rest.sum(), abs=1e-6)
    assert np.all(np.diff(np.asarray(released.position[-1, :, 0])) > 0)   # no member inverted
    assert np.abs(np.asarray(released.velocity[-1])).max() < 1e-6           # at rest


def test_rest_lengths_never_grow(press):
    sim, nodes, run = press
    crushed, released = run()
    rest = np.concatenate([np.asarray(crushed.aux[AUX_KEY]), np.asarray(released.aux[AUX_KEY])])
    assert np.all(np.diff(rest, axis=0) <= 1e-15)
    assert np.all(rest <= L0 + 1e-15)
    # releasing is elastic: no rest length changes after the press lets go
    np.testing.assert_allclose(np.asarray(released.aux[AUX_KEY][0]),
                               np.asarray(released.aux[AUX_KEY][-1]), atol=1e-12)


def test_below_yield_the_bar_is_elastic(press):
    sim, nodes, run = press
    # a press of 10 N/m pushing 0.1 m gives < 1 N < the 5 N yield force: no set at all
    crushed, released = run(kp=10.0)
    assert _length(crushed)[-1] < N * L0 - 1e-3             # it was compressed
    assert _length(released)[-1] == pytest.approx(N * L0, abs=1e-6)
    np.testing.assert_array_equal(np.asarray(released.aux[AUX_KEY][-1]),
                                  np.asarray(sim.init_state().aux[AUX_KEY]))


def test_gradients_are_finite_and_match_finite_differences(press):
    sim, nodes, run = press

    def final_length(eps, k):
        _, released = run(eps, k)
        return released.position[-1, -1, 0] - released.position[-1, 0, 0]
    g_eps, g_k = (float(g) for g in jax.grad(final_length, argnums=(0, 1))(EPS, K))
    assert np.isfinite(g_eps) and np.isfinite(g_k)
    h_eps, h_k = 1e-5, 1e-2
    fd_eps = float(final_length(EPS + h_eps, K) - final_length(EPS - h_eps, K)) / (2 * h_eps)
    fd_k = float(final_length(EPS, K + h_k) - final_length(EPS, K - h_k)) / (2 * h_k)
    assert g_eps == pytest.approx(fd_eps, rel=1e-4)
    assert g_k == pytest.approx(fd_k, rel=1e-3)
    # and both agree with the closed form's derivatives: K L0 / KP + N L0 and eps L0 / KP
    assert g_eps == pytest.approx(K * L0 / KP + N * L0, rel=1e-2)
    assert g_k == pytest.approx(EPS * L0 / KP, rel=1e-2)


def test_rest_update_pointwise():
    rest0, eps = 0.1, 0.05
    lengths = jnp.linspace(0.05, 0.12, 71)
    hard = rest_update(lengths, rest0, rest0, eps, 0.0)
    np.testing.assert_allclose(np.asarray(hard), np.minimum(rest0, np.asarray(lengths)
                                                            + eps * rest0), atol=1e-15)
    smooth = rest_update(lengths, rest0, rest0, eps, 1e-3)
    assert np.all(np.asarray(smooth) <= rest0)
    # exact outside the band (no flow below the yield, full return mapping past it)
    far = np.asarray(lengths) < rest0 * (1 - eps - 1e-3)
    near_elastic = np.asarray(lengths) >= rest0 * (1 - eps)
    np.testing.assert_allclose(np.asarray(smooth)[near_elastic], rest0, atol=0)
    np.testing.assert_allclose(np.asarray(smooth)[far],
                               np.asarray(lengths)[far] + eps * rest0 + 0.5e-3 * rest0,
                               atol=1e-15)
    d = jax.vmap(jax.grad(rest_update), in_axes=(0, None, None, None, None))(
        lengths, rest0, rest0, eps, 1e-3)
    assert np.all(np.isfinite(np.asarray(d)))
    assert np.all((np.asarray(d) >= 0) & (np.asarray(d) <= 1))


def test_scene_without_plastic_springs_traces_no_plastic_code():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    a = scene.add_particle(1.0, (0.0, 0.0, 0.0))
    b = scene.add_particle(1.0, (1.0, 0.0, 0.0))
    scene.add_spring(a, b, k=10.0)
    sim = dp.compile(scene, dt=1e-3)
    state = sim.init_state()
    assert "plastic_rest" not in state.aux and "plastic" not in sim.params().extra
    assert set(state.aux) == {"unstable"}          # only the stability flag
    names, _ = traced_scopes(sim, sim.params())
    assert not any("plastic" in n for n in names)


@pytest.mark.parametrize("kwargs, match", [
    (dict(yield_strain=0.0), r"yield_strain must be in \(0, 1\)"),
    (dict(yield_strain=1.0), r"yield_strain must be in \(0, 1\)"),
    (dict(yield_strain=float("nan")), r"yield_strain must be in \(0, 1\)"),
    (dict(yield_strain=0.1, pinned=[7]), "outside the grid"),
    (dict(yield_strain=0.1, width=0.0), "width .* positive"),
])
def test_crumple_bar_bad_input(kwargs, match):
    scene = dp.Scene()
    with pytest.raises(dp.SceneError, match=match):
        add_crumple_bar(scene, 3, (0, 0, 0), (1, 0, 0), 1.0, 100.0, **kwargs)


def test_plastic_spring_bad_input():
    scene = dp.Scene()
    a = scene.add_particle(1.0, (0.0, 0.0, 0.0))
    b = scene.add_particle(1.0, (1.0, 0.0, 0.0))
    with pytest.raises(dp.SceneError, match="yield_strain="):
        scene.add_plastic_spring(a, b, k=10.0)
    with pytest.raises(dp.SceneError, match=r"\(0, 1\)"):
        scene.add_plastic_spring(a, b, k=10.0, yield_strain=1.5)
    with pytest.raises(dp.SceneError, match="names body 2"):
        scene.add_plastic_spring(a, 2, k=10.0, yield_strain=0.1)
    scene.add_plastic_spring(a, b, k=10.0, yield_strain=0.1)
    with pytest.raises(dp.SceneError, match="already has yield_strain"):
        scene.add_plastic_spring(a, b, yield_strain=0.2)
    sim = dp.compile(scene, dt=1e-3)
    for bad in (0.0, 1.0, -0.1, float("nan")):
        with pytest.raises(dp.SceneError, match=r"yield strain and must be in \(0, 1\)"):
            sim.params(extra={"plastic": {"plastic": bad}})
    scene.plastic_smoothing = -1.0
    with pytest.raises(dp.SceneError, match="plastic_smoothing"):
        dp.compile(scene, dt=1e-3)


def test_truss_crumple_bar_structure():
    scene = dp.Scene()
    idx = add_crumple_bar(scene, 4, (0, 0, 0), (0.3, 0, 0), 1.0, 100.0, width=0.05,
                          yield_strain=0.1, pinned=[0])
    assert idx.shape == (4, 2)
    # rails 2 x 3, rungs 4 - 1 (pinned rung left out), diagonals 2 x 3
    assert len(scene.plastic_springs) == 6 + 3 + 6
    np.testing.assert_allclose(np.ptp([scene.bodies[i].position[1] for i in idx[0]]), 0.05)


def test_yield_is_applied_every_inner_step():
    """With substeps the return mapping ran once per saved step: a plastic spring struck at
    3 m/s kept 0.9440 m at 100 substeps of 1e-4 s against 0.9355 m stepped at 1e-4 s (the
    energy balance gives 0.935). Same inner step, same physics now."""
    def rest(dt, sub, steps):
        s = dp.Scene(gravity=(0.0, 0.0, 0.0))
        a = s.add_particle(1.0, (0.0, 0.0, 0.0), pinned=True)
        b = s.add_particle(1.0, (1.0, 0.0, 0.0), velocity=(-3.0, 0.0, 0.0))
        s.add_plastic_spring(a, b, k=1000.0, c=0.0, yield_strain=0.05)
        sim = dp.compile(s, dt, substeps=sub)
        tr = sim.rollout(sim.params(), steps, save_every=steps)
        return float(tr.aux[AUX_KEY][-1, 0])
    fine = rest(1e-4, 1, 3000)
    assert fine == pytest.approx(0.935, abs=1e-3)
    assert rest(1e-2, 100, 30) == pytest.approx(fine, abs=1e-9)


def test_stiff_plastic_springs_are_in_the_stability_bound():
    """Plastic springs had no rows in the stability bound: k = 1e6 N/m between 1 kg bodies at
    dt = 0.01 s (w h ~ 14) was reported "no limit" and ran to 1e63 m without an error."""
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    a = s.add_particle(1.0, (0.0, 0.0, 0.0), velocity=(0.1, 0.0, 0.0))
    b = s.add_particle(1.0, (1.0, 0.0, 0.0))
    s.add_plastic_spring(a, b, k=1e6, c=0.0, yield_strain=0.5)
    sim = dp.compile(s, 0.01)
    rep = sim.stability(sim.params())
    assert rep.stable_dt == pytest.approx(2.0 / math.sqrt(2.0 * 1e6), rel=1e-6)  # 2 / w, w^2 = 2k/m
    with pytest.raises(dp.StabilityError, match="spring group"):
        sim.rollout(sim.params(), 30)


def test_a_plastic_spring_between_coincident_bodies_says_why():
    """Regression: two bodies at one point joined by a plastic spring without a rest length
    were refused with "rest_length must be positive, got 0.0", an argument not given."""
    scene = dp.Scene()
    a = scene.add_particle(0.1, (0.0, 0.0, 1.0))
    b = scene.add_particle(0.1, (0.0, 0.0, 1.0))
    with pytest.raises(dp.SceneError, match=f"bodies {a} and {b} start at the same point.*"
                                            "move them apart or give rest_length"):
        scene.add_plastic_spring(a, b, k=100.0, yield_strain=0.1)
    assert not scene.plastic_springs
    scene.add_plastic_spring(a, b, k=100.0, yield_strain=0.1, rest_length=0.05)


def test_a_member_crushed_through_its_length_is_flagged_and_warned():
    """Regression (audit17): crumple members have no volume and the nodes no self-contact:
    a crumple bar driven into a wall at 2 m/s had members pass through zero length and turn
    inside out (pushing the wrong way) with no flag and no word. A member crushed below
    COLLAPSE_FRACTION of its length now sets aux["plastic_collapsed"] (kept) and the rollout
    warns; at 0.5 m/s the bar crumples without reaching it."""
    import warnings

    from diffpen.terms.plastic import CollapseWarning

    def hit(v):
        sc = dp.Scene(gravity=(0.0, 0.0, 0.0))
        nodes = add_crumple_bar(sc, 6, (0.1, 0.0, 0.5), (0.6, 0.0, 0.5), 1.0, 2000.0, 1.0,
                                yield_strain=0.05, velocity=(-v, 0.0, 0.0))
        sc.add_plane(normal=(1.0, 0.0, 0.0), offset=0.0)
        sim = dp.compile(sc, dt=1e-4, substeps="auto")
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            t = sim.rollout(sim.params(k=1e5, c=10.0), steps=2000, save_every=10)
        gaps = np.diff(np.asarray(t.position[:, nodes, 0]), axis=1)
        return (np.asarray(t.aux["plastic_collapsed"]), bool((gaps < 0).any()),
                [w.category for w in seen])
    flag, inverted, seen = hit(2.0)
    assert inverted and flag[-1] == 1.0 and CollapseWarning in seen
    first = int(np.argmax(flag > 0))
    assert 0 < first and np.all(flag[first:] == 1.0)            # set once, then kept
    flag, inverted, seen = hit(0.5)
    assert not inverted and not flag.any() and CollapseWarning not in seen
