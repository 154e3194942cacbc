"""Addressing leaves of a :class:`diffpen.Params` pytree by dotted path.

``"contact.<material>.k"``, ``"contact.<material>.c"``, ``"springs.<group>.k"``,
``"springs.<group>.c"``, ``"extra.<name>"`` and, for extension entries that are dicts
(drag coefficients, yield strains per group), ``"extra.<name>.<group>"``. The fitting code
works on a flat ``{path: value}`` dict and rebuilds the pytree with :func:`unflatten`.
"""
from __future__ import annotations

import diffpen as dp

__all__ = ["flatten", "unflatten", "paths", "default_free", "key_name", "leaf_paths"]


def flatten(params: dp.Params) -> dict:
    """``{path: leaf}`` for every leaf of ``params``, in a fixed order."""
    out = {}
    for name, cp in params.contact.items():
        out[f"contact.{name}.k"] = cp.k
        out[f"contact.{name}.c"] = cp.c
    for name, sp in params.springs.items():
        out[f"springs.{name}.k"] = sp.k
        out[f"springs.{name}.c"] = sp.c
    for name, v in params.extra.items():
        if isinstance(v, dict):
            for group, leaf in v.items():
                out[f"extra.{name}.{group}"] = leaf
        else:
            out[f"extra.{name}"] = v
    return out


def unflatten(template: dp.Params, flat: dict) -> dp.Params:
    """A Params like ``template`` with the leaves named in ``flat`` replaced."""
    contact = {n: dp.ContactParams(flat.get(f"contact.{n}.k", cp.k),
                                   flat.get(f"contact.{n}.c", cp.c))
               for n, cp in template.contact.items()}
    springs = {n: dp.SpringParams(flat.get(f"springs.{n}.k", sp.k),
                                  flat.get(f"springs.{n}.c", sp.c))
               for n, sp in template.springs.items()}
    extra = {n: ({g: flat.get(f"extra.{n}.{g}", leaf) for g, leaf in v.items()}
                 if isinstance(v, dict) else flat.get(f"extra.{n}", v))
             for n, v in template.extra.items()}
    return dp.Params(contact, springs, extra)


def paths(params: dp.Params) -> list[str]:
    """All leaf paths of ``params``."""
    return list(flatten(params))


def default_free(params: dp.Params) -> list[str]:
    """The default fitted subset: every contact stiffness and damping."""
    return [p for p in flatten(params) if p.startswith("contact.")]


def key_name(key) -> str:
    """The name of one ``jax.tree_util`` path entry: an attribute name, a dict key or an
    index, as text."""
    for attr in ("name", "key", "idx"):
        if hasattr(key, attr):
            return str(getattr(key, attr))
    return str(key)


def leaf_paths(params) -> dict:
    """``{"contact.board.k": key path, ...}``: every leaf of a params pytree by dotted name,
    from ``jax.tree_util`` key paths (attribute names and dict keys joined by dots)."""
    import jax
    return {".".join(key_name(k) for k in path): path
            for path, _ in jax.tree_util.tree_flatten_with_path(params)[0]}
