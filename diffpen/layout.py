"""The layout of per-body vectors inside a compiled step: (n, 3) rows, or three (n,) columns.

Users see positions and velocities as (n_bodies, 3) arrays. Under ``jax.vmap`` those become
(batch, n_bodies, 3): the minor axis has length 3, and XLA CPU cannot vectorise an update
along the batch. Kept as three (n,) columns instead (:class:`Columns`: structure of arrays),
a batch is three (batch, n) arrays, one contiguous vector per component, which XLA
vectorises like a hand-written loop over scalars.

A simulator compiled with ``layout="columns"`` steps in columns. That needs every force term
of its scene to return its force as :class:`Columns` (``Term.columns``; the plane contact
does) and an integrator that moves the state with :func:`diffpen.integrators.kick` /
:func:`~diffpen.integrators.drift` only (``Integrator.columns``): :func:`check` says what
stands in the way otherwise. ``layout="auto"`` (the default of :func:`diffpen.compile`)
takes columns wherever they are possible and rows elsewhere. With the rollout loop compiled
into one kernel (``diffpen.SMALL_LOOP_BYTES``), columns are as fast as rows at batch 1 and
faster from about a thousand rollouts on (1024 balls: recording 1.06x the plain floor against
1.48x in rows, the gradient 1.02x against 1.30x). The terms always read rows: they get
the state with its columns stacked (:func:`rows`), and XLA turns a slice of that stack (the
ground's ``z``) back into the column itself, so nothing is copied. Rollouts convert once at
the start and, after the loop, the whole saved trajectory at once (each state given to
``observe=`` as it is saved). Values are the same in either layout up to rounding: each
component sees the same operations in the same order, but XLA may fuse them differently
(tilted planes, gravity with x or y parts, rk4: the last bit or two, e.g. 9e-16 m/s after
336 steps in float64); axis-aligned scenes at ``-O0`` agree bit for bit (tested).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp

from .state import State

__all__ = ["LAYOUTS", "check", "Columns", "columns", "rows", "add", "columns_state",
           "rows_state", "is_columns", "axpy"]


#: The layouts ``diffpen.compile(..., layout=...)`` accepts: ``"auto"`` (the default) is
#: ``"columns"`` for a scene that can step in columns, else ``"rows"``.
LAYOUTS = ("auto", "rows", "columns")


def check(layout: str, terms, integrator, *, rigid: bool, searching: bool,
          aux_updates: bool) -> str:
    """``layout`` if the compiled step can use it, else raise ``SceneError`` naming what
    stands in the way (the terms, the integrator, rotating bodies, a broad phase...);
    ``"auto"``: ``"columns"`` when nothing stands in the way, else ``"rows"``."""
    from .errors import SceneError
    if layout not in LAYOUTS:
        raise SceneError(f"layout must be one of {LAYOUTS}, got {layout!r}.")
    if layout == "rows":
        return layout
    why = []
    rows_terms = [t.name for t in terms if not t.columns]
    if not terms:
        why.append("the scene has no force term")
    if rows_terms:
        why.append(f"the terms {rows_terms} return rows")
    if not integrator.columns:
        why.append(f"the integrator {integrator.name!r} steps rows only")
    if rigid:
        why.append("the scene has rotating bodies")
    if searching:
        why.append("a broad phase searches at each step")
    if aux_updates:
        why.append("a term updates State.aux at each step")
    if why and layout == "auto":
        return "rows"
    if why:
        raise SceneError("layout='columns' needs a scene whose every force term returns "
                         "columns (sphere and particle contacts with planes) and an explicit "
                         "integrator; here " + "; ".join(why) + ". Use layout='rows'.")
    return "columns"


class Columns(NamedTuple):
    """The three components of (n, 3) per-body vectors as (n,) arrays: x, y, z (SI units of
    the vectors they hold). A pytree: ``jax.tree_util.tree_map`` applies per component."""
    x: Any
    y: Any
    z: Any


def is_columns(a) -> bool:
    """Whether ``a`` is a :class:`Columns`."""
    return isinstance(a, Columns)


def columns(a) -> Columns:
    """(n, 3) rows -> :class:`Columns` of (n,) arrays (``a`` itself if it is already)."""
    if isinstance(a, Columns):
        return a
    return Columns(a[..., 0], a[..., 1], a[..., 2])


def rows(a):
    """:class:`Columns` -> (n, 3) rows (``a`` itself if it is already rows)."""
    if isinstance(a, Columns):
        return jnp.stack(tuple(a), axis=-1)
    return a


def add(a, b):
    """``a + b`` for forces in either layout (rows + columns gives columns)."""
    if isinstance(a, Columns) or isinstance(b, Columns):
        return Columns(*(u + v for u, v in zip(columns(a), columns(b))))
    return a + b


def columns_state(state: State) -> State:
    """``state`` with position and velocity as :class:`Columns`."""
    return state._replace(position=columns(state.position), velocity=columns(state.velocity))


def rows_state(state: State) -> State:
    """``state`` with position and velocity as (n, 3) rows (what users and terms see)."""
    return state._replace(position=rows(state.position), velocity=rows(state.velocity))


def axpy(h, a, x):
    """``x + h * a`` per component for rows or :class:`Columns` alike."""
    if isinstance(x, Columns):
        return Columns(*(u + h * w for u, w in zip(x, columns(a))))
    return x + h * a
