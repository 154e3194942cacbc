"""Force terms: each one pair law of :mod:`diffpen.laws` / :mod:`diffpen.geometry` lifted to
the scene by ``jax.vmap`` over static index arrays plus a segment sum onto bodies.

One module per kind of term: :mod:`~diffpen.terms.contact` (planes, fixed spheres,
sphere-sphere, broad-phase pairs), :mod:`~diffpen.terms.springs` (springs, world springs,
drag), :mod:`~diffpen.terms.plastic`, :mod:`~diffpen.terms.rigid` (box corners, sphere-box,
anchored springs), :mod:`~diffpen.terms.friction` (smooth Coulomb friction: its law, and
spheres and particles on rough planes and fixed spheres); the record and shared helpers are
:mod:`~diffpen.terms.base`.
A term builder ``build(ctx) -> Term | None`` returns None when the scene does not need the
term, so it is never traced; its Term carries its force, stability bound, aux state
init/update and extra params, and its :class:`~diffpen.terms.base.TermBuilder` declares
the contact materials and spring groups it reads (compile makes ``Params.contact`` /
``Params.springs`` their union). :data:`BUILTIN` is the one fixed tuple of every built-in
builder, in force summation order. Nothing registers itself on import. The pair sources
(all pairs, :class:`diffpen.broadphase.AABB`, :class:`diffpen.broadphase.Grid`) only find
pairs for the contact terms.
"""
from __future__ import annotations

from . import contact, plastic, rigid, springs
from .base import (CompileContext, Term, TermBuilder, declared, gather, merge_extra,
                   plane_offset_extra, plane_offsets, scatter, static_dot, static_scale,
                   with_bound)
from .springs import spring_bands

__all__ = ["Term", "TermBuilder", "CompileContext", "CORE", "BUILTIN", "with_bound",
           "declared", "merge_extra", "gather", "scatter", "static_dot", "static_scale",
           "spring_bands", "plane_offsets", "plane_offset_extra"]

#: The core term builders with their stability bounds, in force summation order.
CORE: tuple = (contact.PLANE, contact.FIXED_SPHERE, contact.SPHERE_SPHERE,
               springs.BODY_SPRINGS, springs.WORLD_SPRINGS, springs.DRAG)

#: Every built-in term builder, in force summation order (fixed; nothing is appended on
#: import). Each returns a Term (carrying its stability bound) or None when the scene does
#: not need it.
BUILTIN: tuple = (*CORE, *plastic.TERMS, *rigid.TERMS, contact.BROADPHASE)
