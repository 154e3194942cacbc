"""A prototype contact law for one free body on a horizontal plane: the step window taken
along the true two-point path of the body (free-flight parabola outside, damped harmonic
motion inside, split at the crossings), which makes the event terms exact at any step
(``docs/gradients.txt``, "Impact phase in the step"). About 50x the default law's cost: a
measured reference for what the default law leaves, not a library law.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .reference import G

__all__ = ["two_point_window_law"]


def two_point_window_law(mass: float, gravity: float = G):
    """PROTOTYPE (measurement only; not used by any simulator unless passed as ``law=``): the
    linear law whose step window follows the continuous path instead of a straight line.

    The window's past half is the true motion through ``d_{n-1} = d_n + h vn`` and ``d_n``
    (semi-implicit Euler's last two positions): damped harmonic about ``m g / k`` when both
    are in contact, a gravity parabola when both are apart, parabola then contact (or contact
    then parabola) when the last step crossed, the crossing speed found by Newton's method;
    its future half continues from ``d_n`` with that path's slope. The force ``k d + c d'``
    along the path is integrated with the hat weight by 16-point Gauss-Legendre on the pieces
    between crossings. With it the positions are exact samples of the continuous motion, so
    contact events carry their exact derivative terms (docs/gradients.txt).

    Only for ONE free body of ``mass`` kg on a horizontal plane with gravity ``gravity``
    m/s^2 along -normal (the ball cases). Costs ~100 force evaluations and 20 Newton steps per
    contact and step. Returns a ``diffpen.laws.ContactLaw``."""
    from diffpen import laws
    m = float(mass)
    G0 = float(gravity)
    GX, GW = (jnp.asarray(a) for a in np.polynomial.legendre.leggauss(16))

    def avg(dn, vn, k, c, h):
        w0sq = k / m; sg = c / (2 * m); w = jnp.sqrt(w0sq - sg * sg); de = m * G0 / k
        def contact(t, d0, D0):
            x0 = d0 - de
            return de + jnp.exp(-sg * t) * (x0 * jnp.cos(w * t)
                                            + ((D0 + sg * x0) / w) * jnp.sin(w * t))
        def free(t, d0, D0):
            return d0 + D0 * t + 0.5 * G0 * t * t
        dp_ = dn + h * vn
        # 0: both in contact, 1: both apart, 2: entered during the last step, 3: left it
        case = jnp.where((dp_ > 0) & (dn > 0), 0,
                         jnp.where((dp_ <= 0) & (dn <= 0), 1, jnp.where(dn > 0, 2, 3)))
        # case 2: entering
        dn2, dp2 = jnp.where(case == 2, dn, 1e-4), jnp.where(case == 2, dp_, -1e-4)
        def tau0_of(U):
            return -2 * dp2 / (U + jnp.sqrt(U * U - 2 * G0 * dp2))
        def r2(U):
            t0 = tau0_of(U)
            return contact(h - t0, 0.0, U + G0 * t0) - dn2
        U = (dn2 - dp2) / h
        U = jax.lax.fori_loop(0, 8, lambda _, u: u - r2(u) / jax.grad(r2)(u), U)
        tau0 = tau0_of(U); Uc = U + G0 * tau0
        # case 3: exiting
        dn3, dp3 = jnp.where(case == 3, dn, -1e-4), jnp.where(case == 3, dp_, 1e-4)
        def rfree(Ue):
            return -2 * dn3 / (-Ue + jnp.sqrt(jnp.maximum(Ue * Ue + 2 * G0 * dn3, 1e-30)))
        def r3(Ue):
            return contact(-(h - rfree(Ue)), 0.0, Ue) - dp3
        Ue = (dn3 - dp3) / h
        Ue = jax.lax.fori_loop(0, 8, lambda _, u: u - r3(u) / jax.grad(r3)(u), Ue)
        tau1 = h - rfree(Ue)
        # case 0
        A = dn - de
        B = (A * jnp.cos(w * h) - (dp_ - de) * jnp.exp(-sg * h)) / jnp.sin(w * h)
        D_free = (dn - dp_) / h + 0.5 * G0 * h
        tc0 = h - tau0
        D_in = jax.grad(lambda t: contact(t, 0.0, Uc))(tc0)
        D0 = jnp.select([case == 0, case == 1, case == 2], [-sg * A + w * B, D_free, D_in],
                        Ue + G0 * rfree(Ue))
        def back(s):
            t = s + h
            p0 = de + jnp.exp(-sg * s) * (A * jnp.cos(w * s) + B * jnp.sin(w * s))
            p1 = free(s, dn, D_free)
            p2 = jnp.where(t < tau0, free(t, dp_, U), contact(t - tau0, 0.0, Uc))
            p3 = jnp.where(t < tau1, contact(t - tau1, 0.0, Ue), free(t - tau1, 0.0, Ue))
            return jnp.select([case == 0, case == 1, case == 2], [p0, p1, p2], p3)
        # forward crossings
        S = jnp.sqrt(jnp.maximum(D0 * D0 - 2 * G0 * jnp.minimum(dn, 0.0), 0.0))
        s0 = jnp.where(D0 > 0, -2 * jnp.minimum(dn, 0.0) / jnp.where(D0 + S > 0, D0 + S, 1.0),
                       (-D0 + S) / G0)
        s0 = jnp.where(dn > 0, h, s0)
        Dc = D0 + G0 * s0
        inside = dn > 0
        exits = inside & (contact(h, jnp.where(inside, dn, 1e-4), D0) < 0)
        s1 = jnp.clip(jnp.where(exits, dn / jnp.maximum(-D0, 1e-9), 0.5 * h), 0.0, h)
        dni = jnp.where(exits, dn, 1e-4); D0i = jnp.where(exits, D0, -1.0)
        def newton_exit(_, s1):
            f_ = contact(s1, dni, D0i); fp = jax.grad(lambda q: contact(q, dni, D0i))(s1)
            return jnp.clip(s1 - f_ / fp, 0.0, h)
        s1 = jax.lax.fori_loop(0, 6, newton_exit, s1)
        def fwd(s):
            pin = contact(s, dn, D0)
            pout = jnp.where(s < s0, free(s, dn, D0), contact(s - s0, 0.0, Dc))
            return jnp.where(inside, pin, pout)
        sb = jnp.where(case == 2, tau0 - h, jnp.where(case == 3, tau1 - h, -0.5 * h))
        sb = jnp.clip(sb, -h, 0.0)
        sf = jnp.where(inside, jnp.where(exits, s1, 0.5 * h), jnp.clip(s0, 0.0, h))
        tot = 0.0
        for a, b, fn in ((-h, sb, back), (sb, 0.0, back), (0.0, sf, fwd), (sf, h, fwd)):
            s = 0.5 * (a + b) + 0.5 * (b - a) * GX
            dd = jax.vmap(fn)(s); dv = jax.vmap(jax.grad(fn))(s)
            fs = jnp.where(dd > 0, k * dd + c * dv, 0.0) * (1 - jnp.abs(s) / h)
            tot = tot + 0.5 * (b - a) * jnp.sum(GW * fs)
        return tot / h
    def vec(d, vn, k, c, h):
        return jax.vmap(lambda a, b: avg(a, b, k, c, h))(
            jnp.atleast_1d(d), jnp.atleast_1d(vn)).reshape(jnp.shape(d))
    return dataclasses.replace(laws.linear(), averaged=vec)
