"""The reference depth of a contact law whose stiffness grows with depth, from the energy a
rollout starts with.

Hunt-Crossley's contact stiffens with depth, ``dF/dd = n k d^(n-1)``, so the safe step takes
it at a reference depth: each body's radius (:class:`~.bounds.Analysis` ``d_ref``), the
deepest a penetration can meaningfully go. A ball dropped from 1 m onto a Hertz contact (1 kg,
k 1e6 N/m^1.5) sinks 1.4 cm, not 10, and its stiffness there is 2.7x smaller: the radius
refuses a step of 1 ms that this ball takes safely.

Energy bounds the depth instead, where the scene lets it: no force besides gravity, the
contacts and drag can give energy back (no springs, no custom terms), gravity's potential is
bounded below (no gravity, or every plane a horizontal floor, unnamed: a fixed offset), no
rotation, and no body starting in contact. Then no contact ever stores more than the start's
kinetic and potential energy ``E0`` (potential measured from the lowest floor), and a contact
of stiffness ``k`` holds it at ``k d^(n+1) / (n+1) = E0``. The bound takes twice ``E0``
(:data:`ENERGY_MARGIN`: room for the explicit step's own energy error, held to several %
per contact event by the safe step), and never more than the radius. Where any condition fails
the radius stays.

:func:`start_energy` computes ``E0`` on the host from a concrete start state (None where the
scene or the state does not qualify); ``Simulator.rollout`` hands it to the up-front gate and,
as a traced argument, to the traced flag, so both count the same depth.
"""
from __future__ import annotations

import numpy as np

__all__ = ["ENERGY_MARGIN", "qualifies", "start_energy", "energy_depth"]

#: the energy a contact may store, in units of the start's kinetic and potential energy
ENERGY_MARGIN = 2.0


def qualifies(scene, law, builtin_terms: bool, rotation: bool) -> bool:
    """Whether ``scene`` compiled with ``law`` (a ``diffpen.laws.ContactLaw``) lets the start
    energy bound its contacts' depth (module docstring); static, at compile time."""
    if float(law.exponent) == 1.0 and float(law.damping_exponent) == 0.0:
        return False                    # the stiffness does not depend on depth
    if not builtin_terms or rotation:
        return False
    if scene.springs or scene.anchored_springs or scene.plastic_springs:
        return False
    g = np.asarray(scene.gravity, float)
    gn = float(np.linalg.norm(g))
    if gn == 0.0:
        return True
    up = -g / gn
    return bool(scene.planes) and all(
        p.name is None and float(np.dot(np.asarray(p.normal, float), up)) > 1.0 - 1e-12
        for p in scene.planes)


def start_energy(scene, mass, radius, pinned, collide, position,
                 velocity) -> float | None:
    """Kinetic and potential energy (J) of a concrete start state (``position``,
    ``velocity`` (n, 3)), potential measured from the lowest floor; None when a colliding body
    (``collide`` (n,) bool, fixed per simulator) starts in contact (with a plane, a fixed
    sphere or another colliding body) or a value is not finite. Assumes :func:`qualifies`."""
    x = np.asarray(position, float)
    v = np.asarray(velocity, float)
    m = np.where(np.asarray(pinned, bool), 0.0, np.asarray(mass, float))
    r = np.asarray(radius, float)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        return None
    collide = np.asarray(collide, bool)
    for p in scene.planes:
        gap = x @ np.asarray(p.normal, float) - float(p.offset) - r
        if np.any(collide & (gap <= 0.0)):
            return None
    for fs in scene.fixed_spheres:
        dist = np.linalg.norm(x - np.asarray(fs.center, float), axis=1)
        if np.any(collide & (dist <= r + float(fs.radius))):
            return None
    idx = np.flatnonzero(collide)
    if idx.size > 1:
        if idx.size > 512:                 # the pair check's cost: keep the radius
            return None
        xc, rc = x[idx], r[idx]
        dist = np.linalg.norm(xc[:, None, :] - xc[None, :, :], axis=-1)
        overlap = dist <= rc[:, None] + rc[None, :]
        np.fill_diagonal(overlap, False)
        if np.any(overlap):
            return None
    energy = 0.5 * float(np.sum(m * np.sum(v * v, axis=1)))
    g = np.asarray(scene.gravity, float)
    gn = float(np.linalg.norm(g))
    if gn > 0.0:
        floor = min(float(p.offset) for p in scene.planes)
        energy += gn * float(np.sum(m * (x @ (-g / gn) - floor)))
    return energy if np.isfinite(energy) else None


def energy_depth(exponent: float, k, energy, xp=np):
    """Depth (m) at which a contact of stiffness ``k`` (N/m^n; an array) stores
    ``ENERGY_MARGIN x energy`` J: ``((n + 1) E / k)^(1 / (n + 1))`` (inf where ``k`` is 0)."""
    n1 = float(exponent) + 1.0
    pos = k > 0.0
    return xp.where(pos, (n1 * ENERGY_MARGIN * energy / xp.where(pos, k, 1.0)) ** (1.0 / n1),
                    xp.inf)
