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
    """``w0 = sqrt(k / m)``, rad/s."""
    return jnp.sqrt(k / mass)


def damping_ratio(k, c, mass):
    """``zeta = c / (2 sqrt(k m))`` (dimensionless)."""
    return c / (2.0 * jnp.sqrt(k * mass))


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


def _positive(name, x):
    import numpy as np
    _require(name, x, lambda a: np.isfinite(a) & (a > 0.0), "a finite number > 0")


def restitution(k, c, mass, law="linear"):
    """Coefficient of restitution of a ball on a fixed plane (no gravity during contact).

    linear: ``exp(-pi zeta / sqrt(1 - zeta^2))``, 0 for ``zeta >= 1`` (the overdamped
    linear contact never lets go); no_tension: ``exp(-2 zeta g(zeta))`` (Schwager &
    Poschel 2007), ``g = arccos(zeta) / sqrt(1 - zeta^2)``, continued as ``arccosh(zeta) /
    sqrt(zeta^2 - 1)`` above 1: the contact ends where its force reaches zero, so it always
    lets go (``e(1) = exp(-2) = 0.135``, ``e ~ 1 / (4 zeta^2)`` for large zeta).
    ``law``: a :class:`diffpen.laws.ContactLaw` or its name.
    """
    return jnp.exp(_family(law, "restitution").log_e(damping_ratio(k, c, mass)))


def contact_time(k, c, mass, law="linear"):
    """Contact duration of a ball on a fixed plane, s (no gravity); ``law`` a
    :class:`diffpen.laws.ContactLaw` or its name. linear: ``pi / (w0 sqrt(1 - zeta^2))``,
    inf for ``zeta >= 1`` (it never lets go); no_tension: ``2 g(zeta) / w0`` for every zeta
    (:func:`restitution`)."""
    family = _family(law, "contact_time")
    return family.w0_time(damping_ratio(k, c, mass)) / natural_frequency(k, mass)


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


def _nt_zeta(log_e):
    """The no-tension damping ratio of ``ln e``: bisection, then one Newton step outside
    ``stop_gradient`` (the implicit-function gradient)."""
    target = jax.lax.stop_gradient(log_e)

    def body(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        go_up = _nt_log_e(mid) > target   # ln e decreases with zeta
        return jnp.where(go_up, mid, lo), jnp.where(go_up, hi, mid)
    lo0 = jnp.zeros_like(target)
    hi0 = jnp.maximum(2.0, 1.0 / jnp.sqrt(jnp.exp(target)))
    lo, hi = jax.lax.fori_loop(0, 80, body, (lo0, hi0))
    z0 = jax.lax.stop_gradient(0.5 * (lo + hi))
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
    :func:`kc_from_time_constant`."""
    z = damping_ratio(k, c, mass)
    return 1.0 / (z * natural_frequency(k, mass)), z


def _hc_residual(y, x):
    # a v_in - ln(1 + a v_in) = -a v_out - ln(1 - a v_out), with x = a v_in, y = a v_out
    return (-y - jnp.log1p(-y)) - (x - jnp.log1p(x))


def hunt_crossley_restitution(a_vin):
    """Restitution of the Hunt-Crossley law ``F = k d^n (1 + a ddot)`` for ``a * v_in``
    (dimensionless, >= 0); independent of k, n and m (Hunt & Crossley 1975)."""
    x = jnp.asarray(a_vin)
    xs = jax.lax.stop_gradient(x)

    def body(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        up = _hc_residual(mid, xs) < 0.0
        return jnp.where(up, mid, lo), jnp.where(up, hi, mid)
    lo, hi = jax.lax.fori_loop(0, 80, body, (jnp.zeros_like(xs), jnp.ones_like(xs)))
    y0 = jax.lax.stop_gradient(0.5 * (lo + hi))
    slope = y0 / (1.0 - y0)                 # d residual / dy
    y = y0 - (_hc_residual(y0, x) - _hc_residual(y0, xs)) / jnp.where(slope > 0, slope, 1.0)
    return jnp.where(x > 0, y / jnp.where(x > 0, x, 1.0), 1.0)


def hunt_crossley_a_from_restitution(e, v_in):
    """Hunt-Crossley ``a = c / k`` (s/m) giving restitution ``e`` in (0, 1] at impact speed
    ``v_in`` (m/s) (``e = 1``: ``a = 0``). Concrete inputs out of range raise ValueError."""
    import numpy as np
    _require("restitution e", e, lambda a: np.isfinite(a) & (a > 0.0) & (a <= 1.0),
             "in (0, 1] (0 would need infinite damping)")
    _positive("impact speed v_in (m/s)", v_in)
    e_in = jnp.asarray(e)
    e = jnp.where(e_in < 1.0, e_in, 0.5)
    es = jax.lax.stop_gradient(e)

    def resid(x, ee):
        return _hc_residual(ee * x, x)

    # residual(x) = -e x - ln(1 - e x) - x + ln(1 + x): zero at the solution, x in (0, 1/e)
    def body(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        neg = resid(mid, es) < 0.0
        return jnp.where(neg, mid, lo), jnp.where(neg, hi, mid)
    hi0 = (1.0 - 1e-12) / es
    lo, hi = jax.lax.fori_loop(0, 200, body, (jnp.full_like(es, 1e-9), hi0))
    x0 = jax.lax.stop_gradient(0.5 * (lo + hi))
    dx = jax.grad(resid, argnums=0)
    slope = jnp.vectorize(dx)(x0, es)
    x = x0 - resid(x0, e) / slope
    # near e = 1 (and at it: a = 0) the series of the balance in x = a v_in, whose slope
    # there is d x / d e = -3/2 (the bisection's branch has none at e = 1 exactly)
    en = jnp.where(e_in > 1.0 - 1e-3, e_in, 1.0)
    x0n = 1.5 * (1.0 - en * en) / (1.0 + en ** 3)
    xn = x0n + 3.0 / (1.0 + en ** 3) * (x0n ** 2 * (1.0 - en ** 4) / 4.0
                                        - x0n ** 3 * (1.0 + en ** 5) / 5.0)
    return jnp.where(e_in > 1.0 - 1e-3, xn, x) / v_in
