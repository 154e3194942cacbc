"""Soft-body builders: structure, cloth sag against an independent scipy equilibrium, contact
of nodes, left-out terms, bad input."""
import re

import numpy as np
import pytest
from scipy.optimize import minimize

import diffpen as dp
from jaxpr_scopes import traced_scopes
from diffpen.builders import add_cloth, add_crumple_bar, add_jelly, add_rope, paper_chain


def _scopes(sim, params):
    return traced_scopes(sim, params)[0]


def _groups(scene):
    out = {}
    for s in scene.springs:
        out.setdefault(s.group, []).append(s)
    return out


def test_rope_structure():
    scene = dp.Scene()
    idx = add_rope(scene, 6, (0.0, 0.0, 1.0), (1.0, 0.0, 1.0), mass=0.6, k=100.0, c=0.1,
                   pinned=[0, -1], bend=(5.0, 0.0))
    assert idx.shape == (6,) and list(idx) == list(range(6))
    assert [b.pinned for b in scene.bodies] == [True] + [False] * 4 + [True]
    assert all(b.mass == pytest.approx(0.1) for b in scene.bodies)
    g = _groups(scene)
    assert len(g["rope.stretch"]) == 5 and len(g["rope.bend"]) == 4
    np.testing.assert_allclose([s.rest_length for s in g["rope.stretch"]], 0.2)
    np.testing.assert_allclose([s.rest_length for s in g["rope.bend"]], 0.4)


def test_cloth_structure_and_pinned_pairs_left_out():
    scene = dp.Scene()
    nx, ny, h = 4, 3, 0.05
    idx = add_cloth(scene, nx, ny, h, mass=1.2, origin=(1.0, 2.0, 3.0),
                    pinned=[(0, -1), (-1, -1), (1, 2)])
    assert idx.shape == (nx, ny)
    np.testing.assert_allclose(scene.bodies[idx[2, 1]].position, (1.0 + 2 * h, 2.0 + h, 3.0))
    g = _groups(scene)
    # structural: (nx-1) ny + nx (ny-1) minus the pinned-pinned pair (0,2)-(1,2)
    assert len(g["cloth.structural"]) == (nx - 1) * ny + nx * (ny - 1) - 1
    assert len(g["cloth.shear"]) == 2 * (nx - 1) * (ny - 1)
    assert len(g["cloth.bend"]) == (nx - 2) * ny + nx * (ny - 2) - 1   # (1,2)-(3,2) pinned
    for name, rest in (("structural", h), ("shear", np.sqrt(2) * h), ("bend", 2 * h)):
        np.testing.assert_allclose([s.rest_length for s in g[f"cloth.{name}"]], rest)
    for s in scene.springs:
        assert not (scene.bodies[s.a].pinned and scene.bodies[s.b].pinned)
    sim = dp.compile(scene, dt=1e-3)
    assert set(sim.spring_groups) == {"cloth.structural", "cloth.shear", "cloth.bend"}


def test_jelly_structure():
    scene = dp.Scene()
    idx = add_jelly(scene, 3, 2, 2, 0.1, mass=1.2)
    assert idx.shape == (3, 2, 2) and scene.n_bodies == 12
    g = _groups(scene)
    cells = 2 * 1 * 1
    assert len(g["jelly.edge"]) == 2 * 2 * 2 + 3 * 1 * 2 + 3 * 2 * 1
    assert len(g["jelly.face"]) == 2 * (2 * 1 * 2 + 2 * 2 * 1 + 3 * 1 * 1)
    assert len(g["jelly.body"]) == 4 * cells
    for name, rest in (("edge", 0.1), ("face", np.sqrt(2) * 0.1), ("body", np.sqrt(3) * 0.1)):
        np.testing.assert_allclose([s.rest_length for s in g[f"jelly.{name}"]], rest)


def _static_equilibrium(scene):
    """Independent reference: minimise the network's potential energy with scipy (numpy
    energy and gradient written here, not the simulator's)."""
    x0 = np.array([b.position for b in scene.bodies])
    free = np.array([not b.pinned for b in scene.bodies])
    m = np.array([b.mass for b in scene.bodies])
    g = np.array(scene.gravity)
    a = np.array([s.a for s in scene.springs])
    b = np.array([s.b for s in scene.springs])
    rest = np.array([s.rest_length for s in scene.springs])
    k = np.array([scene.spring_groups[s.group].k for s in scene.springs])

    def unpack(z):
        x = x0.copy()
        x[free] = z.reshape(-1, 3)
        return x

    def energy(z):
        x = unpack(z)
        d = x[a] - x[b]
        length = np.linalg.norm(d, axis=1)
        e = 0.5 * np.sum(k * (length - rest) ** 2) - np.sum(m[:, None] * x * g)
        f = (k * (length - rest) / length)[:, None] * d
        grad = np.zeros_like(x)
        np.add.at(grad, a, f)
        np.add.at(grad, b, -f)
        grad -= m[:, None] * g
        return e, grad[free].ravel()

    z0 = x0[free].ravel() + 1e-3 * np.random.default_rng(0).standard_normal(3 * free.sum())
    res = minimize(energy, z0, jac=True, method="BFGS", options=dict(gtol=1e-11, maxiter=5000))
    assert np.abs(energy(res.x)[1]).max() < 1e-6        # N: a stationary point
    return unpack(res.x)


def test_cloth_sag_matches_scipy_static_equilibrium():
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    idx = add_cloth(scene, 5, 5, 0.1, mass=0.25, structural=(20.0, 0.05), shear=(10.0, 0.02),
                    bend=(2.0, 0.0), pinned=[(0, 0), (0, -1), (-1, 0), (-1, -1)], drag=0.05)
    sim = dp.compile(scene, dt=2e-3)
    traj = sim.rollout(sim.params(), steps=4000, save_every=4000)
    x = np.asarray(traj.position[-1])
    ref = _static_equilibrium(scene)
    sag_sim, sag_ref = -x[idx[2, 2], 2], -ref[idx[2, 2], 2]
    assert sag_ref > 0.1                       # a real sag, ~0.13 m for these numbers
    assert sag_sim == pytest.approx(sag_ref, rel=1e-6)
    np.testing.assert_allclose(x, ref, atol=1e-7)


def test_rope_nodes_rest_on_a_plane_at_mg_over_k():
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    idx = add_rope(scene, 4, (0.0, 0.0, 0.01), (0.3, 0.0, 0.01), mass=0.4, k=50.0, c=0.5,
                   pinned=[], drag=0.5)
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3)
    k = 1e3
    traj = sim.rollout(sim.params(k=k, c=2.0), steps=3000, save_every=3000)
    z = np.asarray(traj.position[-1, idx, 2])
    np.testing.assert_allclose(z, -0.1 * 9.81 / k, rtol=1e-3)


def test_cloth_nodes_touch_a_fixed_sphere_from_outside():
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    idx = add_cloth(scene, 5, 5, 0.05, mass=0.1, origin=(-0.1, -0.1, 0.12), drag=0.02)
    scene.add_fixed_sphere((0.0, 0.0, 0.0), 0.1)
    sim = dp.compile(scene, dt=1e-3)
    traj = sim.rollout(sim.params(k=500.0, c=0.2), steps=600, save_every=600)
    x = np.asarray(traj.position[-1])
    r = np.linalg.norm(x[idx[2, 2]])
    assert 0.1 - 5e-3 < r < 0.1 + 5e-3          # centre node sits on the sphere
    assert x[idx[0, 0], 2] < x[idx[2, 2], 2]   # corners hang below it


def test_rope_scene_traces_no_rigid_body_or_box_code():
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    add_rope(scene, 5, (0.0, 0.0, 1.0), (0.5, 0.0, 1.0), mass=0.5, k=200.0, c=0.1)
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3)
    params = sim.params(k=1e4, c=10.0)
    state = sim.init_state()
    assert state.orientation is None and state.angular_velocity is None
    assert set(sim.terms) == {"contact_plane", "springs"}
    scopes = {part for s in _scopes(sim, params) for part in s.split("/") if part}
    expected = {"contact_plane", "springs", "gravity"}
    assert expected <= scopes
    unexpected = {s for s in scopes - expected if not s.startswith(("jit", "pjit", "vmap"))}
    assert not unexpected, unexpected
    text = " ".join(scopes)
    for word in ("rigid", "box", "torque", "quat", "orientation", "drag", "plastic"):
        assert word not in text
    _, tau = sim.forces(params, state)
    assert tau is None


@pytest.mark.parametrize("call, match", [
    (lambda s: add_rope(s, 1, (0, 0, 0), (1, 0, 0), 1.0, 10.0), "n must be an integer >= 2"),
    (lambda s: add_rope(s, 3, (0, 0, 0), (0, 0, 0), 1.0, 10.0), "coincide"),
    (lambda s: add_rope(s, 3, (0, 0, 0), (1, 0, 0), 0.0, 10.0), "mass .* positive"),
    (lambda s: add_rope(s, 3, (0, 0, 0), (1, 0, 0), 1.0, -1.0), ">= 0"),
    (lambda s: add_rope(s, 3, (0, 0, 0), (1, 0, 0), 1.0, 1.0, pinned=[3]), "outside the grid"),
    (lambda s: add_cloth(s, 1, 4, 0.1, 1.0), "nx must be an integer >= 2"),
    (lambda s: add_cloth(s, 3, 3, 0.0, 1.0), "spacing .* positive"),
    (lambda s: add_cloth(s, 3, 3, -0.1, 1.0), "spacing .* positive"),
    (lambda s: add_cloth(s, 3, 3, 0.1, 1.0, pinned=[(3, 0)]), "outside the grid"),
    (lambda s: add_cloth(s, 3, 3, 0.1, 1.0, pinned=[5]), "2 integer"),
    (lambda s: add_cloth(s, 3, 3, 0.1, 1.0, structural=None), "structural springs are"),
    (lambda s: add_cloth(s, 3, 3, 0.1, 1.0, axes=((1, 0, 0), (1, 1, 0))), "orthogonal"),
    (lambda s: add_jelly(s, 2, 2, 1, 0.1, 1.0), "nz must be an integer >= 2"),
    (lambda s: add_jelly(s, 2, 2, 2, 0.1, float("nan")), "mass"),
    (lambda s: add_jelly(s, 2, 2, 2, 0.1, 1.0, pinned=[(0, 0, 2)]), "outside the grid"),
])
def test_builder_bad_input(call, match):
    scene = dp.Scene()
    with pytest.raises(dp.SceneError, match=match):
        call(scene)
    assert scene.n_bodies == 0          # validated before anything was added


def test_builder_group_clash_is_an_error():
    scene = dp.Scene()
    add_rope(scene, 3, (0, 0, 0), (1, 0, 0), 1.0, 10.0)
    with pytest.raises(dp.SceneError, match="already exists"):
        add_rope(scene, 3, (0, 0, 1), (1, 0, 1), 1.0, 10.0)
    add_rope(scene, 3, (0, 0, 1), (1, 0, 1), 1.0, 20.0, group="rope2")
    sim = dp.compile(scene, dt=1e-3)
    params = sim.params()
    assert float(params.springs["rope.stretch"].k) == 10.0
    assert float(params.springs["rope2.stretch"].k) == 20.0


def test_cli_simulate_cloth_sag_matches_scipy_static_equilibrium(capsys):
    import json

    from tuning.cli import main
    from tuning.scenes import get_scene
    assert main(["simulate", "cloth", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    setup = get_scene("cloth")
    ref = _static_equilibrium(setup.scene)
    n = 9
    centre = n // 2 * n + n // 2             # node (4, 4) of the 9 x 9 grid
    assert out["max_speed"] < 1e-6
    assert out["centre_sag"] == pytest.approx(-ref[centre, 2], rel=1e-5)


@pytest.mark.parametrize("build, words", [
    # a two-character string was split into (k, c) = (5, 0)
    (lambda s: add_rope(s, 3, (0, 0, 0), (1, 0, 0), 1.0, 10.0, bend="50"), "rope"),
    (lambda s: add_cloth(s, 3, 3, 0.1, 1.0, shear="12"), "cloth"),
    (lambda s: add_rope(s, 3, (0, 0, 0), (1, 0, 0), "2", 10.0), "without quotes"),
    (lambda s: add_rope(s, 3, (0, 0, 0), (1, 0, 0), 1.0, True), "rope"),     # k = 1 N/m
    (lambda s: add_rope(s, 3, (0, 0, 0), (1, 0, 0), 1.0, 10.0, pinned=[True]), "pinned"),
    (lambda s: add_crumple_bar(s, 3, (0, 0, 0), (1, 0, 0), 1.0, 10.0, yield_strain="0.1"),
     "yield_strain"),
    # bend springs asked for on a rope that has none were left out without a word
    (lambda s: add_rope(s, 2, (0, 0, 0), (1, 0, 0), 1.0, 10.0, bend=(5.0, 0.1)),
     "a rope of 2 nodes has none"),
])
def test_builders_refuse_strings_and_bools_as_numbers(build, words):
    """The builders coerced what dp.Scene refuses: bend="50" became (k, c) = (5, 0),
    mass="2" a number, k=True 1 N/m, pinned=[True] node 1."""
    with pytest.raises(dp.SceneError, match=words):
        build(dp.Scene())


@pytest.mark.parametrize("spread", [-5.0, float("nan"), float("inf"), "8"])
def test_paper_chain_spread_is_checked(spread):
    """spread=-5 raised numpy's "high - low < 0", NaN or inf an OverflowError."""
    with pytest.raises(dp.SceneError, match="spread"):
        paper_chain(spread=spread)
    assert paper_chain(spread=0.0)[1] is not None


def test_yield_strain_params_are_real_scalars():
    """sim.params took a string or a vector yield strain (a vector of the wrong length then
    failed inside the rollout with a raw broadcasting error)."""
    s = dp.Scene()
    add_crumple_bar(s, 4, (0, 0, 0), (1, 0, 0), 1.0, 100.0, group="bar")
    sim = dp.compile(s, 1e-3)
    for bad, words in (("0.1", "without quotes"), (np.array([0.1, 0.2]), "scalar"),
                       (True, "must be a number"), (1.5, r"in \(0, 1\)")):
        with pytest.raises(dp.SceneError, match=words):
            sim.params(extra={"plastic": {"bar": bad}})
    sim.params(extra={"plastic": {"bar": 0.1}})


def test_one_pinned_index_pins_that_node_and_anything_else_is_refused_clearly():
    """``add_rope(pinned=0)`` pinned no node at all (``0 or ()``); ``pinned=2`` and
    ``pinned=[1.0]`` ended on raw TypeErrors."""
    for pin, want in ((0, [0]), (2, [2]), (None, []), ((0, -1), [0, 3])):
        s = dp.Scene()
        add_rope(s, 4, (0.0, 0.0, 1.0), (1.0, 0.0, 1.0), 0.1, 100.0, pinned=pin)
        assert [i for i, b in enumerate(s.bodies) if b.pinned] == want, pin
    s = dp.Scene()
    add_crumple_bar(s, 3, (0.0, 0.0, 1.0), (1.0, 0.0, 1.0), 0.1, 100.0, yield_strain=0.1,
                    pinned=0)
    assert [b.pinned for b in s.bodies] == [True, False, False]
    for pin, words in ((True, "pinned must be a list of node indices"),
                       ([1.0], "must be 1 integer grid index(es)")):
        with pytest.raises(dp.SceneError, match=re.escape(words)):
            add_rope(dp.Scene(), 4, (0.0, 0.0, 1.0), (1.0, 0.0, 1.0), 0.1, 100.0, pinned=pin)
    with pytest.raises(dp.SceneError, match="pinned must be a list of node indices"):
        add_cloth(dp.Scene(), 3, 3, 0.1, 0.1, structural=(10.0, 0.1), pinned=0)


def test_builder_coordinates_groups_and_the_paper_chain_take_numbers_and_names_only():
    """Coerced or crashing before: rope start ("0", "0", "1") accepted and (True, False,
    True) refused as "start and end coincide"; group=None made groups "None.stretch";
    paper_chain(g=-9.8) said "chain g = (k, c) must be ...", seed="a" a raw TypeError;
    paper_chain_equilibrium(ks=0) a raw LinAlgError and mass=nan NaN positions."""
    from diffpen.builders import paper_chain_equilibrium
    end = (1.0, 0.0, 1.0)
    cases = ((lambda: add_rope(dp.Scene(), 4, ("0", "0", "1"), end, 0.1, 100.0),
              r"rope start \(m\) must be 3 numbers"),
             (lambda: add_rope(dp.Scene(), 4, (True, False, True), end, 0.1, 100.0),
              r"rope start \(m\) must be 3 numbers"),
             (lambda: add_rope(dp.Scene(), 4, (0.0, 0.0, 1.0), end, 0.1, 100.0, group=None),
              "group must be a non-empty string"),
             (lambda: paper_chain(g=-9.8), r"chain g \(m/s\^2, along -z\) must be a positive"),
             (lambda: paper_chain(seed="a"), "paper chain seed must be an integer"),
             (lambda: paper_chain_equilibrium(ks=0), r"chain KS \(N/m\) must be a positive"),
             (lambda: paper_chain_equilibrium(mass=float("nan")), "chain mass"))
    for call, words in cases:
        with pytest.raises(dp.SceneError, match=words):
            call()
    scene, balls = paper_chain(kd=0.0, g=0.0)         # no drag, no gravity: allowed
    assert scene.gravity == (0.0, 0.0, 0.0) and len(balls) == 7


def test_a_refused_builder_leaves_the_scene_as_it_was():
    """Regression: a builder refused halfway left what it had added: add_rope(drag=-0.1)
    added 5 nodes and 4 springs, then raised, and the corrected retry was refused ("group
    'rope.stretch' already exists"); a cloth whose node started inside a fixed sphere left
    the 6 nodes before it. Now the scene is as before, and the retry builds."""
    scene = dp.Scene()
    scene.add_plane()
    ball = scene.add_sphere(0.05, 1.0, (3.0, 0.0, 0.5))
    with pytest.raises(dp.SceneError, match="must be non-negative"):
        add_rope(scene, 5, (0, 0, 1), (0.4, 0, 1), 0.5, 100.0, drag=-0.1)
    assert len(scene.bodies) == 1 and not scene.springs and not scene.spring_groups
    add_rope(scene, 5, (0, 0, 1), (0.4, 0, 1), 0.5, 100.0, drag=0.1)
    assert len(scene.bodies) == 6 and len(scene.springs) == 4
    scene.add_fixed_sphere((0.0, 0.0, 0.5), 0.15)
    with pytest.raises(dp.SceneError, match="fixed sphere 0"):
        add_cloth(scene, 4, 4, 0.1, 0.5, origin=(-0.3, -0.1, 0.5))
    assert len(scene.bodies) == 6 and "cloth.structural" not in scene.spring_groups
    # the overlap index forgot the refused nodes: a ball where one of them stood is fine
    scene.add_sphere(0.05, 0.1, (-0.3, -0.1, 0.5))
    assert scene.bodies[ball].position[0] == 3.0
    # the scene by keyword, as before the builders restored it (a TypeError naming 'self')
    nodes = add_rope(scene=scene, n=3, start=(0, 1, 1), end=(0.2, 1, 1), mass=0.3, k=50.0,
                     group="tether")
    assert len(nodes) == 3 and "tether.stretch" in scene.spring_groups


@pytest.mark.parametrize("make, words", [
    (lambda sc: sc.chain(dt=0.0), "dt must be a finite number of seconds > 0"),
    (lambda sc: sc.ball(duration=float("nan")), "duration must be a finite number"),
    (lambda sc: sc.cloth(n=1), "cloth n must be a whole number of nodes >= 3"),
])
def test_built_in_scenes_check_their_timing_and_size(make, words):
    """Regression: tuning.scenes.chain(dt=0) and cloth(n=1) raised a bare ZeroDivisionError."""
    from tuning import scenes
    with pytest.raises(dp.SceneError, match=words):
        make(scenes)
