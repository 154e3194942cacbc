"""diffpen.value_and_grad: forward mode (and its vmap rule) against reverse mode, central
finite differences, jit vs eager and vmap vs loop (float64)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp

STEPS = 400


@pytest.fixture(scope="module")
def ball():
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.5))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3, smoothing=1e-3)

    def height(s):          # one observe object: a new function would compile a new rollout
        return s.position[0, 2]

    def loss(k, c):
        h = sim.rollout(sim.params(k=k, c=c), steps=STEPS, observe=height).observed
        return jnp.sum(h ** 2) / STEPS

    def loss_params(p):
        h = sim.rollout(p, steps=STEPS, observe=height).observed
        return jnp.mean(h)
    return sim, loss, loss_params


def test_forward_matches_reverse_and_finite_differences(ball):
    _, loss, _ = ball
    k, c = jnp.asarray(3e3), jnp.asarray(8.0)
    v_f, g_f = jax.jit(dp.value_and_grad(loss, (0, 1), mode="forward"))(k, c)
    reverse = jax.jit(dp.value_and_grad(loss, (0, 1), mode="reverse"))
    v_r, g_r = reverse(k, c)
    assert float(v_f) == pytest.approx(float(v_r), rel=1e-14)
    np.testing.assert_allclose(np.array(g_f), np.array(g_r), rtol=1e-9)

    def value(*args):           # the loss, from the compiled program above
        return float(reverse(*args)[0])
    for i, (h, x) in enumerate([(1e-2, k), (1e-5, c)]):
        args_p = [k, c]
        args_m = [k, c]
        args_p[i] = x + h
        args_m[i] = x - h
        fd = (value(*args_p) - value(*args_m)) / (2 * h)
        assert float(g_f[i]) == pytest.approx(fd, rel=1e-5)


def test_forward_mode_pytree_params_jit_vs_eager(ball):
    sim, _, loss_params = ball
    p = sim.params(k=2e3, c=5.0)
    vg = dp.value_and_grad(loss_params, mode="forward")
    v_e, g_e = vg(p)
    v_j, g_j = jax.jit(vg)(p)
    v_r, g_r = jax.jit(jax.value_and_grad(loss_params))(p)
    assert float(v_e) == float(v_j)
    for a, b, r in zip(jax.tree_util.tree_leaves(g_e), jax.tree_util.tree_leaves(g_j),
                       jax.tree_util.tree_leaves(g_r)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)
        np.testing.assert_allclose(a, r, rtol=1e-9, atol=1e-15)
    assert jax.tree_util.tree_structure(g_e) == jax.tree_util.tree_structure(g_r)


def test_vmap_rule_equals_loop(ball):
    _, loss, _ = ball
    ks = jnp.asarray([1.5e3, 3e3, 6e3])
    cs = jnp.asarray([4.0, 8.0, 12.0])
    vg = dp.value_and_grad(loss, (0, 1), mode="forward")
    v_b, (gk_b, gc_b) = jax.jit(jax.vmap(vg))(ks, cs)
    one = jax.jit(vg)           # one example at a time: one compiled program for the loop
    for i in range(3):
        v, (gk, gc) = one(ks[i], cs[i])
        assert float(v_b[i]) == pytest.approx(float(v), rel=1e-13)
        assert float(gk_b[i]) == pytest.approx(float(gk), rel=1e-10)
        assert float(gc_b[i]) == pytest.approx(float(gc), rel=1e-10)
    # one differentiated argument unbatched, the other batched: per-row gradients
    v_m, (gk_m, gc_m) = jax.vmap(vg, in_axes=(None, 0))(ks[1], cs)
    for i in range(3):
        _, (gk, gc) = one(ks[1], cs[i])
        assert float(gk_m[i]) == pytest.approx(float(gk), rel=1e-10)
        assert float(gc_m[i]) == pytest.approx(float(gc), rel=1e-10)


def test_matches_jax_value_and_grad_conventions():
    def f(p, x, s):
        return jnp.sum(jnp.sin(p["a"] * x) * p["b"][0] + s * p["b"][1] ** 2)
    p = {"a": jnp.asarray(1.3), "b": jnp.asarray([0.5, 2.0])}
    x, s = jnp.linspace(0.0, 1.0, 5), jnp.asarray(0.7)
    for argnums in (0, (0,), (0, 2)):
        ours = dp.value_and_grad(f, argnums, mode="forward")(p, x, s)
        ref = jax.jit(jax.value_and_grad(f, argnums))(p, x, s)
        assert jax.tree_util.tree_structure(ours) == jax.tree_util.tree_structure(ref)
        for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(ref)):
            np.testing.assert_allclose(a, b, rtol=1e-13)

    def g(p, x, s):
        return f(p, x, s), {"twice": 2 * x}
    grad, aux = dp.grad(g, 0, mode="forward", has_aux=True)(p, x, s)
    ref_grad, ref_aux = jax.jit(jax.grad(g, 0, has_aux=True))(p, x, s)
    np.testing.assert_allclose(grad["a"], ref_grad["a"], rtol=1e-13)
    np.testing.assert_allclose(grad["b"], ref_grad["b"], rtol=1e-13)
    np.testing.assert_allclose(aux["twice"], ref_aux["twice"])


def test_gradients_come_in_their_inputs_dtypes_in_every_mode():
    """Regression: a loss computed in float32 (a float32 simulator's) differentiated w.r.t.
    a Python float (float64 under x64) gave a float32 gradient in forward mode and a float64
    one in reverse mode and from ``jax.grad``, so ``mode="auto"`` changed the dtype at its
    threshold; with a float32 argument beside it, forward mode raised ("unravel function
    given array of dtype float32, but expected dtype float64"). Every mode, batched or not,
    now gives ``jax.grad``'s dtypes."""
    x32 = jnp.linspace(0.0, 1.0, 4, dtype=jnp.float32)

    def f(k, a):
        return jnp.sum(jnp.sin(jnp.asarray(k, jnp.float32) * x32) * a)
    a32 = jnp.asarray(0.5, jnp.float32)
    ref = jax.grad(f, (0, 1))(1.3, a32)
    assert [r.dtype for r in ref] == [jnp.float64, jnp.float32]
    for mode in ("forward", "reverse", "auto"):
        got = dp.grad(f, (0, 1), mode=mode)(1.3, a32)
        assert [g.dtype for g in got] == [r.dtype for r in ref], mode
        batched = jax.vmap(dp.grad(f, (0, 1), mode=mode), in_axes=(0, None))(
            jnp.asarray([1.3, 0.2]), a32)
        assert [g.dtype for g in batched] == [r.dtype for r in ref], mode


def test_auto_mode_threshold():
    assert dp.autodiff.resolve_mode("auto", 2) == "forward"
    assert dp.autodiff.resolve_mode("auto", dp.autodiff.MAX_FORWARD + 1) == "reverse"
    assert dp.autodiff.resolve_mode("auto", 5, max_forward=4) == "reverse"
    assert dp.autodiff.resolve_mode("reverse", 1) == "reverse"

    def f(x):
        return jnp.sum(jnp.cos(x) * jnp.arange(x.size))
    for n in (3, 40):            # both sides of the threshold give the reverse-mode answer
        x = jnp.linspace(0.1, 1.0, n)
        np.testing.assert_allclose(dp.grad(f)(x), jax.jit(jax.grad(f))(x), rtol=1e-13)
    # forward mode pushes an n x n basis of tangents through the program; reverse mode none
    fwd = str(jax.make_jaxpr(dp.grad(f))(jnp.ones(3)))
    rev = str(jax.make_jaxpr(dp.grad(f))(jnp.ones(40)))
    assert "[3,3]" in fwd and "[40,40]" not in rev


def test_errors():
    with pytest.raises(ValueError, match="mode must be one of"):
        dp.value_and_grad(jnp.sum, mode="sideways")
    with pytest.raises(ValueError, match="max_forward"):
        dp.value_and_grad(jnp.sum, max_forward=-1)
    with pytest.raises(TypeError, match="scalar loss"):
        dp.value_and_grad(lambda x: x * 2, mode="forward")(jnp.ones(3))
    with pytest.raises(TypeError, match="float inputs"):
        dp.value_and_grad(lambda x: jnp.sum(x) * 1.0, mode="forward")(jnp.arange(3))
    with pytest.raises(ValueError, match="argnums"):
        dp.value_and_grad(lambda x: jnp.sum(x), argnums=2)(jnp.ones(3))


def test_forward_mode_under_vmap_with_a_batched_keyword_or_closure(ball):
    """Forward mode (what "auto" picks here) failed with a bare AssertionError under
    ``jax.vmap`` when the batched value reached the loss as a keyword argument or through
    a closure; both now equal reverse mode row by row."""
    sim, _, _ = ball

    def height(s):
        return s.position[0, 2]

    def loss(k, c, z0=0.5):
        st = sim.state_from(body=0, position=jnp.array([0.0, 0.0, 1.0]) * z0)
        h = sim.rollout(sim.params(k=k, c=c), steps=STEPS, state=st, observe=height).observed
        return jnp.mean(h)
    z0s = jnp.array([0.4, 0.5])
    rev = jax.vmap(lambda z: dp.value_and_grad(loss, (0, 1), mode="reverse")(3e3, 8.0, z0=z))(z0s)
    kw = jax.vmap(lambda z: dp.value_and_grad(loss, (0, 1), mode="auto")(3e3, 8.0, z0=z))(z0s)
    cl = jax.vmap(lambda z: dp.value_and_grad(lambda k, c: loss(k, c, z), (0, 1),
                                              mode="forward")(3e3, 8.0))(z0s)
    for got in (kw, cl):
        np.testing.assert_allclose(got[0], rev[0], rtol=1e-12)
        for g, r in zip(got[1], rev[1]):
            np.testing.assert_allclose(g, r, rtol=1e-9)


def test_forward_mode_can_be_differentiated_again(ball):
    """jax.jacfwd or jax.grad of dp.grad in forward mode (the "auto" default here) failed
    ("vmap must have at least one non-None value", "Linearization failed"); outside a vmap
    of its arguments it is now plain forward mode, which composes: second derivatives equal
    those of jax.grad."""
    _, loss, _ = ball
    k, c = jnp.asarray(3e3), jnp.asarray(8.0)

    @jax.jit
    def second_derivatives(k, c):       # one compiled program for the three of them
        want = jax.jacfwd(jax.grad(loss, (0, 1)), (0, 1))(k, c)
        fwd = jax.jacfwd(dp.grad(loss, (0, 1), mode="forward"), (0, 1))(k, c)
        rev = jax.jacrev(dp.grad(loss, (0, 1), mode="forward"), (0, 1))(k, c)
        return want, {"jacfwd": fwd, "jacrev": rev}
    want, outer = second_derivatives(k, c)
    for name, got in outer.items():
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-7,
                                   err_msg=name)


def test_second_derivatives_through_reverse_mode_at_the_default_law():
    """Regression: at the default law (the step window's closed-form derivatives) every
    second derivative that involved reverse mode crashed inside JAX: jax.hessian,
    jax.jacfwd(jax.grad(f)) ("AssertionError: (ShapedArray(float64[1,1]), ...)") and
    jax.grad(jax.grad(f)) ("Linearization failed to produce known values"), while the
    ball fixture above (smoothing 1e-3) never met that path. The rule's values no longer
    pass through the batched-only form: all orders agree with forward-over-forward."""
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.102))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3)

    def z(k):
        return sim.rollout(sim.params(k=k, c=8.0), steps=60, save_every=60).position[-1, 0, 2]
    k = jnp.asarray(3e3)

    @jax.jit
    def second_derivatives(k):          # one compiled program for all orders
        return jax.jacfwd(jax.jacfwd(z))(k), {
            "grad(grad)": jax.grad(jax.grad(z))(k),
            "jacfwd(grad)": jax.jacfwd(jax.grad(z))(k),
            "hessian": jax.hessian(z)(k),
            "jacrev(grad)": jax.jacrev(jax.grad(z))(k)}
    want, got = second_derivatives(k)
    want = float(want)
    assert want != 0.0
    for name, value in got.items():
        assert float(value) == pytest.approx(want, rel=1e-9), name


def test_forward_mode_composes_through_jit_and_closures():
    """Forward mode failed when differentiated through jax.jit ("Linearization failed"), for
    a gradient with respect to a closed-over value, and under vmap(jit(...)) of a closure
    over the batched value (a bare AssertionError)."""
    def loss(p, s=1.0):
        return jnp.sum(jnp.sin(p * s) * p)
    p, ss = jnp.array([0.3, 0.7]), jnp.array([1.0, 2.0])
    fg = dp.grad(loss, mode="forward")
    want = jax.jit(jax.grad(lambda q: jnp.sum(jax.grad(loss)(q) ** 2)))(p)
    got = jax.grad(jax.jit(lambda q: jnp.sum(fg(q) ** 2)))(p)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    want = jax.jit(jax.grad(lambda s: jnp.sum(jax.grad(lambda q: loss(q, s))(p))))(1.0)
    got = jax.grad(lambda s: jnp.sum(dp.grad(lambda q: loss(q, s), mode="forward")(p)))(1.0)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    want = jax.jit(jax.vmap(lambda s: jax.grad(lambda q: loss(q, s))(p)))(ss)
    got = jax.vmap(jax.jit(lambda s: dp.grad(lambda q: loss(q, s), mode="forward")(p)))(ss)
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_forward_mode_called_with_values_checks_them_as_jax_does(ball):
    """Called outside jit with concrete values, forward mode traced the loss abstractly: a k
    past the safe step, a negative k and a NaN c came back as numbers (a NaN value and
    gradient for the NaN c), and a substeps="auto" simulator raised "traced with abstract
    parameters". jax.value_and_grad refuses the first three and steps the fourth."""
    sim = ball[0]

    def loss(k, c):
        return sim.rollout(sim.params(k=k, c=c), 50, save_every=50).position[-1, 0, 2]
    vg = dp.value_and_grad(loss, (0, 1), mode="forward")
    with pytest.raises(dp.StabilityError):
        vg(5e8, 20.0)
    with pytest.raises(dp.SceneError, match="must be >= 0"):
        vg(-1e4, 20.0)
    with pytest.raises(dp.SceneError, match="must be finite"):
        vg(1e4, float("nan"))
    auto = dp.compile(sim.scene, sim.dt, substeps="auto")

    def auto_loss(k, c):
        return auto.rollout(auto.params(k=k, c=c), 50, save_every=50).position[-1, 0, 2]
    v, g = dp.value_and_grad(auto_loss, (0, 1), mode="forward")(1e4, 20.0)
    v_ref, g_ref = jax.value_and_grad(auto_loss, (0, 1))(1e4, 20.0)
    np.testing.assert_allclose(v, v_ref, rtol=1e-12)
    np.testing.assert_allclose(g, g_ref, rtol=1e-9)
    # under jit nothing is known: the traced flag is the check there, as before
    jax.jit(vg)(1e4, 20.0)


def test_an_int_beside_a_float_is_refused_not_differentiated_to_zero(ball):
    """dp.grad(loss, (0, 1))(10000, 20.0) returned (0, -0.0451): raveling promoted the int
    to float, and unraveling cast its tangent back to int."""
    sim = ball[0]

    def loss(k, c):
        return sim.rollout(sim.params(k=k, c=c), 50, save_every=50).position[-1, 0, 2]
    with pytest.raises(TypeError, match="float inputs only.*argument 0"):
        dp.grad(loss, (0, 1))(10000, 20.0)
    with pytest.raises(TypeError, match="float inputs only"):
        jax.jit(dp.grad(loss, (0, 1)))(10000, 20.0)


@pytest.mark.parametrize("law", ["linear", "no_tension", "hunt_crossley", "no_tension_plain"])
def test_contact_force_derivatives_take_theirquotients_once(law):
    """Regression: the centred laws' force ``num / den`` (damping at the window centre's
    speed) and no_tension's clamp offset ``c vn / k`` were differentiated as ``dnum / den -
    num dden / den^2``, whose ``den ** -2`` and extra products XLA kept apart from the step's
    other work under ``jax.vmap``: reverse-mode gradients of 1024 batched balls took 82-100 ms
    with the centred linear record (44-56 ms after) and 208-221 ms with the plain no_tension
    one (86-92 ms after; float32; README "Performance and scale"). Each
    quotient now has its own derivative ``(dnum - q dden) / den``: fewer negative powers in
    the gradient, and the first and second derivatives are autodiff's of the plain quotient
    (float64)."""
    from jax.extend.core import jaxprs_in_params

    from diffpen import laws, one_contact
    centred = {"linear": one_contact.linear_centred,
               "no_tension": one_contact.no_tension_centred,
               "hunt_crossley": one_contact.hunt_crossley_centred(1.5)}.get(law)
    args = (0.004, -1.3, 2e4, 30.0)          # d (m), vn (m/s), k, c: the window crosses d = 0

    def force(d, vn, k, c):
        if centred is None:                  # the plain step average of no_tension
            return laws._no_tension_averaged(d, vn, k, c, 1e-3)
        return centred(d, vn, k, c, 1e-3, 5e-4, 0.5, -9.81)
    grad = jax.grad(force, argnums=(0, 1, 2, 3))

    def negative_powers(jaxpr):
        return sum((e.primitive.name == "integer_pow" and e.params["y"] < 0)
                   + sum(negative_powers(sub) for sub in jaxprs_in_params(e.params))
                   for e in jaxpr.eqns)

    def hessian(f):           # w.r.t. (k, c); the linear law's (the others cost more to compile)
        return jax.jit(jax.hessian(f, argnums=(2, 3)))(*args) if law == "linear" else None

    def traced():             # a new function each time: make_jaxpr keeps traces by function
        return jax.make_jaxpr(jax.grad(lambda *a: force(*a), argnums=(0, 1, 2, 3)))(*args)
    got = negative_powers(traced().jaxpr)
    orig = one_contact.quotient
    try:        # the plain quotient, differentiated by autodiff, for comparison
        one_contact.quotient = laws.quotient = lambda num, den: num / den
        plain = negative_powers(traced().jaxpr)
        want = jax.jit(jax.grad(lambda *a: force(*a), argnums=(0, 1, 2, 3)))(*args)
        want2 = hessian(lambda *a: force(*a))
    finally:
        one_contact.quotient = laws.quotient = orig
    assert got < plain               # (the window's own quotients are differentiated as before)
    np.testing.assert_allclose(np.array(jax.jit(grad)(*args)), np.array(want), rtol=1e-12)
    if want2 is not None:
        np.testing.assert_allclose(np.array(hessian(force)), np.array(want2), rtol=1e-10,
                                   atol=1e-18)
