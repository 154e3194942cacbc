"""A digest of what a plain Python function computes, for result keys.

A sweep written to a file without ``key=`` stores :func:`code_key` of its ``finalize=``
post-processing (what runs on the host, outside the traced program whose jaxpr is keyed), so
that a rerun post-processing its rows another way is refused instead of resumed into the
same file.
"""
from __future__ import annotations

import hashlib
import json
import types
from typing import Callable

from .io import _plain

__all__ = ["code_key"]

#: how many calls deep the plain functions a function reads as globals are followed
DEPTH = 3

#: top-level packages whose functions are named, not followed (their code is the library's:
#: numpy, jax and diffpen's own are keyed by their versions and source digest)
_LIBRARIES = ("numpy", "jax", "jaxlib", "diffpen", "tuning", "builtins", "math", "scipy")


def code_key(fn: Callable, error=ValueError) -> str:
    """``"module.name sha256:..."``: a digest of ``fn``'s code (its bytecode, constants and
    names, those of the functions defined in it) and of the values it uses: the numbers,
    strings and arrays it closes over, takes as defaults or reads as globals (of anything
    else only the type; of a module its name). The plain functions it reads as globals are
    followed the same way, :data:`DEPTH` calls deep, where they are defined outside the
    libraries (:data:`_LIBRARIES`, named by module and name), also under ``jax.jit`` and in a
    ``functools.partial`` (:func:`_feed_global`). Not covered: a value reached only as an
    attribute (``settings.THRESHOLD``), an object's state, what a library function does:
    give such a function a ``key=`` that says it. Raises ``error`` for a callable without
    code of its own (a ``functools.partial``, an object with ``__call__``)."""
    if getattr(fn, "__code__", None) is None:
        raise error(f"a sweep written to out= needs key= when finalize= is not a plain "
                    f"function (got {type(fn).__name__}): say what it does in the key.")
    h = hashlib.sha256()
    _feed_function(h, fn, set(), DEPTH)
    name = f"{getattr(fn, '__module__', '')}.{getattr(fn, '__qualname__', type(fn).__name__)}"
    return f"{name} sha256:{h.hexdigest()[:16]}"


def _data(v) -> bool:
    """Plain data (numbers, strings, arrays and lists of them): stored by value in a key."""
    import numpy as np
    if isinstance(v, np.ndarray):
        return v.dtype.kind in "biuf"
    if v is None or isinstance(v, (bool, int, float, str, np.number, np.bool_)):
        return True
    if isinstance(v, (list, tuple)):
        return all(_data(x) for x in v)
    if isinstance(v, dict):
        return all(isinstance(k, (str, int)) and _data(x) for k, x in v.items())
    return False


def _as_data(v):
    """``v`` as plain data where it holds some: a JAX array as its values, a set as its
    sorted items, a dict's int keys as text; else ``v``."""
    import numpy as np
    if hasattr(v, "__array__") and not isinstance(v, np.ndarray) and not callable(v):
        try:
            return np.asarray(v)
        except Exception:  # noqa: BLE001 - a tracer: not data
            return v
    if isinstance(v, (set, frozenset)):
        return sorted((_as_data(x) for x in v), key=repr)
    if isinstance(v, (list, tuple)):
        return [_as_data(x) for x in v]
    if isinstance(v, dict):         # an int key and its text are told apart
        return {(k if isinstance(k, str) else f"{type(k).__name__}:{k}"): _as_data(x)
                for k, x in v.items()}
    return v


def _feed_value(h, v) -> None:
    v = _as_data(v)
    h.update((json.dumps(_plain(v)) if _data(v) else type(v).__qualname__).encode())


def _feed_function(h, fn: Callable, seen: set, depth: int) -> None:
    """Feed the digest ``h`` with ``fn``'s code and values (:func:`code_key`)."""
    names: list = []

    def feed(const):
        if hasattr(const, "co_code"):                # the function, or one defined inside
            h.update(const.co_code)
            h.update(repr(const.co_names).encode())
            names.extend(const.co_names)
            for c in const.co_consts:
                feed(c)
        elif isinstance(const, tuple):
            h.update(b"(")
            for c in const:
                feed(c)
            h.update(b")")
        elif isinstance(const, frozenset):           # set literals: no stable order
            h.update(repr(sorted(map(repr, const))).encode())
        else:
            h.update(repr(const).encode())
    seen.add(id(fn))
    feed(fn.__code__)
    for v in getattr(fn, "__defaults__", None) or ():
        _feed_value(h, v)
    for k, v in sorted((getattr(fn, "__kwdefaults__", None) or {}).items()):
        h.update(k.encode())
        _feed_value(h, v)
    for cell in getattr(fn, "__closure__", None) or ():
        try:
            value = cell.cell_contents
        except ValueError:                           # a cell not yet filled
            value = None
        _feed_global(h, value, seen, depth)          # a helper it closes over: followed
    glob = getattr(fn, "__globals__", None) or {}
    for n in dict.fromkeys(names):                   # the globals it reads, in code order
        if n not in glob:
            continue                                 # an attribute's name, or a builtin
        h.update(n.encode() + b"=")
        _feed_global(h, glob[n], seen, depth)


def _feed_global(h, g, seen: set, depth: int) -> None:
    """Feed a global ``g`` a function reads: a module by name; a plain function (also one
    under ``jax.jit`` or another wrapper that keeps ``__wrapped__``, and the function and
    arguments of a ``functools.partial``) followed where it is not a library's; anything
    else by value where it holds data (:func:`_as_data`), else by type."""
    import functools
    wrapped = getattr(g, "__wrapped__", None)
    if isinstance(g, types.ModuleType):
        h.update(g.__name__.encode())
    elif isinstance(g, functools.partial):
        _feed_global(h, g.func, seen, depth)
        for v in g.args:
            _feed_value(h, v)
        for k, v in sorted(g.keywords.items()):
            h.update(k.encode())
            _feed_value(h, v)
    elif not isinstance(g, types.FunctionType) and getattr(wrapped, "__code__", None):
        _feed_global(h, wrapped, seen, depth)
    elif isinstance(g, types.FunctionType) and not _library(g):
        if id(g) in seen:
            h.update(b"<again>")
        elif depth > 0:
            _feed_function(h, g, seen, depth - 1)
        else:
            h.update(f"{g.__module__}.{g.__qualname__}".encode())
    elif callable(g) and not _data(g):
        h.update(f"{getattr(g, '__module__', '')}."
                 f"{getattr(g, '__qualname__', type(g).__qualname__)}".encode())
    else:
        _feed_value(h, g)


def _library(g: Callable) -> bool:
    """Whether ``g`` is defined in one of :data:`_LIBRARIES` (named, not followed)."""
    return str(getattr(g, "__module__", "") or "").split(".")[0] in _LIBRARIES
