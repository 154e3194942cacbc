"""Scene bounds: each force term's Gershgorin rows (:class:`Bound`) summed per body into the
rates of ``M^-1 K`` and ``M^-1 C`` (:func:`rates`), evaluated with numpy (up-front check,
reports) or with ``jax.numpy`` inside the traced rollout (:func:`unsafe`, the ``FLAG``).
See :mod:`diffpen.stability` for the overview.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

from ..integrators import Integrator
from ..params import _known_value
from .depth import energy_depth
from .modes import SAFE_CH, SAFE_STABLE, SAFE_TIE, SAFE_WH, _spectral_radius_2x2

__all__ = ["Bound", "Analysis", "Rates", "rates", "scene_rates", "unsafe", "precision_unsafe",
           "params_out_of_range", "extra_ranges",
           "FLAG", "IMPLICIT_PRECISION", "RESTING_RESOLUTION"]

#: ``State.aux`` key of the traced stability flag: a bool scalar, True once a rollout ran a
#: step past the safe step for its parameter values, or an implicit step its float dtype
#: cannot resolve (:func:`precision_unsafe`) (sticky).
FLAG = "unstable"

#: implicit_euler in a float dtype of machine epsilon eps needs (w h)^2 eps <= this: past it the
#: identity in (I - h A_v - h^2 A_x) is lost to rounding and a free body's matrix is singular.
IMPLICIT_PRECISION = 0.1

#: implicit_euler in a float dtype of machine epsilon eps needs a body's static deflection
#: under gravity, g / K (K its stiffness over mass, 1/s^2), to be at least this fraction of the
#: resolution of its positions, eps x its size: below it the body rests on a contact (or
#: hangs on a spring) within a rounding of its position, and the step's linearisation, which
#: differentiates the forces, gives NaN gradients (float32, k 1e9 N/m on 0.1 g) or finite,
#: wrong ones (float32, 0.1 g at rest: d z / dk -42.9 at k 5e5 N/m, +17.9 at 1e6, where
#: m g / k^2 ~ 1e-15, at deflections of 2.7-16.5% of that resolution; right from 27%).
RESTING_RESOLUTION = 0.5


def _value(x):
    """Concrete float array of a parameter value, or None when it is an abstract tracer."""
    v = _known_value(x)
    return None if v is None else np.asarray(v, dtype=float)


class Bound(NamedTuple):
    """Static rows of one force term's Gershgorin bounds on ``M^-1 K`` and ``M^-1 C``
    (docs/physics-notes.md section 4), carried by the term (:class:`diffpen.terms.Term`).

    Row r adds ``k_weight[r] * k`` and ``c_weight[r] * c`` of its parameter to the stiffness
    (1/s^2) and damping (1/s) rows of body ``body[r]``.

    body: (m,) int body indices.
    param: ``"contact"`` (params.contact), ``"springs"`` (params.springs), ``"load"`` (no
      parameter: ``k_weight`` is the row's stiffness in 1/s^2, fixed by the scene), or the
      name of a ``Params.extra`` entry whose values act as damping (``"friction"``: mu, with
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
    scale: spring groups whose stiffness (``params.springs[g].k``, N/m) multiplies the
      rows as well, row r's ``scale[scale_key[r]]`` (friction under a spring's load: mu
      times the tension ``k |stretch|``, ``k_weight`` then per metre of stretch); ``()``
      for none.  scale_key: (m,) int, or None.
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
    scale: tuple = ()
    scale_key: np.ndarray | None = None

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
      for contact laws whose stiffness grows with depth: its radius, or its start depth
      where it starts deeper (:func:`diffpen.stability.depth.start_depths`), at least 1 mm.
    bounds: every term's :class:`Bound` blocks, in term order.
    contact_scale: ``contact_scale(k, c, d) -> (k, c)``: the contact law's largest stiffness
      and damping for depths up to d (m) (``diffpen.laws.ContactLaw.stiffness``), or None.
    dtype: the simulator's float dtype.  gravity: |g| of the scene, m/s^2.
    contact_wh: the contact springs' safe ``w h`` (``SAFE_WH``, or the contact law's own,
      ``diffpen.laws.ContactLaw.safe_wh``).
    depth_exponent: the contact law's n where the start energy may bound the reference depth
      (:func:`diffpen.stability.depth.qualifies`), else None.
    min_step: the shortest inner step (s) the dtype resolves at the scene's scale
      (:func:`diffpen.precision.min_resolved_step`; shorter ones warn).
    extra_ranges: the ``Params.extra`` entries' ranges (:func:`extra_ranges`).
    events_step: an event-exact contact record's shortest inner step in this dtype
      (:func:`diffpen.precision.events_min_step`; shorter ones warn), or 0 (another law).
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
    gravity: float = 0.0
    contact_wh: float = SAFE_WH
    depth_exponent: float | None = None
    min_step: float = 0.0
    extra_ranges: tuple = ()
    events_step: float = 0.0

    @property
    def inner_dt(self) -> float:
        """dt / substeps (s), with one substep for "auto"."""
        return self.dt / (self.substeps if isinstance(self.substeps, int) else 1)


class Rates(NamedTuple):
    """Gershgorin rows per body: K_row (n,) 1/s^2 of ``M^-1 K``, C_row (n,) 1/s of
    ``M^-1 C``; Kc, Cc (n,) the contact parts alone; ``source(i)`` names what sets body i's
    stiffest entry and ``damper(i)`` its largest damping entry (numpy evaluation only, else
    None)."""
    K_row: Any
    C_row: Any
    Kc: Any
    Cc: Any
    source: Callable | None
    damper: Callable | None = None


def _block_values(block: Bound, params, xp):
    """(k (p,) or None, c (p,)) of the block's parameters, each the max over any batch axis,
    or None when some value is abstract (numpy evaluation)."""
    if block.param == "contact":
        pairs = [params.contact[n] for n in block.names]
    elif block.param == "springs":
        pairs = [params.springs[n] for n in block.names]
    elif block.param == "load":
        pairs = [(1.0, 0.0) for _ in block.names]
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


def _scale_values(block: Bound, params, xp):
    """(g,) the stiffness of the spring groups ``block.scale`` (N/m, each the max over any
    batch axis), or None when some value is abstract (numpy evaluation)."""
    ks = [params.springs[g].k for g in block.scale]
    if xp is not np:
        return xp.stack([xp.max(xp.asarray(k)) for k in ks])
    vals = [_value(k) for k in ks]
    if any(v is None for v in vals):
        return None
    return np.array([float(np.max(v)) for v in vals])


def _at(xp, arr, idx, vals, op):
    if xp is np:
        (np.add if op == "add" else np.maximum).at(arr, idx, vals)
        return arr
    ref = arr.at[idx]
    return ref.add(vals) if op == "add" else ref.max(vals)


def rates(an: Analysis, params, *, xp=np, packed: bool = False,
          energy=None) -> Rates | None:
    """Sum the terms' bounds for ``params``: :class:`Rates`, or None when some parameter is
    an abstract tracer (numpy evaluation).

    ``xp=jax.numpy`` evaluates the same rows on traced values (inside jit, vmap, grad);
    ``packed=True`` counts every candidate sphere neighbour (at most 12) instead of one.
    ``energy``: the rollout's start energy (J, :func:`diffpen.stability.depth.start_energy`)
    where the analysis lets it bound the contacts' reference depth (``depth_exponent``), or
    None (the bodies' radii). Pinned bodies have rows 0.
    """
    n = len(an.mass)
    zeros = (lambda: np.zeros(n)) if xp is np else (lambda: xp.zeros(n, an.dtype))
    cast = (lambda a: a) if xp is np else (lambda a: xp.asarray(a, an.dtype))
    kr, cr, ck, ccr, ek, ec = (zeros() for _ in range(6))
    spring_rows, contact_rows, grouped, damper_rows = [], [], {}, []
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
        if block.scale:                 # times the springs' stiffness that loads the rows
            sk = _scale_values(block, params, xp)
            if sk is None:
                return None
            cc = cc * cast(sk)[block.scale_key]
        if block.param == "contact" and an.contact_scale is not None:
            # the law's stiffness and damping at the reference depth, for every contact
            # block (rigid corners too: a Hunt-Crossley k is N/m^n, its c N s/m^(n+1))
            depth = cast(an.d_ref[block.body])
            if energy is not None and an.depth_exponent is not None:
                depth = xp.minimum(depth, energy_depth(an.depth_exponent, kv[block.key],
                                                       energy, xp))
            kk, cc = an.contact_scale(kk, cc, depth)
        if xp is np and block.labels:
            rate = cc / an.mass[block.body] if block.per_mass else cc
            damper_rows += [(int(b), float(v), lab)
                            for b, v, lab in zip(block.body, rate, block.labels)]
        if block.combine == "contact":
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

    def damper(i: int) -> str:
        """What gives body i its largest damping row entry, in words."""
        rows = [r for r in damper_rows if r[0] == i and r[1] > 0.0]
        return max(rows, key=lambda r: r[1])[2] if rows else ""
    return Rates(K_row, C_row, ck / free_mass, ccr / free_mass, source, damper)


def scene_rates(sim, params, *, packed: bool = False):
    """Gershgorin rows of ``M^-1 K`` (1/s^2) and ``M^-1 C`` (1/s) per body of a compiled
    simulator, or None when some parameter is an abstract tracer.

    Returns ``(K_row (n,), C_row (n,), source, Kc (n,), Cc (n,))`` (see :func:`rates`).
    """
    r = rates(sim.analysis, params, packed=packed)
    return None if r is None else (r.K_row, r.C_row, r.source, r.Kc, r.Cc)


def unsafe(an: Analysis, params, h=None, energy=None):
    """Traced stability flag: a bool scalar, True when an inner step of ``h`` s (default the
    simulator's) is past the safe step for ``params`` (tracers welcome: jit, vmap, grad).

    The same rows as the up-front check (:func:`rates` with ``jax.numpy``) and the same
    limits: ``h > min(SAFE_STABLE x stable_dt, SAFE_STABLE x the undamped limit,
    contact_wh / w_c, SAFE_CH / C_c)``, the stability limit
    from the integrator's closed form when it has one (then it agrees with the up-front check
    to rounding), else from the spectral radius of its amplification matrix at
    ``h / SAFE_STABLE`` for the modes (K, C), (K, 0) and (0, C). Methods without a step limit
    (implicit) have no such test: for them it is :func:`precision_unsafe` (True when the
    dtype cannot resolve the step; always False in float64). Either way also True where a
    parameter is out of its range (:func:`params_out_of_range`). ``energy``: as :func:`rates`
    takes it (the value the up-front gate was given).
    """
    import jax
    import jax.numpy as jnp
    rec = an.integrator
    params = jax.lax.stop_gradient(params)
    if not rec.explicit:
        return precision_unsafe(an, params, h) | params_out_of_range(params, an.extra_ranges)
    h = an.inner_dt if h is None else h
    r = rates(an, params, xp=jnp, energy=energy)
    K, C = jnp.max(r.K_row, initial=0.0), jnp.max(r.C_row, initial=0.0)
    Kc, Cc = jnp.max(r.Kc, initial=0.0), jnp.max(r.Cc, initial=0.0)
    if rec.stable_dt is not None:
        sdt = rec.stable_dt(K, C, xp=jnp)
        sdt = jnp.where((K <= 0.0) & (C <= 0.0), jnp.inf, sdt)
        undamped = rec.stable_dt(K, jnp.zeros_like(C), xp=jnp)
        tie = 1.0 + SAFE_TIE         # a step equal to the safe step is accepted
        bad = (SAFE_STABLE * sdt * tie < h) | ((K > 0.0) & (SAFE_STABLE * undamped * tie < h))
    else:
        # every mode held to SAFE_STABLE of its limit: h / SAFE_STABLE within it
        Ks = jnp.stack([K, K, jnp.zeros_like(K)])
        Cs = jnp.stack([C, jnp.zeros_like(C), C])
        hs = jnp.full((3,), h / (SAFE_STABLE * (1.0 + SAFE_TIE)), K.dtype)
        rho = _spectral_radius_2x2(rec.amplification(Ks, Cs, hs, xp=jnp), jnp)
        # a neutral mode (a pure dashpot's |rho| = 1 exactly) reads 1 + 2e-6 in float32:
        # the margin follows the dtype's rounding
        margin = max(1e-9, 64.0 * float(jnp.finfo(rho.dtype).eps))
        bad = jnp.any(rho > 1.0 + margin)
    wc = jnp.sqrt(Kc)
    tie = 1.0 + SAFE_TIE
    bad = bad | ((Kc > 0.0) & (an.contact_wh * tie / jnp.where(Kc > 0.0, wc, 1.0) < h))
    bad = bad | ((Cc > 0.0) & (SAFE_CH * tie / jnp.where(Cc > 0.0, Cc, 1.0) < h))
    return bad | params_out_of_range(params, an.extra_ranges)


def extra_ranges(defaults: dict, checks: dict) -> tuple:
    """``((name, range), ...)`` of a simulator's ``Params.extra`` entries for
    :func:`params_out_of_range`: each from the check ``sim.params`` runs on it (its
    ``traced_range``: ``(lo, hi, open)``, or None for any finite value); the default check
    (``diffpen.params._check_value``) holds values >= 0, a term's own check without a
    ``traced_range`` any finite value (a custom term's wall position may be negative)."""
    from ..params import _check_value
    return tuple((name, getattr(checks.get(name, _check_value), "traced_range", None))
                 for name in defaults)


def params_out_of_range(params, ranges: tuple = ()):
    """Traced range check of ``params`` (a bool scalar; tracers welcome): True where a value
    is not finite, a contact's or spring group's stiffness or damping is negative, or an
    ``extra`` entry is outside its range (``ranges``, :func:`extra_ranges`: friction and drag
    >= 0, yield strains in (0, 1); entries not named, such as a rollout's ``_...`` step
    constants, finite only): the ranges ``sim.params`` refuses for concrete values. Under
    ``jit`` or ``vmap`` nothing can be refused, and such a value reads as no limit to the
    step tests (every comparison with NaN is False; a negative value never reaches one), so
    the flag carries it."""
    import jax
    import jax.numpy as jnp

    def leaves(tree):
        return [jnp.asarray(a) for a in jax.tree_util.tree_leaves(tree)]
    bad = jnp.zeros((), bool)
    for a in leaves((params.contact, params.springs, params.extra)):
        bad = bad | jnp.any(~jnp.isfinite(a))
    for a in leaves((params.contact, params.springs)):
        bad = bad | jnp.any(a < 0.0)
    for name, rng in ranges:
        if rng is None or name not in params.extra:
            continue
        lo, hi, open_ = rng
        for a in leaves(params.extra[name]):
            bad = bad | jnp.any(((a <= lo) | (a >= hi)) if open_ else ((a < lo) | (a > hi)))
    return bad


def precision_unsafe(an: Analysis, params, h=None):
    """Traced precision flag of an implicit integrator: a bool scalar, True when an inner
    step of ``h`` s (default the simulator's) cannot be resolved in the simulator's float
    dtype for ``params`` (tracers welcome: jit, vmap, grad). The traced form of the up-front
    refusal (:func:`diffpen.stability.gating._implicit_precision`), on the same rows
    (:func:`rates`) and the same limits:

    * ``(w h)^2 eps > IMPLICIT_PRECISION`` (w^2 = K, the largest stiffness row in 1/s^2, eps
      the dtype's machine epsilon): the identity in the step's matrix is lost to rounding;
    * a free body with a stiffness row K_i > 0 whose static deflection under gravity,
      ``g / K_i`` (m), is below ``RESTING_RESOLUTION x eps x d_ref_i`` (its resolution of
      positions): the step's linearisation gives wrong or NaN gradients.

    Always False in a dtype of 8 bytes or more (float64), as the up-front check."""
    import jax
    import jax.numpy as jnp
    dtype = np.dtype(an.dtype)
    if dtype.itemsize >= 8:
        return jnp.zeros((), bool)
    h = an.inner_dt if h is None else h
    eps = float(np.finfo(dtype).eps)
    r = rates(an, jax.lax.stop_gradient(params), xp=jnp)
    K_row = r.K_row
    K = jnp.max(K_row, initial=0.0)
    bad = K * (h * h * eps) > IMPLICIT_PRECISION
    if an.gravity > 0.0:
        free = ~np.asarray(an.pinned, bool)
        # g / K_i < RESTING_RESOLUTION eps d_ref_i, multiplied out (K_i = 0 never flags)
        res = jnp.asarray(RESTING_RESOLUTION * eps * np.asarray(an.d_ref, float), K_row.dtype)
        bad = bad | jnp.any(free & (K_row > 0.0) & (an.gravity < res * K_row))
    return bad
