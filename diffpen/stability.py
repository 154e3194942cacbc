"""Stable time steps of the integrators for a compiled scene, and the rollout gate.

For each integrator the largest stable step of ONE damped mode ``x'' = -K x - C v`` (K = w^2 in
1/s^2, C = 2 zeta w in 1/s) is computed from the integrator's own amplification matrix (the
method applied to that linear mode); the closed forms of physics-notes.md section 4 are its
special cases and are checked by the tests:

  semi_implicit_euler  K h^2 + 2 C h < 4  (k h^2 + 2 c h < 4 m; w h < 2 undamped; h < 2 m / c)
  verlet               w h < 2 undamped
  rk4                  w h < 2.83 undamped
  implicit_euler       unconditionally stable (no limit)

The scene's largest K and C come from Gershgorin bounds on ``M^-1 K`` and ``M^-1 C``
(physics-notes.md section 4, "spring networks"): for each free body i,
``(sum_j k_ij + sum_{j free} k_ij) / m_i`` over its springs, plus ONE contact spring (the
stiffest contact it can make: a plane, a fixed sphere, or another sphere, counted on both
rows). One contact per body is exact for a body on a floor, in a corner of mutually
orthogonal planes, or in a two-sphere collision; a sphere squeezed by several spheres at once
can need a smaller step (``packed_dt`` reports that bound, with up to 12 sphere neighbours).
Each force term carries its own rows of these bounds (a :class:`Bound` on its
:class:`diffpen.terms.Term`): this module only sums them, so a new term brings its bound with
it (the rigid-body terms' rows include rotation: a contact at a lever arm r adds about
k r^2 / I, up to ~3 k / m for a box corner). A term without a bound adds nothing.

Rollouts of explicit integrators are held to a *safe* step (``safe_dt``): the stability limit,
tightened to ``w_c h <= SAFE_WH = 0.5`` and ``C_c h <= SAFE_CH = 1`` for the contact springs
(w_c^2 = k / m, C_c = c / m of the stiffest contact of a body), because a penalty
contact that switches on or off between steps injects energy ~ (w h)^2 / 4 (see SAFE_WH).
Past it, ``Simulator.rollout`` raises StabilityError naming the safe step and the substeps
that reach it; ``substeps="auto"`` picks that count instead.

Traced stability: the same rows and limits are also evaluated inside the traced rollout
(:func:`unsafe`, with ``jax.numpy``), so a rollout under ``jax.jit``, ``jax.vmap`` or
``jax.grad`` (where the up-front check cannot see the parameter values) records in
``State.aux["unstable"]`` (``FLAG``) whether its step is past the safe step for the
parameter values it was given. The flag is sticky and saved in ``Trajectory.aux``.
"""
from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple

import numpy as np

from .errors import SceneError, StabilityError
from .integrators import Integrator, resolve

__all__ = ["mode_amplification", "mode_stable_dt", "stable_dt", "safe_dt", "SAFE_WH", "SAFE_CH",
           "Bound", "Analysis", "Rates", "rates", "scene_rates", "unsafe", "FLAG",
           "StabilityReport", "report", "gate", "GateCache", "MAX_AUTO_SUBSTEPS"]

#: ``substeps="auto"`` refuses to pick more inner steps than this (the run would be too slow).
MAX_AUTO_SUBSTEPS = 100_000

#: ``State.aux`` key of the traced stability flag: a bool scalar, True once a rollout ran a
#: step past the safe step for its parameter values (sticky).
FLAG = "unstable"


# --------------------------------------------------------------------------- one mode
def mode_amplification(integrator, K, C, h):
    """Amplification matrix (..., 2, 2) of one step of ``integrator`` (a name or an
    :class:`diffpen.integrators.Integrator`) on ``x'' = -K x - C v``.

    Args: K (1/s^2), C (1/s), h (s): arrays that broadcast. Maps (x, v) -> (x', v').
    It is the integrator record's own ``amplification`` (tests compare it against the JAX
    steps). Raises SceneError for methods without a step limit (no amplification).
    """
    rec = resolve(integrator)
    if rec.amplification is None:
        raise SceneError(f"integrator {rec.name!r} has no step limit (no amplification "
                         "matrix to analyse).")
    return rec.amplification(K, C, h)


def _spectral_radius(M):
    return np.max(np.abs(np.linalg.eigvals(M)), axis=-1)


def _spectral_radius_2x2(M, xp):
    """Spectral radius of (..., 2, 2) matrices from their trace and determinant (traceable)."""
    tr = M[..., 0, 0] + M[..., 1, 1]
    det = M[..., 0, 0] * M[..., 1, 1] - M[..., 0, 1] * M[..., 1, 0]
    disc = tr * tr - 4.0 * det
    root = xp.sqrt(xp.abs(disc))
    real = 0.5 * xp.maximum(xp.abs(tr + root), xp.abs(tr - root))
    return xp.where(disc >= 0.0, real, xp.sqrt(xp.abs(det)))


def mode_stable_dt(integrator, K: float, C: float) -> float:
    """Largest step h (s) for which ``integrator`` (a name or an
    :class:`diffpen.integrators.Integrator`) is stable on ``x'' = -K x - C v``.

    ``inf`` for methods without amplification (implicit) or a mode with K = C = 0. The
    integrator's closed form when it has one (semi-implicit Euler: exact), else found by
    bisection on the spectral radius of its amplification matrix (stable: radius <= 1 + 1e-9),
    starting from the closed-form undamped / pure-dashpot limits.
    """
    return _mode_stable_dt(resolve(integrator), float(K), float(C))


@functools.lru_cache(maxsize=4096)
def _mode_stable_dt(rec: Integrator, K: float, C: float) -> float:
    if rec.amplification is None or (K <= 0.0 and C <= 0.0):
        return math.inf
    if rec.stable_dt is not None:
        return float(rec.stable_dt(K, C))

    def unstable(h):
        return _spectral_radius(rec.amplification(K, C, h)) > 1.0 + 1e-9
    guess = min(2.0 / math.sqrt(K) if K > 0 else math.inf, 2.0 / C if C > 0 else math.inf)
    lo, hi = 0.0, guess
    while not unstable(hi):
        lo, hi = hi, 2.0 * hi
        if hi > 1e3 * guess:
            return math.inf
    # first crossing below hi: scan down in a fine log grid, then bisect
    grid = np.geomspace(guess * 1e-3, hi, 400)
    bad = _spectral_radius(rec.amplification(K, C, grid)) > 1.0 + 1e-9
    first = int(np.argmax(bad))
    lo, hi = (grid[first - 1] if first > 0 else 0.0), grid[first]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if unstable(mid):
            hi = mid
        else:
            lo = mid
    return lo


def stable_dt(integrator, K: float, C: float) -> float:
    """Largest stable step (s) of ``integrator`` for a scene whose largest mode rates are
    bounded by K (1/s^2) and C (1/s): the smallest of the mode limits at (K, C), (K, 0) and
    (0, C), since the stiffest and the most damped modes need not be the same."""
    cands = [mode_stable_dt(integrator, K, C)]
    if K > 0.0 and C > 0.0:
        cands += [mode_stable_dt(integrator, K, 0.0), mode_stable_dt(integrator, 0.0, C)]
    return min(cands)


#: Explicit integrators are held to ``w_c h <= SAFE_WH`` and ``C_c h <= SAFE_CH`` for the
#: contact springs (w_c^2 = k_contact / m, C_c = c_contact / m) besides linear stability.
#: Linear stability alone (w h < 2 for semi-implicit Euler) is not enough with penalty
#: contact: a contact switches on and off between steps, and the work done by a force held
#: over a step while the body crosses the contact boundary grows like
#: ``(w h)^2 / 4`` of the energy (measured on a ball at 10 m/s and on a ball released from a
#: full-radius overlap: 6% at w h = 0.5, 2% at 0.3, 0.2% at 0.1 for semi-implicit Euler, and
#: up to 470% for velocity Verlet at w h = 1.9). ``C h <= 1`` keeps dashpots from overshooting
#: (no velocity reversal within a step).
SAFE_WH = 0.5
SAFE_CH = 1.0


def safe_dt(integrator, Kc: float, Cc: float, stable: float) -> float:
    """Largest inner step (s) the rollout accepts: the stability limit ``stable`` (s),
    tightened for explicit integrators to ``sqrt(Kc) h <= SAFE_WH`` and ``Cc h <= SAFE_CH``
    where Kc (1/s^2), Cc (1/s) bound the contact springs alone (springs that never switch
    off need linear stability only)."""
    sdt, K, C = stable, Kc, Cc
    if not resolve(integrator).explicit:
        return sdt
    cands = [sdt]
    if K > 0.0:
        cands.append(SAFE_WH / math.sqrt(K))
    if C > 0.0:
        cands.append(SAFE_CH / C)
    return min(cands)


# --------------------------------------------------------------------------- scene bounds
def _value(x):
    """Concrete float array of a parameter value, or None when it is an abstract tracer."""
    import jax
    if isinstance(x, jax.core.Tracer):
        try:
            x = x.to_concrete_value()
        except Exception:  # noqa: BLE001 - any failure means "not concrete"
            return None
        if x is None:
            return None
    return np.asarray(x, dtype=float)


class Bound(NamedTuple):
    """Static rows of one force term's Gershgorin bounds on ``M^-1 K`` and ``M^-1 C``
    (physics-notes.md section 4), carried by the term (:class:`diffpen.terms.Term`).

    Row r adds ``k_weight[r] * k`` and ``c_weight[r] * c`` of its parameter to the stiffness
    (1/s^2) and damping (1/s) rows of body ``body[r]``.

    body: (m,) int body indices.
    param: ``"contact"`` (params.contact), ``"springs"`` (params.springs), or the name of a
      ``Params.extra`` entry whose values act as damping (``"friction"``: mu, with
      ``c_weight`` in 1/s per unit mu and no stiffness).
    names: the material / group names that ``key`` indexes.  key: (m,) int.
    k_weight, c_weight: (m,): dimensionless factors when ``per_mass`` (the row is divided by
      its body's mass), else mobilities in 1/kg that include rotation (``r^2 / I``).
    per_mass: see above.
    combine: ``"sum"`` (rows add), or ``"contact"``: one contact at a time: a body's contact
      rows of every term give their largest (the stiffest contact it can make), scaled by the
      contact law's stiffness at a reference depth, and counted in the contact rates that set
      the safe step (``SAFE_WH``).
    packed: (m,) multiplicities for the packed bound (every candidate neighbour touching at
      once; 0 for rows that stay one at a time), or None.
    labels: (m,) what each row is, in words (names the limit in reports).
    label: one text for all the rows of the block (their per-body sum names the limit), or
      None (then ``labels``).
    """
    body: np.ndarray
    param: str
    names: tuple
    key: np.ndarray
    k_weight: np.ndarray
    c_weight: np.ndarray
    per_mass: bool = True
    combine: str = "sum"
    packed: np.ndarray | None = None
    labels: tuple = ()
    label: str | None = None

    @staticmethod
    def of(rows, param: str, **kw) -> "Bound | None":
        """A Bound from rows ``(body, name, k_weight, c_weight, label)``, or None if empty."""
        if not rows:
            return None
        names = tuple(dict.fromkeys(r[1] for r in rows))
        packed = kw.pop("packed", None)
        return Bound(np.array([r[0] for r in rows], dtype=int), param, names,
                     np.array([names.index(r[1]) for r in rows], dtype=int),
                     np.array([r[2] for r in rows], dtype=float),
                     np.array([r[3] for r in rows], dtype=float),
                     packed=None if packed is None else np.asarray(packed, dtype=float),
                     labels=tuple(r[4] for r in rows), **kw)


class Analysis(NamedTuple):
    """Static data of one simulator's stability analysis (built by ``diffpen.compile``).

    integrator: :class:`diffpen.integrators.Integrator`.  dt: saved step, s.
    substeps: the simulator's inner steps per step (int), or "auto".
    mass: (n,) kg.  pinned: (n,) bool.  d_ref: (n,) m, reference penetration of each body
      (its radius, at least 1 mm) for contact laws whose stiffness grows with depth.
    bounds: every term's :class:`Bound` blocks, in term order.
    contact_scale: ``contact_scale(k, c, d) -> (k, c)``: the contact law's largest stiffness
      and damping for depths up to d (m) (``diffpen.laws.ContactLaw.stiffness``), or None.
    dtype: the simulator's float dtype.
    """
    integrator: Integrator
    dt: float
    substeps: Any
    mass: np.ndarray
    pinned: np.ndarray
    d_ref: np.ndarray
    bounds: tuple
    contact_scale: Callable | None
    dtype: Any

    @property
    def inner_dt(self) -> float:
        """dt / substeps (s), with one substep for "auto"."""
        return self.dt / (self.substeps if isinstance(self.substeps, int) else 1)


class Rates(NamedTuple):
    """Gershgorin rows per body: K_row (n,) 1/s^2 of ``M^-1 K``, C_row (n,) 1/s of
    ``M^-1 C``; Kc, Cc (n,) the contact parts alone; ``source(i)`` names what sets body i's
    stiffest entry (numpy evaluation only, else None)."""
    K_row: Any
    C_row: Any
    Kc: Any
    Cc: Any
    source: Callable | None


def _block_values(block: Bound, params, xp):
    """(k (p,) or None, c (p,)) of the block's parameters, each the max over any batch axis,
    or None when some value is abstract (numpy evaluation)."""
    if block.param == "contact":
        pairs = [params.contact[n] for n in block.names]
    elif block.param == "springs":
        pairs = [params.springs[n] for n in block.names]
    else:
        pairs = [(None, params.extra[block.param][n]) for n in block.names]
    ks, cs = [], []
    for k, c in pairs:
        if xp is np:
            c = _value(c)
            k = None if k is None else _value(k)
            if c is None or (k is None and block.param in ("contact", "springs")):
                return None
            cs.append(float(np.max(c)))
            if k is not None:
                ks.append(float(np.max(k)))
        else:
            cs.append(xp.max(xp.asarray(c)))
            if k is not None:
                ks.append(xp.max(xp.asarray(k)))
    return (xp.stack(ks) if xp is not np else np.array(ks)) if ks else None, \
        (xp.stack(cs) if xp is not np else np.array(cs))


def _at(xp, arr, idx, vals, op):
    if xp is np:
        (np.add if op == "add" else np.maximum).at(arr, idx, vals)
        return arr
    ref = arr.at[idx]
    return ref.add(vals) if op == "add" else ref.max(vals)


def rates(an: Analysis, params, *, xp=np, packed: bool = False) -> Rates | None:
    """Sum the terms' bounds for ``params``: :class:`Rates`, or None when some parameter is
    an abstract tracer (numpy evaluation).

    ``xp=jax.numpy`` evaluates the same rows on traced values (inside jit, vmap, grad);
    ``packed=True`` counts every candidate sphere neighbour (at most 12) instead of one.
    Pinned bodies have rows 0.
    """
    n = len(an.mass)
    zeros = (lambda: np.zeros(n)) if xp is np else (lambda: xp.zeros(n, an.dtype))
    cast = (lambda a: a) if xp is np else (lambda a: xp.asarray(a, an.dtype))
    kr, cr, ck, ccr, ek, ec = (zeros() for _ in range(6))
    spring_rows, contact_rows, grouped = [], [], {}
    contacts = []
    for block in an.bounds:
        vals = _block_values(block, params, xp)
        if vals is None:
            return None
        kv, cv = vals
        if xp is not np:
            kv = None if kv is None else cast(kv)
            cv = cast(cv)
        kk = None if kv is None else cast(block.k_weight) * kv[block.key]
        cc = cast(block.c_weight) * cv[block.key]
        if block.combine == "contact":
            if an.contact_scale is not None:
                kk, cc = an.contact_scale(kk, cc, cast(an.d_ref[block.body]))
            contacts.append((block, kk, cc))
            continue
        if block.per_mass:
            if kk is not None:
                kr = _at(xp, kr, block.body, kk, "add")
            cr = _at(xp, cr, block.body, cc, "add")
        else:
            if kk is not None:
                ek = _at(xp, ek, block.body, kk, "add")
            ec = _at(xp, ec, block.body, cc, "add")
        if xp is np and kk is not None:
            if block.label is not None:
                tot = grouped.setdefault(block.label, np.zeros(n))
                np.add.at(tot, block.body, kk)
            elif block.per_mass:
                spring_rows += [(int(b), float(v), lab)
                                for b, v, lab in zip(block.body, kk, block.labels)]
    # one contact at a time: the stiffest contact of each body; packed: every candidate
    # neighbour at once (rows with a multiplicity) on top of the stiffest other contact
    for block, kk, cc in contacts:
        keep = None if not packed or block.packed is None else block.packed == 0.0
        if keep is None:
            ck = _at(xp, ck, block.body, kk, "max")
            ccr = _at(xp, ccr, block.body, cc, "max")
        elif keep.any():
            ck = _at(xp, ck, block.body[keep], kk[keep], "max")
            ccr = _at(xp, ccr, block.body[keep], cc[keep], "max")
        if xp is np:
            contact_rows += [(int(b), float(v), lab)
                             for b, v, lab in zip(block.body, kk, block.labels)]
    if packed:
        for block, kk, cc in contacts:
            if block.packed is not None and (block.packed != 0.0).any():
                sel = block.packed != 0.0
                ck = _at(xp, ck, block.body[sel], (kk * cast(block.packed))[sel], "add")
                ccr = _at(xp, ccr, block.body[sel], (cc * cast(block.packed))[sel], "add")
    kr = kr + ck
    cr = cr + ccr
    mass = an.mass
    free = ~np.asarray(an.pinned)
    K_row = xp.where(free, kr / cast(mass), 0.0)
    C_row = xp.where(free, cr / cast(mass), 0.0)
    K_row = K_row + xp.where(free, ek, 0.0)
    C_row = C_row + ec
    free_mass = cast(np.where(free, mass, np.inf))
    if xp is not np:
        return Rates(K_row, C_row, ck / free_mass, ccr / free_mass, None)
    best_contact = ck
    best_spring = np.zeros(n)
    for b, v, _ in spring_rows:
        best_spring[b] = max(best_spring[b], v)

    def source(i: int) -> str:
        """What gives body i its stiffest row entry, in words."""
        for label, tot in grouped.items():
            if tot[i] * mass[i] > max(best_contact[i], best_spring[i]) and label:
                return label
        if contact_rows and best_contact[i] > best_spring[i]:
            rows = [r for r in contact_rows if r[0] == i]
            return max(rows, key=lambda r: r[1])[2]
        if spring_rows and best_spring[i] > 0.0:
            rows = [r for r in spring_rows if r[0] == i]
            return max(rows, key=lambda r: r[1])[2]
        return ""
    return Rates(K_row, C_row, ck / free_mass, ccr / free_mass, source)


def scene_rates(sim, params, *, packed: bool = False):
    """Gershgorin rows of ``M^-1 K`` (1/s^2) and ``M^-1 C`` (1/s) per body of a compiled
    simulator, or None when some parameter is an abstract tracer.

    Returns ``(K_row (n,), C_row (n,), source, Kc (n,), Cc (n,))`` (see :func:`rates`).
    """
    r = rates(sim.analysis, params, packed=packed)
    return None if r is None else (r.K_row, r.C_row, r.source, r.Kc, r.Cc)


def unsafe(an: Analysis, params, h=None):
    """Traced stability flag: a bool scalar, True when an inner step of ``h`` s (default the
    simulator's) is past the safe step for ``params`` (tracers welcome: jit, vmap, grad).

    The same rows as the up-front check (:func:`rates` with ``jax.numpy``) and the same
    limits: ``h >= min(stable_dt, SAFE_WH / w_c, SAFE_CH / C_c)``, the stability limit
    from the integrator's closed form when it has one (then it agrees with the up-front check
    to rounding), else from the spectral radius of its amplification matrix at ``h`` for the
    modes (K, C), (K, 0) and (0, C). Always False for methods without a step limit.
    """
    import jax
    import jax.numpy as jnp
    rec = an.integrator
    if not rec.explicit:
        return jnp.zeros((), bool)
    h = an.inner_dt if h is None else h
    params = jax.lax.stop_gradient(params)
    r = rates(an, params, xp=jnp)
    K, C = jnp.max(r.K_row, initial=0.0), jnp.max(r.C_row, initial=0.0)
    Kc, Cc = jnp.max(r.Kc, initial=0.0), jnp.max(r.Cc, initial=0.0)
    if rec.stable_dt is not None:
        sdt = rec.stable_dt(K, C, xp=jnp)
        sdt = jnp.where((K <= 0.0) & (C <= 0.0), jnp.inf, sdt)
        bad = sdt <= h
    else:
        Ks = jnp.stack([K, K, jnp.zeros_like(K)])
        Cs = jnp.stack([C, jnp.zeros_like(C), C])
        rho = _spectral_radius_2x2(rec.amplification(Ks, Cs, h, xp=jnp), jnp)
        bad = jnp.any(rho > 1.0 + 1e-9)
    wc = jnp.sqrt(Kc)
    bad = bad | ((Kc > 0.0) & (SAFE_WH / jnp.where(Kc > 0.0, wc, 1.0) <= h))
    bad = bad | ((Cc > 0.0) & (SAFE_CH / jnp.where(Cc > 0.0, Cc, 1.0) <= h))
    return bad


# --------------------------------------------------------------------------- report
class StabilityReport(NamedTuple):
    """Stability of a compiled scene for given parameters.

    integrator: name.  dt: saved step, s.  substeps: inner steps per saved step (int).
    inner_dt: dt / substeps, s.
    stable_dt: largest linearly stable inner step, s (inf: no limit).
    margin: stable_dt / inner_dt (> 1 stable; < 1 unstable).
    stable: margin > 1.
    safe_dt: largest inner step the rollout accepts, s: ``min(stable_dt, SAFE_WH / w_max,
      SAFE_CH / C)`` for explicit integrators (inf for implicit ones); see ``SAFE_WH``.
    safe_margin: safe_dt / inner_dt; rollout raises StabilityError when it is <= 1.
    safe: safe_margin > 1.
    substeps_needed: smallest substep count whose inner step is within safe_dt.
    omega_max: bound on the highest angular frequency sqrt(K), rad/s.
    damping_rate: bound on the largest C, 1/s.
    limiting_body: body index of the largest K row (None when no springs or contacts).
    limiting: what sets the limit, in words.
    packed_dt: stable step if a sphere touches all its candidate sphere neighbours at once.
    """
    integrator: str
    dt: float
    substeps: int
    inner_dt: float
    stable_dt: float
    margin: float
    stable: bool
    safe_dt: float
    safe_margin: float
    safe: bool
    substeps_needed: int
    omega_max: float
    damping_rate: float
    limiting_body: int | None
    limiting: str
    packed_dt: float

    def __str__(self) -> str:
        def fmt(x):
            return "no limit" if math.isinf(x) else f"{x:.4g} s"
        verdict = ("ok" if self.safe else "UNSTABLE" if not self.stable
                   else "stable but past the safe step")
        return (f"{self.integrator}: inner step {self.inner_dt:.4g} s; stable step "
                f"{fmt(self.stable_dt)} (margin {self.margin:.3g}); safe step "
                f"{fmt(self.safe_dt)} (margin {self.safe_margin:.3g}): {verdict}, needs "
                f"{self.substeps_needed} substep(s); w_max <= {self.omega_max:.4g} rad/s"
                + (f", set by {self.limiting}" if self.limiting else ""))


def _needed(dt: float, sdt: float) -> int:
    if math.isinf(sdt):
        return 1
    if sdt <= 0.0:
        return MAX_AUTO_SUBSTEPS + 1
    n = max(1, math.ceil(dt / sdt))
    while dt / n >= sdt:  # strict: a step equal to the limit is marginal, not stable
        n += 1
    return n


def _analysis(sim) -> Analysis:
    return sim if isinstance(sim, Analysis) else sim.analysis


def report(sim, params, *, substeps: int | None = None,
           packed: bool = True) -> StabilityReport | None:
    """Stability report of ``sim`` (a Simulator or its :class:`Analysis`) for ``params``
    (None when params are abstract tracers).

    ``substeps`` defaults to the simulator's (1 for ``"auto"``). ``packed=False`` skips the
    packed-spheres bound (``packed_dt`` is then ``stable_dt``).
    """
    an = _analysis(sim)
    r = rates(an, params)
    if r is None:
        return None
    K_row, C_row, source, Kc, Cc = r.K_row, r.C_row, r.source, r.Kc, r.Cc
    rec = an.integrator
    K, C = float(np.max(K_row, initial=0.0)), float(np.max(C_row, initial=0.0))
    sdt = stable_dt(rec, K, C)
    pdt = sdt
    if packed and any(b.packed is not None for b in an.bounds):
        pk = rates(an, params, packed=True)
        pdt = stable_dt(rec, float(np.max(pk.K_row, initial=0.0)),
                        float(np.max(pk.C_row, initial=0.0)))
    if substeps is None:
        substeps = an.substeps if isinstance(an.substeps, int) else 1
    h = an.dt / substeps
    margin = math.inf if math.isinf(sdt) else sdt / h
    safe = safe_dt(rec, float(np.max(Kc, initial=0.0)), float(np.max(Cc, initial=0.0)), sdt)
    safe_margin = math.inf if math.isinf(safe) else safe / h
    body = int(np.argmax(K_row)) if K > 0.0 else None
    return StabilityReport(rec.name, an.dt, substeps, h, sdt, margin, margin > 1.0,
                           safe, safe_margin, safe_margin > 1.0,
                           _needed(an.dt, safe), math.sqrt(K), C, body,
                           (f"{source(body)} on body {body}" if body is not None else ""),
                           pdt)


class GateCache:
    """Verdicts of the up-front check (:func:`gate`) per set of scalar parameter values, so
    a repeated rollout pays a dictionary look-up, not the analysis. An explicit object held
    by the simulator (``sim.gate_cache``); a traced rollout never reads it (abstract values
    have no key), so a traced program never depends on earlier calls.
    """

    def __init__(self, size: int = 1024):
        self.size = size
        self._verdicts: dict = {}

    def get(self, key):
        return None if key is None else self._verdicts.get(key)

    def put(self, key, n: int) -> None:
        if key is None:
            return
        if len(self._verdicts) >= self.size:
            self._verdicts.clear()
        self._verdicts[key] = n

    def __len__(self) -> int:
        return len(self._verdicts)


def gate(sim, params, *, check: bool = True, substeps: int | None = None,
         cache: GateCache | None = None) -> int:
    """The up-front check ``Simulator.rollout`` runs before tracing. Returns the substep
    count to use: ``substeps`` when given, the pick of ``substeps="auto"``, else the
    simulator's own count.

    Raises StabilityError when an explicit integrator would run past its safe step (fixed
    substeps), or when ``"auto"`` would need more than MAX_AUTO_SUBSTEPS. With abstract
    (jit-traced) parameters nothing is checked here (the traced flag :func:`unsafe` records
    it in the rollout instead) and ``"auto"`` raises a SceneError: under tracing the count
    must be given (``rollout(..., substeps=N)``). ``cache`` memoises verdicts per set of
    concrete scalar values.
    """
    an = _analysis(sim)
    auto = an.substeps == "auto" and substeps is None
    fixed = substeps if substeps is not None else (an.substeps if not auto else None)
    if not an.integrator.explicit:
        if check and np.dtype(an.dtype).itemsize < 8:
            _implicit_precision(an, params, fixed or 1)
        return fixed or 1
    if not (check or auto):
        return fixed
    key = _scalar_key(params)
    key = None if key is None else (fixed, key)
    if cache is not None:
        hit = cache.get(key)
        if hit is not None:
            return hit
    n = _gate(an, params, auto, fixed)
    if cache is not None:
        cache.put(key, n)
    return n


#: implicit_euler in a float dtype of machine epsilon eps needs (w h)^2 eps <= this: past it the
#: identity in (I - h A_v - h^2 A_x) is lost to rounding and a free body's matrix is singular.
IMPLICIT_PRECISION = 0.1


def _implicit_precision(an: Analysis, params, substeps: int) -> None:
    """Raise StabilityError when implicit_euler's linear system cannot be resolved in the
    simulator's dtype (float32 with a very stiff, light body and a large step)."""
    r = rates(an, params)
    if r is None:
        return
    K = float(np.max(r.K_row, initial=0.0))
    eps = float(np.finfo(np.dtype(an.dtype)).eps)
    h = an.dt / substeps
    if K * h * h * eps <= IMPLICIT_PRECISION:
        return
    h_ok = math.sqrt(IMPLICIT_PRECISION / (eps * K))
    n = _needed(an.dt, h_ok)
    raise StabilityError(
        f"{an.integrator.name} cannot resolve this system in {np.dtype(an.dtype).name}: "
        f"(w h)^2 = {K * h * h:.3g} swamps the identity at machine epsilon {eps:.2g} (the "
        f"matrix is singular in rounding). Use dtype=float64, or a step <= {h_ok:.3g} s "
        f"(substeps={n}).", stable_dt=h_ok, substeps=n)


def _scalar_key(params):
    """Tuple of the float values of every parameter (contact, springs, extra), or None
    (arrays, abstract tracers)."""
    import jax
    try:
        return tuple(float(v) for v in jax.tree_util.tree_leaves(params))
    except Exception:  # noqa: BLE001 - non-scalar or abstract: take the slow path
        return None


def _gate(an: Analysis, params, auto: bool, fixed: int | None) -> int:
    rep = report(an, params, packed=False, substeps=fixed)
    if rep is None:
        if not auto:
            return fixed
        raise SceneError(
            "substeps='auto' picks the substep count from concrete k and c, but rollout "
            "was traced with abstract parameters (inside jax.jit, vmap or grad). Give the "
            "count: sim.rollout(params, steps, substeps=N) with N = "
            "sim.stability(concrete_params).substeps_needed, or compile with substeps=N; "
            "the rollout's State.aux['unstable'] flag then says whether N was enough.")
    if auto:
        n = rep.substeps_needed
        if n > MAX_AUTO_SUBSTEPS:
            raise StabilityError(
                f"substeps='auto' would need {n} substeps per step of dt={an.dt:g} s "
                f"(safe step {rep.safe_dt:.3g} s, {rep.limiting}): too slow. Lower the "
                "stiffness, raise the mass, or use integrator='implicit_euler'.",
                stable_dt=rep.safe_dt, substeps=n)
        return n
    if not rep.safe:
        why = ("unstable" if not rep.stable else
               f"stable but past its safe step for contact (w_c h = "
               f"{SAFE_WH * rep.inner_dt / rep.safe_dt:.3g} > {SAFE_WH}: contact energy "
               "errors of several % or more)")
        raise StabilityError(
            f"integrator {an.integrator.name!r} is {why} at step {rep.inner_dt:.4g} s: the "
            f"largest safe step is {rep.safe_dt:.4g} s (linear stability limit "
            f"{rep.stable_dt:.4g} s; w_max <= {rep.omega_max:.4g} rad/s, set by "
            f"{rep.limiting or 'the springs and contacts'}). Use dt <= {rep.safe_dt:.3g} s, "
            f"compile with substeps={rep.substeps_needed} (or substeps='auto'), or "
            "integrator='implicit_euler'.",
            stable_dt=rep.safe_dt, substeps=rep.substeps_needed)
    return fixed
