"""The workshop paper's ball-spring chain and the velocity drag term.

References are independent of the builder: the equilibrium is assembled here from the
scene's own springs (a graph Laplacian) and solved with scipy; force signs are checked
against Hooke's law written out by hand.
"""
import jax
import jax.extend.core
import numpy as np
import pytest
import scipy.linalg

import diffpen as dp
from jaxpr_scopes import traced_scopes
from diffpen.builders import PAPER_CHAIN, paper_chain, paper_chain_equilibrium


def _scopes(sim, params):
    return " ".join(traced_scopes(sim, params)[0])


def _laplacian_equilibrium(scene):
    """Static equilibrium of a zero-rest-length spring network under gravity, solved directly:
    sum_j k_ij (x_j - x_i) + m_i g = 0 for every free node i."""
    n = scene.n_bodies
    free = np.array([not b.pinned for b in scene.bodies])
    x = np.array([b.position for b in scene.bodies])
    L = np.zeros((n, n))
    for s in scene.springs:
        assert s.rest_length == 0.0
        k = scene.spring_groups[s.group].k
        L[s.a, s.a] += k
        L[s.b, s.b] += k
        L[s.a, s.b] -= k
        L[s.b, s.a] -= k
    m = np.array([b.mass for b in scene.bodies])
    rhs = m[free, None] * np.array(scene.gravity)[None, :] - L[np.ix_(free, ~free)] @ x[~free]
    x = x.copy()
    x[free] = scipy.linalg.solve(L[np.ix_(free, free)], rhs, assume_a="pos")
    return x


@pytest.fixture(scope="module")
def chain():
    scene, balls = paper_chain(seed=0)
    sim = dp.compile(scene, dt=PAPER_CHAIN["dt"])
    return scene, balls, sim


def test_chain_constants_match_the_paper(chain):
    scene, balls, sim = chain
    assert len(balls) == 7
    assert [b.mass for b in scene.bodies] == [10.0] * 7
    assert scene.bodies[0].pinned and scene.bodies[-1].pinned
    assert scene.bodies[0].position == (100.0, 0.0, 100.0)
    assert scene.bodies[-1].position == (500.0, 0.0, 100.0)
    assert scene.gravity == (0.0, 0.0, -9.8)
    params = sim.params()
    assert float(params.springs["chain.spring"].k) == 50.0
    assert float(params.springs["chain.spring"].c) == 0.0
    assert float(params.extra["drag"]["chain.drag"]) == 1.0
    assert sim.dt == 0.1
    # reproducible scatter: same seed, same start; another seed, another start
    again, _ = paper_chain(seed=0)
    other, _ = paper_chain(seed=1)
    assert [b.position for b in again.bodies] == [b.position for b in scene.bodies]
    assert [b.position for b in other.bodies] != [b.position for b in scene.bodies]


def test_chain_forces_pull_towards_neighbours_and_drag_opposes_velocity(chain):
    scene, balls, sim = chain
    state = sim.init_state()
    rng = np.random.default_rng(3)
    v = rng.normal(size=(7, 3))
    v[[0, -1]] = 0.0
    state = state._replace(velocity=state.velocity + v)
    f, tau = sim.forces(sim.params(), state)
    assert tau is None
    x = np.array([b.position for b in scene.bodies])
    ks, kd = 50.0, 1.0
    for i in range(1, 6):
        hooke = ks * (x[i - 1] - x[i]) + ks * (x[i + 1] - x[i])   # towards the neighbours
        np.testing.assert_allclose(np.asarray(f[i]), hooke - kd * v[i], rtol=1e-12, atol=1e-9)


def test_chain_reaches_the_directly_solved_equilibrium(chain):
    scene, balls, sim = chain
    ref = _laplacian_equilibrium(scene)
    np.testing.assert_allclose(paper_chain_equilibrium(), ref, rtol=0, atol=1e-10)
    traj = sim.rollout(sim.params(), steps=4000, save_every=2000)
    err_2000 = np.abs(np.asarray(traj.position[0]) - ref).max()
    err_4000 = np.abs(np.asarray(traj.position[1]) - ref).max()
    # start offsets ~100 decay like exp(-KD t / 2m): e^-10 after 2000 steps, e^-20 after 4000
    assert err_2000 < 0.02
    assert err_4000 < 1e-5
    # the sag is real (not the straight line between the ends) and the chain is symmetric
    assert ref[3, 2] < 100.0 - 8.0
    np.testing.assert_allclose(ref[1:6, 2], ref[5:0:-1, 2], atol=1e-9)


def test_paper_dt_is_inside_the_semi_implicit_euler_stability_limit(chain):
    scene, balls, sim = chain
    m, ks, kd, h = 10.0, 50.0, 1.0, 0.1
    K = ks * (2 * np.eye(5) - np.eye(5, k=1) - np.eye(5, k=-1))
    w_max = np.sqrt(np.linalg.eigvalsh(K).max() / m)
    assert w_max == pytest.approx(np.sqrt(ks * (2 + np.sqrt(3)) / m))   # value in docstring
    assert w_max * h < 2.0
    assert w_max ** 2 * m * h ** 2 + 2 * kd * h < 4 * m


def test_drag_matches_closed_form_decay():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    b = scene.add_particle(2.0, (0.0, 0.0, 0.0), velocity=(1.0, -2.0, 0.5))
    scene.add_drag(b, c=0.4)
    sim = dp.compile(scene, dt=1e-3)
    traj = sim.rollout(sim.params(), steps=1000)
    # semi-implicit Euler on v' = -(c/m) v: v_n = (1 - h c / m)^n v_0
    expected = (1 - 1e-3 * 0.4 / 2.0) ** 1000 * np.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(np.asarray(traj.velocity[-1, 0]), expected, rtol=1e-12)
    # the coefficient is a differentiable parameter
    g = jax.grad(lambda c: sim.rollout(sim.params(extra={"drag": {"drag": c}}), 100)
                 .velocity[-1, 0, 0])(0.4)
    assert np.isfinite(g) and g < 0.0


def test_drag_term_absent_when_not_used():
    scene = dp.Scene()
    a = scene.add_particle(1.0, (0.0, 0.0, 1.0))
    scene.add_spring(a, (0.0, 0.0, 2.0), k=10.0)
    sim = dp.compile(scene, dt=1e-3)
    params = sim.params()
    assert "drag" not in sim.terms and "drag" not in params.extra
    assert "drag" not in _scopes(sim, params)
    scene.add_drag(a, c=0.1)
    sim2 = dp.compile(scene, dt=1e-3)
    assert "drag" in sim2.terms and "drag" in _scopes(sim2, sim2.params())


@pytest.mark.parametrize("call, match", [
    (lambda s: s.add_drag(5, c=1.0), "names body 5"),
    (lambda s: s.add_drag(0, c=-1.0), "non-negative"),
    (lambda s: s.add_drag(0), "is new: give c"),
    (lambda s: s.add_drag([], c=1.0), "no bodies"),
])
def test_drag_bad_input(call, match):
    scene = dp.Scene()
    scene.add_particle(1.0, (0.0, 0.0, 1.0))
    with pytest.raises(dp.SceneError, match=match):
        call(scene)


def test_drag_unknown_group_in_params_is_an_error():
    scene = dp.Scene()
    scene.add_drag(scene.add_particle(1.0, (0.0, 0.0, 1.0)), c=1.0, group="air")
    sim = dp.compile(scene, dt=1e-3)
    with pytest.raises(dp.SceneError, match="not in this scene"):
        sim.params(extra={"drag": {"water": 2.0}})
    with pytest.raises(dp.SceneError, match=">= 0"):
        sim.params(extra={"drag": {"air": -2.0}})


def test_cli_simulate_chain_prints_final_positions_at_the_equilibrium(capsys):
    import json

    from tuning.cli import main
    assert main(["simulate", "chain", "--steps", "2000", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    final = np.array(out["final_positions"])
    assert final.shape == (7, 3)
    scene, _ = paper_chain(seed=0)
    np.testing.assert_allclose(final, _laplacian_equilibrium(scene), atol=0.02)


def test_tuning_fits_chain_stiffness_and_drag_params_by_path(chain):
    """Soft-body parameters (spring groups and per-group extra entries) are fittable with
    tuning.fit; the fitted KS matches the closed form of the zero-rest chain's sag."""
    from tuning import fit, params as P
    scene, balls, sim = chain
    p0 = sim.params()
    assert set(P.flatten(p0)) == {"springs.chain.spring.k", "springs.chain.spring.c",
                                  "extra.drag.chain.drag"}

    def metrics(p):
        return {"sag": 100.0 - sim.rollout(p, 2000, save_every=2000).position[-1, 3, 2]}
    res = fit.fit(metrics, p0, {"sag": 5.0}, free=["springs.chain.spring.k"], progress=False,
                  maxiter=100, rtol=1e-4)
    assert res.reached
    # middle ball of 7, zero-rest springs: sag = m g / (2 KS) * 3 * 3
    assert res.values["springs.chain.spring.k"] == pytest.approx(10 * 9.8 * 9 / (2 * 5.0),
                                                                 rel=1e-3)
    again = P.unflatten(p0, {"extra.drag.chain.drag": 2.0})
    assert float(again.extra["drag"]["chain.drag"]) == 2.0
