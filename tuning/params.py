"""Addressing leaves of a :class:`diffpen.Params` pytree by dotted path.

``"contact.<material>.k"``, ``"contact.<material>.c"``, ``"springs.<group>.k"``,
``"springs.<group>.c"``, ``"extra.<name>"`` and, for extension entries that are dicts
(drag coefficients, yield strains per group), ``"extra.<name>.<group>"``. A path is the
``jax.tree_util`` key path of the leaf (attribute names and dict keys) joined by dots, so any
pytree of params gets the same names. The fitting code works on a flat ``{path: value}`` dict
and rebuilds the pytree with :func:`unflatten`.
"""
from __future__ import annotations

import jax
import numpy as np

__all__ = ["flatten", "unflatten", "paths", "default_free", "key_name", "path_name",
           "leaf_paths"]


def key_name(key) -> str:
    """The name of one ``jax.tree_util`` path entry: an attribute name, a dict key or an
    index, as text."""
    for attr in ("name", "key", "idx"):
        if hasattr(key, attr):
            return str(getattr(key, attr))
    return str(key)


def path_name(path) -> str:
    """The dotted name of a ``jax.tree_util`` key path, e.g. ``"contact.board.k"``."""
    return ".".join(key_name(k) for k in path)


def flatten(params) -> dict:
    """``{path: leaf}`` for every leaf of ``params``, in ``jax.tree_util`` order (fields in
    their order, dict keys sorted)."""
    return {path_name(path): leaf
            for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]}


def unflatten(template, flat: dict):
    """A pytree like ``template`` with the leaves named in ``flat`` replaced (the other
    leaves kept), each in its template leaf's float dtype where that leaf has one (a float32
    simulator's fitted params stay float32: a fit's float64 values made them a mix)."""
    def put(path, leaf):
        name = path_name(path)
        if name not in flat:
            return leaf
        value, dtype = flat[name], getattr(leaf, "dtype", None)
        if dtype is None or not np.issubdtype(dtype, np.inexact):
            return value            # an int leaf (a hand-built Params) takes the fit's floats
        return value.astype(dtype) if hasattr(value, "astype") else np.asarray(value, dtype)
    return jax.tree_util.tree_map_with_path(put, template)


def paths(params) -> list[str]:
    """All leaf paths of ``params``."""
    return list(flatten(params))


def default_free(params) -> list[str]:
    """The default fitted subset: every contact stiffness and damping."""
    return [p for p in flatten(params) if p.startswith("contact.")]


def leaf_paths(params) -> dict:
    """``{"contact.board.k": key path, ...}``: every leaf of a params pytree by dotted name,
    with its ``jax.tree_util`` key path."""
    return {path_name(path): path
            for path, _ in jax.tree_util.tree_flatten_with_path(params)[0]}
