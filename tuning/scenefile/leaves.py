"""Params leaves of a scene file's simulator: dotted paths, keystr aliases, the search
space of a leaf, and the default params from the materials' k and c."""
from __future__ import annotations

import numpy as np

from ..params import key_name


def param_leaves(params) -> dict:
    """``{dotted path: leaf}`` of a params pytree, from ``jax.tree_util`` key paths
    (``contact.rubber.k``, ``extra.friction.rubber``, ...)."""
    import jax
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    return {".".join(key_name(k) for k in path): leaf for path, leaf in leaves}


def _keystr_paths(params) -> dict:
    import jax
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    return {jax.tree_util.keystr(path): ".".join(key_name(k) for k in path)
            for path, _ in leaves}


#: leaves that may take any sign (fitted in linear space)
SIGNED = ("offset",)


def signed_leaf(path: str) -> bool:
    """Whether leaf ``path`` may take negative values (a part naming an offset: a plane
    offset); the others (stiffness, damping, friction, slip speed, drag, yield strain) are
    >= 0."""
    parts = path.split(".")
    kind = parts[1] if parts[0] == "extra" and len(parts) > 1 else parts[-1]
    return any(s in kind for s in SIGNED)


def leaf_space(path: str, value) -> str:
    """``"linear"`` for signed leaves (:func:`signed_leaf`, or a value <= 0), ``"log"`` for
    the positive ones (stiffness, damping, friction, slip speed, drag, yield strain)."""
    if signed_leaf(path):
        return "linear"
    try:
        v = float(np.asarray(value))
    except (TypeError, ValueError):
        return "linear"
    return "log" if v > 0.0 else "linear"


def _default_params(sim, k, c):
    contact = {}
    for name in sim.materials:
        m = sim.scene.materials[name]
        contact[name] = (m.k if m.k is not None else k, m.c if m.c is not None else c)
    return sim.params(contact=contact)
