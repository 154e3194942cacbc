"""The start energy of a simulator's rollout: what bounds the reference depth of a contact law
that stiffens with depth (:mod:`diffpen.stability.depth`), read from a simulator, its start
state and its params.

* :func:`host`: the energy (J) on the host, for the up-front check (``sim.start_energy``);
  None where the radii bound the depth, or where a value it needs is traced;
* :func:`traced`: the same from traced values (a start state under ``jax.vmap``, a named
  plane's offset under ``jax.jit``), for the rollout's traced flag: ``inf`` where the radii
  bound the depth;
* :func:`left_to_flag` and :func:`with_hint`: an up-front refusal whose start is traced says
  that the check counted the radius and how the traced flag counts the energy instead.
"""
from __future__ import annotations

import jax.numpy as jnp

from .errors import StabilityError
from .params import _is_concrete
from .stability import depth as _depth
from .terms.plastic import AUX_KEY as _PLASTIC_REST

__all__ = ["host", "traced", "left_to_flag", "with_hint"]


def _spin(sim, state) -> dict:
    if sim._rigid is None:
        return {}
    return dict(orientation=state.orientation, angular_velocity=state.angular_velocity,
                inertia=sim._moments)


def _plane_offsets(sim, params) -> list | None:
    """The planes' offsets (m), a named plane's from ``params`` (None: a named plane and no
    params)."""
    if all(p.name is None for p in sim.scene.planes):
        return [float(p.offset) for p in sim.scene.planes]
    if params is None:
        return None
    given = params.extra.get("plane_offset", {})
    return [given[p.name] if p.name is not None else float(p.offset) for p in sim.scene.planes]


def _spring_k(params) -> dict | None:
    """The spring groups' stiffness (N/m) in ``params`` (None without params)."""
    return None if params is None else {g: sp.k for g, sp in params.springs.items()}


def _state_values(sim, state) -> tuple:
    return (state.position, state.velocity, state.aux.get(_PLASTIC_REST),
            *_spin(sim, state).values())


def left_to_flag(sim, state, params) -> bool:
    """Whether the start state or a named plane's offset is traced in a scene whose energy
    could bound the depth: :func:`host` cannot count it, the traced flag does."""
    if sim.analysis.depth_exponent is None:
        return False
    offsets = _plane_offsets(sim, params) or []
    return not all(map(_is_concrete, (*_state_values(sim, state), *offsets)))


def host(sim, state, params=None) -> float | None:
    """``sim.start_energy(state, params)`` (its docstring): the energy (J) on the host, or
    None (also where a spring stiffness in ``params`` is traced: :func:`traced` counts it)."""
    if sim.analysis.depth_exponent is None:
        return None
    offsets, ks = _plane_offsets(sim, params), _spring_k(params)
    if (offsets is None or left_to_flag(sim, state, params)
            or not all(map(_is_concrete, (ks or {}).values()))):
        return None
    return _depth.start_energy(sim.scene, sim.mass, sim.radius, sim.pinned, sim._collide,
                               state.position, state.velocity, offsets=offsets, spring_k=ks,
                               plastic_rest=state.aux.get(_PLASTIC_REST), **_spin(sim, state))


def traced(sim, params, state):
    """:func:`host` from traced values, for the traced flag: ``inf`` where the radii bound
    the depth."""
    return _depth.energy_bound(sim.scene, sim.mass, sim.radius, sim.pinned, sim._collide,
                               state.position, state.velocity,
                               offsets=_plane_offsets(sim, params), spring_k=_spring_k(params),
                               plastic_rest=state.aux.get(_PLASTIC_REST), xp=jnp,
                               **_spin(sim, state))


def with_hint(exc: StabilityError) -> StabilityError:
    """``exc`` (the up-front check's refusal of a rollout whose start is traced:
    :func:`left_to_flag`) saying that the radius was counted and how to count the energy."""
    return StabilityError(
        f"{exc} The start state (or a named plane's offset) is traced under jit or vmap, so "
        "this check counted the contact at the bodies' radius, not at the depth the start "
        "energy allows (diffpen.stability.depth): give a concrete start state, or pass "
        "check_stability=False and read the rollout's traced flag (traj.aux['unstable']), "
        "which counts each traced start's own energy.", stable_dt=exc.stable_dt,
        substeps=exc.substeps)
