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
import numpy as np

__all__ = ["dot", "safe_norm", "safe_unit", "sphere_plane", "sphere_sphere", "box_corners",
           "quat_to_matrix", "sphere_box", "rotate", "rotate_back"]


def dot(a, b):
    """``sum(a * b, axis=-1)`` over 3-vectors ``(..., 3)``, written as three products and two
    adds: elementwise, so XLA fuses it with what follows (a reduction over an axis of 3 ends
    a fusion, and at batch 1 each fusion costs about as much as the arithmetic)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def safe_norm(v, axis=-1, keepdims=False):
    """Euclidean norm with a finite (zero) gradient at ``v = 0``."""
    sq = jnp.sum(v * v, axis=axis, keepdims=keepdims)
    pos = sq > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def safe_unit(v):
    """``(v / |v|, |v|)`` of 3-vectors ``v`` (..., 3), with the unit vector 0 and finite
    gradients where ``v = 0`` (:func:`safe_norm`)."""
    length = safe_norm(v)
    inv = jnp.where(length > 0.0, 1.0 / jnp.where(length > 0.0, length, 1.0), 0.0)
    return v * inv[..., None], length


def sphere_plane(x, r, normal, offset):
    """Sphere (or particle, ``r = 0``) against the half-space ``normal . p <= offset``.

    Args:
      x: (3,) sphere centre, m.  r: radius, m.
      normal: (3,) unit outward plane normal.  offset: plane offset, m (``normal . p = offset``).
    Returns:
      ``(d, n)`` with ``d = r - (normal . x - offset)`` and ``n = normal``.
    """
    return r - (dot(normal, x) - offset), normal


def sphere_sphere(xa, ra, xb, rb):
    """Sphere ``a`` against sphere ``b`` (either may be a particle, radius 0).

    Returns ``(d, n)`` with ``d = ra + rb - |xa - xb|`` and ``n = (xa - xb) / |xa - xb|``
    (``n = 0`` when the centres coincide, so no force and a finite gradient).
    """
    n, dist = safe_unit(xa - xb)
    return ra + rb - dist, n


def quat_to_matrix(q, xp=jnp):
    """Rotation matrices (..., 3, 3) from unit quaternions q (..., 4) = (w, x, y, z).
    ``xp=numpy`` evaluates on the host in the input's precision (no JAX dispatch)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def box_corners(half_extents):
    """The 8 corners of a box in its body frame, (8, 3) m (numpy, static), from
    ``half_extents`` (3,) m."""
    signs = np.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)
                      for sz in (-1.0, 1.0)])
    return signs * np.asarray(half_extents, dtype=float)


def sphere_box(xs, rs, xb, rot, half):
    """Sphere (or particle, ``rs = 0``) ``s`` against the box ``b``.

    Args:
      xs: (3,) sphere centre, m.  rs: sphere radius, m.
      xb: (3,) box centre, m.  rot: (3, 3) box rotation, body to world.
      half: (3,) box half extents, m.
    Returns:
      ``(d, n, p)``: penetration depth d (m; ``rs - distance`` from the centre to the box, or
      ``rs + depth`` of the centre inside the box along its shallowest face), the unit normal
      n (3,) pointing from the box to the sphere, and the contact point p (3,) on the box
      surface, world frame, m. d and p are continuous across the box surface; n is
      continuous while the centre is outside the box, at faces, edges and corners alike (it
      follows the closest point), and where the centre crosses a face away from its edges.
      With the centre inside the box or on its surface, the face of least depth decides, so
      n and p jump inside where two faces are equally deep, and n jumps where the centre
      crosses the surface at an edge or corner (outside it points along the diagonal, on and
      inside along a face normal). Finite gradients when the centre lies on the surface.
    """
    local = rotate_back(rot, xs - xb)
    closest = jnp.clip(local, -half, half)
    delta = local - closest
    out, dist = safe_unit(delta)
    # centre inside: push out through the face of least depth
    depth_in = half - jnp.abs(local)
    axis = jnp.argmin(depth_in)
    onehot = jnp.arange(3) == axis
    sign = jnp.where(local[axis] >= 0.0, 1.0, -1.0)
    inside = dist <= 0.0
    n_local = jnp.where(inside, jnp.where(onehot, sign, 0.0), out)
    p_local = jnp.where(inside & onehot, sign * half, closest)
    d = jnp.where(inside, rs + jnp.min(depth_in), rs - dist)
    return d, rotate(rot, n_local), xb + rotate(rot, p_local)


def rotate(m, v):
    """``m @ v`` for rotations (..., 3, 3) and vectors (..., 3), written elementwise (batches
    better than a dot_general)."""
    return jnp.sum(m * v[..., None, :], axis=-1)


def rotate_back(m, v):
    """``m^T @ v`` (world to body frame for a body-to-world rotation m), elementwise."""
    return jnp.sum(m * v[..., :, None], axis=-2)

