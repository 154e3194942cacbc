"""Pytrees that change: the simulation state and saved trajectories, and the parameters.

* :class:`Params` -- the ONLY thing tuning differentiates: per contact material and per spring
  group stiffness and damping. Values may be Python floats, arrays, or tracers (vmap/grad);
  changing them never recompiles.
* :class:`State` -- what changes each step.
* :class:`Trajectory` -- saved states of a rollout, leading axis = saved step.
"""
from __future__ import annotations

import collections
import inspect
from typing import Any, NamedTuple

__all__ = ["ContactParams", "SpringParams", "Params", "State", "Trajectory"]


class ContactParams(NamedTuple):
    """Penalty contact of one material.

    k: stiffness, N/m (Hunt-Crossley: N/m^n), >= 0.
    c: damping, N s/m (Hunt-Crossley: N s/m^(n+1)), >= 0.
    """
    k: Any
    c: Any


class SpringParams(NamedTuple):
    """Damped springs of one group: k (N/m), c (N s/m)."""
    k: Any
    c: Any


def _own_empty_dicts(name: str, fields: tuple, required: int, dicts: tuple):
    """A namedtuple base of ``fields`` (the first ``required`` of them required, the others
    None by default) whose fields ``dicts``, when left out, each get a new empty dict: a
    shared ``{}`` default would be one dict for every instance, so that
    ``State(t, x, v).aux["key"] = value`` changed every later state's default (a field
    given, None included, is kept as given: ``None`` in a ``jax.vmap`` axes spec)."""
    base = collections.namedtuple(name, fields, defaults=(None,) * (len(fields) - required))

    class Fresh(base):
        __slots__ = ()

        def __new__(cls, *args, **kwargs):
            given = set(fields[:len(args)]) | set(kwargs)
            for field in dicts:
                if field not in given:
                    kwargs[field] = {}
            return base.__new__(cls, *args, **kwargs)
    # what help() and editors show: the fields, their defaults ({} for the dicts)
    kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
    Fresh.__signature__ = inspect.Signature(
        [inspect.Parameter(f, kind) for f in fields[:required]]
        + [inspect.Parameter(f, kind, default={} if f in dicts else None)
           for f in fields[required:]])
    return Fresh


_STATE_FIELDS = ("time", "position", "velocity", "orientation", "angular_velocity", "aux")


class Params(_own_empty_dicts("Params", ("contact", "springs", "extra"), 2,
                              ("extra",))):
    """Differentiable parameters of a compiled scene.

    contact: ``{material name: ContactParams}`` for every material some contact pair uses.
    springs: ``{group name: SpringParams}`` for every spring group in the scene.
    extra: ``{name: value}`` of the other terms' parameters: the built-in ones keep
      ``"friction"`` ``{material: mu}``, ``"drag"`` ``{group: c}`` (N s/m),
      ``"plane_offset"`` ``{plane name: offset}`` (m) and ``"plastic"`` ``{group: yield
      strain}`` where the scene has them, extension terms their own (default: a new empty
      dict).
    """
    __slots__ = ()


class State(_own_empty_dicts("State", _STATE_FIELDS, 3, ("aux",))):
    """Simulation state.

    time: scalar, s.
    position: (n_bodies, 3) body centres, m.
    velocity: (n_bodies, 3) m/s.
    orientation: (n_bodies, 4) unit quaternions (w, x, y, z), or None for scenes without
      rotating bodies (then no orientation code is traced).
    angular_velocity: (n_bodies, 3) world-frame rad/s, or None (as orientation).
    aux: a dict of what terms carry between steps (e.g. plastic rest lengths, the broad
      phase's overflow flag) and ``"unstable"``: a bool scalar, set (and kept) by a rollout
      whose step is past the safe step for its parameter values (:mod:`diffpen.stability`;
      computed inside the traced program, so it works under jit, vmap and grad). Default:
      a new empty dict.
    """
    __slots__ = ()


class Trajectory(_own_empty_dicts("Trajectory", _STATE_FIELDS + ("observed",), 3,
                                  ("aux",))):
    """States saved by a rollout; the leading axis of every field is the saved step.

    time: (n_saved,) s, the time after each saved step.
    position: (n_saved, n_bodies, 3) m.  velocity: (n_saved, n_bodies, 3) m/s.
    orientation: (n_saved, n_bodies, 4) or None.  angular_velocity: (n_saved, n_bodies, 3)
      or None.
    aux: saved ``State.aux`` entries, leading axis n_saved (``aux["unstable"][-1]``: whether
      the rollout ran past its safe step).
    observed: ``observe(state)`` saved at each saved step when the rollout was given an
      ``observe`` function (then position, velocity, orientation and angular_velocity are
      None: only what was asked for is stored); else None.
    """
    __slots__ = ()

    @property
    def final(self) -> State:
        """The last saved state, usable as the start of another rollout."""
        import jax
        if self.position is None:
            raise ValueError("this trajectory saved only observe(state): roll out without "
                             "observe= to keep full states.")
        return State(*jax.tree_util.tree_map(lambda a: a[-1], tuple(self)[:6]))
