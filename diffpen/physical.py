"""Physical parameterisations of contact <-> (k, c), differentiable (closed forms of
docs/physics-notes.md section 2).

All functions are pure ``jax.numpy`` and work on scalars or arrays (elementwise), under
``jit``, ``vmap`` and ``grad``. ``mass`` is the effective mass of the contact in kg (the body's
mass against a fixed collider; ``m_a m_b / (m_a + m_b)`` for two bodies).

* (restitution e, contact time t_c [s]) <-> (k [N/m], c [N s/m]) for the ``linear`` and
  ``no_tension`` laws, without gravity during contact.
* (time constant tau [s], damping ratio zeta) <-> (k, c) with MuJoCo's ``solref`` convention:
  ``tau = 1 / (zeta w0)`` is the decay time of the contact oscillation, so
  ``c = 2 m / tau`` and ``k = m / (zeta tau)^2``.
* Hunt-Crossley restitution from ``a v_in`` and its inverse.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from . import laws as _laws

__all__ = [
    "damping_ratio", "natural_frequency",
    "restitution", "contact_time", "kc_from_restitution",
    "kc_from_time_constant", "time_constant",
    "zeta_from_restitution",
    "hunt_crossley_restitution", "hunt_crossley_a_from_restitution",
]


def natural_frequency(k, mass):
    """``w0 = sqrt(k / m)``, rad/s. Concrete ``k`` (N/m) or ``mass`` (kg) not a finite number
    > 0 raise ValueError naming it; traced, give NaN."""
    _positive("stiffness k (N/m)", k)
    _positive("mass (kg)", mass)
    ok = (jnp.asarray(k) > 0.0) & (jnp.asarray(mass) > 0.0)
    return _nan_unless(ok, jnp.sqrt(k / mass))


def damping_ratio(k, c, mass):
    """``zeta = c / (2 sqrt(k m))`` (dimensionless). Concrete input out of range (k, mass not
    > 0; c < 0; not finite) raises ValueError naming the argument; traced, gives NaN."""
    return _nan_unless(_contact(k, c, mass), c / (2.0 * jnp.sqrt(k * mass)))


def _family(law, what: str) -> "_Family":
    """The closed forms (:class:`_Family`) of ``law``, a :class:`diffpen.laws.ContactLaw`
    or a law name: the record names its family (``ContactLaw.closed_form``)."""
    try:
        rec = _laws.get(law)
    except ValueError as e:
        raise ValueError(str(e)) from None
    family = _FAMILIES.get(rec.closed_form)
    if family is None:
        raise ValueError(f"{what} closed form exists for the {sorted(_FAMILIES)} laws, not "
                         f"{rec.name!r}; use hunt_crossley_restitution for Hunt-Crossley.")
    return family


def _nt_g(z):
    """``g(zeta) = arccos(zeta) / sqrt(1 - zeta^2)`` for ``zeta < 1``, its continuation
    ``arccosh(zeta) / sqrt(zeta^2 - 1)`` above (the overdamped no-tension contact still lets
    go), 1 at ``zeta = 1``; near 1 its series ``sum a_n (zeta - 1)^n``, ``a_0 = 1``,
    ``a_n = -n a_(n-1) / (2n + 1)`` (from ``(1 - z^2) g' = z g - 1``), so nothing cancels."""
    u = z - 1.0
    near = jnp.abs(u) < 0.1
    un = jnp.where(near, u, 0.0)
    series, a, p = jnp.ones_like(un), 1.0, jnp.ones_like(un)
    for n in range(1, 14):
        a = -n * a / (2 * n + 1)
        p = p * un
        series = series + a * p
    below = z < 1.0
    zb = jnp.where(~near & below, z, 0.5)
    za = jnp.where(~near & ~below, z, 2.0)
    under = jnp.arccos(zb) / jnp.sqrt(1.0 - zb * zb)
    over = jnp.arccosh(za) / jnp.sqrt(za * za - 1.0)
    return jnp.where(near, series, jnp.where(below, under, over))


def _nt_log_e(z):
    """ln e of the no-tension law at damping ratio ``zeta`` >= 0 (every zeta: the contact
    ends where its force reaches zero, with the body still moving out)."""
    return -2.0 * z * _nt_g(z)


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _require(name: str, x, ok, what: str) -> None:
    """Raise ValueError naming ``name`` when concrete ``x`` fails ``ok`` (traced values pass:
    under jit, vmap and grad out-of-range inputs give NaN or inf, as documented)."""
    if not _concrete(x):
        return
    import numpy as np
    a = np.asarray(x, dtype=float)
    good = ok(a)
    if not np.all(good):
        bad = a[~good] if a.ndim else a
        raise ValueError(f"{name} must be {what}, got {float(np.ravel(bad)[0]):g}.")


def _nan_unless(ok, value):
    """``value`` where ``ok``, NaN elsewhere (traced out-of-range inputs)."""
    return jnp.where(ok, value, jnp.nan)


def _positive(name, x):
    import numpy as np
    _require(name, x, lambda a: np.isfinite(a) & (a > 0.0), "a finite number > 0")


def _contact(k, c, mass):
    """Check a contact's ``k`` (N/m) > 0, ``c`` (N s/m) >= 0 and ``mass`` (kg) > 0 where
    concrete (ValueError naming the argument); returns where all three are in range (traced
    values out of range give NaN, not a plausible restitution: NaN k gave e = 0, c < 0
    gave e > 1)."""
    import numpy as np
    _positive("stiffness k (N/m)", k)
    _require("damping c (N s/m)", c, lambda a: np.isfinite(a) & (a >= 0.0),
             "a finite number >= 0")
    _positive("mass (kg)", mass)
    return (jnp.asarray(k) > 0.0) & (jnp.asarray(c) >= 0.0) & (jnp.asarray(mass) > 0.0)


def restitution(k, c, mass, law="linear"):
    """Coefficient of restitution of a ball on a fixed plane (no gravity during contact).

    linear: ``exp(-pi zeta / sqrt(1 - zeta^2))``, 0 for ``zeta >= 1`` (the overdamped
    linear contact never lets go); no_tension: ``exp(-2 zeta g(zeta))`` (Schwager &
    Poschel 2007), ``g = arccos(zeta) / sqrt(1 - zeta^2)``, continued as ``arccosh(zeta) /
    sqrt(zeta^2 - 1)`` above 1: the contact ends where its force reaches zero, so it always
    lets go (``e(1) = exp(-2) = 0.135``, ``e ~ 1 / (4 zeta^2)`` for large zeta).
    ``law``: a :class:`diffpen.laws.ContactLaw` or its name. Concrete ``k``, ``c``, ``mass``
    out of range (k, mass not > 0; c < 0; not finite) raise ValueError; traced, give NaN.
    """
    ok = _contact(k, c, mass)
    return _nan_unless(ok, jnp.exp(_family(law, "restitution").log_e(damping_ratio(k, c, mass))))


def contact_time(k, c, mass, law="linear"):
    """Contact duration of a ball on a fixed plane, s (no gravity); ``law`` a
    :class:`diffpen.laws.ContactLaw` or its name. linear: ``pi / (w0 sqrt(1 - zeta^2))``,
    inf for ``zeta >= 1`` (it never lets go); no_tension: ``2 g(zeta) / w0`` for every zeta
    (:func:`restitution`; out-of-range inputs as there)."""
    family = _family(law, "contact_time")
    ok = _contact(k, c, mass)
    return _nan_unless(ok, family.w0_time(damping_ratio(k, c, mass)) / natural_frequency(k, mass))


def zeta_from_restitution(e, law="linear"):
    """Damping ratio giving restitution ``e`` in (0, 1] (1: no damping); ``law`` a
    :class:`diffpen.laws.ContactLaw` or its name.

    linear: ``zeta = -ln e / sqrt(pi^2 + ln^2 e)`` (< 1). no_tension: solved by bisection
    over ``[0, max(2, 1 / sqrt(e))]`` (it reaches every e > 0, overdamped below
    ``exp(-2)``) with an implicit-function gradient (one Newton step outside
    ``stop_gradient``). A concrete e outside (0, 1] raises ValueError.
    """
    import numpy as np
    family = _family(law, "zeta_from_restitution")
    _require("restitution e", e, lambda a: np.isfinite(a) & (a > 0.0) & (a <= 1.0),
             "in (0, 1] (0 would need infinite damping)")
    return family.zeta(jnp.log(e))


def kc_from_restitution(e, t_c, mass, law="linear"):
    """(k [N/m], c [N s/m]) giving restitution ``e`` in (0, 1] and contact time ``t_c`` [s].

    Inverse of :func:`restitution` and :func:`contact_time` (no gravity during contact).
    Concrete inputs out of range (e outside (0, 1], t_c or mass not > 0) raise ValueError.
    """
    _positive("contact time t_c (s)", t_c)
    _positive("mass (kg)", mass)
    z = zeta_from_restitution(e, law)
    w0 = _family(law, "kc_from_restitution").w0_time(z) / t_c
    return mass * w0 ** 2, 2.0 * z * mass * w0


# --------------------------------------------------------------------------- families
def _linear_log_e(z):
    under = z < 1.0
    zs = jnp.where(under, z, 0.5)
    return jnp.where(under, -jnp.pi * zs / jnp.sqrt(1.0 - zs * zs), -jnp.inf)


def _linear_w0_time(z):
    under = z < 1.0
    zs = jnp.where(under, z, 0.5)
    return jnp.where(under, jnp.pi / jnp.sqrt(1.0 - zs * zs), jnp.inf)


def _linear_zeta(log_e):
    return -log_e / jnp.sqrt(jnp.pi ** 2 + log_e ** 2)


@jax.jit
def _nt_zeta(log_e):
    """The no-tension damping ratio of ``ln e``: bisection, then one Newton step outside
    ``stop_gradient`` (the implicit-function gradient); compiled once per shape and dtype
    (run op by op, the bisection's loop was compiled again at every call: ~170 ms)."""
    target = jax.lax.stop_gradient(log_e)
    hi0 = jnp.maximum(2.0, 1.0 / jnp.sqrt(jnp.exp(target)))
    # ln e decreases with zeta: the root of target - ln e(zeta), negative below it
    z0 = jax.lax.stop_gradient(_bisect(lambda z: target - _nt_log_e(z),
                                       jnp.zeros_like(target), hi0, 80))
    slope = jnp.vectorize(jax.grad(_nt_log_e))(z0)
    return z0 - (_nt_log_e(z0) - log_e) / slope


class _Family(NamedTuple):
    """The closed forms of one law family, functions of the damping ratio zeta: ``log_e``
    (ln of the restitution), ``w0_time`` (contact time x w0) and ``zeta`` (of ln e)."""
    log_e: Callable
    w0_time: Callable
    zeta: Callable


#: closed forms per family name (``ContactLaw.closed_form``)
_FAMILIES = {
    "linear": _Family(_linear_log_e, _linear_w0_time, _linear_zeta),
    "no_tension": _Family(_nt_log_e, lambda z: 2.0 * _nt_g(z), _nt_zeta),
}


def kc_from_time_constant(tau, zeta, mass):
    """(k, c) from time constant ``tau = 1 / (zeta w0)`` [s] and damping ratio ``zeta``.

    MuJoCo's ``solref`` convention: ``c = 2 m / tau``, ``k = m / (zeta tau)^2``. Concrete
    inputs that are not > 0 raise ValueError.
    """
    _positive("time constant tau (s)", tau)
    _positive("damping ratio zeta", zeta)
    _positive("mass (kg)", mass)
    return mass / (zeta * tau) ** 2, 2.0 * mass / tau


def time_constant(k, c, mass):
    """(time constant tau [s], damping ratio zeta) of (k, c): inverse of
    :func:`kc_from_time_constant` (out-of-range inputs as in :func:`restitution`)."""
    ok = _contact(k, c, mass)
    z = damping_ratio(k, c, mass)
    return _nan_unless(ok, 1.0 / (z * natural_frequency(k, mass))), _nan_unless(ok, z)


#: e(x) = sum_k _HC_SERIES[k] x^k: the Hunt-Crossley restitution at x = a v_in as a power
#: series (the reversion of its energy balance x - ln(1 + x) = -e x - ln(1 - e x)),
#: exact to rounding in float64 for x <= _HC_SERIES_X (its terms fall like 0.07 x^k)
_HC_SERIES = (
    1.0, -0.6666666666666666, 0.4444444444444444, -0.32592592592592595,
    0.25679012345679014, -0.21164021164021163, 0.17984714873603763, -0.15626886145404664,
    0.1380974154636706, -0.12367106429109173, 0.11194448206924527, -0.10222750667857032,
    0.09404628321338172, -0.08706478047189273, 0.08103813977135456, -0.07578375581573293,
    0.07116269936142636,
)
_HC_SERIES_X = 0.1


def _hc_series(x):
    """``(e, de/dx)`` of the series :data:`_HC_SERIES` at ``x`` (Horner)."""
    e, de = jnp.zeros_like(x), jnp.zeros_like(x)
    for c in reversed(_HC_SERIES):
        de = de * x + e
        e = e * x + c
    return e, de


def _hc_balance(x):
    """``x - ln(1 + x)``: the energy balance's side of the impact speed ``x = a v_in``."""
    return x - jnp.log1p(x)


def _hc_u_residual(u, x):
    """The Hunt-Crossley energy balance in ``u = -ln(1 - y)`` (``y = a v_out = 1 -
    exp(-u)``), ``u - y = x - ln(1 + x)``: ``y`` next to 1 (``e x`` of a strongly damped
    impact, 1 - 2e-9 at e = 0.05) is not a float32 number, ``u`` (20 there) is."""
    return u + jnp.expm1(-u) - _hc_balance(x)


def _bisect(f, lo, hi, iters: int):
    """The root of ``f``, negative at ``lo`` and positive at ``hi`` (elementwise)."""
    def body(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        neg = f(mid) < 0.0
        return jnp.where(neg, mid, lo), jnp.where(neg, hi, mid)
    lo, hi = jax.lax.fori_loop(0, iters, body, (lo, hi))
    return 0.5 * (lo + hi)


def hunt_crossley_restitution(a_vin):
    """Restitution of the Hunt-Crossley law ``F = k d^n (1 + a ddot)`` for ``a * v_in``
    (dimensionless, >= 0); independent of k, n and m (Hunt & Crossley 1975).

    Up to ``a v_in = 0.1`` the power series of the energy balance (``e = 1 - 2x/3 + 4x^2/9
    - ...``, slope -2/3 at 0); above it the balance solved for ``u = -ln(1 - a v_out)`` by
    bisection, with one Newton step outside ``stop_gradient`` for the implicit-function
    derivative. Accurate to rounding in float32 and float64 at every ``a v_in``. A concrete
    input that is negative or not finite raises ValueError; traced, it gives NaN.
    """
    import numpy as np
    _require("a * v_in", a_vin, lambda a: np.isfinite(a) & (a >= 0.0),
             "a finite number >= 0")
    x = jnp.asarray(a_vin)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    return _hc_restitution(x)


@jax.jit
def _hc_restitution(x):
    """:func:`hunt_crossley_restitution` of a float array ``x``, compiled once per shape and
    dtype (run op by op, its bisection's loop was traced and compiled again at every call:
    ~85 ms a call)."""
    small = x <= _HC_SERIES_X
    e_series, _ = _hc_series(jnp.where(small, x, 0.0))
    xl = jnp.where(small, 2.0 * _HC_SERIES_X, x)        # the solve's lane, never small
    xs = jax.lax.stop_gradient(xl)
    # u - y <= u - 1 + e^-u and u - y = balance(x) <= x: the root lies in (0, x + 1]
    u0 = jax.lax.stop_gradient(_bisect(lambda u: _hc_u_residual(u, xs), jnp.zeros_like(xs),
                                       xs + 1.0, 100))
    u = u0 - _hc_u_residual(u0, xl) / -jnp.expm1(-u0)   # d residual / du = 1 - e^-u
    e_solved = -jnp.expm1(-u) / xl
    return _nan_unless(x >= 0.0, jnp.where(small, e_series, e_solved))


def hunt_crossley_a_from_restitution(e, v_in):
    """Hunt-Crossley ``a = c / k`` (s/m) giving restitution ``e`` in (0, 1] at impact speed
    ``v_in`` (m/s) (``e = 1``: ``a = 0``, slope ``da/de = -3 / (2 v_in)`` there).

    The inverse of :func:`hunt_crossley_restitution`: where ``a v_in <= 0.1`` (``e >=
    0.937``) Newton's method on its power series; below, bisection on the energy balance
    in ``u = -ln(1 - e a v_in)``; one Newton step outside ``stop_gradient`` gives the
    implicit-function derivative. Accurate in float32 and float64 for every e in (0, 1].
    Concrete inputs out of range raise ValueError; traced, they give NaN.
    """
    import numpy as np
    _require("restitution e", e, lambda a: np.isfinite(a) & (a > 0.0) & (a <= 1.0),
             "in (0, 1] (0 would need infinite damping)")
    _positive("impact speed v_in (m/s)", v_in)
    e_in = jnp.asarray(e)
    if not jnp.issubdtype(e_in.dtype, jnp.inexact):
        e_in = e_in.astype(jnp.result_type(float))
    return _hc_a_from_restitution(e_in, v_in)


@jax.jit
def _hc_a_from_restitution(e_in, v_in):
    """:func:`hunt_crossley_a_from_restitution` of a float array ``e_in``, compiled once per
    shape and dtype (as :func:`_hc_restitution`)."""
    e_split = _hc_series(jnp.asarray(_HC_SERIES_X, e_in.dtype))[0]
    near = e_in >= e_split
    # near e = 1: Newton's method on the series from its first term, x = 3 (1 - e) / 2
    en = jnp.where(near, e_in, 1.0)
    ens = jax.lax.stop_gradient(en)
    xn = 1.5 * (1.0 - ens)
    for _ in range(6):
        val, slope = _hc_series(xn)
        xn = jnp.clip(xn - (val - ens) / slope, 0.0, 1.5 * _HC_SERIES_X)
    xn = jax.lax.stop_gradient(xn)
    val, slope = _hc_series(xn)
    xn = xn - (val - en) / slope
    # below: the balance u - y = balance(y / e) in u, y = 1 - e^-u, between x = 0.05 (below
    # the root, which is past 0.1 here) and x = 1 / e (y = 1: u - y = balance(x) <= x)
    ef = jnp.where(near, 0.5, e_in)
    efs = jax.lax.stop_gradient(ef)

    def resid(u, ee):
        return _hc_u_residual(u, -jnp.expm1(-u) / ee)
    lo = -jnp.log1p(-0.05 * efs)
    u0 = jax.lax.stop_gradient(_bisect(lambda u: resid(u, efs), lo, 1.0 / efs + 1.0, 200))
    slope = jnp.vectorize(jax.grad(resid))(u0, efs)
    u = u0 - resid(u0, ef) / slope
    xf = -jnp.expm1(-u) / ef
    ok = (e_in > 0.0) & (e_in <= 1.0) & (jnp.asarray(v_in) > 0.0)
    return _nan_unless(ok, jnp.where(near, xn, xf) / v_in)
