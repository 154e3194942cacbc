"""Plastic (crumple) springs: rest lengths that shorten irreversibly under compression.

A plastic spring (``scene.add_plastic_spring``) is a damped spring ``F = -k (l - L) - c dl/dt``
whose rest length ``L`` (m) lives in ``State.aux["plastic_rest"]`` (shape ``(m,)``, one per
plastic spring) and is updated after every step from the new length ``l`` by a smooth return
mapping, written for ONE spring in :func:`rest_update`::

    e     = (L - l) / L0 - eps_y          # compression beyond the yield, in strain
    L_new = L - L0 * ramp(e - w / 2, w)    # laws.ramp: C1, exactly 0 for e <= 0

``L0`` is the initial rest length (static), ``eps_y`` the yield strain (dimensionless, in
(0, 1); ``params.extra["plastic"][group]``, differentiable) and ``w`` the static smoothing width
in strain (``scene.plastic_smoothing``, default 1e-3; 0 gives the hard mapping
``L_new = min(L, l + eps_y L0)``). So:

* below the yield (``L - l <= eps_y L0``) nothing changes: the spring is elastic;
* beyond it the rest length follows the compressed length, keeping an elastic compression of
  about ``eps_y L0`` (exactly, once the flow has converged), so after unloading the spring
  springs back by ``eps_y L0`` only and stays shorter (permanent set);
* ``L`` never grows: the deformation is irreversible; stretching is elastic;
* the update is C1 in ``l``, ``L`` and ``eps_y``, so gradients exist through yielding.

``k`` and ``c`` are the spring group's (``params.springs[group]``). A scene without plastic
springs traces none of this and carries no ``aux`` entry.
"""
from __future__ import annotations

import jax
import numpy as np

from .. import geometry, laws
from ..errors import SceneError
from .base import CompileContext, Term, TermBuilder, _select, scatter
from .springs import _spring_axis

__all__ = ["rest_update", "AUX_KEY", "COLLAPSED", "COLLAPSE_FRACTION", "TERMS"]

#: ``State.aux`` key of the plastic rest lengths, (m,) metres.
AUX_KEY = "plastic_rest"
#: ``State.aux`` key of a 0 / 1 scalar, set to 1 (and kept) once a plastic spring has been crushed
#: below :data:`COLLAPSE_FRACTION` of its initial rest length: members have no volume and
#: nodes no self-contact, so a member crushed that far passes through zero length and turns
#: inside out (its axis flips and it pushes the wrong way) unnoticed; a rollout that sets it
#: warns (:class:`CollapseWarning`)
COLLAPSED = "plastic_collapsed"
#: the shortest length, as a fraction of the initial rest length, a plastic spring may reach
#: before :data:`COLLAPSED` is set
COLLAPSE_FRACTION = 0.05


class CollapseWarning(UserWarning):
    """A plastic spring (crumple member) crushed below :data:`COLLAPSE_FRACTION` of its
    length: past what a model without member volume or self-contact describes."""


def warn_collapse(traj) -> None:
    """Warn when a concrete trajectory's ``aux["plastic_collapsed"]`` is set."""
    from ..errors import warn
    flag = traj.aux.get(COLLAPSED) if isinstance(traj.aux, dict) else None
    if flag is not None and float(np.asarray(flag).reshape(-1)[-1]) > 0.0:
        warn(f"a plastic spring (crumple member) was crushed below {COLLAPSE_FRACTION:g} of "
             "its initial length: members have no volume and nodes no self-contact, so past "
             "that it passes through zero length and turns inside out (a crumple bar hit at "
             "2 m/s inverted, unflagged). The rollout's aux['plastic_collapsed'] says so; "
             "stiffen the members (k) or raise the yield strain, or slow the impact.",
             CollapseWarning)


def rest_update(length, rest, rest0, yield_strain, width: float):
    """New rest length of ONE plastic spring after a step.

    Args:
      length: current length l, m.  rest: current rest length L, m.
      rest0: initial rest length L0, m.  yield_strain: eps_y, dimensionless in (0, 1).
      width: static smoothing width in strain (>= 0).
    Returns: the new rest length, m (never larger than ``rest``).
    """
    excess = (rest - length) / rest0 - yield_strain
    return rest - rest0 * laws.ramp(excess - 0.5 * width, width)


def _check_yield(label: str, value) -> None:
    """A yield strain: a real scalar as every parameter (``params._check_value``: no strings,
    bools or arrays), within (0, 1) when concrete (under jax.grad too)."""
    from ..params import _check_value, _known_value
    try:
        known = _known_value(value)
        arr = None if known is None else np.asarray(known, dtype=float)
    except (TypeError, ValueError):
        known = arr = None                    # not a number: _check_value says so
    if arr is None or np.all(np.isfinite(arr) & (arr >= 0.0)):
        _check_value(label, value)       # a real scalar (its range is checked below)
    elif arr.shape != ():
        _check_value(label, np.full(arr.shape, 0.5))    # says: one scalar, not an array
    if known is None:
        return
    arr = np.asarray(known, dtype=float)
    if not np.all((arr > 0.0) & (arr < 1.0)):
        raise SceneError(f"{label} is a yield strain and must be in (0, 1) (compression at "
                         f"which a member starts to crumple, as a fraction of its length), got "
                         f"{value!r}.")


_check_yield.traced_range = (0.0, 1.0, True)     # open (diffpen.stability.bounds)


def _plastic_springs(ctx: CompileContext) -> Term | None:
    springs = ctx.scene.plastic_springs
    if not springs:
        return None
    groups = list(dict.fromkeys(s.group for s in springs))
    ia = np.array([s.a for s in springs], dtype=np.int32)
    ib = np.array([s.b for s in springs], dtype=np.int32)
    gi = np.array([ctx.group_index[s.group] for s in springs], dtype=np.int32)
    yi = np.array([groups.index(s.group) for s in springs], dtype=np.int32)
    rest0 = ctx.const([s.rest_length for s in springs])
    width = float(ctx.scene.plastic_smoothing)
    if not (np.isfinite(width) and width >= 0.0):
        raise SceneError(f"scene.plastic_smoothing must be a strain width >= 0 (0 = hard "
                         f"yield), got {ctx.scene.plastic_smoothing!r}.")
    n = ctx.n

    def force(params, state):
        k, c = ctx.spring_kc(params, gi)
        rest = state.aux[AUX_KEY]
        length, rate, u = _spring_axis(state.position[ia] - state.position[ib],
                                       state.velocity[ia] - state.velocity[ib], 0.0)
        f = laws.spring_force(length - rest, rate, k, c)[:, None] * u
        return scatter(f, ia, n) - scatter(f, ib, n), None

    def aux_update(params, state):
        with jax.named_scope("plastic_yield"):
            eps = _select([params.extra["plastic"][g] for g in groups], yi)
            length = geometry.safe_norm(state.position[ia] - state.position[ib])
            new = rest_update(length, state.aux[AUX_KEY], rest0, eps, width)
            crushed = jax.numpy.any(length < COLLAPSE_FRACTION * rest0)
            old = state.aux[COLLAPSED]          # 0 or 1 (the aux entries take the float dtype)
        return {AUX_KEY: new, COLLAPSED: jax.numpy.maximum(
            old, jax.lax.stop_gradient(crushed).astype(old.dtype))}

    return Term("plastic_springs", force,
                extra={"plastic": {g: ctx.scene.plastic_groups[g] for g in groups}},
                checks={"plastic": _check_yield},
                aux={AUX_KEY: np.array([s.rest_length for s in springs]),
                     COLLAPSED: 0.0}, update=aux_update, report=warn_collapse)


def _plastic_groups(ctx: CompileContext) -> tuple:
    """The spring groups of the plastic springs (their k, c), in scene order."""
    return tuple(dict.fromkeys(s.group for s in ctx.scene.plastic_springs))


def _plastic_bound(ctx: CompileContext):
    """The plastic springs' Gershgorin rows: those of springs with their group's k and c
    (yielding only shortens the rest length; the stiffness stays)."""
    from .springs import _spring_rows
    return _spring_rows(ctx, ctx.scene.plastic_springs)


#: The plastic-spring term builder, with its stability bound.
TERMS: tuple = (TermBuilder(_plastic_springs, _plastic_bound, groups=_plastic_groups),)
