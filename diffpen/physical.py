"""Physical parameterisations of contact <-> (k, c), differentiable (closed forms of
physics-notes.md section 2).

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


def _family(law, what: str) -> str:
    """The closed-form family (``"linear"`` or ``"no_tension"``) of ``law``, a
    :class:`diffpen.laws.ContactLaw` or a law name (``ContactLaw.closed_form``)."""
    try:
        rec = _laws.get(law)
    except ValueError as e:
        raise ValueError(str(e)) from None
    if rec.closed_form not in ("linear", "no_tension"):
        raise ValueError(f"{what} closed form exists for the 'linear' and 'no_tension' laws, not "
                         f"{rec.name!r}; use hunt_crossley_restitution for Hunt-Crossley.")
    return rec.closed_form


def _nt_log_e(z):
    """ln e for the no-tension law as a function of zeta in (0, 1)."""
    return -2.0 * z * jnp.arccos(z) / jnp.sqrt(1.0 - z * z)


def restitution(k, c, mass, law="linear"):
    """Coefficient of restitution of a ball on a fixed plane (no gravity during contact).

    linear: ``exp(-pi zeta / sqrt(1 - zeta^2))``; no_tension: Schwager & Poschel (2007).
    ``law``: a :class:`diffpen.laws.ContactLaw` or its name. Returns 0 for ``zeta >= 1``.
    """
    family = _family(law, "restitution")
    z = damping_ratio(k, c, mass)
    under = z < 1.0
    zs = jnp.where(under, z, 0.5)
    if family == "linear":
        log_e = -jnp.pi * zs / jnp.sqrt(1.0 - zs * zs)
    else:
        log_e = _nt_log_e(zs)
    return jnp.where(under, jnp.exp(log_e), 0.0)


def contact_time(k, c, mass, law="linear"):
    """Contact duration of a ball on a fixed plane, s (underdamped, no gravity); ``law`` a
    :class:`diffpen.laws.ContactLaw` or its name."""
    family = _family(law, "contact_time")
    w0 = natural_frequency(k, mass)
    z = damping_ratio(k, c, mass)
    s = jnp.sqrt(1.0 - z * z)
    if family == "linear":
        return jnp.pi / (w0 * s)
    return 2.0 * jnp.arccos(z) / (w0 * s)


def zeta_from_restitution(e, law="linear"):
    """Damping ratio giving restitution ``e`` in (0, 1); ``law`` a
    :class:`diffpen.laws.ContactLaw` or its name.

    linear: ``zeta = -ln e / sqrt(pi^2 + ln^2 e)``. no_tension: solved by bisection with an
    implicit-function gradient (one Newton step outside ``stop_gradient``).
    """
    family = _family(law, "zeta_from_restitution")
    log_e = jnp.log(e)
    if family == "linear":
        return -log_e / jnp.sqrt(jnp.pi ** 2 + log_e ** 2)
    target = jax.lax.stop_gradient(log_e)

    def body(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        go_up = _nt_log_e(mid) > target   # ln e decreases with zeta
        return jnp.where(go_up, mid, lo), jnp.where(go_up, hi, mid)
    lo0 = jnp.zeros_like(target) + 1e-12
    lo, hi = jax.lax.fori_loop(0, 60, body, (lo0, jnp.ones_like(target) - 1e-12))
    z0 = jax.lax.stop_gradient(0.5 * (lo + hi))
    dz = jax.grad(lambda z: _nt_log_e(z))
    slope = jnp.vectorize(dz)(z0)
    return z0 - (_nt_log_e(z0) - log_e) / slope


def kc_from_restitution(e, t_c, mass, law="linear"):
    """(k [N/m], c [N s/m]) giving restitution ``e`` in (0, 1) and contact time ``t_c`` [s].

    Inverse of :func:`restitution` and :func:`contact_time` (no gravity during contact).
    """
    z = zeta_from_restitution(e, law)
    s = jnp.sqrt(1.0 - z * z)
    if _family(law, "kc_from_restitution") == "linear":
        w0 = jnp.pi / (t_c * s)
    else:
        w0 = 2.0 * jnp.arccos(z) / (t_c * s)
    return mass * w0 ** 2, 2.0 * z * mass * w0


def kc_from_time_constant(tau, zeta, mass):
    """(k, c) from time constant ``tau = 1 / (zeta w0)`` [s] and damping ratio ``zeta``.

    MuJoCo's ``solref`` convention: ``c = 2 m / tau``, ``k = m / (zeta tau)^2``.
    """
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
    """Hunt-Crossley ``a = c / k`` (s/m) giving restitution ``e`` in (0, 1) at impact speed
    ``v_in`` (m/s)."""
    e = jnp.asarray(e)
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
    return x / v_in
