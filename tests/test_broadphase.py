"""Broad phase: same pairs and forces as brute force, fixed capacity, overflow reported."""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen import broadphase as bp


def random_scene(seed, n_spheres=30, n_boxes=4, spread=0.5, pinned_every=0):
    """Spheres of mixed radii, a few particles and tilted boxes packed in a cube."""
    rng = np.random.default_rng(seed)
    scene = dp.Scene(allow_overlap=True)   # packed at random: overlaps on purpose
    scene.add_material("soft", k=5e3, c=5.0)
    for i in range(n_spheres):
        pinned = pinned_every and i % pinned_every == 0
        scene.add_sphere(rng.uniform(0.04, 0.12), 1.0, rng.uniform(-spread, spread, 3),
                         (0.0, 0.0, 0.0) if pinned else rng.normal(size=3) * 0.5,
                         pinned=bool(pinned),
                         material="soft" if i % 3 == 0 else "default")
    for _ in range(4):
        scene.add_particle(0.1, rng.uniform(-spread, spread, 3))
    for _ in range(n_boxes):
        scene.add_box(rng.uniform(0.03, 0.15, 3), 2.0, rng.uniform(-spread, spread, 3),
                      rng.normal(size=3) * 0.2, orientation=rng.normal(size=4),
                      angular_velocity=rng.normal(size=3))
    return scene


_FINDERS = {}


def find(sim, state):
    """The pairs ``sim``'s broad phase finds in ``state`` (one compiled search per sim)."""
    if sim not in _FINDERS:
        _FINDERS[sim] = jax.jit(lambda s: bp.find_pairs(sim.broadphase, sim.context, s))
    return _FINDERS[sim](state)


_FORCES = {}


def traced_forces(sim, params, state, h=None):
    """``sim.forces`` called inside one jitted program per sim (and ``h``): the same forces,
    without the host-side overflow report a concrete call adds (it compiles the search
    once more; test_forces_warn_when_their_search_overflows checks that report)."""
    if (sim, h) not in _FORCES:
        _FORCES[sim, h] = jax.jit(lambda p, s: sim.forces(p, s, h=h))
    return _FORCES[sim, h](params, state)


_PROBES = {}


def search_and_forces(sim, params, state):
    """``(find(sim, state), sim.forces(params, state))`` from one jitted program per sim."""
    if sim not in _PROBES:
        _PROBES[sim] = jax.jit(lambda p, s: (bp.find_pairs(sim.broadphase, sim.context, s),
                                             sim.forces(p, s)))
    return _PROBES[sim](params, state)


def pair_set(pairs):
    # to numpy first: iterating a jax array compiles an unstack per shape
    i, j, valid = (np.asarray(a) for a in (pairs.i, pairs.j, pairs.valid))
    return {(int(a), int(b)) for a, b, v in zip(i, j, valid) if v}


STRATEGIES = [bp.AABB(max_pairs=300), bp.Grid(max_per_cell=12, max_pairs=300)]


@pytest.fixture(scope="module")
def random_sims():
    """The bodies of ``random_scene(0)`` compiled once with all pairs and with each strategy,
    and two states of them: seed 0's own and one with the positions, velocities and poses
    that seed 1 draws (same body kinds and counts: only the values differ, so both seeds
    run the same compiled search and forces)."""
    scene = random_scene(0, pinned_every=5)
    ref = dp.compile(scene, dt=1e-3)
    sims = {name: dp.compile(scene, dt=1e-3, broadphase=s)
            for name, s in zip(("aabb", "grid"), STRATEGIES)}
    other = dp.compile(random_scene(1, pinned_every=5), dt=1e-3).init_state()

    def moved(state):
        return state._replace(position=other.position, velocity=other.velocity,
                              orientation=other.orientation,
                              angular_velocity=other.angular_velocity)
    return ref, sims, moved


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("strategy", ["aabb", "grid"])
def test_broadphase_finds_the_brute_force_pairs_and_forces(random_sims, seed, strategy):
    ref, sims, moved = random_sims
    sim = sims[strategy]
    assert "contact_broadphase" in sim.terms
    assert "contact_sphere_sphere" not in sim.terms and "contact_sphere_box" not in sim.terms
    state, ref_state = sim.init_state(), ref.init_state()
    if seed == 1:
        state, ref_state = moved(state), moved(ref_state)
    params = dict(contact={"default": (1e4, 10.0), "soft": (5e3, 5.0)})
    # the search and the forces in one compiled program per strategy (both seeds)
    pairs, (f1, t1) = search_and_forces(sim, sim.params(**params), state)
    want = bp.brute_force_pairs(sim.context, state)
    assert pair_set(pairs) == want and int(pairs.count) == len(want)
    assert not bool(pairs.overflow)
    # exact narrow phase on the found pairs: contacts (d > 0) exist and forces agree
    f0, t0 = traced_forces(ref, ref.params(**params), ref_state)
    assert np.abs(np.asarray(f0)).max() > 1.0
    np.testing.assert_allclose(np.asarray(f1), np.asarray(f0), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(np.asarray(t1), np.asarray(t0), rtol=1e-10, atol=1e-9)


@pytest.fixture(scope="module")
def pile():
    """27 spheres in a jittered, slightly overlapping lattice and 3 boxes falling onto the
    ground."""
    rng = np.random.default_rng(7)
    scene = dp.Scene()
    for x in np.stack(np.meshgrid(*[np.arange(3)] * 3), -1).reshape(-1, 3):
        scene.add_sphere(0.1, 1.0, tuple(x * 0.19 + (0, 0, 0.1) + rng.uniform(0, 0.01, 3)))
    for _ in range(3):
        scene.add_box((0.12, 0.08, 0.05), 1.0, rng.uniform((-0.2, -0.2, 0.7), (0.6, 0.6, 1.0)),
                      orientation=rng.normal(size=4))
    scene.add_plane()
    return scene


def test_grid_rollout_equals_all_pairs_rollout_and_keeps_overflow_clear(pile):
    ref = dp.compile(pile, dt=1e-3)
    sim = dp.compile(pile, dt=1e-3, broadphase=bp.Grid(max_per_cell=8, max_pairs=400))
    p_ref, p = ref.params(k=1e4, c=20.0), sim.params(k=1e4, c=20.0)
    t_ref = ref.rollout(p_ref, steps=300, save_every=100)
    t = sim.rollout(p, steps=300, save_every=100)
    np.testing.assert_allclose(np.asarray(t.position), np.asarray(t_ref.position), atol=1e-9)
    np.testing.assert_array_equal(np.asarray(t.aux[bp.OVERFLOW]), 0.0)
    # contacts do happen in this run: spheres overlap each other
    x = np.asarray(t.position[:, :27])
    dist = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1) + 10.0 * np.eye(27)
    assert dist.min() < 0.2


@pytest.fixture(scope="module")
def column():
    """Eight touching spheres stacked on a plane (spheres only: every integrator runs it)."""
    scene = dp.Scene()
    for i in range(8):
        scene.add_sphere(0.1, 1.0, (0.003 * i, 0.0, 0.1 + 0.19 * i))
    scene.add_plane()
    return scene


@pytest.fixture(scope="module")
def crowded(column):
    """The column with room for 3 pairs only: its searches overflow."""
    return dp.compile(column, dt=1e-3, broadphase=bp.Grid(max_per_cell=8, max_pairs=3))


def test_overflow_is_reported_never_silent(crowded):
    sim = crowded                                        # a column of touching spheres
    state = sim.init_state()
    pairs = find(sim, state)
    assert int(pairs.count) > 3 and bool(pairs.overflow)
    assert float(state.aux[bp.OVERFLOW]) == 1.0
    with pytest.warns(bp.BroadPhaseOverflowWarning, match="max_pairs"):
        traj = sim.rollout(sim.params(k=1e4, c=20.0), steps=20, save_every=10)
    np.testing.assert_array_equal(np.asarray(traj.aux[bp.OVERFLOW]), 1.0)


def test_forces_warn_when_their_search_overflows(crowded):
    """sim.forces on a crowded state returned forces missing contacts (4061 N off all
    pairs) with no flag and no warning; only step and rollout reported the overflow."""
    state = crowded.init_state()
    p = crowded.params(k=1e4, c=20.0)
    with pytest.warns(bp.BroadPhaseOverflowWarning, match="some contacts were not evaluated"):
        crowded.forces(p, state)
    # the same simulator on the column spread out (nothing overlaps): its search has room
    # for every pair, and the same compiled forces and report are silent
    far = state._replace(position=state.position * 10.0)
    assert not bool(find(crowded, far).overflow)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        crowded.forces(p, far)                    # room for every pair: silent


def test_full_cell_is_reported_as_overflow():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0), allow_overlap=True)     # crowded on purpose
    for i in range(5):                                    # five spheres in one cell
        scene.add_sphere(0.1, 1.0, (0.01 * i, 0.0, 0.0))
    scene.add_sphere(0.1, 1.0, (3.0, 0.0, 0.0))
    # the start state's flag: the search of the initial state, run when the simulator is
    # compiled (find_pairs itself, as find() below; one compiled search less)
    sim = dp.compile(scene, dt=1e-3, broadphase=bp.Grid(max_per_cell=4))
    assert float(sim.init_state().aux[bp.OVERFLOW]) == 1.0
    ok = dp.compile(scene, dt=1e-3, broadphase=bp.Grid(max_per_cell=5))
    assert float(ok.init_state().aux[bp.OVERFLOW]) == 0.0
    pairs = find(ok, ok.init_state())
    assert not bool(pairs.overflow) and len(pair_set(pairs)) == 10


@pytest.mark.filterwarnings("ignore::diffpen.ContactWarning")   # they pass through: by design
def test_overflow_flag_becomes_set_when_bodies_crowd_later():
    """Two spheres fly into a crowded cell: the flag is clear at first and set once they
    arrive (and stays set)."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    # both pinned spheres well inside one cell (not on a cell boundary)
    scene.add_sphere(0.1, 1.0, (0.02, 0.0, 0.0), pinned=True)
    scene.add_sphere(0.1, 1.0, (0.07, 0.0, 0.0), pinned=True)
    scene.add_sphere(0.1, 1.0, (-2.0, 0.0, 0.0), (20.0, 0.0, 0.0))
    sim = dp.compile(scene, dt=1e-3, broadphase=bp.Grid(max_per_cell=2, bounds=((-3, -1, -1),
                                                                               (3, 1, 1))))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", bp.BroadPhaseOverflowWarning)
        traj = sim.rollout(sim.params(k=1e3, c=0.0), steps=200, save_every=10)
    flag = np.asarray(traj.aux[bp.OVERFLOW])
    assert flag[0] == 0.0 and flag[-1] == 1.0 and np.all(np.diff(flag) >= 0.0)


def test_bodies_outside_grid_bounds_are_clamped_not_lost():
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    a = scene.add_sphere(0.1, 1.0, (5.0, 5.0, 5.0))
    b = scene.add_sphere(0.1, 1.0, (5.15, 5.0, 5.0))
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.0))
    strategy = bp.Grid(bounds=((-1, -1, -1), (1, 1, 1)))
    sim = dp.compile(scene, dt=1e-3, broadphase=strategy)
    assert pair_set(find(sim, sim.init_state())) == {(a, b)}


def test_grid_cost_is_linear_in_bodies():
    """No intermediate of the grid search grows like n^2: the largest array for 4x the
    bodies is at most ~4x larger (the all-pairs AABB list grows 16x)."""
    def largest(n, strategy):
        scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
        side = int(round(n ** (1 / 3)))
        grid = np.stack(np.meshgrid(*[np.arange(side)] * 3), -1).reshape(-1, 3) * 0.25
        for x in grid:
            scene.add_sphere(0.1, 1.0, tuple(x))
        sim = dp.compile(scene, dt=1e-3, broadphase=strategy)
        term = sim.term("contact_broadphase")
        jaxpr = jax.make_jaxpr(term.force)(sim.params(k=1.0, c=0.0), sim.init_state())
        return max(int(np.prod(v.aval.shape)) for e in jaxpr.jaxpr.eqns for v in e.outvars)
    g1, g4 = largest(64, bp.Grid(max_per_cell=4)), largest(512, bp.Grid(max_per_cell=4))
    a1, a4 = largest(64, bp.AABB(max_pairs=300)), largest(512, bp.AABB(max_pairs=2400))
    assert g4 / g1 < 8.0 * 1.1 and a4 / a1 > 50.0       # 8x bodies: linear vs quadratic


def test_gradients_through_broadphase_match_all_pairs():
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.1))
    scene.add_sphere(0.1, 1.0, (0.02, 0.0, 0.3))
    scene.add_sphere(0.1, 1.0, (0.05, 0.01, 0.5))
    scene.add_plane()

    def loss(sim):
        def f(k, c):
            traj = sim.rollout(sim.params(k=k, c=c), steps=150, save_every=150,
                               check_finite=False)
            return jnp.sum(traj.position[-1, :, 2])
        return jax.jit(jax.grad(f, argnums=(0, 1)))(3e3, 10.0)
    g_ref = loss(dp.compile(scene, dt=1e-3))
    g_bp = loss(dp.compile(scene, dt=1e-3, broadphase=bp.Grid(max_pairs=3)))
    for a, b in zip(g_bp, g_ref):
        assert np.isfinite(float(a)) and abs(float(b)) > 0.0
        np.testing.assert_allclose(float(a), float(b), rtol=1e-9)


@pytest.mark.parametrize("strategy, match", [
    ("grid", "broadphase must be"),
    (bp.AABB(max_pairs=0), "max_pairs"),
    (bp.Grid(max_per_cell=0), "max_per_cell"),
    (bp.Grid(cell_size=0.05), "cell_size"),
    (bp.Grid(bounds=((0, 0, 0), (0, 1, 1))), "bounds"),
    (bp.Grid(margin=-0.1), "margin"),
])
def test_bad_broadphase_options_raise_clear_error(strategy, match):
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.0))
    scene.add_sphere(0.1, 1.0, (1.0, 0.0, 0.0))
    with pytest.raises(dp.SceneError, match=match):
        dp.compile(scene, dt=1e-3, broadphase=strategy)


def _count_eqns(jaxpr, keep):
    """Equations of ``jaxpr`` (nested jaxprs included) for which ``keep(eqn)`` holds."""
    from jax.extend.core import jaxprs_in_params
    n = 0
    for eqn in jaxpr.eqns:
        n += bool(keep(eqn))
        for sub in jaxprs_in_params(eqn.params):
            n += _count_eqns(sub, keep)
    return n


def _step_jaxpr(sim, substeps=None):
    step = sim.step if substeps is None else sim.step_function(substeps)
    return jax.make_jaxpr(step)(sim.params(k=1e4, c=20.0), sim.init_state()).jaxpr


def _searches_per_step(sim, substeps=None, jaxpr=None):
    """How many pair searches one ``sim.step`` (or the step of ``substeps`` inner steps, or
    the given ``jaxpr``) traces: equations under the search's named scope in the step's
    jaxpr over those of one search traced alone."""
    def scoped(eqn):
        return bp.SEARCH_SCOPE in str(eqn.source_info.name_stack)
    one = _count_eqns(jax.make_jaxpr(lambda s: bp.find_pairs(sim.broadphase, sim.context, s))(
        sim.init_state()).jaxpr, scoped)
    assert one > 0
    return _count_eqns(_step_jaxpr(sim, substeps) if jaxpr is None else jaxpr, scoped) / one




@pytest.mark.parametrize("strategy", ["aabb", "grid"])
def test_default_step_searches_pairs_once(random_sims, strategy):
    """Semi-implicit Euler evaluates forces once per step, so one step runs one pair search:
    the force term and the overflow flag share it. (The random scene's simulators: spheres,
    particles and boxes.)"""
    sim = random_sims[1][strategy]
    assert sim.integrator == "semi_implicit_euler" and sim.broadphase is STRATEGIES[
        ["aabb", "grid"].index(strategy)]
    if strategy == "grid":                      # the grid search sorts the bodies once
        assert _count_eqns(_step_jaxpr(sim), lambda e: e.primitive.name == "sort") == 1
    assert _searches_per_step(sim) == 1.0
    # with substeps=3 (the step dp.compile(..., substeps=3) jits: the same simulator's
    # step_function(3), without compiling a second simulator)
    assert _searches_per_step(sim, substeps=3) == 1.0   # once per inner step (scan's body)


COLUMN_RUN = dict(steps=60, save_every=20)


@pytest.mark.parametrize("integrator, evaluations",
                         [("verlet", 2), ("rk4", 4), ("implicit_euler", None)])
def test_multi_evaluation_integrators_search_per_evaluation_and_match_all_pairs(
        column, integrator, evaluations):
    """Integrators with several force evaluations per step search once per evaluation (none
    extra for the flag) and give the all-pairs result. (The margin covers the smoothing
    ramp, which acts up to ``smoothing / 2`` before the spheres touch.)"""
    sim = dp.compile(column, dt=1e-3, integrator=integrator,
                     broadphase=bp.Grid(max_pairs=40, margin=1e-3))
    ref = dp.compile(column, dt=1e-3, integrator=integrator)
    p = sim.params(k=1e4, c=20.0)
    if evaluations is not None:
        # the searches in the step the rollout scans (sim.step's step function; this trace
        # is the one the rollout below compiles, not a second one)
        run = jax.make_jaxpr(lambda p: sim.rollout(p, **COLUMN_RUN))(p).jaxpr
        assert _count_eqns(run, lambda e: e.primitive.name == "scan") >= 1
        assert _searches_per_step(sim, jaxpr=run) == evaluations
    t = sim.rollout(p, **COLUMN_RUN)
    t_ref = ref.rollout(ref.params(k=1e4, c=20.0), **COLUMN_RUN)
    np.testing.assert_allclose(np.asarray(t.position), np.asarray(t_ref.position), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(t.aux[bp.OVERFLOW]), 0.0)


def test_overflow_flag_comes_from_the_step_search_and_vmaps(crowded):
    """A step records the overflow of the state it starts from; under vmap each candidate
    keeps its own flag."""
    sim = crowded
    state = sim.init_state()
    assert bool(find(sim, state).overflow) and float(state.aux[bp.OVERFLOW]) == 1.0
    # start states built on the host (numpy): eager jnp ops compile a program per shape
    cleared = state._replace(aux={**state.aux,
                                  bp.OVERFLOW: np.zeros_like(state.aux[bp.OVERFLOW])})
    p = sim.params(k=1e4, c=20.0)
    assert float(sim.step(p, cleared).aux[bp.OVERFLOW]) == 1.0
    far = cleared._replace(position=np.asarray(state.position) * 10.0)   # nothing overlaps
    assert not bool(find(sim, far).overflow)
    assert float(sim.step(p, far).aux[bp.OVERFLOW]) == 0.0

    # vmap over (k, start state) of a grid rollout: the crowded start's flag set, the far
    # one's clear, in the same batch; and the batch equals one rollout per candidate (the
    # loop reuses the rollout program of test_overflow_is_reported_never_silent)
    ks = np.asarray([1e4, 2e4])
    starts = jax.tree_util.tree_map(lambda a, b: np.stack([a, b]), cleared, far)

    def run(k, s, check_finite=False):
        return sim.rollout(sim.params(k=k, c=20.0), 20, s, save_every=10,
                           check_finite=check_finite)
    both = jax.vmap(run)(ks, starts)
    np.testing.assert_array_equal(np.asarray(both.aux[bp.OVERFLOW]), [[1.0, 1.0], [0.0, 0.0]])
    with pytest.warns(bp.BroadPhaseOverflowWarning, match="max_pairs"):
        one = run(float(ks[0]), cleared, True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", bp.BroadPhaseOverflowWarning)
        other = run(float(ks[1]), far, True)
    for i, t in enumerate((one, other)):
        np.testing.assert_array_equal(np.asarray(t.aux[bp.OVERFLOW]), [1.0 - i] * 2)
        np.testing.assert_allclose(np.asarray(both.position)[i], np.asarray(t.position),
                                   atol=1e-12)
    # the crowded candidate's contacts act: its k changes its run (the far one falls free)
    with pytest.warns(bp.BroadPhaseOverflowWarning):
        stiffer = run(float(ks[1]), cleared)
    assert np.abs(np.asarray(one.position) - np.asarray(stiffer.position)).max() > 1e-9


@pytest.fixture(scope="module")
def ramp_pair():
    """Two spheres 3 mm apart with a 1 cm smoothing width, and their all-pairs forces
    (shared by both strategies)."""
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    scene.add_sphere(0.1, 1.0, (0.203, 0.0, 0.0), (-0.1, 0.0, 0.0))
    ref = dp.compile(scene, dt=1e-3, smoothing=1e-2)
    return scene, np.asarray(traced_forces(ref, ref.params(k=1e4, c=10.0), ref.init_state())[0])


@pytest.mark.parametrize("strategy", STRATEGIES, ids=["aabb", "grid"])
def test_pairs_inside_the_smoothing_ramp_are_found(ramp_pair, strategy):
    """Two spheres 3 mm apart with a 1 cm smoothing width already push each other (the ramp
    starts at a gap of width / 2): with margin 0 the broad phase must still find them."""
    scene, want = ramp_pair
    sim = dp.compile(scene, dt=1e-3, smoothing=1e-2, broadphase=strategy)
    got = np.asarray(traced_forces(sim, sim.params(k=1e4, c=10.0), sim.init_state())[0])
    assert abs(want[0, 0]) > 1e-3                        # the ramp pushes at this gap
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)


def test_fast_and_oblique_approaches_equal_all_pairs():
    """Two spheres closing head-on at 6 m/s: the Grid's cells (2 x radius) could not hold
    their boxes swept by |v| dt, the pair was missed from step 33 and the run gained
    energy, with no overflow reported. Spheres passing at an angle: the boxes were swept
    per axis (|v_x| dt, ...) while the window acts from a gap of |vn| h along the normal,
    so AABB and Grid dropped a force all pairs applied."""
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_sphere(0.05, 1.0, (0.0, 0.0, 0.0), (3.0, 0.0, 0.0))
    s.add_sphere(0.05, 1.0, (0.3, 0.0, 0.0), (-3.0, 0.0, 0.0))
    runs = {}
    for name, b in (("all", None), ("aabb", bp.AABB()), ("grid", bp.Grid())):
        sim = dp.compile(s, 1e-3, broadphase=b)
        t = sim.rollout(sim.params(k=1e4, c=0.0), 80)
        runs[name] = np.asarray(t.velocity)
        if b is not None:
            assert float(np.asarray(t.aux[bp.OVERFLOW])[-1]) == 0.0
    for name in ("aabb", "grid"):
        np.testing.assert_allclose(runs[name], runs["all"], rtol=0, atol=1e-12)
    u = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_sphere(0.05, 1.0, (0.0, 0.0, 0.0), (0.0, 5.0, 0.0))
    s.add_sphere(0.05, 1.0, tuple(0.16 * u), (0.0, -5.0, 0.0))
    forces = {}
    for name, b in (("all", None), ("aabb", bp.AABB()), ("grid", bp.Grid())):
        sim = dp.compile(s, 1e-2, broadphase=b)
        forces[name] = np.asarray(traced_forces(sim, sim.params(k=1e2, c=0.0),
                                                sim.init_state(), h=1e-2)[0])
    assert np.abs(forces["all"]).max() > 1e-3
    for name in ("aabb", "grid"):
        np.testing.assert_allclose(forces[name], forces["all"], rtol=1e-12)


def test_a_spinning_box_reaches_a_sphere_its_centre_speed_does_not():
    """A 10 cm box spinning at 100 rad/s (corners at 14 m/s) with a ball 5 mm from its face:
    the bounding boxes were swept by the centre's |v| dt only, so AABB and Grid dropped the
    pair (0 N against 5.76 N from all pairs) with no overflow reported."""
    s = dp.Scene(gravity=(0.0, 0.0, 0.0))
    s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, -100.0))
    ball = s.add_sphere(0.02, 0.1, (0.125, 0.09, 0.0))
    runs = {}
    for name, b in (("all", None), ("aabb", bp.AABB()), ("grid", bp.Grid())):
        sim = dp.compile(s, 1e-3, broadphase=b)
        v = np.asarray(sim.rollout(sim.params(k=1e4, c=5.0), 20).velocity)
        # the force on the ball at the start state, as the first step applies it (the
        # step-averaged force, sim.forces(..., h=dt); the ball starts at rest, no gravity):
        # m v1 / dt, to a few roundings (no second compiled program for sim.forces: its
        # broad-phase path is checked in test_broadphase_finds_the_brute_force_pairs_and_forces)
        runs[name] = (v[0, ball] * 0.1 / 1e-3, v)
    assert runs["all"][0][0] > 1.0
    for name in ("aabb", "grid"):
        np.testing.assert_allclose(runs[name][0], runs["all"][0], rtol=1e-12)
        np.testing.assert_allclose(runs[name][1], runs["all"][1], rtol=0, atol=1e-12)


def test_broadphase_pairs_take_the_centred_law_as_all_pairs_do():
    """The broad-phase pair force called the contact law without the effective mass and
    gravity: with laws.linear(centred=True) two stacked balls ended 0.26 mm apart from the
    all-pairs run."""
    s = dp.Scene()
    s.add_sphere(0.05, 1.0, (0.0, 0.0, 0.05))
    s.add_sphere(0.05, 0.5, (0.0, 0.0, 0.16))
    s.add_plane()
    law = dp.laws.linear(centred=True)
    ends = {}
    for name, b in (("all", None), ("aabb", bp.AABB()), ("grid", bp.Grid())):
        sim = dp.compile(s, 1e-3, law=law, broadphase=b)
        ends[name] = np.asarray(sim.rollout(sim.params(k=1e4, c=20.0), 300,
                                            save_every=300).position)
    for name in ("aabb", "grid"):
        np.testing.assert_allclose(ends[name], ends["all"], rtol=0, atol=1e-12)


def test_boolean_capacities_are_refused():
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    s.add_sphere(0.1, 1.0, (1.0, 0.0, 1.0))
    for b in (bp.AABB(max_pairs=True), bp.Grid(max_per_cell=True)):
        with pytest.raises(dp.SceneError, match="positive int"):
            dp.compile(s, 1e-3, broadphase=b)
