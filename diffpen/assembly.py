"""Term assembly, the first half of ``diffpen.compile``: which term builders run
(:func:`builders`), the params keys they declare (:func:`declared`), and the terms built in
force summation order with what they declare gathered onto the :class:`CompileContext`
(:func:`build_terms`: ``Params.extra`` defaults and checks, ``State.aux`` entries and
updates)."""
from __future__ import annotations

from . import terms as _terms
from .errors import SceneError
from .terms import CompileContext, Term

__all__ = ["builders", "declared", "build_terms"]


def builders(terms) -> tuple:
    """The term builders of ``compile(..., terms=...)``: ``diffpen.terms.BUILTIN`` for None."""
    if terms is None:
        return _terms.BUILTIN
    if isinstance(terms, (str, bytes)) or not hasattr(terms, "__iter__"):
        raise SceneError(f"terms must be a sequence of term builders (e.g. "
                         f"(*diffpen.terms.BUILTIN, my_builder)), got {terms!r}.")
    terms = tuple(terms)
    for b in terms:
        if not callable(b):
            raise SceneError(f"terms must hold term builders, build(ctx) -> Term | None "
                             f"(diffpen.terms.TermBuilder or a function); got {b!r}.")
        if not isinstance(getattr(b, "passive", False), bool):
            raise SceneError(f"a term builder's passive must be True or False (whether the "
                             f"term only takes energy away), got {b.passive!r}.")
    return terms


def declared(builders, ctx: CompileContext, facet: str, known: dict, what: str,
              fix: str) -> tuple:
    """The union of the builders' ``facet`` declarations (:func:`diffpen.terms.declared`),
    each one checked against the scene's ``known`` names."""
    names = _terms.declared(builders, ctx, facet)
    for name in names:
        if not isinstance(name, str) or name not in known:
            raise SceneError(f"a term declares the {what} {name!r}, which the scene does not "
                             f"have: declare it with {fix.format(name)}; the scene has "
                             f"{sorted(known)}.")
    return names


def build_terms(builders, ctx: CompileContext) -> tuple:
    """Build every term the scene needs, in order, and assemble onto ``ctx`` what they
    declare: ``Params.extra`` defaults and checks, initial ``State.aux`` entries and the
    aux updates run after each step."""
    built = []
    for build in builders:
        term = build(ctx)
        if term is None:
            continue
        if not isinstance(term, Term):
            raise SceneError(f"term builder {build!r} returned {type(term).__name__}, not a "
                             "diffpen.terms.Term (or None).")
        _terms.merge_extra(ctx.extra_defaults, term.extra)
        ctx.extra_checks.update(term.checks)
        ctx.aux_init.update(term.aux)
        if term.update is not None:
            ctx.aux_updates.append(term.update)
        built.append(term)
    return tuple(built)
