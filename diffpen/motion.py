"""Limits of a start state's motion that the step-size check cannot see, checked before a
rollout runs (concrete states) and flagged inside it (traced ones):

* spin: semi-implicit Euler steps Euler's equations explicitly, so a fast spin of a body
  with unequal moments gains energy until it turns NaN (:data:`SPIN_LIMIT`,
  :func:`check_spin`, :func:`spin_unsafe` for the traced ``aux["unstable"]`` flag);
* impacts: bodies closing faster than their penalty contact can stop before their centres
  meet pass through each other (:func:`check_tunnelling`, a :class:`ContactWarning`).
"""
from __future__ import annotations


import jax.numpy as jnp
import numpy as np

from .errors import ContactWarning, StabilityError, warn

__all__ = ["SPIN_LIMIT", "anisotropy", "spin_anisotropy", "check_spin", "spin_unsafe",
           "tunnelling_table", "check_tunnelling"]


#: Largest start spin that semi-implicit Euler is allowed to step, as ``kappa |w| h`` (rad per
#: inner step ``h``, scaled by the body's inertia anisotropy ``kappa = max |I_j - I_k| / I_i``,
#: 0 for a sphere or a cube, 1 for moments 1:2:3). It integrates Euler's equations
#: explicitly, which grows a spinning body's energy by about ``0.16 (kappa |w| h)^2`` per
#: step (over 5000 steps, worst of three spin axes: +2% at 0.005, +8% at 0.01, +42% at 0.02,
#: x2.5 at 0.03, NaN from 0.05 to 0.1); verlet and rk4 stay within 0.4% at |w| h = 0.3.
SPIN_LIMIT = 0.05


def anisotropy(inertia) -> float:
    """``kappa = max_i |I_j - I_k| / I_i`` of principal moments ``inertia`` (3,): how fast the
    gyroscopic term ``w x I w`` turns a spin, per unit ``|w|`` (0 for equal moments)."""
    i = np.asarray(inertia, dtype=float)
    return float(max(abs(i[1] - i[2]) / i[0], abs(i[0] - i[2]) / i[1],
                     abs(i[0] - i[1]) / i[2]))


def spin_anisotropy(scene) -> np.ndarray:
    """(n,) :func:`anisotropy` of each free rigid body's principal moments (0 for other
    bodies), computed once per simulator."""
    from .rigid import inertia_diagonal
    return np.array([anisotropy(inertia_diagonal(b)) if b.rigid and not b.pinned else 0.0
                     for b in scene.bodies])


def _kick_drift(sim) -> bool:
    """The simulator steps as semi-implicit Euler (by its record's step, not its name)."""
    from .integrators import kick_then_drift
    rec = getattr(getattr(sim, "analysis", None), "integrator", None)
    return kick_then_drift(rec if rec is not None else sim.integrator)


def check_spin(sim, state, substeps: int, *, auto: bool = False) -> int:
    """The inner steps a concrete start state needs so that no rigid body spins faster than
    :data:`SPIN_LIMIT` (``kappa |w| h``) under semi-implicit Euler: ``substeps`` when it is
    enough; else, with ``auto``, the count that is, and otherwise :class:`StabilityError`
    saying which dt, substeps or integrator would step it."""
    from .checks import _batched
    from .params import _is_concrete
    w = getattr(state, "angular_velocity", None)
    kappa = getattr(sim, "_spin_kappa", None)
    if (w is None or kappa is None or not kappa.any() or not _kick_drift(sim)
            or not _is_concrete(w) or _batched(state)):
        return substeps
    h = sim.dt / substeps
    speed = np.linalg.norm(np.asarray(w, dtype=float).reshape(-1, 3), axis=-1)
    rate = kappa * speed * h
    if not rate.size or not np.isfinite(rate).all() or rate.max() <= SPIN_LIMIT:
        return substeps
    b = int(np.argmax(rate))
    need = int(np.ceil(rate[b] / SPIN_LIMIT)) * substeps
    if auto:
        return need
    raise StabilityError(
        f"body {b} spins at |w| = {speed[b]:.4g} rad/s with inertia anisotropy kappa = "
        f"{kappa[b]:.3g}: kappa |w| h = {rate[b]:.3g} per step of {h:.3g} s. Semi-implicit "
        "Euler steps the gyroscopic term explicitly and grows such a spin's energy until it "
        f"turns NaN (above {SPIN_LIMIT}). Use dt <= {SPIN_LIMIT / (kappa[b] * speed[b]):.3g} s, "
        f"substeps={need} (or substeps='auto'), or integrator='verlet' or 'rk4' (stable to "
        "about |w| h = 0.3).",
        stable_dt=SPIN_LIMIT / (kappa[b] * speed[b]), substeps=need)


def tunnelling_table(scene):
    """The static part of :func:`check_tunnelling`, once per simulator: the colliding
    spheres ``(index (n,), radius (n,), mass (n,) with inf for pinned, material (n,))``, the
    free colliding spheres and particles the fixed spheres act on ``(index (p,), radius (p,),
    mass (p,), material (p,))`` and the fixed spheres ``(centre (f, 3), radius (f,),
    material (f,))``, or None when nothing can pass through anything."""
    bodies = scene.bodies
    idx = [i for i, b in enumerate(bodies)
           if b.kind == "sphere" and b.collide and b.radius > 0.0]
    fixed = scene.fixed_spheres
    fidx = [i for i, b in enumerate(bodies)
            if fixed and b.kind in ("sphere", "particle") and b.collide and not b.pinned]
    if len(idx) < 2 and not fidx:
        return None

    def rows(ids):
        return (np.array(ids, dtype=int), np.array([bodies[i].radius for i in ids]),
                np.array([np.inf if bodies[i].pinned else bodies[i].mass for i in ids]),
                [bodies[i].material for i in ids])
    return (rows(idx if len(idx) >= 2 else []), rows(fidx),
            (np.array([f.center for f in fixed], dtype=float).reshape(-1, 3),
             np.array([f.radius for f in fixed]), [f.material for f in fixed]))


def _impact(rel, vrel, reach):
    """Normal speed (m/s) at which bodies at relative position ``rel`` (k, 3) with relative
    velocity ``vrel`` (k, 3) (both b - a) would touch at centre distance ``reach`` (k,), moving
    in straight lines: ``|u| sqrt(1 - b^2 / reach^2)`` with ``b`` the distance between their
    paths; 0 when they move apart or their paths pass further apart than ``reach``."""
    u2 = np.einsum("ij,ij->i", vrel, vrel)
    along = -np.einsum("ij,ij->i", rel, vrel)                   # > 0: approaching
    b2 = np.einsum("ij,ij->i", rel, rel) - np.where(u2 > 0.0, along ** 2 / np.where(
        u2 > 0.0, u2, 1.0), 0.0)
    frac = np.clip(1.0 - np.maximum(b2, 0.0) / reach ** 2, 0.0, 1.0)
    return np.where(along > 0.0, np.sqrt(u2 * frac), 0.0)


def check_tunnelling(sim, params, state) -> None:
    """Warn (:class:`ContactWarning`) when, in a concrete start state, two colliding spheres
    (or a sphere or particle and a fixed sphere) would reach each other faster than their
    contact can stop before their centres meet: the kinetic energy of the normal speed they
    would touch at (straight paths from the start state: none if the paths pass further apart
    than the contact reaches), ``mu v_n^2 / 2`` (``mu`` the reduced mass), above the law's
    stored energy at the depth ``r_a + r_b`` (``ContactLaw.energy``; damping, which only
    helps, left out). Such bodies pass through each other if they meet. Start speeds only:
    what gravity or springs add on the way is not counted. A screen with the fastest speed
    and heaviest mass against the softest contact skips the pairwise check in ordinary
    scenes; more than 4000 spheres are not checked pairwise."""
    table = getattr(sim, "_tunnel_table", None)
    if table is None:
        return
    (idx, rad, mass, mats), (fidx, frad, fmass, fmats_b), (fc, fr, fmats) = table
    vel = np.asarray(state.velocity, dtype=float)
    both = np.concatenate([idx, fidx]).astype(int)
    vmax = float(np.linalg.norm(vel[both], axis=-1).max(initial=0.0)) if both.size else 0.0
    if not vmax > 0.0 or not np.isfinite(vmax):
        return
    law = sim.contact_law

    def k_of(m):
        return float(np.asarray(params.contact[m].k))
    allm = np.concatenate([mass, fmass])
    finite = allm[np.isfinite(allm)]
    m_max = float(finite.max(initial=0.0))
    k_min = min([k_of(m) for m in set(mats) | set(fmats) | {"default"} if m in params.contact]
                or [np.inf])
    r_min = min(2.0 * float(rad.min(initial=np.inf)),
                float(frad.min(initial=np.inf)) + float(fr.min(initial=np.inf)))
    if m_max * vmax ** 2 <= float(law.energy(r_min, k_min)) or len(idx) > 4000:
        return                                   # no pair can bring that much
    pos = np.asarray(state.position, dtype=float)
    from .terms.base import _pair_material
    worst = None

    def consider(ke, vn, mat, reach, a, other):
        nonlocal worst
        if mat not in params.contact:
            return
        k = k_of(mat)
        cap = float(law.energy(reach, k))
        if ke > cap and (worst is None or ke / cap > worst[0]):
            worst = (ke / cap, a, other, vn, mat, k, cap, ke)

    def reduced(ma, mb):
        inv = (1.0 / ma if np.isfinite(ma) else 0.0) + np.where(
            np.isfinite(mb), 1.0 / np.where(np.isfinite(mb), mb, 1.0), 0.0)
        return np.where(inv > 0.0, 1.0 / np.where(inv > 0.0, inv, 1.0), 0.0)
    for a in range(len(idx)):                     # sphere pairs, b > a
        reach = rad[a] + rad[a + 1:]
        vn = _impact(pos[idx[a + 1:]] - pos[idx[a]], vel[idx[a + 1:]] - vel[idx[a]], reach)
        ke = 0.5 * reduced(mass[a], mass[a + 1:]) * vn ** 2
        for c in np.nonzero(ke > 0.0)[0]:
            consider(ke[c], vn[c], _pair_material(sim.scene, mats[a], mats[a + 1 + c]),
                     reach[c], int(idx[a]), f"sphere {int(idx[a + 1 + c])}")
    for a in range(len(fidx)):                    # bodies against the fixed spheres
        reach = frad[a] + fr
        vn = _impact(fc - pos[fidx[a]], -np.broadcast_to(vel[fidx[a]], fc.shape), reach)
        ke = 0.5 * fmass[a] * vn ** 2
        for c in np.nonzero(ke > 0.0)[0]:
            consider(ke[c], vn[c], fmats[c], reach[c], int(fidx[a]), f"fixed sphere {c}")
    if worst is not None:
        ratio, i, other, vn, mat, k, cap, ke = worst
        kind = sim.scene.bodies[i].kind
        warn(
            f"{kind} {i} and {other} would meet at {vn:.3g} m/s: their contact (material "
            f"{mat!r}, k = {k:.3g}) stores at most {cap:.3g} J before their centres meet, and "
            f"they bring {ke:.3g} J: if they meet they pass through each other (a penalty "
            f"contact cannot stop them). Raise k above {k * ratio:.3g}, or slow them down.",
            ContactWarning)


def spin_unsafe(sim, state, h: float):
    """Traced counterpart of :func:`check_spin`: a bool scalar, True when a rigid body of the
    (possibly traced, e.g. vmapped) start ``state`` spins past :data:`SPIN_LIMIT`
    (``kappa |w| h``) under semi-implicit Euler, ``h`` the inner step in s. It joins the
    rollout's ``State.aux["unstable"]`` flag, so a sweep over start spins marks the rows a
    concrete rollout would refuse (they end NaN)."""
    w = getattr(state, "angular_velocity", None)
    kappa = getattr(sim, "_spin_kappa", None)
    if w is None or kappa is None or not kappa.any() or not _kick_drift(sim):
        return jnp.zeros((), bool)
    w = jnp.asarray(w)
    speed = jnp.sqrt(jnp.sum(w * w, axis=-1))
    rate = jnp.asarray(kappa, speed.dtype) * speed * h
    return jnp.any(rate > SPIN_LIMIT) | jnp.any(~jnp.isfinite(rate))
