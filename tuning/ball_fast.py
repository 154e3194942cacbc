"""A batched fast path for the ball on a plane (a prototype of a batch-minor layout): the
rollouts of a batch of (k, c) near the speed of the plain floor, with results identical to
``sim.rollout`` under ``jax.vmap``.

Under ``jax.vmap`` a rows-layout state is (batch, bodies, 3): its minor axis has length 3, so
XLA CPU cannot vectorise the step along the batch. (The default layout, ``"auto"``, steps such
a ball in columns and now comes close: recording at batch 1024 1.43x the plain floor against
this path's 1.21x, ``benchmarks/scale_table.py``.) For the most common sweep, one sphere dropped
onto one plane ``z = offset`` with the semi-implicit Euler step, this module steps the whole
batch as one (B,) array per component (structure of arrays, batch minor) and records the
heights time-major, (steps, B). It evaluates the very contact force the simulator applies
(``sim.contact_law.step_force`` with the simulator's smoothing width and step) with the same
operations in the same order as the compiled step, so every height equals the rollout's bit
for bit (``tests/test_tuning_sweep_fast.py`` checks it against ``sim.rollout``
and the whole sweep against the generic one). :func:`supports` says when it applies;
anything else takes the generic path.
"""
from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp
from diffpen.integrators import kick_then_drift

from . import params as P
from .compiled import ProgramCache

__all__ = ["supports", "ball_heights", "ball_sweep_evaluator"]


def supports(sim: dp.Simulator) -> str | None:
    """None when the fast path reproduces ``sim.rollout`` exactly, else the reason it does
    not: one sphere, one plane with normal (0, 0, 1), gravity along z, the plane contact as
    the only term, the semi-implicit Euler step without substeps or a broad phase, no
    horizontal start velocity."""
    scene = sim.scene
    if sim.n_bodies != 1 or len(scene.planes) != 1:
        return "the fast path needs exactly one body and one plane"
    if tuple(sim.terms) != ("contact_plane",):
        return f"the fast path handles the plane contact only, not {list(sim.terms)}"
    if not kick_then_drift(sim.analysis.integrator) or sim.substeps != 1:
        return "the fast path needs the semi-implicit Euler step without substeps"
    if sim.broadphase is not None or bool(np.any(sim.pinned)):
        return "the fast path needs no broad phase and a free body"
    if tuple(scene.planes[0].normal) != (0.0, 0.0, 1.0):
        return "the fast path needs the plane's normal (0, 0, 1)"
    if scene.gravity[0] != 0.0 or scene.gravity[1] != 0.0:
        return "the fast path needs gravity along z"
    with jax.ensure_compile_time_eval():     # concrete even inside a traced function
        s0 = sim.init_state()
    extra_aux = set(s0.aux) - {dp.stability.FLAG}          # the stability flag is not state
    if s0.orientation is not None or extra_aux or bool(np.any(np.asarray(s0.velocity)[0, :2])):
        return "the fast path needs a sphere without horizontal start velocity"
    return None


def ball_heights(sim: dp.Simulator, k, c, steps: int, *, velocities: bool = False,
                 unroll: int = 1):
    """Heights and vertical velocities of the ball for a batch of contact (k, c).

    Args:
      sim: a simulator :func:`supports` accepts.  k: (B,) stiffness, N/m.  c: (B,) damping,
        N s/m (the plane's material; cast to ``sim.dtype`` as the rollout does).
      steps: number of steps (static).  velocities: also record the vertical velocities.
      unroll: of the ``lax.scan`` (1, the fastest measured on 1024 balls).
    Returns: (steps, B) centre heights (m) after every step, time-major, or ``(z, v)`` with
      the vertical velocities (m/s) when ``velocities``; ``z[:, i]`` equals
      ``sim.rollout(sim.params(k=k[i], c=c[i]), steps).position[:, 0, 2]`` bit for bit.
    """
    why = supports(sim)
    if why is not None:
        raise ValueError(why)
    key = (sim, int(steps), bool(velocities), int(unroll))
    run = _PROGRAMS.get(key, lambda: jax.jit(functools.partial(
        _heights, sim, steps=key[1], velocities=key[2], unroll=key[3])))
    return run(jnp.asarray(k, sim.dtype), jnp.asarray(c, sim.dtype))


#: compiled :func:`ball_heights` programs by (simulator, steps, velocities, unroll), the
#: last 8 (an eager scan over a new closure compiled again at every call: 0.1 s a call)
_PROGRAMS = ProgramCache()


def _heights(sim, k, c, *, steps: int, velocities: bool, unroll: int):
    """:func:`ball_heights` of (B,) ``k`` and ``c`` of the simulator's dtype."""
    dtype = sim.dtype
    law = sim.contact_law         # the simulator's record: its step-averaged force
    width = sim.smoothing
    # NumPy constants, as the compiled step has them: XLA folds them into the arithmetic the
    # same way (e.g. (radius - z) + h becomes (radius + h) - z in the smoothing blend)
    npdt = np.dtype(dtype)
    radius = np.asarray(sim.radius[:1], npdt)
    offset = np.asarray([sim.scene.planes[0].offset], npdt)
    inv_m = np.asarray(np.where(sim.pinned, 0.0, 1.0 / sim.mass)[:1], npdt)
    g = np.asarray(sim.scene.gravity[2], npdt)
    dt = sim.dt
    # the plane term's call (diffpen.terms.contact): centred laws take the effective inverse
    # mass and gravity's separating acceleration as constants of the simulator's dtype
    inv_mc, g_c = jnp.asarray(inv_m[0], dtype), jnp.asarray(g, dtype)
    centred = width == 0.0 and law.averaged is not None and law.centred is not None

    def force(d, vn):
        if centred:
            return law.centred_force(d, vn, k, c, dt, 0.5 * dt, inv_mc, g_c)
        return law.step_force(d, vn, k, c, width, h=dt)
    s0 = sim.init_state()

    def step(s, _):
        z, v = s
        d = radius - (z - offset)         # penetration, as the compiled step computes it
        a = force(d, v) * inv_m + g
        v = v + dt * a
        z = z + dt * v
        return (z, v), ((z, v) if velocities else z)
    z0 = jnp.broadcast_to(jnp.asarray(s0.position[0, 2], dtype), k.shape)
    v0 = jnp.broadcast_to(jnp.asarray(s0.velocity[0, 2], dtype), k.shape)
    _, rec = jax.lax.scan(step, (z0, v0), None, length=steps, unroll=unroll)
    return rec


def ball_sweep_evaluator(sim: dp.Simulator, steps: int, params0: dp.Params, names: list, *,
                         n_apex: int = 3, settle_tol: float = 1e-3, keys: list | None = None,
                         mesh=None) -> Callable:
    """``evaluate(batch (B, P)) -> {metric: (B, ...)}`` for :func:`tuning.sweep.sweep`, equal
    to ``make_evaluator(bounce_metrics_fn(sim, steps, n_apex=n_apex, settle_tol=settle_tol),
    params0, names, keys)`` bit for bit, the rollouts taken by :func:`ball_heights` and the
    batch split over every device (``tuning.shard.sharded_map(..., batched=True)``).

    ``names`` may be the plane material's ``k`` and ``c`` paths (the others keep
    ``params0``'s values). Raises ``ValueError`` when :func:`supports` refuses ``sim``.
    """
    from .bounce import bounce_metrics_fn
    from .metrics import ball_metrics
    from .stable import rollout_unstable
    from .shard import sharded_map
    why = supports(sim)
    if why is not None:
        raise ValueError(why)
    mat = sim.scene.planes[0].material
    kpath, cpath = f"contact.{mat}.k", f"contact.{mat}.c"
    flat0 = P.flatten(params0)
    for n in names:
        if n not in (kpath, cpath):
            raise ValueError(f"the ball fast path sweeps {kpath!r} and {cpath!r}, not {n!r}.")
    t_end = steps * sim.dt
    del bounce_metrics_fn       # the generic evaluator this one reproduces

    def one(x, z, v):
        # built inside the traced function, as the rollout builds them: XLA then folds the
        # same constants into the metrics' arithmetic (results equal bit for bit); the body
        # never moves sideways (supports() asks for no horizontal start velocity)
        s0 = sim.init_state()
        time = s0.time + sim.dt * 1 * jnp.arange(1, steps + 1, dtype=sim.dtype)
        xy, vxy = s0.position[0, :2], s0.velocity[0, :2]
        flat = dict(flat0)
        for i, n in enumerate(names):
            flat[n] = x[i]
        params = P.unflatten(params0, flat)
        pos = jnp.concatenate([jnp.broadcast_to(xy, (steps, 2)), z[:, None]], axis=1)
        vel = jnp.concatenate([jnp.broadcast_to(vxy, (steps, 2)), v[:, None]], axis=1)
        traj = dp.Trajectory(time, pos[:, None, :], vel[:, None, :], None, None, {})
        m = ball_metrics(sim, traj, params, n_apex=n_apex, settle_tol=settle_tol,
                         state0=s0)._asdict()
        m["settling_time"] = jnp.where(m["settled"], m["settling_time"], t_end)
        m["unstable"] = rollout_unstable(sim, traj, params)     # as bounce_metrics_fn
        return {kk: jnp.asarray(v) for kk, v in m.items()
                if keys is None or kk in keys or kk == "unstable"}

    def batched(x):
        k = x[:, names.index(kpath)] if kpath in names else jnp.full(x.shape[:1],
                                                                     flat0[kpath])
        c = x[:, names.index(cpath)] if cpath in names else jnp.full(x.shape[:1],
                                                                     flat0[cpath])
        z, v = ball_heights(sim, k, c, steps, velocities=True)
        return jax.vmap(one, in_axes=(0, 1, 1))(x, z, v)
    return sharded_map(batched, mesh, batched=True)
