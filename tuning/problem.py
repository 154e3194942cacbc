"""A fitting problem: which leaves of a :class:`diffpen.Params` are fitted, within which
bounds, to which targets, and how far a point is from them.

Targets are ``{metric: value or list}``; :func:`normalise_targets` turns them into
``{metric: (n,) float array}`` (finite, non-zero: they are compared relatively) and
:func:`target_spec` into the static layout of the residual vector (one :class:`TargetSpec`
per metric: entry count, weight, relative tolerance). :func:`residuals` gives the weighted
relative residuals ``sqrt(w_j) (m_j - t_j) / |t_j|`` (traceable), :func:`achieved` the values
met and the reached test, :func:`tolerances` the per-residual stopping thresholds.

The fitted leaves live in log space (``theta = log value``, so k and c stay positive and steps
are relative) inside box bounds: :func:`default_bounds` per leaf, capped by
:func:`safe_bounds` at the safe explicit step of the simulator
(:func:`tuning.stable.safe_contact_bounds`, from :mod:`diffpen.stability`). :class:`FreeLeaves`
holds that parameter side; :class:`Problem` adds the metrics function and the targets, and is
what the optimisers (:mod:`tuning.lm`, :mod:`tuning.optimise`) work on; they return a
:class:`Solution`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import params as P
from .errors import FitError
from .compiled import ProgramCache
from .stable import FLAG, params_unstable, safe_contact_bounds, safe_contact_limits

__all__ = ["FitError", "TargetSpec", "normalise_targets", "target_spec", "tolerances",
           "target_slices", "ABSENT_ERROR", "residuals", "achieved", "RESIDUAL_FACTOR",
           "residual_reached", "default_bounds", "safe_bounds", "with_flag", "FreeLeaves",
           "Problem", "Solution"]


# --------------------------------------------------------------------------- targets
class TargetSpec(NamedTuple):
    """Static layout of one target in the residual vector: metric ``name``, ``count``
    entries (the metric's first ``count``), ``weight`` (> 0) and relative tolerance
    ``rtol``. A tuple of them is hashable (it keys compiled programs)."""
    name: str
    count: int
    weight: float
    rtol: float


def normalise_targets(targets: dict) -> dict:
    """``{metric: (n,) float array}`` from ``{metric: value or list}`` (units of the metric).

    Raises :class:`FitError` for no targets, an empty, non-finite or zero entry (targets are
    compared relatively, ``|achieved - target| / |target|``)."""
    if not isinstance(targets, dict):
        raise FitError(f"targets must be a dict {{metric: value or list}}, e.g. "
                       f"{{'apex_heights': [0.4]}}; got {type(targets).__name__} {targets!r}.")
    if not targets:
        raise FitError("no targets: give at least one, e.g. {'apex_heights': [0.4]}.")
    from .bounce import BOUNCE_METRICS          # heights, times, depths: all > 0
    out = {}
    for name, val in targets.items():
        if any(isinstance(v, (str, bytes, bool, np.bool_)) for v in np.ravel(
                np.asarray(val, dtype=object))):         # "0.4" was read as 0.4, True as 1
            raise FitError(f"target {name!r} must be a number or a list of numbers, got "
                           f"{val!r}" + (": write it without quotes." if "'" in repr(val)
                                          or '"' in repr(val) else "."))
        try:
            arr = np.atleast_1d(np.asarray(val, dtype=float))
        except (TypeError, ValueError):
            raise FitError(f"target {name!r} must be a number or a list of numbers, got "
                           f"{val!r}.") from None
        if arr.size == 0:
            raise FitError(f"target {name!r} is empty.")
        if not np.all(np.isfinite(arr)):
            raise FitError(f"target {name!r} must be finite, got {val!r}.")
        if np.any(arr == 0.0):
            raise FitError(f"target {name!r} has a zero entry; targets are compared relatively "
                           "(|achieved - target| / |target|): give a non-zero value.")
        if name in BOUNCE_METRICS and np.any(arr < 0.0):    # ran to the iteration limit
            raise FitError(f"target {name!r} must be positive (a height above the plane, a "
                           f"time, a depth or a ratio), got {val!r}.")
        out[name] = arr
    return out


def target_spec(targets: dict, weights: dict | None, rtol) -> tuple:
    """``(TargetSpec, ...)``, one per entry of the normalised ``targets``, in their order.

    weights: ``{metric: weight}`` (default 1; must be > 0).  rtol: relative tolerance, a float
    for every metric or ``{metric: tol}`` (default 1e-3 for metrics left out)."""
    weights = weights or {}
    for what, given in (("weights", weights), ("rtol", rtol if isinstance(rtol, dict) else {})):
        stray = [n for n in given if n not in targets]
        if stray:        # a misspelt metric would otherwise be ignored silently
            raise FitError(f"{what} names {stray}, which are not targets; the targets are "
                           f"{list(targets)}.")
    spec = []
    for name, arr in targets.items():
        try:
            w = float(weights.get(name, 1.0))
            tol = float(rtol.get(name, 1e-3) if isinstance(rtol, dict) else rtol)
        except (TypeError, ValueError):
            raise FitError(f"weight and rtol of target {name!r} must be numbers, got "
                           f"{weights.get(name, 1.0)!r} and {rtol!r}.") from None
        if not (w > 0.0 and math.isfinite(w)):
            raise FitError(f"weight of target {name!r} must be a finite number > 0, got "
                           f"{w!r}.")
        if not (tol > 0.0 and math.isfinite(tol)):
            raise FitError(f"rtol of target {name!r} must be a finite number > 0 (a relative "
                           f"tolerance, e.g. 1e-3), got {tol!r}.")
        spec.append(TargetSpec(name, arr.size, w, tol))
    return tuple(spec)


def tolerances(spec: tuple) -> np.ndarray:
    """(m,) stopping threshold of each residual: ``rtol * sqrt(weight)`` of its target (a
    residual within it means its target is within ``rtol``)."""
    return np.concatenate([np.full(s.count, s.rtol * math.sqrt(s.weight)) for s in spec])


def target_slices(spec: tuple) -> dict:
    """``{metric: slice}``: the rows of the residual vector that belong to each target."""
    slices, pos = {}, 0
    for s in spec:
        slices[s.name] = slice(pos, pos + s.count)
        pos += s.count
    return slices


#: The relative error an absent event (a metric entry that is nan: a bounce, or the end of a
#: contact, that the rollout does not have) counts as in :func:`residuals`: more than a point
#: with the event leaves, so an optimiser never trades the event away and the lowest loss
#: found is at a point that has it. (Counted as a value of 0, a point without a rebound
#: scored -1 per target, below an apex 2x its target, and as it has no gradient there either,
#: fits stopped at it and reported nan.)
ABSENT_ERROR = 1e4


def residuals(metrics: dict, targets: dict, spec: tuple):
    """Weighted relative residuals (m,) = ``sqrt(w) (m - t) / |t|`` per target entry
    (traceable; dimensionless). An absent event (nan) counts as ``sqrt(w)``
    :data:`ABSENT_ERROR`, with no gradient.

    metrics: ``{metric: scalar or (n,) array}``.  targets: ``{metric: (n,) array}``."""
    parts = []
    for name, count, w, _ in spec:
        if name not in metrics:
            raise FitError(f"target {name!r} is not a metric of this problem; metrics: "
                           f"{sorted(metrics)}.")
        m = jnp.atleast_1d(metrics[name])[:count]
        if m.shape[0] < count:
            raise FitError(f"target {name!r} has {count} entries but the metric has only "
                           f"{m.shape[0]}.")
        present = jnp.isfinite(m)
        m = jnp.where(present, m, 0.0)
        tgt = jnp.asarray(targets[name], dtype=m.dtype)
        parts.append(math.sqrt(w) * jnp.where(present, (m - tgt) / jnp.abs(tgt),
                                              ABSENT_ERROR))
    return jnp.concatenate(parts)


def achieved(metrics: dict, targets: dict, spec: tuple) -> tuple[dict, dict, bool]:
    """``(achieved, rel_error, reached)`` of concrete ``metrics`` against ``targets``.

    achieved: ``{metric: value or list}`` (the metric's first entries, its units).
    rel_error: ``{metric: max |achieved - target| / |target|}`` (inf for an absent event).
    reached: every entry within its ``rtol``, and the rollout not past its safe step (a
    metrics ``"unstable"`` entry that is true is never a result: :mod:`tuning.stable`)."""
    ach, rel, ok = {}, {}, True
    for name, count, _, tol in spec:
        m = np.atleast_1d(np.asarray(metrics[name], dtype=float))[:count]
        t = targets[name]
        err = np.abs(m - t) / np.abs(t)
        err = np.where(np.isfinite(err), err, np.inf)
        if name == "settling_time" and "settled" in metrics and not bool(
                np.all(np.asarray(metrics["settled"]))):
            err = np.full_like(err, np.inf)      # never settled: its time is the rollout's end
        ach[name] = m.tolist() if np.ndim(metrics[name]) else float(m[0])
        rel[name] = float(np.max(err))
        ok = ok and bool(np.all(err <= tol))
    if FLAG in metrics and bool(np.any(np.asarray(metrics[FLAG]))):
        ok = False        # past the safe step: never a result (tuning.stable)
    return ach, rel, ok


#: a residual rms above this many times the expected noise means the model does not explain
#: the record (a good fit leaves ~1x: the noise itself)
RESIDUAL_FACTOR = 3.0


def residual_reached(rms: float, noise: float, dt_error: float = 0.0,
                     factor: float = RESIDUAL_FACTOR) -> bool:
    """Whether a trajectory fit explains its record: the residual rms (m) is within
    ``factor`` times what noise alone leaves, ``sqrt(noise^2 + dt_error^2)`` (the record's
    estimated noise and the model's discretisation error, m). NaN never counts as reached."""
    expected = math.sqrt(float(noise) ** 2 + float(dt_error) ** 2)
    return bool(math.isfinite(rms) and rms <= factor * expected)


# --------------------------------------------------------------------------- bounds
def default_bounds(path: str, value: float, dt: float | None = None,
                   mass: float | None = None) -> tuple[float, float]:
    """Box bounds (lo, hi) for a fitted leaf ``path`` with start ``value`` (SI units).

    Contact/spring stiffness 1e-2..1e9 N/m and damping 1e-6..1e6 N s/m; when ``dt`` (s) and
    the smallest moving ``mass`` (kg) are given, the upper bounds are tightened to the safe
    explicit step of :mod:`diffpen.stability` (:func:`tuning.stable.safe_contact_limits`).
    Other leaves: value/1e4..1e4 x value.
    """
    limits = None if dt is None or mass is None else safe_contact_limits(dt, mass)
    if path.endswith(".k"):
        lo, hi = 1e-2, 1e9
        if limits is not None:
            hi = min(hi, limits[0])
    elif path.endswith(".c"):
        lo, hi = 1e-6, 1e6
        if limits is not None:
            hi = min(hi, limits[1])
    else:
        lo, hi = abs(value) / 1e4, abs(value) * 1e4
    return lo, hi


def safe_bounds(free, x0, bounds: dict | None, sim=None, *, state=None,
                values: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Box bounds (lo, hi) (n,) in SI units for the ``free`` leaves with start values ``x0``:
    ``bounds[path]`` or :func:`default_bounds`, and, when the simulator ``sim`` is given, every
    contact k and c capped at :func:`tuning.stable.safe_contact_bounds` of ``sim`` (the safe
    explicit step of its lightest movable body), so an optimiser cannot walk past the safe step.
    ``state``: the concrete start state of the fitted rollouts, whose energy may bound a
    Hunt-Crossley contact's reference depth (``safe_contact_bounds``); a contact's damping cap
    then holds down to the lower bound of its fitted k (or its value in ``values``, ``{path:
    value}`` of the frozen leaves). Raises :class:`FitError` when a given lower bound is
    already past it."""
    bounds = bounds or {}
    lo = np.array([bounds.get(p, default_bounds(p, v))[0] for p, v in zip(free, x0)], float)
    hi = np.array([bounds.get(p, default_bounds(p, v))[1] for p, v in zip(free, x0)], float)
    if sim is not None:
        values = values or {}
        for i, p in enumerate(free):
            if not (p.startswith("contact.") and p.endswith((".k", ".c"))):
                continue
            kp = p[:-2] + ".k"
            k_min = lo[free.index(kp)] if kp in free else values.get(kp)
            k_max, c_max = safe_contact_bounds(sim, state=state, k_min=k_min)
            cap = k_max if p.endswith(".k") else c_max
            if hi[i] > cap:
                if lo[i] >= cap:
                    raise FitError(f"the lower bound {lo[i]:g} of {p!r} is past the safe step "
                                   f"of this simulator ({cap:g} at dt={float(sim.dt):g} s); "
                                   "lower it, or use a smaller dt or more substeps.")
                hi[i] = cap
    return lo, hi


def with_flag(metrics_fn: Callable, sim, state=None) -> Callable:
    """``metrics_fn`` with the stability flag ``"unstable"`` added
    (:func:`tuning.stable.params_unstable` of ``sim``, for rollouts from ``state`` when
    given) when it returns none; ``metrics_fn`` itself when ``sim`` is None."""
    if sim is None:
        return metrics_fn

    def fn(params):
        m = metrics_fn(params)
        return m if FLAG in m else {**m, FLAG: params_unstable(sim, params, state)}
    return fn


# --------------------------------------------------------------------------- the problem
@dataclasses.dataclass(frozen=True)
class FreeLeaves:
    """The fitted leaves of a problem and their box, in log space.

    params0: :class:`diffpen.Params` giving the start and the frozen leaves.
    free: (P,) fitted leaf paths (:mod:`tuning.params`).  flat0: ``{path: leaf}`` of params0.
    x0: (P,) start values of the free leaves (SI units; as given, not clipped).
    lo, hi: (P,) box bounds (SI units, 0 < lo < hi).
    """
    params0: object
    free: tuple
    flat0: dict
    x0: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def build(cls, params0, free=None, bounds: dict | None = None, sim=None, *,
              positive_start: bool = False, state=None) -> "FreeLeaves":
        """Check ``free`` (default every contact k and c) and ``bounds`` (``{path: (lo,
        hi)}`` SI units, default :func:`default_bounds`) against ``params0`` and bound the
        leaves with :func:`safe_bounds` (inside the safe step of ``sim`` when given);
        ``positive_start``: the start values of ``params0`` must be > 0 too; ``state``: the
        fitted rollouts' start state, as :func:`safe_bounds` takes it.
        Raises :class:`FitError` naming what to change."""
        flat0 = P.flatten(params0)
        free = list(P.default_free(params0) if free is None else free)
        if not free:
            raise FitError("nothing to fit: 'free' is empty.")
        twice = sorted({p for p in free if free.count(p) > 1})
        if twice:                # fit_batch fitted both copies and reported the start value
            raise FitError(f"free names {twice} more than once; name each fitted parameter "
                           f"once.")
        for p in free:
            if p not in flat0:
                raise FitError(f"unknown parameter {p!r}; this scene has {list(flat0)}.")
        for p in bounds or {}:
            if p not in flat0:
                raise FitError(f"bounds given for unknown parameter {p!r}; known: "
                               f"{list(flat0)}.")
            if p not in free:          # a bound that bounds nothing: a typo or a missing free
                raise FitError(f"bounds given for {p!r}, which is not fitted; the fitted "
                               f"parameters are {list(free)} (add it to free, or drop its "
                               "bounds).")
        x0 = np.array([float(flat0[p]) for p in free])
        if positive_start and np.any(x0 <= 0.0):
            bad = [p for p, v in zip(free, x0) if v <= 0.0]
            raise FitError(f"fitted parameters need a positive start value (fitting is in log "
                           f"space); got {dict(zip(bad, x0[x0 <= 0.0]))}.")
        lo, hi = safe_bounds(free, x0, bounds, sim, state=state, values=flat0)
        if np.any(~(lo > 0.0)) or np.any(hi <= lo):
            box = {p: (float(a), float(b)) for p, a, b in zip(free, lo, hi)}
            raise FitError(f"bounds must satisfy 0 < lo < hi (fitting is in log space); got "
                           f"{box}.")
        return cls(params0, tuple(free), flat0, x0, lo, hi)

    @property
    def log_lo(self) -> np.ndarray:
        """(P,) log of the lower bounds."""
        return np.log(self.lo)

    @property
    def log_hi(self) -> np.ndarray:
        """(P,) log of the upper bounds."""
        return np.log(self.hi)

    def params_of(self, theta):
        """The :class:`diffpen.Params` at log values ``theta`` (P,) of the free leaves
        (traceable); the frozen leaves are those of ``params0``."""
        flat = dict(self.flat0)
        for i, p in enumerate(self.free):
            flat[p] = jnp.exp(theta[i])
        return P.unflatten(self.params0, flat)

    def start_values(self, starts) -> np.ndarray:
        """(n, P) start values (SI units) from ``[{path: value}, ...]`` (paths left out start
        at ``x0``), clipped to the box. Raises :class:`FitError` for a path that is not fitted
        or a value that is not finite and > 0."""
        x = np.empty((len(starts), len(self.free)))
        for i, st in enumerate(starts):
            extra = set(st) - set(self.free)
            if extra:
                raise FitError(f"start row {i} sets parameters that are not fitted: "
                               f"{sorted(extra)}; fitted: {list(self.free)}.")
            x[i] = [float(st.get(p, v)) for p, v in zip(self.free, self.x0)]
        if not np.all(np.isfinite(x)) or np.any(x <= 0.0):
            bad = sorted({int(i) for i in np.nonzero(~(x > 0.0) | ~np.isfinite(x))[0]})
            raise FitError(f"start values must be finite and > 0 (fitting is in log space); "
                           f"rows {bad} are not.")
        return np.clip(x, self.lo, self.hi)


#: compiled fit programs by (``Problem.program_key``, what), the last 16
_PROGRAMS = ProgramCache(16)


@dataclasses.dataclass(frozen=True)
class Problem:
    """One fitting problem: ``metrics_fn`` at the free leaves of ``leaves`` against
    ``targets``.

    metrics_fn: traceable ``params -> {metric: scalar or (n,) array}`` (with the stability
      flag added from ``sim`` when it had none: :func:`with_flag`).
    leaves: :class:`FreeLeaves`.  x0: (P,) start (SI units, clipped to the box).
    targets: ``{metric: (n,) float array}`` (:func:`normalise_targets`).
    spec: ``(TargetSpec, ...)``.  scalar: metrics whose target was given as a scalar.
    program_key: what the compiled residual program depends on besides the targets and the
      free values (the given metrics function, simulator, fitted paths, frozen leaf values
      and dtypes, target layout), or None where that cannot be told (a start ``state``,
      array leaves): equal keys may share one compiled program, the targets passed to it.
    """
    metrics_fn: Callable
    leaves: FreeLeaves
    x0: np.ndarray
    targets: dict
    spec: tuple
    scalar: frozenset
    _tgt: dict = dataclasses.field(repr=False, compare=False)
    program_key: tuple | None = dataclasses.field(default=None, repr=False, compare=False)

    @classmethod
    def build(cls, metrics_fn: Callable, params0, targets: dict, *, free=None,
              bounds: dict | None = None, weights: dict | None = None, rtol=1e-3,
              sim=None, state=None) -> "Problem":
        """Check everything and build the problem (arguments as in :func:`tuning.fit.fit`).
        Raises :class:`FitError` before anything is traced."""
        scalar = frozenset(k for k, v in targets.items() if np.ndim(v) == 0)
        targets = normalise_targets(targets)
        spec = target_spec(targets, weights, rtol)
        leaves = FreeLeaves.build(params0, free, dict(bounds or {}), sim, positive_start=True,
                                  state=state)
        key = None
        if state is None:
            try:
                frozen = tuple((p, float(v), str(np.asarray(v).dtype))
                               for p, v in leaves.flat0.items() if p not in leaves.free)
                key = (metrics_fn, sim, leaves.free, spec,
                       jax.tree_util.tree_structure(params0), frozen)
                hash(key)
            except (TypeError, ValueError):
                key = None
        return cls(with_flag(metrics_fn, sim, state), leaves,
                   np.clip(leaves.x0, leaves.lo, leaves.hi), targets, spec, scalar,
                   {k: jnp.asarray(v) for k, v in targets.items()}, key)

    @property
    def free(self) -> tuple:
        """(P,) fitted leaf paths."""
        return self.leaves.free

    @property
    def theta0(self) -> np.ndarray:
        """(P,) log start."""
        return np.log(self.x0)

    def program(self, what, build: Callable):
        """The compiled program ``what`` (a hashable tag of the method and its own static
        settings) of this problem: ``build()``'s, kept for later problems of the same
        :attr:`program_key` (a later fit with new targets or starts runs it, the targets
        passed as an argument; a program built at each fit compiled again: 1.6-2.8 s), or
        built afresh where the key is None."""
        if self.program_key is None:
            return build()
        return _PROGRAMS.get((self.program_key, what), build)

    def evaluate(self, theta, targets: dict | None = None):
        """``(residuals (m,), metrics)`` at log values ``theta`` (P,) (traceable), against
        ``targets`` (``{metric: (n,) array}``, traced too) or the problem's own."""
        m = self.metrics_fn(self.leaves.params_of(theta))
        return residuals(m, self._tgt if targets is None else targets, self.spec), m

    def params_of(self, theta):
        """The :class:`diffpen.Params` at log values ``theta`` (P,)."""
        return self.leaves.params_of(theta)

    def start_points(self, starts: list | None) -> list:
        """``[theta0, theta_1, ...]``: the log start and one (P,) log point per extra start
        ``{path: value}`` (paths left out start at ``x0``), clipped to the box
        (:meth:`FreeLeaves.start_values`)."""
        if not starts:
            return [self.theta0]
        x = self.leaves.start_values([{**dict(zip(self.free, self.x0)), **st}
                                      for st in starts])
        return [self.theta0] + list(np.log(x))

    def achieved(self, metrics: dict) -> tuple[dict, dict, bool]:
        """:func:`achieved` of concrete ``metrics`` against this problem's targets."""
        return achieved(metrics, self.targets, self.spec)

    def target_values(self) -> dict:
        """The targets as given: a float for a scalar target, else a list."""
        return {k: (float(v[0]) if k in self.scalar else v.tolist())
                for k, v in self.targets.items()}


class Solution(NamedTuple):
    """What an optimiser returns on a :class:`Problem`.

    theta: (P,) log values of the reported point.  metrics: the metrics there.
    history: (iterations + 1,) or (iterations,) loss (sum of squared residuals) per iteration.
    iterations: iterations run.  converged: the stopping rule fired.  message: in words.
    traces: times the residual function was traced.  evaluations: compiled-function calls.
    eval_history: (evaluations,) loss at every evaluated point, in order.
    """
    theta: np.ndarray
    metrics: dict
    history: np.ndarray
    iterations: int
    converged: bool
    message: str
    traces: int
    evaluations: int
    eval_history: np.ndarray
