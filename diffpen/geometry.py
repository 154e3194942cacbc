"""Narrow phase: penetration depth and contact normal for ONE pair of shapes.

Each function takes one pair (positions of shape ``(3,)``, radii as scalars) and returns
``(d, n)``: the penetration depth ``d`` in metres (positive when overlapping) and the unit
normal ``n`` of shape ``(3,)`` pointing from the second shape to the first, i.e. the direction
in which a positive contact force pushes the first shape. ``diffpen.compile`` lifts these with
``jax.vmap``.

Norms are "safe" (double-where): gradients stay finite when two centres coincide.
"""
from __future__ import annotations

import jax.numpy as jnp

__all__ = ["safe_norm", "sphere_plane", "sphere_sphere"]


def safe_norm(v, axis=-1, keepdims=False):
    """Euclidean norm with a finite (zero) gradient at ``v = 0``."""
    sq = jnp.sum(v * v, axis=axis, keepdims=keepdims)
    pos = sq > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def sphere_plane(x, r, normal, offset):
    """Sphere (or particle, ``r = 0``) against the half-space ``normal . p <= offset``.

    Args:
      x: (3,) sphere centre, m.  r: radius, m.
      normal: (3,) unit outward plane normal.  offset: plane offset, m (``normal . p = offset``).
    Returns:
      ``(d, n)`` with ``d = r - (normal . x - offset)`` and ``n = normal``.
    """
    return r - (jnp.sum(normal * x, axis=-1) - offset), normal


def sphere_sphere(xa, ra, xb, rb):
    """Sphere ``a`` against sphere ``b`` (either may be a particle, radius 0).

    Returns ``(d, n)`` with ``d = ra + rb - |xa - xb|`` and ``n = (xa - xb) / |xa - xb|``
    (``n = 0`` when the centres coincide, so no force and a finite gradient).
    """
    delta = xa - xb
    dist = safe_norm(delta)
    inv = jnp.where(dist > 0.0, 1.0 / jnp.where(dist > 0.0, dist, 1.0), 0.0)
    return ra + rb - dist, delta * inv
