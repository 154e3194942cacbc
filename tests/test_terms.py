"""The facets the term builders declare (diffpen.terms): the params keys are the union of
what the builders say they read, in builder order, and each Term carries its extra params
and aux state. Compile only: no rollout."""
import numpy as np
import pytest

import diffpen as dp
from diffpen.broadphase import AABB


def _mixed_scene():
    s = dp.Scene()
    for m in ("ground", "A", "B", "steel", "post"):
        s.add_material(m, k=1e4, c=10.0)
    s.add_plane(material="ground")
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 0.2), material="A")
    s.add_sphere(0.1, 1.0, (1.0, 0.0, 0.2), material="B")
    s.add_sphere(0.1, 1.0, (2.0, 0.0, 0.2), material="A")
    s.add_box((0.1, 0.1, 0.1), 1.0, (3.0, 0.0, 0.2), material="steel")
    s.add_particle(0.5, (3.0, 0.5, 0.2), material="steel")   # a steel-steel pair with the box
    s.add_fixed_sphere((5.0, 0.0, 0.0), 0.5, material="post")
    return s


@pytest.mark.parametrize("pairs", [None, AABB()], ids=["all_pairs", "aabb"])
def test_materials_are_the_union_of_the_builders_declarations(pairs):
    """Colliders first (plane, fixed sphere), then same-material sphere pairs, "default" for
    mixed pairs, then sphere-box pairs, whichever term (all pairs or the broad phase) finds
    the sphere pairs; the index the terms use follows that order."""
    sim = dp.compile(_mixed_scene(), 1e-3, broadphase=pairs)
    expected = ("ground", "post", "A", "default", "steel")
    assert sim.materials == expected
    assert tuple(sim.params(k=1e4, c=10.0).contact) == expected
    assert sim.context.material_index == {m: i for i, m in enumerate(expected)}
    assert dp.terms.declared(dp.terms.BUILTIN, sim.context, "materials") == expected


def test_spring_groups_keep_the_scene_order_and_inert_springs():
    """Groups follow the order the scene's springs name them (a world spring before a body
    spring stays first), then plastic, then anchored springs; a world spring on a pinned
    body (which no term evaluates) keeps its group a parameter."""
    s = dp.Scene()
    a = s.add_particle(1.0, (0.0, 0.0, 1.0))
    b = s.add_particle(1.0, (1.0, 0.0, 1.0))
    pin = s.add_particle(1.0, (2.0, 0.0, 1.0), pinned=True)
    s.add_spring(a, (0.0, 0.0, 2.0), k=10.0, group="hanger")
    s.add_spring(a, b, k=10.0, group="rod")
    s.add_spring(pin, (2.0, 0.0, 2.0), k=10.0, group="idle")
    s.add_plastic_spring(a, b, k=10.0, yield_strain=0.1, group="crumple")
    box = s.add_box((0.1, 0.1, 0.1), 1.0, (4.0, 0.0, 1.0), collide=False)
    s.add_anchored_spring(box, None, (0.1, 0.0, 0.0), (4.1, 0.0, 1.5), k=10.0, group="tie")
    sim = dp.compile(s, 1e-3)
    assert sim.spring_groups == ("hanger", "rod", "idle", "crumple", "tie")
    assert tuple(sim.params().springs) == sim.spring_groups
    assert sim.terms == ("springs", "world_springs", "plastic_springs", "anchored_springs")

    # the plastic term carries its extra param, its check, its aux state and update
    term = sim.term("plastic_springs")
    assert dict(term.extra) == {"plastic": {"crumple": 0.1}}
    np.testing.assert_array_equal(term.aux["plastic_rest"], [1.0])
    assert term.update is not None and "plastic" in term.checks
    assert set(sim.init_state().aux) == {"plastic_rest", "plastic_collapsed", "unstable"}
    with pytest.raises(dp.SceneError, match="yield strain"):
        sim.params(extra={"plastic": {"crumple": 1.5}})


def test_zero_length_springs_keep_their_stiffness_where_the_ends_meet():
    """A zero-rest spring's force -k |delta| u had a zero Jacobian where its ends meet (the
    norm's derivative is taken as 0 there): a particle started on its spring's anchor got
    d x(T) / d x0 = +1 against the discrete motion's -0.9907 (cos(w T) = -0.9900); two
    particles on one spring, world springs and anchored springs alike. Now -k delta."""
    import jax
    import jax.numpy as jnp
    k, dt, n = 100.0, 1e-3, 300

    def gradient(build):
        scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
        moved = build(scene)
        sim = dp.compile(scene, dt=dt, dtype=jnp.float64)
        params = sim.params()

        def x_end(x0):
            st = sim.state_from(body=moved, position=jnp.stack([x0, 0.0, 0.0]))
            return sim.rollout(params, n, st, save_every=n).position[-1, moved, 0]
        h = 1e-6

        @jax.jit
        def derivatives():      # one compiled program: both modes and the two values
            ends = jax.vmap(x_end)(jnp.array([h, -h]))
            return jax.grad(x_end)(0.0), jax.jacfwd(x_end)(0.0), ends
        rev, fwd, ends = derivatives()
        fd = (float(ends[0]) - float(ends[1])) / (2 * h)
        return float(rev), float(fwd), fd

    def world(scene):
        p = scene.add_particle(1.0, (0.0, 0.0, 0.0))
        scene.add_spring(p, (0.0, 0.0, 0.0), k=k, c=0.0, rest_length=0.0, group="s")
        return p

    def pair(scene):
        a = scene.add_particle(1.0, (0.0, 0.0, 0.0))
        b = scene.add_particle(1.0, (0.0, 0.0, 0.0), allow_overlap=True)
        scene.add_spring(a, b, k=k, c=0.0, rest_length=0.0, group="s")
        return b

    def anchored(scene):
        p = scene.add_particle(1.0, (0.0, 0.0, 0.0))
        scene.add_anchored_spring(p, None, anchor_b=(0.0, 0.0, 0.0), k=k, c=0.0,
                                  rest_length=0.0, group="s")
        return p
    w = np.sqrt(k)
    # the moved particle: cos(w T) on a world anchor; on a pair, the centre of mass stays
    # at x0 / 2 and the separation turns at sqrt(2) w
    for build, want in ((world, np.cos(w * n * dt)), (anchored, np.cos(w * n * dt)),
                        (pair, 0.5 * (1.0 + np.cos(np.sqrt(2.0) * w * n * dt)))):
        rev, fwd, fd = gradient(build)
        assert rev == pytest.approx(fd, rel=1e-6) and fwd == pytest.approx(fd, rel=1e-6)
        assert fd == pytest.approx(want, abs=1e-2)
