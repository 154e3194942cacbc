"""Contact laws and contact events: zero force apart (every contact kind, every law), the
step-averaged force against its definition, and the step's continuity through contact start
and end."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp
from diffpen import laws

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


@pytest.mark.parametrize("law,width,h", [("no_tension", 0.05, None),
                                         ("hunt_crossley", 0.05, None),
                                         ("linear", 0.0, 1e-3)],
                         ids=["no_tension-smoothed", "hunt_crossley-smoothed",
                              "linear-step-averaged"])
def test_zero_force_and_derivative_apart_every_contact_kind(law, width, h):
    """Bodies 0.3 m apart (more than the smoothing band, 2.5 cm, and the step window,
    1 mm): exactly zero force and torque, and exactly zero derivatives w.r.t. k, c and the
    state. (The force-space clamp of no_tension / hunt_crossley left k width^n / 8 acting at
    any distance: 1.25 N at k = 1e5, width = 1e-2.)"""
    sim = dp.compile(_apart_scene(), 1e-3, law=law, smoothing=width, exponent=1.5)
    kinds = {"contact_plane", "contact_sphere_sphere", "contact_sphere_box",
             "contact_box_plane", "contact_fixed_sphere", "contact_box_fixed_sphere"}
    assert kinds <= set(sim.terms)
    state = sim.init_state()

    def total(k, c, x, v):
        f, tau = sim.forces(sim.params(k=k, c=c),
                            state._replace(position=x, velocity=v), h=h)
        return jnp.concatenate([f.ravel(), tau.ravel()])
    args = (jnp.float64(1e5), jnp.float64(30.0), state.position, state.velocity)
    value, jacs = jax.jit(lambda *a: (total(*a), jax.jacfwd(total, (0, 1, 2, 3))(*a)))(*args)
    assert np.all(np.asarray(value) == 0.0)
    for i, jac in enumerate(jacs):
        assert np.all(np.asarray(jac) == 0.0), i


@pytest.mark.parametrize("law", LAWS)
def test_pair_law_zero_just_outside_the_band(law):
    """Per pair: 0 and zero slope from ``d = -width / 2`` on (pointwise), and from
    ``d = -|vn| h`` on (step-averaged), for approaching, still and separating contacts."""
    rec = laws.get(law, 1.5)
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
