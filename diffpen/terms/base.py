"""The term record and what every term shares: :class:`Term`, :class:`TermBuilder`,
:class:`CompileContext`, :func:`with_bound`, and the lifting helpers (gather / scatter over
static index arrays)."""
from __future__ import annotations

import dataclasses
import types
from typing import Any, Callable, Iterable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..layout import Columns
from ..scene import DEFAULT, Scene
from ..state import Params, State

__all__ = ["Term", "TermBuilder", "CompileContext", "with_bound", "declared", "merge_extra",
           "gather", "scatter", "static_dot", "static_scale", "plane_offsets",
           "plane_offset_extra"]

#: The ``Params.extra`` entries a rollout adds for its loop, ``{site: step constants}`` under
#: ``"_step_factors h"`` (h the inner step, s; :meth:`CompileContext.with_step_factors`):
#: never part of the params a user builds.
STEP_FACTORS = "_step_factors"


def _factors_key(h) -> str:
    return f"{STEP_FACTORS} {float(h)!r}"


_EMPTY: Mapping = types.MappingProxyType({})


# --------------------------------------------------------------------------- lifting helpers
def gather(x, idx: np.ndarray, n: int):
    """``x[idx]`` along axis 0, skipped when ``idx`` is ``arange(n)`` (decided at build time)."""
    if idx.shape[0] == n and np.array_equal(idx, np.arange(n)):
        return x
    if np.all(idx == idx[0]):
        return jnp.broadcast_to(x[int(idx[0])], (idx.shape[0],) + x.shape[1:])
    return x[idx]


#: :func:`scatter` sums by static row picks (no XLA scatter) when there are at most this many
#: pairs, each body in at most :data:`SCATTER_ROUNDS` of them
SCATTER_PAIRS = 256
SCATTER_ROUNDS = 8


def _rounds(idx: np.ndarray, n: int):
    """(R, n) static row picks for :func:`scatter`: round r takes, for each body, its r-th pair
    (in pair order), or the index ``m`` (a zero row) when it has fewer; None past the
    limits above."""
    m = idx.shape[0]
    if m > SCATTER_PAIRS or m == 0:
        return None
    counts = np.bincount(idx, minlength=n)
    R = int(counts.max())
    if R > SCATTER_ROUNDS:
        return None
    table = np.full((R, n), m, dtype=np.int64)
    seen = np.zeros(n, dtype=np.int64)
    for p, b in enumerate(idx):
        table[seen[b], b] = p
        seen[b] += 1
    return table


def _pick(ext, rows: np.ndarray):
    """``ext[rows]`` for static ``rows``: a slice when they are consecutive."""
    if np.array_equal(rows, np.arange(rows[0], rows[0] + rows.shape[0])):
        return ext[int(rows[0]):int(rows[0]) + rows.shape[0]]
    return ext[jnp.asarray(rows)]


def scatter(values, idx: np.ndarray, n: int):
    """Segment sum of per-pair ``values`` (m, ...) onto ``n`` bodies by static ``idx`` (m,);
    per column for :class:`diffpen.layout.Columns`.

    Small ones (:data:`SCATTER_PAIRS`, :data:`SCATTER_ROUNDS`) are sums of static row picks
    in pair order (the same additions as the segment sum, so the same values for one force
    evaluation; whole rollouts may differ by rounding where XLA fuses around them): XLA CPU
    compiles a rollout loop into one kernel only when its body has no scatter
    (``diffpen.SMALL_LOOP_BYTES``)."""
    if idx.shape[0] == n and np.array_equal(idx, np.arange(n)):
        return values
    if isinstance(values, Columns):
        return Columns(*(scatter(v, idx, n) for v in values))
    table = _rounds(np.asarray(idx), n)
    if table is None:
        return jax.ops.segment_sum(values, jnp.asarray(idx), num_segments=n)
    ext = jnp.concatenate([values, jnp.zeros((1,) + values.shape[1:], values.dtype)])
    out = _pick(ext, table[0])
    for rows in table[1:]:
        out = out + _pick(ext, rows)
    return out


def static_dot(n: np.ndarray, v):
    """``dot(n, v)`` for a normal ``n`` (m, 3) known when the scene is compiled: components
    that are 0 for every row are left out, and +-1 columns need no product, so the ground
    plane's ``n . x`` is one slice of ``x``. ``v``: (m, 3) (or broadcastable)."""
    out = None
    for a in range(3):
        col = n[:, a]
        if not col.any():
            continue
        va = v[..., a]
        term = (va if (col == 1.0).all() else -va if (col == -1.0).all()
                else va * jnp.asarray(col, jnp.result_type(v)))
        out = term if out is None else out + term
    return jnp.zeros(jnp.shape(v)[:-1], jnp.result_type(v)) if out is None else out


def static_scale(f, n: np.ndarray, *, as_columns: bool = False):
    """``f[:, None] * n`` for a normal ``n`` (m, 3) known when the scene is compiled, built
    column by column so that XLA computes ``f`` once, not once per component, and writes
    zeros for components that are 0 in every row. ``f``: (m,). Returns (m, 3), or with
    ``as_columns`` the three (m,) columns as :class:`diffpen.layout.Columns`."""
    cols = []
    for a in range(3):
        col = n[:, a]
        cols.append(jnp.zeros_like(f) if not col.any() else f if (col == 1.0).all()
                    else -f if (col == -1.0).all()
                    else f * jnp.asarray(col, jnp.result_type(f)))
    return Columns(*cols) if as_columns else jnp.stack(cols, axis=-1)


class Term(NamedTuple):
    """One force term of a compiled scene.

    name: used as ``jax.named_scope`` (visible in the jaxpr).
    force: ``force(params, state) -> (F, tau)``: F (n, 3) newtons on body centres, tau (n, 3)
      torques in N m about the centres, or None when the term produces no torque.
    search: optional ``search(params, state) -> found``, a search the force needs (the broad
      phase's candidate pairs). A step runs it once, at the state it starts from, and passes
      the result to the force evaluations at that state as ``force(params, state, found)``;
      called as ``force(params, state)`` the force searches itself.
    record: optional ``record(aux, found) -> {name: array}``: the ``State.aux`` entries a step
      updates from its search (``aux``: the step's current entries).
    step_aware: True when ``force`` takes the integrator's inner step as a keyword,
      ``force(..., h=h)`` (s): contact terms then apply their step-averaged force
      (``ContactLaw.step_force``); without it (or ``h=None``) the instantaneous force.
    bound: the term's rows of the stability bounds, a tuple of
      :class:`diffpen.stability.Bound` (empty: the term adds nothing to the step limit).
    extra: defaults of the ``Params.extra`` entries the force reads, ``{name: value}`` (a
      value may be a ``{group: scalar}`` dict: such entries of several terms are merged, and
      ``sim.params(extra=...)`` checks each group's value; other values are kept as given).
    checks: ``{extra name: check(label, value)}`` validating concrete values given to
      ``sim.params`` (raises SceneError); default: a real, finite scalar >= 0. A check's
      ``traced_range`` attribute, ``(lo, hi, open)``, is what the traced stability flag holds
      traced values to (none: any finite value; ``diffpen.stability.bounds.extra_ranges``).
    aux: initial ``State.aux`` entries, ``{name: array}`` (e.g. plastic rest lengths, m).
    update: optional ``update(params, state) -> {name: array}``: the ``State.aux`` entries
      recomputed after every step from the new state (e.g. plastic yield).
    report: optional ``report(traj)``: a host-side check of a concrete
      :class:`diffpen.Trajectory` after ``sim.rollout`` (e.g. the broad phase warns when its
      overflow flag is set).
    columns: True when ``force`` returns F as :class:`diffpen.layout.Columns` (three (n,)
      arrays) instead of (n, 3) rows. When every term of a scene does, the simulator steps
      in columns (:mod:`diffpen.layout`), which XLA vectorises along a batch.

    The contact materials and spring groups a term reads (the ``Params.contact`` /
    ``Params.springs`` keys) are declared by its :class:`TermBuilder`, before any term is
    built, so that ``CompileContext.material_index`` is complete when builders run.
    """
    name: str
    force: Callable[..., tuple[Any, Any]]
    search: Callable[[Params, State], Any] | None = None
    record: Callable[[dict, Any], dict] | None = None
    step_aware: bool = False
    bound: tuple = ()
    extra: Mapping[str, Any] = _EMPTY
    checks: Mapping[str, Callable[[str, Any], None]] = _EMPTY
    aux: Mapping[str, Any] = _EMPTY
    update: Callable[[Params, State], dict] | None = None
    report: Callable[[Any], None] | None = None
    columns: bool = False


@dataclasses.dataclass
class CompileContext:
    """What a term builder sees: the scene and the static per-body arrays."""
    scene: Scene
    dtype: Any
    #: the contact law (``diffpen.laws.ContactLaw``; callable as its pointwise force)
    law: Callable
    width: float
    mass: np.ndarray        # (n,) kg
    radius: np.ndarray      # (n,) m
    pinned: np.ndarray      # (n,) bool
    collide: np.ndarray     # (n,) bool
    #: ``{material: index}`` / ``{group: index}`` of ``Params.contact`` / ``Params.springs``:
    #: the union of the builders' declarations (:func:`declared`), filled by compile before
    #: any term is built (empty while the declarations are asked for).
    material_index: dict = dataclasses.field(default_factory=dict)
    group_index: dict = dataclasses.field(default_factory=dict)
    #: Assembled by compile from the built Terms, in summation order (builders declare these
    #: on their Term: ``extra``, ``checks``, ``aux``, ``update``): the defaults of the
    #: ``Params.extra`` entries (``{name: pytree}``), their checks, the initial ``State.aux``
    #: entries (``{name: array}``) and the ``update(params, state) -> {name: array}``
    #: functions applied after every step.
    extra_defaults: dict = dataclasses.field(default_factory=dict)
    aux_init: dict = dataclasses.field(default_factory=dict)
    aux_updates: list = dataclasses.field(default_factory=list)
    extra_checks: dict = dataclasses.field(default_factory=dict)
    #: Broad phase of dynamic pairs (``diffpen.broadphase``), or None: all pairs statically.
    broadphase: Any = None
    #: The simulator's step dt, s (the longest inner step): a step-averaged contact acts from
    #: a gap of ``|vn| h`` on, so searches for pairs reach that far.
    step: float | None = None
    #: How far the state's velocity lags the force evaluation's position, as a fraction of
    #: the inner step: 1/2 for semi-implicit Euler (its velocity is the mean over the step
    #: that ended), 0 for the others. Contacts that know their effective mass then apply
    #: their damping at the window centre's speed (``ContactLaw.centred_force``).
    velocity_lag: float = 0.0
    #: Contacts whose law takes per-contact step constants (``ContactLaw.step_factors``):
    #: ``[(material indices, inverse masses)]``, registered by the contact terms
    #: (:meth:`factor_site`); a rollout computes their constants once, before its loop
    #: (:meth:`with_step_factors`).
    factor_sites: list = dataclasses.field(default_factory=list)

    @property
    def n(self) -> int:
        return len(self.mass)

    def const(self, a):
        """A static numpy array as a constant of the simulator's float dtype (placed with
        ``jax.device_put``: ``jnp.asarray`` of a host array compiles a program per shape)."""
        return jax.device_put(np.asarray(np.asarray(a, dtype=float), dtype=self.dtype))

    def factor_site(self, mat: np.ndarray, inv_mass) -> int | None:
        """Register contacts of material indices ``mat`` and effective inverse masses
        ``inv_mass`` whose law takes step constants (``ContactLaw.step_factors``, used where
        the centred record is); returns the key :meth:`step_factors` reads, or None."""
        if (getattr(self.law, "step_factors", None) is None or self.velocity_lag == 0.0
                or self.width != 0.0 or getattr(self.law, "centred", None) is None):
            return None
        self.factor_sites.append((np.asarray(mat), inv_mass))
        return len(self.factor_sites) - 1

    def with_step_factors(self, params: Params, h: float) -> Params:
        """``params`` with the step constants of every registered site for the inner step
        ``h`` (s) in ``Params.extra`` (key ``"_step_factors h"``): what a rollout passes
        its loop, so they are computed (and differentiated) once per rollout, not at every
        step."""
        if not self.factor_sites:
            return params
        table = {}
        for key, (mat, inv_mass) in enumerate(self.factor_sites):
            k, c = self.contact_kc(params, mat)
            # in the simulator's dtype: numpy's float64 masses made a float32 simulator's
            # constants float64 where x64 is on (the event-exact step's branches then differed)
            table[key] = self.law.step_factors(k, c, jnp.asarray(inv_mass, self.dtype), h)
        return params._replace(extra={**params.extra, _factors_key(h): table})

    def step_factors(self, params: Params, key: int | None, h):
        """The constants :meth:`with_step_factors` put in ``params`` for site ``key`` and this
        inner step ``h``, or None (computed where they are used)."""
        if key is None or h is None:
            return None
        table = params.extra.get(_factors_key(h))
        return None if table is None else table[key]

    def contact_force(self, d, vn, k, c, h=None, inv_mass=None, accel=0.0, factors=None):
        """Normal force (N) of contacts at depth ``d`` (m), separating speed ``vn`` (m/s):
        the law's step average over an inner step ``h`` (s), or its pointwise force for
        ``h=None`` (``diffpen.laws.ContactLaw.step_force``). With ``inv_mass`` (the
        contacts' effective inverse mass along the normal, 1/kg) and ``accel`` (their other
        separating acceleration, m/s^2: gravity) the step average takes its damping at the
        window centre's speed where the integrator's velocity lags (``velocity_lag``)."""
        if (h is None or inv_mass is None or self.velocity_lag == 0.0 or self.width != 0.0
                or getattr(self.law, "centred", None) is None):
            return self.law.step_force(d, vn, k, c, self.width, h)
        return self.law.centred_force(d, vn, k, c, h, self.velocity_lag * h, inv_mass, accel,
                                      factors)

    def normal_gravity(self, normal: np.ndarray, bodies: np.ndarray):
        """Gravity's separating acceleration ``n . g`` (m/s^2) of contacts of free bodies
        ``bodies`` (m,) against fixed colliders with normals ``normal`` (m, 3) (0 for pinned
        bodies): a numpy constant."""
        g = np.asarray(self.scene.gravity, dtype=float)
        return np.where(self.pinned[bodies], 0.0, np.asarray(normal, float) @ g)

    def inv_mass(self, bodies: np.ndarray):
        """``1 / m`` (1/kg) of ``bodies`` (m,), 0 for pinned ones: a numpy array."""
        return np.where(self.pinned[bodies], 0.0, 1.0 / self.mass[bodies])

    def contact_kc(self, params: Params, mat: np.ndarray):
        """Per-pair (k, c) for material indices ``mat`` (m,), scalars when all pairs share one."""
        names = list(self.material_index)
        ks = [params.contact[name].k for name in names]
        cs = [params.contact[name].c for name in names]
        return _select(ks, mat), _select(cs, mat)

    def spring_kc(self, params: Params, grp: np.ndarray):
        names = list(self.group_index)
        ks = [params.springs[name].k for name in names]
        cs = [params.springs[name].c for name in names]
        return _select(ks, grp), _select(cs, grp)


def _select(values: list, idx: np.ndarray):
    first = int(idx[0])
    if np.all(idx == first):
        return values[first]
    return jnp.stack([jnp.asarray(v) for v in values])[jnp.asarray(idx)]


# --------------------------------------------------------------------------- core terms
def _uniform(ctx: CompileContext, a: np.ndarray):
    """A per-contact numpy constant as a scalar of the simulator's dtype when all rows share
    one value (fewer operands in the step), else an (m,) array."""
    a = np.asarray(a, dtype=float)
    return ctx.const(a[0] if np.all(a == a[0]) else a)


def _pair_material(scene: Scene, *names: str) -> str:
    return names[0] if len(set(names)) == 1 else DEFAULT


def _named_planes(ctx: CompileContext, plane_ids) -> list:
    planes = ctx.scene.planes
    return list(dict.fromkeys(planes[j].name for j in plane_ids if planes[j].name))


def plane_offset_extra(ctx: CompileContext, plane_ids) -> tuple[dict, dict]:
    """The ``(extra, checks)`` of a Term whose force reads :func:`plane_offsets` of the planes
    ``plane_ids``: ``{"plane_offset": {name: scene offset (m)}}`` for the named planes among
    them (any finite sign), or empty dicts when none is named."""
    names = _named_planes(ctx, plane_ids)
    if not names:
        return {}, {}
    return ({"plane_offset": {pl.name: pl.offset for pl in ctx.scene.planes
                              if pl.name in names}},
            {"plane_offset": _check_finite})


def plane_offsets(ctx: CompileContext, plane_ids):
    """``offsets(params) -> (m,)`` offsets (m) of the planes ``plane_ids`` (m,): constants,
    except for planes named in ``Scene.add_plane(name=...)``, whose offset is the leaf
    ``params.extra["plane_offset"][name]`` (the Term declares it with
    :func:`plane_offset_extra`)."""
    planes = ctx.scene.planes
    const = ctx.const([planes[j].offset for j in plane_ids])
    names = _named_planes(ctx, plane_ids)
    if not names:
        return lambda params: const
    sel = np.array([names.index(planes[j].name) if planes[j].name else -1 for j in plane_ids])

    def offsets(params):
        vals = jnp.stack([jnp.asarray(params.extra["plane_offset"][g], ctx.dtype)
                          for g in names])
        return jnp.where(sel >= 0, vals[np.maximum(sel, 0)], const)
    return offsets


def _check_finite(label: str, v) -> None:
    if isinstance(v, jax.core.Tracer):
        return
    if not np.all(np.isfinite(np.asarray(v, dtype=float))):
        from ..errors import SceneError
        raise SceneError(f"{label} must be a finite number of metres, got {v!r}.")


_check_finite.traced_range = None       # any sign (diffpen.stability.bounds)


def _one(bound):
    return () if bound is None else (bound,)


class TermBuilder(NamedTuple):
    """A term builder with its compile-time facets; calling it builds the Term.

    build: ``build(ctx) -> Term | None`` (None: the scene does not need the term; it is then
      never traced).
    bound: optional ``bound(ctx) -> tuple`` of :class:`diffpen.stability.Bound`, put on the
      built Term (its rows of the stability bound).
    materials: optional ``materials(ctx) -> names``: the contact materials the term reads
      for this scene (``Params.contact`` keys, in a fixed order).
    groups: optional ``groups(ctx) -> names``: the spring groups it reads
      (``Params.springs`` keys).
    passive: True when the term never gives the bodies energy they did not have at the start
      (a drag, a damper: forces that only dissipate). A contact law that stiffens with depth
      may then take its reference depth from the start energy
      (:mod:`diffpen.stability.depth`); a custom term that is not declared passive keeps
      each body's radius there. Declaring passive a term that adds energy (a motor, a
      spring whose stored energy the start does not count) lets the safe step trust depths
      the bodies can exceed.

    ``materials`` and ``groups`` are asked before any term is built (``ctx.material_index``
    and ``ctx.group_index`` are then empty); compile makes the params keys their union over
    the builders, in builder order (:func:`declared`). A plain function ``build(ctx)`` is a
    builder without facets.
    """
    build: Callable[[CompileContext], Term | None]
    bound: Callable[[CompileContext], tuple] | None = None
    materials: Callable[[CompileContext], Iterable[str]] | None = None
    groups: Callable[[CompileContext], Iterable[str]] | None = None
    passive: bool = False

    def __call__(self, ctx: CompileContext) -> Term | None:
        term = self.build(ctx)
        if term is None or self.bound is None:
            return term
        return term._replace(bound=tuple(self.bound(ctx)))


def with_bound(build: Callable[[CompileContext], Term | None],
               bound: Callable[[CompileContext], tuple] | None, *,
               materials: Callable[[CompileContext], Iterable[str]] | None = None,
               groups: Callable[[CompileContext], Iterable[str]] | None = None,
               passive: bool = False) -> TermBuilder:
    """A :class:`TermBuilder`: ``build`` whose Term carries ``bound(ctx)`` (a tuple of
    :class:`diffpen.stability.Bound`), declaring ``materials(ctx)`` / ``groups(ctx)`` (and
    whether it is ``passive``): how a term, its stability bound and the params keys it reads
    are registered together (one line per term)."""
    return TermBuilder(build, bound, materials, groups, passive)


def declared(builders: Iterable, ctx: CompileContext, facet: str) -> tuple[str, ...]:
    """The union of the builders' ``facet`` (``"materials"`` or ``"groups"``) declarations
    for ``ctx``, in builder order, each name once (builders without it declare nothing)."""
    names: dict = {}
    for build in builders:
        fn = getattr(build, facet, None)
        if fn is None:
            continue
        got = fn(ctx)
        if isinstance(got, (str, bytes)):
            from ..errors import SceneError
            raise SceneError(f"a term builder's {facet}(ctx) must return a sequence of names, "
                             f"got the string {got!r}: write ({got!r},).")
        names.update(dict.fromkeys(got))
    return tuple(names)


def merge_extra(into: dict, extra: Mapping) -> dict:
    """Merge ``Params.extra`` defaults ``extra`` into ``into`` (in place; returned): dict
    values (``{group: value}``) of a name already there are merged group by group, other
    values replace."""
    for name, value in extra.items():
        if isinstance(value, Mapping) and isinstance(into.get(name), dict):
            into[name].update(value)
        else:
            into[name] = dict(value) if isinstance(value, Mapping) else value
    return into
