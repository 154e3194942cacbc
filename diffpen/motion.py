"""Limits of a start state's motion that the step-size check cannot see, checked before a
rollout runs (concrete states) and flagged inside it (traced ones):

* spin: a fast spin of a body with unequal moments turns more per step than an integrator
  steps accurately (verlet and rk4 step Euler's gyroscopic term explicitly and gain energy
  until it turns NaN) (:data:`SPIN_LIMITS`, :func:`check_spin`, :func:`spin_unsafe` for the
  traced ``aux["unstable"]`` flag);
* impacts: bodies closing faster than their penalty contact can stop before their centres
  meet pass through each other (:func:`check_tunnelling`, a :class:`ContactWarning`).
"""
from __future__ import annotations


import jax.numpy as jnp
import numpy as np

from .errors import ContactWarning, SpinWarning, StabilityError, warn

__all__ = ["SPIN_LIMIT", "SPIN_LIMITS", "anisotropy", "spin_anisotropy", "spin_limit",
           "spin_speed", "spin_step", "check_spin", "with_spin", "warn_spun_up",
           "spin_unsafe",
           "tunnelling_table", "check_tunnelling"]


#: Largest start spin that semi-implicit Euler is allowed to step, as ``kappa |w| h`` (rad per
#: inner step ``h``, scaled by the body's inertia anisotropy ``kappa = max |I_j - I_k| / I_i``,
#: 0 for a sphere or a cube, 1 for moments 1:2:3). It carries each body's angular momentum
#: (:meth:`diffpen.rigid.RigidDynamics.transport`), which no spin turns NaN; the limit is
#: accuracy: over 5000 free steps of a 1:2:3 box spun about four axes the energy stays within
#: 0.05% at 0.05, 0.73% at 0.1, 17% at 0.2. (Before, the gyroscopic term stepped explicitly
#: gained energy every step: +45% at 0.02, NaN from 0.04.)
SPIN_LIMIT = 0.05

#: The spin limit of each integrator that has one, by its step factory's name: where 5000 free
#: steps of that box keep its energy within about 0.3%. verlet steps the gyroscopic term
#: explicitly (0.34% at 0.05, 1-4% at 0.1, NaN from 0.2); rk4 0.28% at 0.2, 5-15% at 0.5, NaN
#: from 2-2.5. implicit Euler carries the angular momentum as semi-implicit Euler does (its
#: linearised gyroscopic term gained energy +1.7% / +39% and lost angular momentum 2.7% / 58%
#: over 5000 steps at 0.005 / 0.05), with its energy figures, and has no limit: it is chosen
#: for steps past the explicit limit, where a landing box turns 0.1 per step and its contact
#: error (tens of mm against rk4 at 5 ms) is far larger. The error grows about
#: linearly with the steps: at the limits 0.5% / 2.8% / 1.3% after 50 000 steps, 6% / 45% /
#: 16% after 500 000 (semi-implicit Euler / verlet / rk4).
SPIN_LIMITS = {"semi_implicit_euler": SPIN_LIMIT, "verlet": 0.05, "rk4": 0.2}


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


def _stepper(sim) -> str | None:
    """The name of the built-in integrator the simulator's steps as, by its record's step
    factory (a renamed record steps the same): a key of :data:`SPIN_LIMITS`, or
    ``"implicit_euler"`` (no limit), or None (an integrator made outside the package)."""
    from . import integrators as _integrators
    rec = getattr(getattr(sim, "analysis", None), "integrator", None)
    make = _integrators.resolve(rec if rec is not None else sim.integrator).make
    make = getattr(make, "func", make)              # implicit_euler_with(...)'s partials
    return {_integrators.semi_implicit_euler: "semi_implicit_euler",
            _integrators.implicit_euler: "implicit_euler",
            _integrators.verlet: "verlet", _integrators.rk4: "rk4"}.get(make)


def spin_limit(sim) -> float | None:
    """The spin limit (``kappa |w| h``, :data:`SPIN_LIMITS`) of the simulator's integrator,
    or None where it has none."""
    return SPIN_LIMITS.get(_stepper(sim))


def spin_speed(w, q, moments, xp=np):
    """(n,) ``sqrt(w_b . I w_b / I_min)`` (rad/s) of bodies turning at world angular
    velocity ``w`` (n, 3) rad/s with orientation ``q`` (n, 4) and principal moments
    ``moments`` (n, 3) kg m^2 (0 for bodies that do not rotate: 0 here): the largest ``|w|``
    the body reaches without torque (its rotational energy ``E = w_b . I w_b / 2`` is kept
    and ``|w|^2 <= 2 E / I_min``), so a free body near its middle axis, whose ``|w|`` grows
    1.16x for moments 1:2:3, is judged as it will turn. ``>= |w|`` always."""
    from .geometry import quat_to_matrix
    m = xp.asarray(moments, dtype=w.dtype)
    wb = xp.sum(quat_to_matrix(q, xp=xp) * w[..., :, None], axis=-2)   # R^T w, body frame
    low = m.min(axis=-1)
    e2 = xp.sum(m * wb * wb, axis=-1)
    return xp.sqrt(xp.where(low > 0.0, e2, 0.0) / xp.where(low > 0.0, low, 1.0))


def spin_step(sim, state):
    """``(h_max, body, speed, kappa, limit)``: the largest inner step (s) at which a concrete,
    unbatched start ``state`` spins within the simulator's spin limit (``kappa |w| h <=
    limit``, :data:`SPIN_LIMITS`, ``|w|`` the body's :func:`spin_speed`), the body that sets
    it, that speed (rad/s) and its anisotropy; None where nothing limits it (no spinning body
    with unequal moments, an integrator without a limit, a traced or batched state)."""
    from .checks import _batched
    from .params import _is_concrete
    w = getattr(state, "angular_velocity", None)
    kappa = getattr(sim, "_spin_kappa", None)
    if (w is None or kappa is None or not kappa.any() or not _is_concrete(w)
            or _batched(state)):
        return None
    limit = spin_limit(sim)
    if limit is None:
        return None
    q = getattr(state, "orientation", None)
    if q is None or not _is_concrete(q):
        return None
    speed = spin_speed(np.asarray(w, dtype=float).reshape(-1, 3),
                       np.asarray(q, dtype=float).reshape(-1, 4), sim._moments)
    rate = kappa * speed
    if not rate.size or not np.isfinite(rate).all() or rate.max() <= 0.0:
        return None
    b = int(np.argmax(rate))
    return limit / rate[b], b, float(speed[b]), float(kappa[b]), limit


def check_spin(sim, state, substeps: int, *, auto: bool = False) -> int:
    """The inner steps a concrete start state needs so that no rigid body spins faster than
    its integrator's spin limit (``kappa |w| h``, :data:`SPIN_LIMITS`): ``substeps`` when it
    is enough; else, with ``auto``, the count that is, and otherwise :class:`StabilityError`
    saying which dt, substeps or integrator would step it."""
    from .stability.gating import MAX_AUTO_SUBSTEPS, _count, _down, _needed
    found = spin_step(sim, state)
    h = sim.dt / substeps
    if found is None or h <= found[0]:
        return substeps
    h_max, b, speed, kappa, limit = found
    need = max(_needed(sim.dt, h_max), substeps)     # as sim.stability(params, state) says
    if auto and need > MAX_AUTO_SUBSTEPS:
        raise StabilityError(
            f"substeps='auto' would need {_count(need)} substeps per step of dt={sim.dt:g} s "
            f"for body {b}'s spin (|w| = {speed:.4g} rad/s, kappa |w| h <= {limit} under "
            f"{sim.integrator}): too slow. Slow the spin down, or give the body equal "
            "moments if it has them (a cube has no spin limit).", stable_dt=h_max,
            substeps=need)
    if auto:
        return need
    why = (f"{sim.integrator} keeps the angular momentum but not the energy at such a "
           "turn per step" if _stepper(sim) in ("semi_implicit_euler", "implicit_euler") else
           f"{sim.integrator} steps the gyroscopic term explicitly and gains energy at such "
           "a turn per step, until it turns NaN")
    rate = kappa * speed * h
    raise StabilityError(
        f"body {b} spins at up to |w| = {speed:.4g} rad/s (sqrt(2 E / I_min), its energy's "
        f"speed) with inertia anisotropy kappa = {kappa:.3g}: kappa |w| h = {rate:.3g} per "
        f"step of {h:.3g} s, past "
        f"{sim.integrator}'s spin limit {limit}. {why}. Use dt <= {_down(h_max, 3):.3g} s "
        f"(an inner step), substeps={need} (or substeps='auto'), or "
        "integrator='implicit_euler' (no spin limit, first order).", stable_dt=h_max,
        substeps=need)


def with_spin(sim, report, state):
    """``report`` (a :class:`diffpen.stability.StabilityReport`) with the start spin's limit
    (:func:`spin_step`) where it is the tighter one: its ``safe_dt``, ``safe_margin``,
    ``safe``, ``substeps_needed`` and ``limiting`` then say so."""
    from .stability.gating import _needed
    found = spin_step(sim, state)
    if found is None or found[0] >= report.safe_dt or not report.stable:
        return report           # (an unstable step's limit is said first)
    h_max, b, speed, kappa, limit = found
    return report._replace(
        safe_dt=h_max, safe_margin=h_max / report.inner_dt, safe=h_max >= report.inner_dt,
        substeps_needed=max(_needed(report.dt, h_max), report.substeps_needed),
        limiting_body=b, limiting=f"body {b}'s spin (|w| = {speed:.4g} rad/s, inertia "
        f"anisotropy kappa = {kappa:.3g}): {sim.integrator}'s spin limit kappa |w| h <= {limit}")


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
        ratio = ke / cap if cap > 0.0 else np.inf          # k = 0 stores nothing
        if ke > cap and (worst is None or ratio > worst[0]):
            # the stiffness that stores ke (every law's energy is linear in k)
            worst = (ratio, a, other, vn, mat, k, cap, ke, ke / float(law.energy(reach, 1.0)))

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
        ratio, i, other, vn, mat, k, cap, ke, k_need = worst
        kind = sim.scene.bodies[i].kind
        warn(
            f"{kind} {i} and {other} would meet at {vn:.3g} m/s: their contact (material "
            f"{mat!r}, k = {k:.3g}) stores at most {cap:.3g} J before their centres meet, and "
            f"they bring {ke:.3g} J: if they meet they pass through each other (a penalty "
            f"contact cannot stop them). Raise k above {k_need:.3g}, or slow them down.",
            ContactWarning)


def warn_spun_up(sim, traj, checked: bool, start=None) -> None:
    """Warn (:class:`diffpen.SpinWarning`) when a concrete rollout whose start passed the
    up-front checks (``checked``: its params within the safe step, its start spin within the
    limit) and whose ``start`` state's own ``aux["unstable"]`` flag was clear (a rollout
    continued from a flagged state keeps it) has the flag set: each step ors in whether a
    rigid body spins past its integrator's limit (:func:`diffpen.stepping._spin_flagged`),
    and nothing else sets it there. A torque spun the body up during the rollout."""
    from .params import _is_concrete
    from .stability import FLAG
    aux = getattr(traj, "aux", None)
    if not checked or not isinstance(aux, dict) or FLAG not in aux:
        return
    limit = spin_limit(sim) if np.any(sim._spin_kappa) else None
    if limit is None or not _is_concrete(aux[FLAG]):
        return                          # (under vmap the flag can be traced, alone)
    given = getattr(start, "aux", {}).get(FLAG) if start is not None else None
    # (host arrays: np.any of a jax array runs its own .any(), a program of its own)
    if given is not None and (not _is_concrete(given) or np.asarray(given).any()):
        return
    flag = np.asarray(aux[FLAG])
    if flag.ndim != 1 or not flag.any():
        return
    from .stability.gating import _down, _needed
    i = int(np.argmax(flag))
    fix = "Use a smaller dt or more substeps."
    w, q = getattr(traj, "angular_velocity", None), getattr(traj, "orientation", None)
    if w is not None and q is not None:        # the fastest saved spin says how much smaller
        w, q = np.asarray(w, float), np.asarray(q, float)
        rate = np.max(sim._spin_kappa * spin_speed(w, q, sim._moments))
        if np.isfinite(rate) and rate > 0.0:
            h_max = limit / rate
            fix = (f"Use dt <= {_down(h_max, 3):.3g} s (an inner step) or substeps >= "
                   f"{_needed(sim.dt, h_max)}, by its fastest saved spin.")
    warn(f"a rigid body spun past {sim.integrator}'s spin limit (kappa |w| h > {limit}, "
         f"diffpen.motion.SPIN_LIMITS) during the rollout, first by saved step {i} (t = "
         f"{float(np.asarray(traj.time)[i]):.4g} s): a torque spun it up after a start within "
         "the limit, and the integrator's energy error at that turn per step is in the "
         f"results from there (aux['unstable'] is set). {fix}", SpinWarning)


def spin_unsafe(sim, state, h: float):
    """Traced counterpart of :func:`check_spin`: a bool scalar, True when a rigid body of the
    (possibly traced, e.g. vmapped) start ``state`` spins past its integrator's spin limit
    (``kappa |w| h``, :data:`SPIN_LIMITS`), ``h`` the inner step in s. It joins the
    rollout's ``State.aux["unstable"]`` flag, so a sweep over start spins marks the rows a
    concrete rollout would refuse."""
    w = getattr(state, "angular_velocity", None)
    kappa = getattr(sim, "_spin_kappa", None)
    limit = None if w is None or kappa is None or not kappa.any() else spin_limit(sim)
    if limit is None:
        return jnp.zeros((), bool)
    w = jnp.asarray(w)
    speed = spin_speed(w, jnp.asarray(state.orientation), sim._moments, xp=jnp)
    rate = jnp.asarray(kappa, speed.dtype) * speed * h
    return jnp.any(rate > limit) | jnp.any(~jnp.isfinite(rate))
