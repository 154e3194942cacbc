"""Parameter values -> the :class:`diffpen.Params` pytree of a compiled simulator.

:func:`build` is ``Simulator.params``: it fills the values not given from the scene's
material / spring group / extension defaults, validates each one (:func:`_check_value`: a
real, finite scalar >= 0) and casts it to the simulator's dtype (:func:`cast`). Its keys
(``sim.materials``, ``sim.spring_groups``, the ``extra`` entries) are what the simulator's
terms declare (:mod:`diffpen.terms`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .errors import SceneError
from .state import ContactParams, Params, SpringParams


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _known_value(x):
    """``x`` itself when concrete, the concrete value under a tracer that has one (jax.grad,
    jax.jvp outside jit), else None (jit, vmap: abstract)."""
    if _is_concrete(x):
        return x
    try:
        return x.to_concrete_value()        # None for an abstract tracer
    except Exception:  # noqa: BLE001 - any failure means "abstract"
        return None


def _check_value(name: str, v) -> None:
    """Validate a parameter value: a real scalar (no strings or bools, no arrays: vmap over
    values instead); finite and >= 0 when concrete."""
    if v is None or isinstance(v, (str, bytes, bool, np.bool_)):
        raise SceneError(f"{name} must be a number, got {v!r}"
                         + (": write it without quotes." if isinstance(v, str) else "."))
    if not _is_concrete(v):
        shape = v.shape
    else:
        try:
            raw = np.asarray(v)
        except Exception:  # noqa: BLE001 - ragged lists, odd objects
            raw = np.asarray(None)
        if raw.dtype.kind not in "iuf":
            raise SceneError(f"{name} must be a real number, got {v!r}.")
        shape = raw.shape
    if shape != ():
        raise SceneError(f"{name} must be a scalar, got an array of shape {shape}: "
                         "for several values, jax.vmap a function that calls "
                         "sim.params(k=...) per value (or use tuning.sweep).")
    known = _known_value(v)     # under jax.grad the value is known: check it too
    if known is None:
        return
    arr = np.asarray(known, dtype=float)
    shown = v if known is v else float(arr)
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"{name} must be finite, got {shown!r}.")
    if np.any(arr < 0.0):
        why = ("stiffness and damping cannot be negative" if name.startswith(_PAIR_KINDS)
               else "it cannot be negative")
        raise SceneError(f"{name} must be >= 0, got {shown!r}: {why}.")


#: the range the traced stability flag holds values of this check to (diffpen.stability.bounds)
_check_value.traced_range = (0.0, float("inf"), False)


#: the names under which :func:`_check_value` sees stiffness and damping values
_PAIR_KINDS = ("contact k", "contact c", "spring k", "spring c")


def cast(dtype, v):
    """``v`` as an array of ``dtype``: a host (numpy) array for host values, so building
    params makes no device round trip; a JAX array for JAX arrays and tracers."""
    if isinstance(v, (int, float, np.number, np.ndarray)):
        return np.asarray(v, dtype=dtype)      # host value: no device round trip
    return jnp.asarray(v, dtype=dtype)


def _given_or_declared(given: dict, name: str, fallback, declared):
    """``(k, c)`` of ``name``: ``given[name]`` (else ``fallback``), each None replaced by the
    scene's declared ``declared.k`` / ``declared.c``."""
    pair = given.get(name, fallback)
    if hasattr(pair, "shape") and tuple(pair.shape) == (2,):     # an array (k, c)
        pair = (pair[0], pair[1])
    if not isinstance(pair, (tuple, list)) or len(pair) != 2:
        raise SceneError(f"the value for {name!r} must be a (k, c) pair (None keeps the "
                         f"scene's value), got {pair!r}.")
    kk, cc = pair
    return (declared.k if kk is None else kk), (declared.c if cc is None else cc)


def _checked_pair(sim, make, kind: str, owner: str, kk, cc):
    """``make(k, c)`` in the simulator's dtype after checking both (errors name them as
    ``"{kind} k of {owner} (N/m)"``)."""
    _check_value(f"{kind} k of {owner} (N/m)", kk)
    _check_value(f"{kind} c of {owner} (N s/m)", cc)
    return make(_in_dtype(sim, f"{kind} k of {owner} (N/m)", kk),
                _in_dtype(sim, f"{kind} c of {owner} (N s/m)", cc))


def _in_dtype(sim, name: str, v):
    """:func:`cast` of a checked value to the simulator's dtype, refusing a host value past
    the dtype's largest number (float32: k = 1e300 became inf, and the rollout then said
    "k must be finite, got inf" of a value given finite)."""
    with np.errstate(over="ignore"):        # refused just below, by name
        out = cast(sim.dtype, v)
    if isinstance(out, np.ndarray) and not np.all(np.isfinite(out)):
        top = float(np.finfo(sim.dtype).max)
        raise SceneError(f"{name} = {float(np.asarray(v)):.4g} is past "
                         f"{np.dtype(sim.dtype).name}'s largest number ({top:.4g}): it would "
                         "become inf. Rescale the units, or compile with dtype=jnp.float64.")
    return out


def build(sim, k=None, c=None, *, contact: dict | None = None, spring_k=None,
          spring_c=None, springs: dict | None = None, extra: dict | None = None) -> Params:
    """``sim.params(...)``: see :meth:`diffpen.Simulator.params` (arguments, units)."""
    for what, given, example in (("contact", contact, "{'default': (1e4, 20.0)}"),
                                 ("springs", springs, "{'rope.stretch': (500.0, 0.5)}"),
                                 ("extra", extra, "{'friction': {'default': 0.3}}")):
        if given is not None and not isinstance(given, dict):
            raise SceneError(f"sim.params({what}=...) takes a dict, e.g. {what}={example}; "
                             f"got {given!r}.")
    contact = dict(contact or {})
    springs = dict(springs or {})
    for name in contact:
        if name not in sim.materials:
            raise SceneError(f"contact material {name!r} is not used by any contact pair of "
                             f"this scene; used: {list(sim.materials)}.")
    for name in springs:
        if name not in sim.spring_groups:
            raise SceneError(f"spring group {name!r} is not in this scene; groups: "
                             f"{list(sim.spring_groups)}.")
    out_c = {}
    for name in sim.materials:
        kk, cc = _given_or_declared(contact, name, (k, c), sim.scene.materials[name])
        if kk is None or cc is None:
            raise SceneError(f"contact material {name!r} has no {'k' if kk is None else 'c'}: "
                             "pass sim.params(k=..., c=...) or declare it with "
                             f"scene.add_material({name!r}, k=..., c=...).")
        out_c[name] = _checked_pair(sim, ContactParams, "contact", f"material {name!r}",
                                    kk, cc)
    out_s = {}
    for name in sim.spring_groups:
        kk, cc = _given_or_declared(springs, name, (spring_k, spring_c),
                                    sim.scene.spring_groups[name])
        out_s[name] = _checked_pair(sim, SpringParams, "spring", f"group {name!r}", kk, cc)
    out_x = dict(extra or {})
    unknown = set(out_x) - set(sim._extra_defaults)
    if unknown:
        raise SceneError(f"params extra names {sorted(unknown)}, not in this scene; known: "
                         f"{sorted(sim._extra_defaults)}.")
    for name, default in sim._extra_defaults.items():
        given = out_x.get(name, {})
        if isinstance(default, dict):
            if not isinstance(given, dict):
                raise SceneError(f"params extra[{name!r}] must be a dict of group name -> "
                                 f"value (groups: {sorted(default)}), got {given!r}.")
            unknown = set(given) - set(default)
            if unknown:
                raise SceneError(f"params extra[{name!r}] names {sorted(unknown)}, not in "
                                 f"this scene; known: {sorted(default)}.")
            merged = {g: given.get(g, v) for g, v in default.items()}
            check = sim._extra_checks.get(name, _check_value)
            for g, v in merged.items():
                check(f"{name} parameter of group {g!r}", v)
            out_x[name] = {g: _in_dtype(sim, f"{name} parameter of group {g!r}", v)
                           for g, v in merged.items()}
        elif name not in out_x:
            out_x[name] = default
    return Params(out_c, out_s, out_x)


def validate(sim, params: Params) -> None:
    """Check a :class:`Params` given to a rollout as :func:`build` checks its arguments: the
    simulator's materials, spring groups and extra entries, each value a scalar; finite and
    within its range when concrete (a params tree edited with ``_replace`` passes through
    here too). Raises :class:`SceneError` saying what to change. A set of concrete values
    checked once is remembered per simulator (a repeated rollout pays a look-up)."""
    memo = getattr(sim, "_validated", None)
    key = None
    if memo is not None:
        from .stability.gating import _scalar_key
        values = _scalar_key(params)
        if values is not None:
            key = (jax.tree_util.tree_structure(params), values)
            if key in memo:
                return
    _validate(sim, params)
    if key is not None:
        if len(memo) >= 1024:
            memo.clear()
        memo[key] = True


def _validate(sim, params: Params) -> None:
    """:func:`validate` without the memo."""
    def same(kind, got, want):
        if not isinstance(got, dict) or set(got) != set(want):
            have = sorted(got) if isinstance(got, dict) else type(got).__name__
            raise SceneError(f"params.{kind} has {have}, this simulator has {sorted(want)}: "
                             "build params with sim.params(...) (edits with ._replace keep "
                             "every entry).")
    same("contact", params.contact, sim.materials)
    same("springs", params.springs, sim.spring_groups)
    same("extra", params.extra, sim._extra_defaults)
    for kind, tree, owner, record in (("contact", params.contact, "material", ContactParams),
                                      ("spring", params.springs, "group", SpringParams)):
        for name, pair in tree.items():
            if not isinstance(pair, record):    # a plain (k, c) tuple failed inside the step
                raise SceneError(
                    f"params.{'contact' if kind == 'contact' else 'springs'}[{name!r}] is a "
                    f"{type(pair).__name__}; it must be a diffpen.{record.__name__}: write "
                    f"dp.{record.__name__}(k, c), or build params with sim.params(...).")
            _check_value(f"{kind} k of {owner} {name!r} (N/m)", pair[0])
            _check_value(f"{kind} c of {owner} {name!r} (N s/m)", pair[1])
    for name, default in sim._extra_defaults.items():
        if not isinstance(default, dict):
            continue
        same(f"extra[{name!r}]", params.extra[name], default)
        check = sim._extra_checks.get(name, _check_value)
        for g, v in params.extra[name].items():
            check(f"{name} parameter of group {g!r}", v)
