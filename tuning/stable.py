"""The stability limit of a rollout as tuning reads it, and the contact bounds that keep
optimisers inside it. The limits' constants come from :mod:`diffpen.stability`; the contact
bounds (:func:`safe_contact_limits`, :func:`implicit_contact_limits`) are those limits solved
for the largest k and c at a given step, so a change to a limit there must be made here
too.

diffpen carries ``State.aux["unstable"]`` (``FLAG``: a sticky bool scalar set inside the traced
program when a step was past the safe step for the traced parameter values, or when an
``implicit_euler`` iterative solve missed its system; "past its safe step" below and in the
modules that read it means either), so
``traj.aux["unstable"][-1]`` says whether a rollout can be trusted; it works under ``jit``,
``vmap`` and ``grad``. :func:`rollout_unstable` returns it; for a trajectory without the flag
it falls back to :func:`params_unstable`, the same test (:func:`diffpen.stability.unsafe`)
evaluated on the parameters alone. :func:`safe_contact_bounds` inverts the contact part of the
safe step (``w h <= SAFE_WH``, ``c h / m <= SAFE_CH``) into bounds on one contact's k and c.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from diffpen import laws as _dp_laws
from diffpen import stability as _dp_stability
from diffpen.integrators import solves_iteratively
from diffpen.stability.bounds import IMPLICIT_PRECISION, RESTING_RESOLUTION
from diffpen.stability.depth import energy_depth

from .errors import FitError

__all__ = ["FLAG", "rollout_unstable", "params_unstable", "contact_unstable",
           "unsafe_start", "start_energy", "contact_scales", "law_k", "law_c", "law_units",
           "safe_contact_limits", "safe_contact_bounds", "implicit_contact_limits"]

#: key of the flag in ``State.aux`` / ``Trajectory.aux``
FLAG = _dp_stability.FLAG


def _light_mass(sim) -> float:
    """Mass (kg) of the lightest movable body of ``sim`` (of any body if all are pinned)."""
    an = sim.analysis
    m = np.asarray(an.mass, float)[~np.asarray(an.pinned, bool)]
    return float(m.min()) if m.size else float(np.asarray(an.mass).min())


def start_energy(sim, state, params=None) -> float | None:
    """The energy (J) with which a rollout of ``sim`` from ``state`` bounds the reference
    depth of a contact that stiffens with depth (:mod:`diffpen.stability.depth`, as
    ``sim.rollout(params, steps, state)`` counts it), or None: no state given, the law's
    stiffness does not grow with depth, the scene does not qualify, the state is traced, a
    body starts in contact, or a named plane's offset is not given by ``params`` (then the
    bodies' radii bound the depth). ``state`` may also be a batch of start states (a State
    whose leaves have a leading axis, as :class:`tuning.record_batch.Batch` ``start``) or a
    list of such batches: the largest of their energies (None if any is None)."""
    if state is None:
        return None
    if isinstance(state, (list, tuple)) and not hasattr(state, "_fields"):
        parts = [start_energy(sim, s, params) for s in state]
        return None if not parts or any(e is None for e in parts) else max(parts)
    if np.ndim(state.position) == 3:             # a batch: one start state per record
        leaves = jax.tree_util.tree_leaves(state)
        if any(isinstance(a, jax.core.Tracer) for a in leaves):
            return None
        state = jax.tree_util.tree_map(np.asarray, state)    # one transfer, then rows
        rows = [jax.tree_util.tree_map(lambda a, i=i: a[i], state)
                for i in range(np.shape(state.position)[0])]
        return start_energy(sim, rows, params)
    return sim.start_energy(state, params)


def params_unstable(sim, params, state=None):
    """Traceable bool: an inner step of ``sim`` is past its safe step for ``params``
    (:func:`diffpen.stability.unsafe` on the simulator's own stability analysis: every term's
    bound, the integrator's limit, the contact limits ``SAFE_WH`` / ``SAFE_CH``), or some
    contact k or c is not finite. Always False for integrators without a step limit (besides
    the non-finite test). Parameters may be tracers (jit, vmap, grad).

    ``state``: the concrete start state of the rollouts judged (e.g. ``sim.init_state()``):
    a Hunt-Crossley contact's stiffness is then counted at the depth where it would store
    twice that state's energy, as a rollout from it counts it (:func:`start_energy`);
    default None: at the bodies' radii (conservative for any start).

    A scalar for scalar contact values; contact k or c given as (N,) arrays (N points, e.g. a
    sweep's) give (N,) flags, one per point."""
    if any(jnp.ndim(x) for cp in params.contact.values() for x in cp):
        axes = params._replace(
            contact={n: type(cp)(*(0 if jnp.ndim(x) else None for x in cp))
                     for n, cp in params.contact.items()},
            springs=None, extra=None)
        return jax.vmap(lambda p: params_unstable(sim, p, state), in_axes=(axes,))(params)
    bad = _dp_stability.unsafe(sim.analysis, params, energy=start_energy(sim, state, params))
    for cp in params.contact.values():
        bad = bad | ~jnp.all(jnp.isfinite(jnp.asarray(cp.k))) | ~jnp.all(
            jnp.isfinite(jnp.asarray(cp.c)))
    return bad


#: the former name of :func:`params_unstable` (kept: scripts and the sweep CLI use it)
contact_unstable = params_unstable


def rollout_unstable(sim, traj, params):
    """Traceable bool scalar: the rollout went past its safe step.

    ``traj.aux["unstable"][-1]`` when the trajectory carries the flag, else
    :func:`params_unstable` of ``params``."""
    aux = getattr(traj, "aux", None) or {}
    if FLAG in aux:
        return jnp.asarray(aux[FLAG])[-1].astype(bool)
    return params_unstable(sim, params)


def safe_contact_limits(h: float, mass: float,
                        wh: float | None = None) -> tuple[float, float]:
    """Upper bounds (k_max N/m, c_max N s/m) of one contact on a body of ``mass`` kg that keep
    an explicit inner step of ``h`` s inside the safe step of :mod:`diffpen.stability`, with a
    1% margin: ``sqrt(k / m) h <= wh`` (default ``SAFE_WH``; a simulator's own is its
    ``analysis.contact_wh``) and ``c h / m <= SAFE_CH`` (these also keep the step linearly
    stable: ``k h^2 + 2 c h < 4 m``)."""
    h, m = float(h), float(mass)
    wh = _dp_stability.SAFE_WH if wh is None else float(wh)
    return (0.99 * (wh / h) ** 2 * m, 0.99 * _dp_stability.SAFE_CH * m / h)


def implicit_contact_limits(sim, mass: float | None = None) -> tuple[float, float]:
    """Upper bounds (k_max N/m, c_max N s/m) of one linear contact that an implicit
    integrator of ``sim`` resolves in its float dtype, with a 1% margin: the precision limits
    of :mod:`diffpen.stability` (``IMPLICIT_PRECISION``, ``RESTING_RESOLUTION``), i.e.
    ``(k / m) h^2 eps <= IMPLICIT_PRECISION`` at the inner step ``h`` (s) and, under gravity
    ``g`` (m/s^2), a static deflection ``m g / k >= RESTING_RESOLUTION eps d`` (``d`` the
    body's reference size in m, ``eps`` the dtype's machine epsilon). ``mass`` (kg) is the
    body's (then ``d`` is the largest reference size of the movable bodies); by default every
    movable body is checked and the tightest bound kept. Damping has no precision limit
    (``c_max`` inf); both are inf in float64."""
    an = sim.analysis
    dtype = np.dtype(an.dtype)
    if dtype.itemsize >= 8:
        return math.inf, math.inf
    eps = float(np.finfo(dtype).eps)
    free = ~np.asarray(an.pinned, bool)
    if not free.any():
        free = np.ones_like(free)
    masses = np.asarray(an.mass, float)[free]
    sizes = np.asarray(an.d_ref, float)[free]
    if mass is not None:
        masses, sizes = np.array([float(mass)]), np.array([float(np.max(sizes))])
    h = an.inner_dt
    k_max = float(np.min(masses)) * IMPLICIT_PRECISION / (eps * h * h)
    if an.gravity > 0.0:
        k_max = min(k_max, float(np.min(
            masses * an.gravity / (RESTING_RESOLUTION * eps * sizes))))
    return 0.99 * k_max, math.inf


def safe_contact_bounds(sim, mass: float | None = None, *, state=None,
                        k_min: float | None = None, params=None) -> tuple[float, float]:
    """:func:`safe_contact_limits` at the inner step of ``sim`` for a body of ``mass`` kg
    (default: the lightest movable body), in the units of the simulator's contact law: a law
    whose stiffness grows with depth (Hunt-Crossley, ``k`` N/m^n, ``c`` N s/m^(n+1)) has the
    limits divided by its stiffness and damping at the deepest reference depth of the
    analysis (``ContactLaw.stiffness``, as :mod:`diffpen.stability` counts it). Integrators
    without a step limit (implicit) get :func:`implicit_contact_limits` instead: the
    stiffness their float dtype resolves (``(inf, inf)`` in float64).

    ``state``: the concrete start state of the rollouts bounded (e.g. ``sim.init_state()``).
    Where its energy bounds the depth (:func:`start_energy`) the reference depth is the one
    at which a contact of stiffness ``k`` stores twice that energy (never deeper than the
    radius), as a rollout from ``state`` counts it: ``k_max`` is then the largest ``k``
    whose stiffness at its own depth is inside the step (found by bisection; the stiffness
    grows with ``k``), and ``c_max`` takes the depth of ``k_min`` (N/m^n; the smallest
    stiffness the bound must hold for: the softest contact sinks deepest; default: the
    radius). Default None: the radii (conservative for any start). ``state`` may be a
    batch of start states (:func:`start_energy`: the largest energy counts); ``params``
    gives a named plane's offset (without it a named plane keeps the radii)."""
    an = sim.analysis
    if not an.integrator.explicit:
        k_max, c_max = implicit_contact_limits(sim, mass)
        if math.isinf(k_max):
            return math.inf, math.inf
    else:
        k_max, c_max = safe_contact_limits(an.inner_dt,
                                           _light_mass(sim) if mass is None else mass,
                                           an.contact_wh)
    if an.contact_scale is not None:
        if not an.integrator.explicit:
            state = None
        c_scale = (contact_scales(sim, k_min, state=state, params=params)[1]
                   if k_min and k_min > 0.0 else contact_scales(sim, 0.0)[1])
        return law_k(sim, k_max, state=state, params=params), c_max / c_scale
    return k_max, c_max


def _reference(sim, state, params=None) -> tuple[float, float | None]:
    """``(d_ref, energy)``: the deepest reference depth of the movable bodies (m) and the
    start energy of ``state`` (J, :func:`start_energy`; None: the depth is ``d_ref``)."""
    an = sim.analysis
    free = ~np.asarray(an.pinned)
    d = float(np.max(np.asarray(an.d_ref)[free])) if free.any() else 1.0
    energy = start_energy(sim, state, params) if an.depth_exponent is not None else None
    return d, energy


def _scales_at(an, k: float, d_ref: float, energy: float | None) -> tuple[float, float]:
    """:func:`contact_scales` given the reference radius ``d_ref`` (m) and the start energy
    (J, or None)."""
    d = d_ref
    if energy is not None and k > 0.0:
        d = min(d, float(energy_depth(an.depth_exponent, np.float64(k), energy)))
    return tuple(float(x) for x in an.contact_scale(1.0, 1.0, d))


def contact_scales(sim, k: float, *, state=None, params=None) -> tuple[float, float]:
    """The factors ``(stiffness / k, damping / c)`` of ``sim``'s contact law for a contact of
    stiffness ``k`` (the law's units) at its reference depth, as the safe step counts them
    (``ContactLaw.stiffness``): 1 and 1 for the linear laws; for Hunt-Crossley
    ``(n d^(n-1), d^n)`` at the depth ``d`` where the contact would store twice the energy of
    ``state`` (:func:`start_energy`; never deeper than the bodies' largest radius, which is
    the depth without a state or for ``k`` 0)."""
    return _scales_at(sim.analysis, k, *_reference(sim, state, params))


def law_units(law, exponent: float = 1.0) -> tuple[str, str]:
    """Units of a contact law's k and c (``law`` a record or a name, ``exponent`` for
    ``"hunt_crossley"``): ``F = k d^n - c vn d^m`` has k in N/m^n and c in N s/m^(m+1) (N/m
    and N s/m for the linear laws)."""
    rec = _dp_laws.get(law or "linear", exponent)
    n, m = float(rec.exponent), float(rec.damping_exponent)
    return ("N/m" if n == 1.0 else f"N/m^{n:g}", "N s/m" if m == 0.0 else f"N s/m^{m + 1:g}")


def law_k(sim, stiffness: float, *, state=None, params=None) -> float:
    """The largest stiffness ``k`` in the units of ``sim``'s contact law (Hunt-Crossley
    N/m^n) whose stiffness at its reference depth (:func:`contact_scales`) is at most
    ``stiffness`` N/m: ``stiffness`` itself for the linear laws; at the radius a division;
    with a ``state`` whose energy bounds the depth, bisection on log k (the stiffness grows
    with k)."""
    an = sim.analysis
    d_ref, energy = _reference(sim, state, params)      # the start energy, once
    k_rad = stiffness / _scales_at(an, 0.0, d_ref, None)[0]   # at the radius: the bound holds
    if energy is None:
        return k_rad

    def fits(k):
        return k * _scales_at(an, k, d_ref, energy)[0] <= stiffness
    if not fits(k_rad):
        return k_rad
    lo = hi = k_rad
    while fits(hi) and hi < 1e30:
        lo, hi = hi, hi * 10.0
    for _ in range(80):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


def law_c(sim, damping: float, k: float, *, state=None, params=None) -> float:
    """The damping ``c`` in the units of ``sim``'s contact law (Hunt-Crossley N s/m^(n+1))
    that damps a contact of stiffness ``k`` (its units) by ``damping`` N s/m at its
    reference depth (:func:`contact_scales`)."""
    return damping / contact_scales(sim, k, state=state, params=params)[1]


def solver_miss(sim) -> str:
    """The words messages about ``sim``'s FLAG add for its other cause: ``""`` unless ``sim``
    has a rigid body with a spin limit (each step flags a spin past it) or solves its implicit
    steps by GMRES or CG (:func:`diffpen.integrators.solves_iteratively`), whose missed solve
    sets the flag too and which a smaller step or softer contact may not cure; then a clause
    naming that cause and its remedy."""
    if sim is None:
        return ""
    from diffpen.motion import spin_limit
    if np.any(getattr(sim, "_spin_kappa", 0.0)) and spin_limit(sim) is not None:
        # each step flags a rigid body spun past its integrator's limit (diffpen.motion)
        return (" (or a rigid body spun past its integrator's spin limit, "
                "diffpen.motion.SPIN_LIMITS: a smaller dt or more substeps cures that too)")
    if not solves_iteratively(sim.analysis.integrator, 3 * sim.n_bodies,
                              rigid=sim.scene.has_rotation):
        return ""
    return (" (or its iterative implicit solve missed its system: compile with "
            "integrator=diffpen.integrators.implicit_euler_with('dense'), which solves "
            "exactly)")


def unsafe_start(start, dt: float | None = None, sim=None) -> FitError:
    """The error of a fit whose start point is past the simulator's safe step: ``start`` is
    ``{leaf name: value}`` (None: every candidate start is past it or blows up), ``dt`` the
    step (s) if known, ``sim`` the simulator if known (:func:`solver_miss`)."""
    what = ("every start point blows up or is" if start is None
            else f"the start point {dict(start)} is")
    at = "" if dt is None else f" at dt = {dt:g} s"
    return FitError(f"{what} past the safe step{at}{solver_miss(sim)}; past the simulator's "
                    "safe step no rollout is a result (sim.stability(params) says what limits "
                    "it): start from softer k / smaller c, or use a smaller dt or more "
                    "substeps.")
