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
Force terms added by extensions are not included unless they append a function to
``EXTRA_BOUNDS``; in particular the rotational modes of rigid bodies (a contact at a lever arm
r adds about k r^2 / I, up to ~3 k / m for a box corner) are not bounded here.

Rollouts of explicit integrators are held to a *safe* step (``safe_dt``): the stability limit,
tightened to ``w_c h <= SAFE_WH = 0.5`` and ``C_c h <= SAFE_CH = 1`` for the contact springs
(w_c^2 = k / m, C_c = c / m of the stiffest contact of a body), because a penalty
contact that switches on or off between steps injects energy ~ (w h)^2 / 4 (see SAFE_WH).
Past it, ``Simulator.rollout`` raises StabilityError naming the safe step and the substeps
that reach it; ``substeps="auto"`` picks that count instead.
"""
from __future__ import annotations

import functools
import math
from typing import Callable, NamedTuple

import numpy as np

from .errors import SceneError, StabilityError
from .integrators import IMPLICIT

__all__ = ["mode_amplification", "mode_stable_dt", "stable_dt", "safe_dt", "SAFE_WH", "SAFE_CH",
           "scene_rates",
           "StabilityReport", "report", "gate", "EXTRA_BOUNDS", "MAX_AUTO_SUBSTEPS"]

#: Hooks ``f(sim, params) -> (K_row (n,), C_row (n,))`` (1/s^2, 1/s) added to the core bounds;
#: a hook's ``label`` attribute names it in reports when it sets a body's limit.
EXTRA_BOUNDS: list[Callable] = []

#: ``substeps="auto"`` refuses to pick more inner steps than this (the run would be too slow).
MAX_AUTO_SUBSTEPS = 100_000

_KISSING = 12  # most equal spheres that can touch one sphere at once


# --------------------------------------------------------------------------- one mode
def mode_amplification(integrator: str, K, C, h):
    """Amplification matrix (..., 2, 2) of one step of ``integrator`` on ``x'' = -K x - C v``.

    Args: K (1/s^2), C (1/s), h (s): arrays that broadcast. Maps (x, v) -> (x', v').
    Mirrors diffpen.integrators exactly (tests compare against the JAX steps).
    """
    K, C, h = np.broadcast_arrays(np.asarray(K, float), np.asarray(C, float),
                                  np.asarray(h, float))
    A = np.zeros(K.shape + (2, 2))
    A[..., 0, 1] = 1.0
    A[..., 1, 0] = -K
    A[..., 1, 1] = -C
    eye = np.broadcast_to(np.eye(2), A.shape)
    hA = h[..., None, None] * A
    if integrator == "semi_implicit_euler":
        # v' = v + h a(x, v); x' = x + h v'
        kick = eye + h[..., None, None] * (A * np.array([[0, 0], [1, 1]]))
        drift = eye + h[..., None, None] * np.array([[0.0, 1.0], [0.0, 0.0]])
        return drift @ kick
    if integrator == "verlet":
        # v+ = v + h/2 a(x, v); x' = x + h v+; v' = v+ + h/2 a(x', 2 v+ - v)
        out = np.zeros(K.shape + (2, 2))
        for col, (x, v) in enumerate(((1.0, 0.0), (0.0, 1.0))):
            vh = v + 0.5 * h * (-K * x - C * v)
            x1 = x + h * vh
            v1 = vh + 0.5 * h * (-K * x1 - C * (2.0 * vh - v))
            out[..., 0, col] = x1
            out[..., 1, col] = v1
        return out
    if integrator == "rk4":
        hA2 = hA @ hA
        hA3 = hA2 @ hA
        return eye + hA + hA2 / 2.0 + hA3 / 6.0 + hA3 @ hA / 24.0
    if integrator == "implicit_euler":
        # (I - h A_v - h^2 A_x) dv = h (a + h A_x v); x' = x + h v'
        Kx, Cv = -K, -C
        denom = 1.0 - h * Cv - h * h * Kx
        out = np.zeros(K.shape + (2, 2))
        # dv = h (Kx x + Cv v + h Kx v) / denom
        dvx = h * Kx / denom
        dvv = h * (Cv + h * Kx) / denom
        out[..., 1, 0] = dvx
        out[..., 1, 1] = 1.0 + dvv
        out[..., 0, 0] = 1.0 + h * dvx
        out[..., 0, 1] = h * (1.0 + dvv)
        return out
    raise SceneError(f"no stability analysis for integrator {integrator!r}.")


def _spectral_radius(M):
    return np.max(np.abs(np.linalg.eigvals(M)), axis=-1)


@functools.lru_cache(maxsize=4096)
def mode_stable_dt(integrator: str, K: float, C: float) -> float:
    """Largest step h (s) for which ``integrator`` is stable on ``x'' = -K x - C v``.

    ``inf`` for implicit integrators or a mode with K = C = 0. Found by bisection on the
    spectral radius of :func:`mode_amplification` (stable: radius <= 1 + 1e-9), starting from
    the closed-form undamped / pure-dashpot limits; exact for semi-implicit Euler.
    """
    K, C = float(K), float(C)
    if integrator in IMPLICIT or (K <= 0.0 and C <= 0.0):
        return math.inf
    if integrator == "semi_implicit_euler":
        if K <= 0.0:
            return 2.0 / C
        return (-C + math.sqrt(C * C + 4.0 * K)) / K      # K h^2 + 2 C h = 4

    def unstable(h):
        return _spectral_radius(mode_amplification(integrator, K, C, h)) > 1.0 + 1e-9
    guess = min(2.0 / math.sqrt(K) if K > 0 else math.inf, 2.0 / C if C > 0 else math.inf)
    lo, hi = 0.0, guess
    while not unstable(hi):
        lo, hi = hi, 2.0 * hi
        if hi > 1e3 * guess:
            return math.inf
    # first crossing below hi: scan down in a fine log grid, then bisect
    grid = np.geomspace(guess * 1e-3, hi, 400)
    bad = _spectral_radius(mode_amplification(integrator, K, C, grid)) > 1.0 + 1e-9
    first = int(np.argmax(bad))
    lo, hi = (grid[first - 1] if first > 0 else 0.0), grid[first]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if unstable(mid):
            hi = mid
        else:
            lo = mid
    return lo


def stable_dt(integrator: str, K: float, C: float) -> float:
    """Largest stable step (s) of ``integrator`` for a scene whose largest mode rates are
    bounded by K (1/s^2) and C (1/s): the smallest of the mode limits at (K, C), (K, 0) and
    (0, C), since the stiffest and the most damped modes need not be the same."""
    cands = [mode_stable_dt(integrator, K, C)]
    if K > 0.0 and C > 0.0:
        cands += [mode_stable_dt(integrator, K, 0.0), mode_stable_dt(integrator, 0.0, C)]
    return min(cands)


#: Explicit integrators are held to ``w_c h <= SAFE_WH`` and ``C_c h <= SAFE_CH`` for the
#: contact springs (w_c^2 = k_contact / m, C_c = c_contact / m) besides linear stability. Linear stability alone (w h < 2 for semi-implicit Euler) is not enough
#: with penalty contact: a contact switches on and off between steps, and the work done by a
#: force held over a step while the body crosses the contact boundary grows like
#: ``(w h)^2 / 4`` of the energy (measured on a ball at 10 m/s and on a ball released from a
#: full-radius overlap: 6% at w h = 0.5, 2% at 0.3, 0.2% at 0.1 for semi-implicit Euler, and
#: up to 470% for velocity Verlet at w h = 1.9). ``C h <= 1`` keeps dashpots from overshooting
#: (no velocity reversal within a step).
SAFE_WH = 0.5
SAFE_CH = 1.0


def safe_dt(integrator: str, Kc: float, Cc: float, stable: float) -> float:
    """Largest inner step (s) the rollout accepts: the stability limit ``stable`` (s),
    tightened for explicit integrators to ``sqrt(Kc) h <= SAFE_WH`` and ``Cc h <= SAFE_CH``
    where Kc (1/s^2), Cc (1/s) bound the contact springs alone (springs that never switch
    off need linear stability only)."""
    sdt, K, C = stable, Kc, Cc
    if integrator in IMPLICIT:
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


class _Structure(NamedTuple):
    """Static part of the bounds, built once per simulator: rows are contributions."""
    spring_rows: tuple      # (body (m,), group index (m,), factor (m,))
    contact_rows: tuple     # (body, material index, factor, label index, neighbour count)
    labels: list            # text of each source
    spring_labels: list
    d_ref: np.ndarray       # (n,) m, Hunt-Crossley reference penetration


def _structure(sim) -> _Structure:
    cached = getattr(sim, "_stability_structure", None)
    if cached is not None:
        return cached
    scene = sim.scene
    n = sim.n_bodies
    pinned = np.asarray(sim.pinned)
    radius = np.asarray(sim.radius, float)
    groups = list(sim.spring_groups)
    sb, sg, sf = [], [], []
    for s in scene.springs:
        ends = [s.a] if s.b is None else [s.a, s.b]
        both_free = s.b is not None and not pinned[s.a] and not pinned[s.b]
        for i in ends:
            if not pinned[i]:
                sb.append(i)
                sg.append(groups.index(s.group))
                sf.append(2.0 if both_free else 1.0)
    mats = list(sim.materials)
    labels: list[str] = []
    cb, cm, cf, cl = [], [], [], []
    collide = np.array([b.collide for b in scene.bodies])
    terms = set(sim.terms)

    cmult = []

    def add(i, mat, factor, label, mult=1):
        cb.append(i)
        cm.append(mats.index(mat))
        cf.append(factor)
        cl.append(len(labels))
        cmult.append(mult)
        labels.append(label)
    for i in range(n):
        if pinned[i] or not collide[i]:
            continue
        if "contact_plane" in terms:
            for p_i, pl in enumerate(scene.planes):
                add(i, pl.material, 1.0, f"contact with plane {p_i} (material {pl.material!r})")
        if "contact_fixed_sphere" in terms:
            for s_i, fs in enumerate(scene.fixed_spheres):
                add(i, fs.material, 1.0,
                    f"contact with fixed sphere {s_i} (material {fs.material!r})")
    if "contact_sphere_sphere" in terms:
        # O(n): a sphere's candidate partners are the other colliding spheres; a pair uses
        # their shared material, else "default"; counted twice (both rows) when both are free
        from .scene import DEFAULT
        spheres = [i for i in range(n) if collide[i] and radius[i] > 0.0
                   and scene.bodies[i].kind == "sphere"]
        count, free_count = {}, {}
        for i in spheres:
            m = scene.bodies[i].material
            count[m] = count.get(m, 0) + 1
            free_count[m] = free_count.get(m, 0) + (0 if pinned[i] else 1)
        total, total_free = len(spheres), sum(free_count.values())
        for i in spheres:
            if pinned[i]:
                continue
            m = scene.bodies[i].material
            same, same_free = count[m] - 1, free_count[m] - 1
            other, other_free = total - count[m], total_free - free_count[m]
            n_same = min(same, _KISSING)
            if same > 0:
                add(i, m, 2.0 if same_free > 0 else 1.0,
                    f"contact between sphere {i} and another sphere (material {m!r})", n_same)
            if other > 0:
                add(i, DEFAULT, 2.0 if other_free > 0 else 1.0,
                    f"contact between sphere {i} and a sphere of another material",
                    min(other, _KISSING - n_same))
    arr = lambda x, t=float: np.array(x, dtype=t)  # noqa: E731
    out = _Structure((arr(sb, int), arr(sg, int), arr(sf)),
                     (arr(cb, int), arr(cm, int), arr(cf), arr(cl, int), arr(cmult)), labels,
                     [f"spring group {g!r}" for g in groups], np.maximum(radius, 1e-3))
    sim._stability_structure = out
    return out


def _values(pairs: list):
    """(k (m,), c (m,)) max over any batch axis, or None when some value is abstract."""
    ks, cs = [], []
    for k, c in pairs:
        k, c = _value(k), _value(c)
        if k is None or c is None:
            return None
        ks.append(float(np.max(k)))
        cs.append(float(np.max(c)))
    return np.array(ks), np.array(cs)


def scene_rates(sim, params, *, packed: bool = False):
    """Gershgorin rows of ``M^-1 K`` (1/s^2) and ``M^-1 C`` (1/s) per body, with the source
    of each row's largest stiffness, or None when some parameter is an abstract tracer.

    Returns ``(K_row (n,), C_row (n,), source, Kc (n,), Cc (n,))``; pinned bodies have rows 0;
    ``source(i)`` names what sets body i's stiffest entry; ``Kc``, ``Cc`` are the contact
    parts alone (1/s^2, 1/s).
    ``packed=True`` counts every candidate sphere neighbour (at most 12) instead of one.
    """
    st = _structure(sim)
    n = sim.n_bodies
    mass = np.asarray(sim.mass, float)
    kr, cr = np.zeros(n), np.zeros(n)
    best_spring, best_contact = np.zeros(n), np.zeros(n)
    spring_k = contact_k = None
    ck, ccr = np.zeros(n), np.zeros(n)
    sb, sg, sf = st.spring_rows
    if sb.size:
        vals = _values([params.springs[g] for g in sim.spring_groups])
        if vals is None:
            return None
        kk, cc = sf * vals[0][sg], sf * vals[1][sg]
        np.add.at(kr, sb, kk)
        np.add.at(cr, sb, cc)
        np.maximum.at(best_spring, sb, kk)
        spring_k = kk
    cb, cm, cf, cl, cmult = st.contact_rows
    if cb.size:
        vals = _values([params.contact[m] for m in sim.materials])
        if vals is None:
            return None
        kk, cc = cf * vals[0][cm], cf * vals[1][cm]
        if sim.law == "hunt_crossley":
            # stiffness n k d^(n-1), damping c d^n at a reference penetration (the body's
            # radius, at least 1 mm): conservative for penetrations below it
            e, d = sim.exponent, st.d_ref[cb]
            kk, cc = e * kk * d ** (e - 1.0), cc * d ** e
        if packed:
            # every candidate sphere neighbour at once (at most _KISSING per body) plus the
            # stiffest fixed collider
            sphere = cmult != 1.0
            sphere |= np.array([st.labels[j].startswith("contact between") for j in cl])
            np.maximum.at(ck, cb[~sphere], kk[~sphere])
            np.maximum.at(ccr, cb[~sphere], cc[~sphere])
            np.add.at(ck, cb[sphere], (kk * cmult)[sphere])
            np.add.at(ccr, cb[sphere], (cc * cmult)[sphere])
        else:
            np.maximum.at(ck, cb, kk)
            np.maximum.at(ccr, cb, cc)
        best_contact, contact_k = ck, kk
        kr += ck
        cr += ccr
    free = ~np.asarray(sim.pinned)
    K_row = np.where(free, kr / mass, 0.0)
    C_row = np.where(free, cr / mass, 0.0)
    best_extra, extra_label = np.zeros(n), [""] * n
    for hook in EXTRA_BOUNDS:
        extra = hook(sim, params)
        if extra is None:
            return None
        ek = np.where(free, np.asarray(extra[0], float), 0.0)
        K_row = K_row + ek
        C_row = C_row + np.asarray(extra[1], float)
        for i in np.flatnonzero(ek * mass > best_extra):
            best_extra[i], extra_label[i] = ek[i] * mass[i], getattr(hook, "label", "")

    def source(i: int) -> str:
        """What gives body i its stiffest row entry, in words."""
        if best_extra[i] > max(best_contact[i], best_spring[i]) and extra_label[i]:
            return extra_label[i]
        if contact_k is not None and best_contact[i] > best_spring[i]:
            rows = np.flatnonzero(cb == i)
            return st.labels[int(cl[rows[np.argmax(contact_k[rows])]])]
        if spring_k is not None and best_spring[i] > 0.0:
            rows = np.flatnonzero(sb == i)
            return st.spring_labels[int(sg[rows[np.argmax(spring_k[rows])]])]
        return ""
    free_mass = np.where(free, mass, np.inf)
    return K_row, C_row, source, ck / free_mass, ccr / free_mass


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


def report(sim, params, *, substeps: int | None = None,
           packed: bool = True) -> StabilityReport | None:
    """Stability report of ``sim`` for ``params`` (None when params are abstract tracers).

    ``substeps`` defaults to the simulator's (1 for ``"auto"``). ``packed=False`` skips the
    packed-spheres bound (``packed_dt`` is then ``stable_dt``).
    """
    rates = scene_rates(sim, params)
    if rates is None:
        return None
    K_row, C_row, source, Kc, Cc = rates
    K, C = float(np.max(K_row, initial=0.0)), float(np.max(C_row, initial=0.0))
    sdt = stable_dt(sim.integrator, K, C)
    pdt = sdt
    if packed and "contact_sphere_sphere" in sim.terms:
        pk = scene_rates(sim, params, packed=True)
        pdt = stable_dt(sim.integrator, float(np.max(pk[0], initial=0.0)),
                        float(np.max(pk[1], initial=0.0)))
    if substeps is None:
        substeps = sim.substeps if isinstance(sim.substeps, int) else 1
    h = sim.dt / substeps
    margin = math.inf if math.isinf(sdt) else sdt / h
    safe = safe_dt(sim.integrator, float(np.max(Kc, initial=0.0)),
                   float(np.max(Cc, initial=0.0)), sdt)
    safe_margin = math.inf if math.isinf(safe) else safe / h
    body = int(np.argmax(K_row)) if K > 0.0 else None
    return StabilityReport(sim.integrator, sim.dt, substeps, h, sdt, margin, margin > 1.0,
                           safe, safe_margin, safe_margin > 1.0,
                           _needed(sim.dt, safe), math.sqrt(K), C, body,
                           (f"{source(body)} on body {body}" if body is not None else ""),
                           pdt)


def gate(sim, params, *, check: bool = True) -> int:
    """Called by ``Simulator.rollout`` before running. Returns the substep count to use
    (1 unless ``substeps="auto"``; the simulator's fixed count is already in its step).

    Raises StabilityError when an explicit integrator would run past its limit (fixed
    substeps), or when ``"auto"`` would need more than MAX_AUTO_SUBSTEPS. With abstract
    (jit-traced) parameters a fixed-substep simulator is not checked; ``"auto"`` reuses the
    count it picked last for concrete parameters, or raises a SceneError saying what to do.
    """
    auto = sim.substeps == "auto"
    if sim.integrator in IMPLICIT:
        if check and np.dtype(sim.dtype).itemsize < 8:
            _implicit_precision(sim, params)
        return 1
    if not (check or auto):
        return 1
    # fast path: a verdict per set of scalar parameter values, memoised on the simulator
    # (the check costs a few microseconds on a repeated rollout)
    key = _scalar_key(params)
    memo = sim.__dict__.setdefault("_stability_memo", {})
    if key is not None and key in memo:
        if auto:
            sim._auto_last = memo[key]
        return memo[key]
    n = _gate(sim, params, auto)
    if key is not None:
        if len(memo) > 1024:
            memo.clear()
        memo[key] = n
    return n


#: implicit_euler in a float dtype of machine epsilon eps needs (w h)^2 eps <= this: past it the
#: identity in (I - h A_v - h^2 A_x) is lost to rounding and a free body's matrix is singular.
IMPLICIT_PRECISION = 0.1


def _implicit_precision(sim, params) -> None:
    """Raise StabilityError when implicit_euler's linear system cannot be resolved in the
    simulator's dtype (float32 with a very stiff, light body and a large step)."""
    rates = scene_rates(sim, params)
    if rates is None:
        return
    K = float(np.max(rates[0], initial=0.0))
    eps = float(np.finfo(np.dtype(sim.dtype)).eps)
    h = sim.dt / (sim.substeps if isinstance(sim.substeps, int) else 1)
    if K * h * h * eps <= IMPLICIT_PRECISION:
        return
    h_ok = math.sqrt(IMPLICIT_PRECISION / (eps * K))
    n = _needed(sim.dt, h_ok)
    raise StabilityError(
        f"implicit_euler cannot resolve this system in {np.dtype(sim.dtype).name}: "
        f"(w h)^2 = {K * h * h:.3g} swamps the identity at machine epsilon {eps:.2g} (the "
        f"matrix is singular in rounding). Use dtype=float64, or a step <= {h_ok:.3g} s "
        f"(substeps={n}).", stable_dt=h_ok, substeps=n)


def _scalar_key(params):
    """Tuple of the float values of all contact and spring parameters, or None (arrays,
    abstract tracers)."""
    try:
        return tuple(float(v) for p in (*params.contact.values(), *params.springs.values())
                     for v in p)
    except Exception:  # noqa: BLE001 - non-scalar or abstract: take the slow path
        return None


def _gate(sim, params, auto: bool) -> int:
    rep = report(sim, params, packed=False)
    if rep is None:
        if not auto:
            return 1
        last = getattr(sim, "_auto_last", None)
        if last is None:
            raise SceneError(
                "substeps='auto' picks the substep count from concrete k and c, but rollout "
                "was traced with abstract parameters (inside jax.jit or vmap). Call "
                "sim.rollout once with concrete params first (the count is then reused), or "
                "compile with substeps=N (see sim.stability(params).substeps_needed).")
        return last
    if auto:
        n = rep.substeps_needed
        if n > MAX_AUTO_SUBSTEPS:
            raise StabilityError(
                f"substeps='auto' would need {n} substeps per step of dt={sim.dt:g} s "
                f"(safe step {rep.safe_dt:.3g} s, {rep.limiting}): too slow. Lower the "
                "stiffness, raise the mass, or use integrator='implicit_euler'.",
                stable_dt=rep.safe_dt, substeps=n)
        sim._auto_last = n
        return n
    if not rep.safe:
        h = rep.inner_dt
        why = ("unstable" if not rep.stable else
               f"stable but past its safe step for contact (needs w h < {SAFE_WH} and "
               f"c h / m < {SAFE_CH}; here w h = {rep.omega_max * h:.3g}, c h / m = "
               f"{rep.damping_rate * h:.3g}, bounds from the stiffest and most damped contact:"
               " contact energy errors of several % or more)")
        raise StabilityError(
            f"integrator {sim.integrator!r} is {why} at step {h:.6g} s: the step must be "
            f"below {rep.safe_dt:.6g} s (linear stability limit {rep.stable_dt:.4g} s; w_max "
            f"<= {rep.omega_max:.4g} rad/s, C/m <= {rep.damping_rate:.4g} 1/s, set by "
            f"{rep.limiting or 'the springs and contacts'}). Use dt < {rep.safe_dt:.4g} s, "
            f"compile with substeps={rep.substeps_needed} (or substeps='auto'), or "
            "integrator='implicit_euler'.",
            stable_dt=rep.safe_dt, substeps=rep.substeps_needed)
    return 1
