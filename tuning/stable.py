"""The stability flag of a rollout, as tuning reads it, and bounds that keep optimisers inside
the stable region.

diffpen carries ``State.aux["unstable"]`` (a sticky bool scalar set inside the traced program
when a step was past the safe step for the traced parameter values), so
``traj.aux["unstable"][-1]`` says whether a rollout can be trusted; it works under ``jit``,
``vmap`` and ``grad``. :func:`rollout_unstable` returns it. For a trajectory without the flag
(e.g. a simulator from outside diffpen) it falls back to the same condition computed from the
parameters (contact safe step
of the lightest movable body: ``w h <= SAFE_WH``, ``c h / m <= SAFE_CH``, and the linear limit
``k h^2 + 2 c h < 4 m``), which is exact for one body on colliders.
"""
from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from diffpen import stability as _dp_stability

__all__ = ["FLAG", "rollout_unstable", "contact_unstable", "safe_contact_bounds"]

#: key of the flag in ``State.aux`` / ``Trajectory.aux``
FLAG = getattr(_dp_stability, "FLAG", "unstable")


def _inner_dt(sim) -> float:
    sub = getattr(sim, "substeps", 1)
    return float(sim.dt) / (sub if isinstance(sub, int) and sub > 0 else 1)


def _light_mass(sim) -> float:
    m = np.asarray(sim.mass, float)[~np.asarray(sim.pinned, bool)]
    return float(m.min()) if m.size else float(np.asarray(sim.mass).min())


def contact_unstable(sim, params):
    """Traceable bool: some contact material's (k, c) is past the explicit safe step for
    the lightest movable body (False for implicit integrators)."""
    from diffpen import stability as S
    if getattr(sim, "integrator", "") == "implicit_euler":
        return jnp.asarray(False)
    h, m = _inner_dt(sim), _light_mass(sim)
    bad = jnp.asarray(False)
    for cp in params.contact.values():
        k, c = jnp.asarray(cp.k), jnp.asarray(cp.c)
        w = jnp.sqrt(jnp.maximum(k, 0.0) / m)
        bad = bad | (w * h >= S.SAFE_WH) | (c * h / m >= S.SAFE_CH) | (
            k * h * h + 2.0 * c * h >= 4.0 * m) | ~jnp.isfinite(k) | ~jnp.isfinite(c)
    return bad


def rollout_unstable(sim, traj, params):
    """Traceable bool scalar: the rollout went past its safe step.

    ``traj.aux["unstable"][-1]`` when the simulator carries the flag, else
    :func:`contact_unstable` of ``params``."""
    aux = getattr(traj, "aux", None) or {}
    if FLAG in aux:
        return jnp.asarray(aux[FLAG])[-1].astype(bool)
    return contact_unstable(sim, params)


def safe_contact_bounds(sim, mass: float | None = None) -> tuple[float, float]:
    """Upper bounds (k_max N/m, c_max N s/m) of one contact that keep an explicit step inside
    the safe region for a body of ``mass`` kg (default: the lightest movable body), with a
    1% margin: ``w h <= SAFE_WH``, ``c h / m <= SAFE_CH``."""
    from diffpen import stability as S
    h = _inner_dt(sim)
    m = _light_mass(sim) if mass is None else float(mass)
    if getattr(sim, "integrator", "") == "implicit_euler":
        return math.inf, math.inf
    return 0.99 * (S.SAFE_WH / h) ** 2 * m, 0.99 * S.SAFE_CH * m / h
