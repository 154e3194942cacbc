"""The closed forms of diffpen.physical against an independent high-precision solution, in
float32 and float64: the Hunt-Crossley restitution and its inverse over every ``a v_in``,
and the forward conversions' refusal of out-of-range inputs."""
from decimal import Decimal, localcontext

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffpen import physical


def _hc_reference(x: float):
    """(e, de/dx) of the Hunt-Crossley energy balance ``x - ln(1 + x) = u - y``, ``y = e x =
    1 - exp(-u)``, solved for ``u`` by bisection in 60-digit decimals (no series, no
    float), the slope from the balance's implicit derivative."""
    if x == 0.0:
        return 1.0, -2.0 / 3.0
    with localcontext() as ctx:
        ctx.prec = 60
        xd = Decimal(repr(x))
        g = xd - (1 + xd).ln()
        lo, hi = Decimal(0), g + 1
        for _ in range(300):
            mid = (lo + hi) / 2
            if mid - (1 - (-mid).exp()) < g:
                lo = mid
            else:
                hi = mid
        u = (lo + hi) / 2
        gap = (-u).exp()                     # 1 - y
        y = 1 - gap
        dydx = (xd / (1 + xd)) / (y / gap)
        return float(y / xd), float(dydx / xd - y / xd / xd)


#: a v_in across the series' switch (0.1) and far past it
XS = [0.0, 1e-12, 1e-9, 1e-7, 1e-5, 1e-3, 0.05, 0.0999, 0.1, 0.1001, 0.3, 1.0, 3.0, 30.0]
#: value and slope tolerances (relative) per dtype
TOL = {"float64": (1e-13, 1e-11), "float32": (3e-6, 3e-4)}


@pytest.fixture(scope="module")
def hc_programs():
    """value_and_grad of the forward and inverse closed forms, jitted once per module."""
    return (jax.jit(jax.value_and_grad(physical.hunt_crossley_restitution)),
            jax.jit(jax.value_and_grad(
                lambda e: physical.hunt_crossley_a_from_restitution(e, 2.0))))


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_hunt_crossley_restitution_at_every_a_vin(hc_programs, dtype):
    """Regression: below a v_in ~ 1e-6 (float64) and 1e-3 (float32) the bisection of the
    balance cancelled: float64 gave a slope of 0 at 0 (true -2/3), e = 0.99992 with slope
    +2.7e8 at 1e-12, +2 at 1e-8 (the wrong sign); float32 e = 0 at 1e-9 and 0.843 at 1e-7,
    slope +16 at 1e-4. Now a power series up to 0.1, the balance in u = -ln(1 - y) above."""
    forward, _ = hc_programs
    rv, rg = TOL[dtype]
    for x in XS:
        e, g = forward(jnp.asarray(x, dtype))
        e_ref, g_ref = _hc_reference(x)
        assert float(e) == pytest.approx(e_ref, rel=rv), x
        assert float(g) == pytest.approx(g_ref, rel=rg), x


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_hunt_crossley_a_from_restitution_at_every_e(hc_programs, dtype):
    """Regression: float32 gave NaN for e from 0.005 to 0.05 (``e a v_in`` rounds to 1 there,
    and ``ln(1 - e a v_in)`` to -inf), and 1% off just below its series' switch (e =
    0.99899). Now the returned a gives back e (the reference's restitution at a v_in) and
    its slope is 1 / (v_in de/dx)."""
    _, inverse = hc_programs
    rv, rg = TOL[dtype]
    for e in [1.0, 0.99999, 0.999, 0.99899, 0.99, 0.94, 0.9375, 0.93, 0.5, 0.1, 0.05, 0.03,
              0.01, 0.005, 0.001]:
        a, da = inverse(jnp.asarray(e, dtype))
        assert np.isfinite(float(a)) and np.isfinite(float(da)), e
        e_back, dedx = _hc_reference(2.0 * float(a))
        assert e_back == pytest.approx(e, rel=10 * rv), e
        assert float(da) == pytest.approx(1.0 / (2.0 * dedx), rel=rg), e


@pytest.mark.parametrize("call, words", [
    (lambda: physical.restitution(float("nan"), 20.0, 1.0), "stiffness k (N/m)"),
    (lambda: physical.restitution(-1e4, 20.0, 1.0), "stiffness k (N/m)"),
    (lambda: physical.restitution(1e4, -20.0, 1.0), "damping c (N s/m) must be a finite "
                                                      "number >= 0, got -20"),
    (lambda: physical.contact_time(1e4, 20.0, -1.0), "mass (kg)"),
    (lambda: physical.time_constant(1e4, float("inf"), 1.0), "damping c"),
    (lambda: physical.hunt_crossley_restitution(float("nan")), "a * v_in"),
    (lambda: physical.hunt_crossley_restitution(-0.5), "a * v_in must be a finite number "
                                                       ">= 0"),
])
def test_forward_conversions_refuse_out_of_range_values(call, words):
    """Regression: the forward closed forms returned plausible numbers for bad input:
    restitution(k=nan) 0.0, restitution(k=-1e4) 0.0, restitution(c=-20) 1.371 (e > 1),
    hunt_crossley_restitution(nan) and (-0.5) 1.0. The inverses already refused them."""
    with pytest.raises(ValueError) as e:
        call()
    assert words in str(e.value)


def test_traced_out_of_range_values_give_nan():
    """Under jit nothing can be refused: out-of-range values give NaN, never a plausible e."""
    e = jax.jit(lambda k, c: physical.restitution(k, c, 1.0))
    assert np.isnan(float(e(jnp.nan, 20.0))) and np.isnan(float(e(-1e4, 20.0)))
    assert np.isnan(float(e(1e4, -20.0)))
    assert float(e(1e4, 20.0)) == pytest.approx(float(physical.restitution(1e4, 20.0, 1.0)))
    hc = jax.jit(physical.hunt_crossley_restitution)
    assert np.isnan(float(hc(jnp.nan))) and np.isnan(float(hc(-0.5)))


def test_traced_frequency_and_damping_ratio_out_of_range_give_nan():
    """Regression: damping_ratio gave -0.025 for c = -5 and inf for mass 0 (concrete values
    now raise, test_core); traced, NaN; in range, the closed forms."""
    z = jax.jit(lambda k, c, m: physical.damping_ratio(k, c, m))
    w = jax.jit(lambda k, m: physical.natural_frequency(k, m))
    assert np.isnan(float(z(1e4, -5.0, 1.0))) and np.isnan(float(z(1e4, 5.0, 0.0)))
    assert np.isnan(float(w(-1.0, 1.0))) and np.isnan(float(w(1e4, 0.0)))
    assert float(z(1e4, 20.0, 1.0)) == pytest.approx(0.1, rel=1e-6)
    assert float(w(1e4, 4.0)) == pytest.approx(50.0, rel=1e-6)
    g = jax.grad(lambda c: physical.damping_ratio(1e4, c, 1.0))(20.0)
    assert float(g) == pytest.approx(1.0 / 200.0, rel=1e-6)


def test_solved_conversions_compile_once(caplog):
    """Regression: called on concrete numbers, the Hunt-Crossley restitution and its inverse
    and the no_tension damping ratio of a restitution (so its k and c) traced and compiled
    their bisection's loop again at every call (~85 and ~170 ms a call: minutes for a Python
    loop over 1000 targets). A call with new values of the same shape and dtype now
    compiles nothing, and gives what a fresh call gives."""
    import logging
    first = (physical.hunt_crossley_restitution(0.3),
             physical.hunt_crossley_a_from_restitution(0.6, 1.0),
             physical.zeta_from_restitution(0.6, "no_tension"),
             physical.kc_from_restitution(0.6, 0.01, 1.0, "no_tension")[1])
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="jax"), jax.log_compiles():
        again = (physical.hunt_crossley_restitution(0.31),
                 physical.hunt_crossley_a_from_restitution(0.61, 1.2),
                 physical.zeta_from_restitution(0.61, "no_tension"),
                 physical.kc_from_restitution(0.61, 0.01, 1.0, "no_tension")[1])
    compiled = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling")]
    assert compiled == [], compiled
    assert all(float(b) < float(a) for a, b in zip(first, again))
