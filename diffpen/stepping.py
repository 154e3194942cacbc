"""The step a simulator integrates, built from its terms: the integrator's step over ``dt`` in
``n`` inner steps (:func:`build`), the accelerations it evaluates at the inner step ``h``
(contacts averaged over the step's window), the terms' searches run once per step at the
state it starts from, and the terms' ``State.aux`` updates after each inner step.
:meth:`diffpen.Simulator.step_function` builds one per substep count and keeps it.
"""
from __future__ import annotations

import jax
import numpy as np

from .checks import state_values_ok
from .integrators import build_step, substepped

__all__ = ["build", "hold_pins", "jitted", "flagged"]


def build(sim, n: int):
    """The pure step ``step(params, state) -> state`` of ``sim`` over ``dt`` in ``n`` inner
    steps of ``h = dt / n`` (:mod:`diffpen.integrators`), with the terms' aux updates after
    each inner step (a plastic spring yields at the inner step's resolution, whatever ``n``:
    applied once per saved step, its permanent set came out 13% short at 100 substeps)."""
    h = sim.dt / n if n != 1 else sim.dt
    method = sim.analysis.integrator
    inv_mass = np.where(sim.pinned, 0.0, 1.0 / sim.mass)
    if sim._searching:
        inner = _searching_step(sim, h, inv_mass)
    else:
        inner = _carrying(sim, build_step(method, _accel_at(sim, h), h, inv_mass=inv_mass), h)
    if sim._aux_updates:
        inner = _with_aux_updates(inner, sim._aux_updates)
    return _spin_flagged(sim, substepped(inner, n), h)


def _spin_flagged(sim, step, h: float):
    """``step`` that also ors into a state's ``aux["unstable"]`` flag (where it has one)
    whether a rigid body spins past its integrator's limit after it
    (:func:`diffpen.motion.spin_unsafe`): a torque can spin a body up during a rollout whose
    start was within the limit. ``step`` itself where no body has a spin limit (no rigid
    body with unequal moments, or an integrator without one)."""
    from . import motion as _motion
    from .stability import FLAG
    if not (np.any(sim._spin_kappa) and _motion.spin_limit(sim) is not None):
        return step

    def flagged_step(params, state):
        new = step(params, state)
        if FLAG not in new.aux:
            return new
        with jax.named_scope("spin_flag"):
            spun = _motion.spin_unsafe(sim, new, h)
        return new._replace(aux={**new.aux, FLAG: new.aux[FLAG] | spun})
    return flagged_step


def hold_pins(sim, state):
    """``state`` with the velocity (and spin) of ``sim``'s pinned bodies set to zero; the state
    itself when the scene has none. A pinned body takes no force (inverse mass 0), so once
    its velocity is zero it stays in place: :meth:`~diffpen.Simulator.rollout` and
    :meth:`~diffpen.Simulator.step` apply this to the state they start from. A concrete start
    state with a pin moving is refused up front; one built under jit or vmap cannot be
    checked (its values are tracers), and this keeps its pins in place. The step itself is
    left as it is (no select per step)."""
    if not np.any(sim.pinned):
        return state
    import jax.numpy as jnp
    held = np.asarray(sim.pinned, bool)[:, None]
    state = state._replace(velocity=jnp.where(held, 0.0, state.velocity))
    if state.angular_velocity is not None:
        state = state._replace(angular_velocity=jnp.where(held, 0.0, state.angular_velocity))
    return state


def _carrying(sim, step, h: float):
    """``step`` followed by the rigid bodies' angular-momentum transport where the simulator
    carries it (semi-implicit or implicit Euler and a body with unequal moments:
    :meth:`diffpen.rigid.RigidDynamics.transport`); ``step`` itself otherwise."""
    rigid = sim._rigid
    if rigid is None or rigid.carried.size == 0:
        return step

    def carried(params, state):
        new = step(params, state)
        with jax.named_scope("angular_momentum_transport"):
            return rigid.transport(state, new, h)
    return carried


def _accel_at(sim, h: float):
    """``accel_fn(params, state)`` of an integrator whose inner step is ``h`` s."""
    def accel(params, state):
        return sim.acceleration(params, state, h=h)
    return accel


def _with_aux_updates(step, updates):
    """Apply the terms' ``aux_update(params, state)`` after each (inner) step (e.g. plastic
    rest lengths, updated from the new positions)."""
    def stepped(params, state):
        state = step(params, state)
        aux = dict(state.aux)
        for update in updates:
            aux.update(update(params, state))
        return state._replace(aux=aux)
    return stepped


def _searching_step(sim, h: float, inv_mass):
    """One integrator step of ``h`` s that runs each term's ``search`` once, at the state
    the step starts from: the force evaluation at that state (the first one of every
    integrator, the only one of semi-implicit Euler) uses it, and ``record`` writes its
    ``State.aux`` entries. Evaluations at other states (verlet's second, rk4's stages 2-4,
    implicit Euler's Jacobian products) search for themselves."""
    searching = sim._searching
    method = sim.analysis.integrator

    def step(params, state):
        found = {}
        for term in searching:
            with jax.named_scope(term.name):
                found[term.name] = term.search(params, state)

        def accel(p, s):
            # the very objects the step got: the integrator evaluates at its start state
            return sim.acceleration(p, s, found if (s is state and p is params) else None,
                                    h=h)
        new = _carrying(sim, build_step(method, accel, h, inv_mass=inv_mass), h)(params, state)
        aux = dict(new.aux)
        for term in searching:
            if term.record is not None:
                aux.update(term.record(aux, found[term.name]))
        return new._replace(aux=aux)
    return step


def flag_mode(params, state, check: bool):
    """What :meth:`~diffpen.Simulator.step` sets in ``aux["unstable"]``: ``"bound"`` for
    traced params (:func:`flagged`, as a rollout), ``"values"`` for concrete params (the
    gate checked them) and a traced state (its spin and whether it is finite: cheap), else
    None."""
    def traced(tree):
        return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))
    if not check:
        return None
    return "bound" if traced(params) else "values" if traced(state) else None


def flagged(sim, params, state, h, energy=None, add: bool = False, bound: bool = True):
    """``state`` with its ``aux["unstable"]`` flag or-ed with whether ``params`` (cast) are
    past the safe step at the inner step ``h`` (not without ``bound``), its spin past the
    spin limit or its values not finite: the traced flag of a rollout (once, before its
    loop) and of a step in a jitted scan (every step). ``energy``: the up-front gate's (else
    traced from ``state`` where the contact law needs one). A state without the flag gets
    one only with ``add`` (a step keeps the structure of the state it is given)."""
    import jax.numpy as jnp

    from . import motion as _motion
    from . import start_energy as _start_energy
    from . import stability as _stability
    old = state.aux.get(_stability.FLAG)
    if old is None and not add:
        return state
    flag = _motion.spin_unsafe(sim, state, h)
    if bound:
        if energy is None and sim.analysis.depth_exponent is not None:
            # the start state or a named plane's offset is traced: the same energy, traced
            energy = _start_energy.traced(sim, params, state)
        flag = flag | _stability.unsafe(sim.analysis, params, h=h, energy=energy)
    for a in (state.position, state.velocity, state.orientation, state.angular_velocity):
        if a is not None:       # a traced start state with NaN or inf in it (audit17)
            flag = flag | ~jnp.all(jnp.isfinite(a))
    flag = flag if old is None else (jnp.asarray(old, bool) | flag)
    return state._replace(aux={**state.aux, _stability.FLAG: flag})


def jitted(sim, n: int | None, flag: str | None = None):
    """``sim``'s jitted step over ``n`` inner steps (None: its own count, 1 for "auto"),
    built once per count: what :meth:`~diffpen.Simulator.step` calls. It takes the state as
    given and returns ``(new state, ok)``: the step from the state with its pins held
    (:func:`hold_pins`) and whether the given state's values are valid
    (:func:`diffpen.checks.state_values_ok`). With ``flag`` (:func:`flag_mode`) the
    state's ``aux["unstable"]`` flag is set first (:func:`flagged`)."""
    n = int(n) if n is not None else (sim.substeps if isinstance(sim.substeps, int) else 1)
    key = ("jit", n, flag)
    if key not in sim._steps:
        step = sim.step_function(n)

        def run(params, state):
            ok = state_values_ok(sim, state)
            if flag:
                state = flagged(sim, params, state, sim.dt / n, bound=flag == "bound")
            return step(params, hold_pins(sim, state)), ok
        sim._steps[key] = jax.jit(run)
    return sim._steps[key]
