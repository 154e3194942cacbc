"""Scenes refuse bodies starting inside colliders or each other (unless asked), with the
overlap and the move that fixes it; the check looks at neighbours only."""
import numpy as np
import pytest

import diffpen as dp
from diffpen.overlap import OverlapIndex


# --------------------------------------------------------------------------- overlaps
@pytest.mark.parametrize("build, words", [
    # a sphere 5 m below the ground (issue: launched to 460 m)
    (lambda s: (s.add_plane(), s.add_sphere(0.1, 1.0, (0.0, 0.0, -5.0))),
     ["plane 0", "overlap by 5.1 m", "move it 5.1 m along the plane's normal"]),
    # the plane added after the body: the same check
    (lambda s: (s.add_sphere(0.1, 1.0, (0.0, 0.0, -5.0)), s.add_plane()),
     ["plane 0", "overlap by 5.1 m"]),
    # coincident spheres never separate
    (lambda s: (s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0)), s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))),
     ["sphere 1", "sphere 0", "centres coincide", "0.2 m apart"]),
    (lambda s: (s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0)), s.add_sphere(0.1, 1.0, (0.05, 0, 1.0))),
     ["overlap by 0.15 m", "further apart along (1, 0, 0)"]),
    (lambda s: (s.add_box((0.2, 0.2, 0.2), 1.0, (0.0, 0.0, 1.0)),
                s.add_sphere(0.05, 1.0, (0.0, 0.0, 1.1))), ["box 0", "out of the box"]),
    (lambda s: (s.add_sphere(0.05, 1.0, (0.0, 0.0, 1.1)),
                s.add_box((0.2, 0.2, 0.2), 1.0, (0.0, 0.0, 1.0))), ["box 1", "sphere 0"]),
    (lambda s: (s.add_plane(), s.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.0))),
     ["box 0", "plane 0", "raise it by 0.1 m"]),
    (lambda s: (s.add_fixed_sphere((0, 0, 0), 0.5), s.add_particle(1.0, (0.0, 0.0, 0.1))),
     ["particle 0", "inside fixed sphere 0"]),
    # a box deep inside a fixed sphere, either added first (issue: accepted, 5500 N at step 1)
    (lambda s: (s.add_fixed_sphere((0, 0, 0), 0.5), s.add_box((0.1,) * 3, 1.0, (0, 0, 0.05))),
     ["box 0", "fixed sphere 0", "overlap by 0.55 m", "move it 0.55 m along (0, 0, 1)"]),
    (lambda s: (s.add_box((0.1,) * 3, 1.0, (0, 0, 0.05)), s.add_fixed_sphere((0, 0, 0), 0.5)),
     ["box 0", "fixed sphere 0", "overlap by 0.55 m", "move it 0.55 m along (0, 0, 1)"]),
    # a particle inside a box: any overlap, as against planes and fixed spheres (issue: 4 cm
    # inside a 0.1 m box was accepted)
    (lambda s: (s.add_box((0.1,) * 3, 1.0, (0, 0, 0)), s.add_particle(1.0, (0.0, 0.0, 0.06))),
     ["particle 1", "box 0", "overlap by 0.04 m"]),
    (lambda s: (s.add_particle(1.0, (0.0, 0.0, 0.099)), s.add_box((0.1,) * 3, 1.0, (0, 0, 0))),
     ["box 1", "particle 0", "overlap by 0.001 m"]),
    # a particle's limit is no overlap at all (the message quoted "more than 0 m, 50% of the
    # smaller size")
    (lambda s: (s.add_particle(1.0, (0.0, 0.0, -0.01)), s.add_plane()),
     ["particle 0", "plane 0", "a particle has no size, so any overlap counts"]),
])
def test_bodies_starting_inside_are_refused_with_the_overlap_and_the_fix(build, words):
    with pytest.raises(dp.SceneError) as exc:
        build(dp.Scene())
    for w in words:
        assert w in str(exc.value), (w, str(exc.value))
    if "centres coincide" in words:
        # regression: allow_overlap accepted coincident spheres, which then stayed overlapped
        # for ever with no force, no gradient and no flag (the contact has no direction)
        assert "allow_overlap" not in str(exc.value)        # no advice that cannot work
        with pytest.raises(dp.SceneError, match="start at the same centre: their contact "
                                                "has no direction"):
            build(dp.Scene(allow_overlap=True))
        return
    assert "allow_overlap=True" in str(exc.value)
    build(dp.Scene(allow_overlap=True))             # asked for explicitly: accepted


def test_resting_and_pinned_overlaps_pass_and_allow_overlap_is_per_body():
    scene = dp.Scene()
    scene.add_plane()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 0.099))           # resting: 1 mm = m g / k
    scene.add_sphere(0.1, 1.0, (0.5, 0.0, 0.5), pinned=True)
    scene.add_sphere(0.1, 1.0, (0.55, 0.0, 0.5), pinned=True)   # two pinned: never evaluated
    i = scene.add_sphere(0.1, 1.0, (0.0, 0.0, -0.2), allow_overlap=True)
    assert i == 3
    scene.add_plane((0.0, 0.0, 1.0), -0.02)       # a later plane skips the allowed body
    with pytest.raises(dp.SceneError, match="allow_overlap must be True or False"):
        scene.add_sphere(0.1, 1.0, (3.0, 0.0, 1.0), allow_overlap="yes")
    # a rejected body leaves no trace in the scene or the index
    n = scene.n_bodies
    with pytest.raises(dp.SceneError):
        scene.add_sphere(0.1, 1.0, (0.0, 0.0, -1.0))
    assert scene.n_bodies == n
    scene.add_sphere(0.1, 1.0, (2.0, 0.0, 1.0))


def test_boxes_touching_fixed_spheres_and_particles_on_boxes_pass():
    """The box-fixed-sphere and particle-box checks refuse starts inside only: a box resting
    on a fixed sphere, a particle on a box face, pinned and allowed bodies pass, and
    state_from checks a box's start pose against fixed spheres too."""
    scene = dp.Scene()
    scene.add_fixed_sphere((0.0, 0.0, 0.0), 0.5)
    b = scene.add_box((0.1,) * 3, 1.0, (0.0, 0.0, 0.599))       # resting: 1 mm deep
    scene.add_particle(1.0, (0.0, 0.0, 0.699))                  # on the box's top face
    scene.add_box((0.1,) * 3, 1.0, (0.0, 0.0, 0.0), pinned=True)
    scene.add_box((0.1,) * 3, 1.0, (2.0, 0.0, 0.0), allow_overlap=True)
    scene.add_fixed_sphere((2.0, 0.0, 0.0), 0.3)                # skips the allowed box
    sim = dp.compile(scene, 1e-3)
    with pytest.raises(dp.SceneError, match=r"box 0 started at \(0, 0, 0.3\) .* fixed sphere 0 "
                       r".* move its start 0.3 m along \(0, 0, 1\)"):
        sim.state_from(body=b, position=(0.0, 0.0, 0.3))
    sim.state_from(body=b, position=(0.0, 0.0, 0.6))             # touching: fine


def test_overlap_check_looks_only_at_neighbours():
    """A dense lattice: each new sphere is compared with the spheres of its own cells only,
    never with all earlier bodies (no O(n^2) loop)."""
    scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
    g = np.stack(np.meshgrid(*[np.arange(12)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.21
    for p in g:
        scene.add_sphere(0.1, 1.0, tuple(p))
    idx = scene._overlap
    assert isinstance(idx, OverlapIndex)
    counts = [len(idx._near(p, 0.1, scene.n_bodies)) for p in g[::97]]
    assert max(counts) <= 27 and scene.n_bodies == 1728


def test_allow_overlap_refuses_only_coincident_sphere_centres():
    """Regression: with ``allow_overlap`` two spheres at one centre were accepted, and they
    stayed overlapped for ever (the contact's normal is 0 there: no force, no gradient, no
    flag). A sphere added with it at another's centre is refused now, either order; a
    compressed start, a pinned pair, a non-colliding sphere and a particle (which has no
    contact with spheres) at the same point still pass."""
    scene = dp.Scene()
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    with pytest.raises(dp.SceneError, match=r"sphere 1 at \(0, 0, 1\) and sphere 0 start at "
                                            r"the same centre.*move one of them"):
        scene.add_sphere(0.1, 3.0, (0.0, 0.0, 1.0), allow_overlap=True)
    assert scene.n_bodies == 1                      # the refused body left no trace
    scene.add_sphere(0.1, 3.0, (0.0, 0.0, 1.05), allow_overlap=True)     # compressed: fine
    scene.add_particle(1.0, (0.0, 0.0, 1.0))
    scene.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0), collide=False, allow_overlap=True)
    pinned = dp.Scene()
    pinned.add_sphere(0.1, 1.0, (1.0, 0.0, 1.0), pinned=True)
    pinned.add_sphere(0.1, 1.0, (1.0, 0.0, 1.0), pinned=True, allow_overlap=True)
    other = dp.Scene()
    other.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0), allow_overlap=True)
    with pytest.raises(dp.SceneError, match="start at the same centre"):
        other.add_sphere(0.2, 1.0, (0.0, 0.0, 1.0), allow_overlap=True)
    # a refusal whose worst overlap is another sphere offers no allow_overlap when one of
    # the overlapped spheres shares the centre (review: it offered what is then refused)
    three = dp.Scene()
    three.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    three.add_sphere(0.3, 1.0, (0.05, 0.0, 1.0), allow_overlap=True)
    with pytest.raises(dp.SceneError, match="sphere 2 .* and sphere 1") as exc:
        three.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    assert "allow_overlap" not in str(exc.value)
    # the same in the simulator's dtype (review): 1e-9 m apart is one centre in float32, a
    # refusal at compile; float64 resolves it, and those spheres part
    import jax.numpy as jnp
    near = dp.Scene()
    near.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    near.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0 + 1e-9), allow_overlap=True)
    with pytest.raises(dp.SceneError, match="1e-09 m apart, the same centre in float32"):
        dp.compile(near, 1e-3, dtype=jnp.float32)
    # float64 compiles without checking the spheres again (adding them checked them at its
    # resolution; the compile-time pass repeated that work for every allowed sphere)
    from diffpen.overlap import OverlapIndex
    calls = []
    original = OverlapIndex._coincident
    OverlapIndex._coincident = lambda self, *a, **k: calls.append(a) or original(self, *a, **k)
    try:
        dp.compile(near, 1e-3, dtype=jnp.float64)
    finally:
        OverlapIndex._coincident = original
    assert calls == []


def test_a_spring_between_two_bodies_at_one_point_warns():
    """audit17: two particles at one point joined by a spring of rest length 0.1 m stayed
    together for ever, without a word (the spring has no direction there). Not refused (a
    contact or another spring may part them first): it warns. Ends apart, ends that move
    apart (other velocities), a zero rest length and a world anchor at the body are silent."""
    import warnings
    scene = dp.Scene()
    for v in ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)):
        scene.add_particle(1.0, (0.0, 0.0, 1.0), velocity=v)
    scene.add_particle(1.0, (0.0, 0.0, 1.2))
    with pytest.warns(UserWarning, match=r"spring 0 joins bodies 0 and 1, which start at one "
                                         r"point with one velocity.*rest length 0\.1 m"):
        scene.add_spring(0, 1, k=100.0, c=1.0, rest_length=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene.add_spring(0, 2, rest_length=0.1)       # they move apart at once
        scene.add_spring(1, 2, rest_length=0.0)
        scene.add_spring(0, 3, rest_length=0.1)
        scene.add_spring(1, (0.0, 0.0, 1.0), rest_length=0.1)   # gravity parts it
