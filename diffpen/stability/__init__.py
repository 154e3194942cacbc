"""Stable time steps of the integrators for a compiled scene, and the rollout gate.

For each integrator the largest stable step of ONE damped mode ``x'' = -K x - C v`` (K = w^2 in
1/s^2, C = 2 zeta w in 1/s) is computed from the integrator's own amplification matrix (the
method applied to that linear mode); the closed forms of docs/physics-notes.md section 4 are its
special cases and are checked by the tests:

  semi_implicit_euler  K h^2 + 2 C h < 4  (k h^2 + 2 c h < 4 m; w h < 2 undamped; h < 2 m / c)
  verlet               w h < 2 undamped
  rk4                  w h < 2.83 undamped
  implicit_euler       unconditionally stable (no limit)

The scene's largest K and C come from Gershgorin bounds on ``M^-1 K`` and ``M^-1 C``
(docs/physics-notes.md section 4, "spring networks"): for each free body i,
``(sum_j k_ij + sum_{j free} k_ij) / m_i`` over its springs, plus ONE contact spring (the
stiffest contact it can make: a plane, a fixed sphere, or another sphere, counted on both
rows). One contact per body is exact for a body on a floor, in a corner of mutually
orthogonal planes, or in a two-sphere collision; a sphere squeezed by several spheres at once
can need a smaller step (``packed_dt`` reports that bound, with up to 12 sphere neighbours).
Each force term carries its own rows of these bounds (a :class:`Bound` on its
:class:`diffpen.terms.Term`): this module only sums them, so a new term brings its bound with
it (the rigid-body terms' rows include rotation: a contact at a lever arm r adds about
k r^2 / I, up to ~3 k / m for a box corner). A term without a bound adds nothing.

Rollouts of explicit integrators are held to a *safe* step (``safe_dt``): ``SAFE_STABLE = 0.9``
of the stability limit (near the limit a stable oscillation's amplitude grows without bound),
tightened to ``w_c h <= SAFE_WH = 0.5`` and ``C_c h <= SAFE_CH = 1`` for the contact springs
(w_c^2 = k / m, C_c = c / m of the stiffest contact of a body), because a penalty
contact that switches on or off between steps injects energy ~ (w h)^2 / 4 (see SAFE_WH).
A contact law may carry its own contact limit (``ContactLaw.safe_wh``, in the simulator's
``analysis.contact_wh``): the event-exact linear and no_tension records, which follow the
continuous motion through those steps, are held to ``w_c h <= 1.0``. Past it,
``Simulator.rollout`` raises StabilityError naming the safe step and the substeps that reach
it; ``substeps="auto"`` picks that count instead.

Traced stability: the same rows and limits are also evaluated inside the traced rollout
(:func:`unsafe`, with ``jax.numpy``), so a rollout under ``jax.jit``, ``jax.vmap`` or
``jax.grad`` (where the up-front check cannot see the parameter values) records in
``State.aux["unstable"]`` (``FLAG``) whether its step is past the safe step for the
parameter values it was given; for implicit integrators (no step limit) it records instead
whether the float dtype cannot resolve the step (:func:`precision_unsafe`, the traced form of
the float32 refusal); for every integrator also whether a parameter is out of the range that
concrete values are refused for (:func:`params_out_of_range`). The flag is sticky and saved in
``Trajectory.aux``.

A contact law that stiffens with depth (Hunt-Crossley) is counted at a reference depth: each
body's radius, or, where the scene lets the start state's energy bound it, the depth at which
the contact would store twice that energy (:mod:`.depth`; a rollout hands the same energy to
the up-front gate and to the traced flag, which counts it from traced start states and named
planes' traced offsets too).

Layout: :mod:`.modes` (one oscillator mode: amplification, stable and safe steps),
:mod:`.bounds` (the terms' :class:`Bound` rows summed into rates, numpy and traced),
:mod:`.gating` (the up-front gate, its cache and the :class:`StabilityReport`), :mod:`.depth`
(the reference depth from the start energy).
"""
from .bounds import (FLAG, Analysis, Bound, Rates, params_out_of_range, precision_unsafe, rates,
                     scene_rates, unsafe)
from .gating import MAX_AUTO_SUBSTEPS, GateCache, StabilityReport, gate, report, step_gate
from .modes import (SAFE_CH, SAFE_STABLE, SAFE_WH, mode_amplification, mode_stable_dt, safe_dt,
                    stable_dt)

__all__ = ["mode_amplification", "mode_stable_dt", "stable_dt", "safe_dt", "SAFE_WH",
           "SAFE_CH", "SAFE_STABLE", "Bound", "Analysis", "Rates", "rates", "scene_rates",
           "unsafe", "precision_unsafe", "params_out_of_range", "FLAG", "StabilityReport",
           "report", "gate", "step_gate",
           "GateCache", "MAX_AUTO_SUBSTEPS"]
