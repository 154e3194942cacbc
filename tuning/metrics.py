"""Trajectory metrics of a bouncing body: exact, event-located, differentiable.

Every function here takes saved samples (times ``t`` (S,) in s and a height signal ``h`` (S,)
in m, plus velocities where needed) and returns a number defined on the trajectory itself, not
on the saved grid:

* apex heights come from the free-flight parabola through the three samples around each
  maximum (exact for any integrator whose free flight is a parabola in the samples: the
  symplectic Euler positions lie exactly on one, so the vertex is the flight's true top);
* crossing times (contact start/end, settling) are located by interpolation between the two
  samples that straddle the level;
* the settling time is *the last time* ``|z - rest| > tol``, interpolated.

All functions are pure ``jax.numpy`` with static output shapes, so they work under ``jit``,
``vmap`` and ``grad``. Event selection (which sample is the n-th apex, which interval is the
last exceedance) is piecewise constant in the parameters; the values are smooth functions of
the samples, so gradients are the exact derivatives of the exact metric within each piece.
Absent events (fewer bounces than asked for, a body that never settles) are ``nan`` in the
value and ``False`` in the companion ``valid`` mask where one is returned.

Heights: ``h`` is the height of the body's *lowest point* above the contact surface
(``n . x - offset - radius`` for a plane ``n . p = offset``): negative means penetration.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .compiled import ProgramCache

__all__ = [
    "height_above_plane", "apex_heights", "hidden_contacts", "restitutions", "crossings",
    "contact_durations",
    "max_penetration", "resting_height", "settling_time", "BallMetrics", "ball_metrics",
    "ball_metrics_dict", "ball_model_gaps", "check_ball_model",
    "initial_apex", "energy_decay_time", "ball_energy", "plane_offset", "DECAY_TAIL",
]

#: :func:`ball_metrics` reports the decay time only when the energy above rest left at the
#: end of the record is at most this fraction of the start's (the integral then misses at
#: most about this fraction of an exponential decay's area); otherwise the rollout cut the
#: decay short: ``decay_time`` is nan and ``decay_valid`` False.
DECAY_TAIL = 1e-3


def plane_offset(plane, params=None):
    """The offset (m) the simulation uses for ``plane`` (a :class:`diffpen.elements.Plane`):
    ``params.extra["plane_offset"][plane.name]`` for a named plane when ``params`` carries
    it (a fitted, differentiable offset), else the scene's ``plane.offset``."""
    if plane.name and params is not None:
        named = getattr(params, "extra", {}).get("plane_offset", {})
        if plane.name in named:
            return named[plane.name]
    return plane.offset


def height_above_plane(position, radius: float, normal=(0.0, 0.0, 1.0), offset: float = 0.0):
    """Height of a sphere's lowest point above a plane.

    Args:
      position: (..., 3) centre positions, m.
      radius: sphere radius, m.
      normal: (3,) unit plane normal.  offset: plane offset, m (plane ``n . p = offset``).
    Returns:
      (...,) height, m; negative = penetration depth.
    """
    n = jnp.asarray(normal, dtype=jnp.result_type(position))
    return jnp.sum(position * n, axis=-1) - offset - radius


def _rank_select(values, mask, n: int):
    """The first ``n`` entries of ``values`` (S,) where ``mask`` (S,) is True, in order.

    Returns (values (n,), valid (n,) bool); missing entries are nan. Differentiable w.r.t.
    ``values``.
    """
    # n first-index passes, O(n S): a cumsum of the mask would be O(S^2) on XLA CPU (it
    # lowers to a reduce-window) and made batched metrics 12x slower than the rollout itself
    s = mask.shape[0]
    idx = jnp.arange(s)
    after = jnp.full((), -1, idx.dtype)
    picked, valid = [], []
    for _ in range(n):
        i = _first(mask & (idx > after))
        ok = i < s
        picked.append(values[jnp.minimum(i, s - 1)])
        valid.append(ok)
        after = i
    picked, valid = jnp.stack(picked), jnp.stack(valid)
    return jnp.where(valid, picked, jnp.nan), valid


def _first(mask):
    """Index of the first True entry of ``mask`` (S,), or S when there is none. A min
    reduction over indices: XLA CPU vectorises it, unlike ``argmax`` (about 5x slower on
    batched trajectories)."""
    s = mask.shape[0]
    return jnp.min(jnp.where(mask, jnp.arange(s), s), initial=s)


def _triples(h, flight_gap):
    """``(h0, q, flying)`` of the middle samples ``1 .. S - 2`` (S - 2,): each sample, the
    second difference around it, and whether it and its two neighbours are in free flight
    (``h > flight_gap``)."""
    hm, h0, hp = h[:-2], h[1:-1], h[2:]
    flying = (hm > flight_gap) & (h0 > flight_gap) & (hp > flight_gap)
    return h0, hm - 2.0 * h0 + hp, flying


def _kinks(h, free_fall, flight_gap, scale=0.0):
    """(S - 2,) bool, :func:`hidden_contacts` at the middle samples ``1 .. S - 2``."""
    h0, q, flying = _triples(h, flight_gap)
    # the rounding of q, a few times over: of the positions the heights come from (their
    # size is about the height plus ``scale``), not of the heights near the ground
    rounding = 16.0 * jnp.finfo(h.dtype).eps * (jnp.abs(h0) + scale)
    return flying & (q > rounding - 0.5 * free_fall)


def hidden_contacts(h, free_fall, flight_gap: float = 0.0, scale=0.0):
    """(S,) bool: True at sample ``i`` where a contact happened between samples ``i - 1`` and
    ``i + 1`` although all three are in free flight (``h > flight_gap``): a contact shorter
    than the save interval (a stiff contact, or ``substeps``), seen as an upward kink of the
    samples. In free flight under gravity the second difference ``h[i+1] - 2 h[i] + h[i-1]``
    of uniform samples is ``-free_fall`` (``g dt_s^2``, m; exactly, as a parabola); a contact
    can only push, so a second difference above ``-free_fall / 2`` (plus rounding) is one.
    ``scale``: m, what the positions add to the heights (the radius plus the plane's
    ``|offset|``), whose rounding the heights carry (float32 at a save step of 2e-5 s saw
    kinks in the last millimetre of a fall without it)."""
    out = jnp.zeros(h.shape, bool)
    if h.shape[0] < 3:
        return out
    return out.at[1:-1].set(_kinks(h, free_fall, flight_gap, scale))


def apex_heights(h, n: int, *, flight_gap: float = 0.0, after_contact: bool = True,
                 free_fall=None, scale=0.0):
    """The first ``n`` apex heights of free flights, m.

    An apex is a saved sample ``i`` with ``h[i-1] <= h[i] > h[i+1]`` whose two neighbours are
    in free flight (``h > flight_gap``; pass the simulator's ``smoothing / 2``, inside which the
    smoothed contact force already acts). Its value is the vertex of the parabola through the
    three samples: exact for a free flight under constant gravity (the saved samples of
    symplectic Euler lie exactly on one parabola), and independent of the save interval.

    Args:
      h: (S,) height of the lowest point above the surface, m, uniformly sampled.
      n: number of apexes to return (static).
      flight_gap: m; samples with ``h <= flight_gap`` count as in contact.
      after_contact: count only apexes after the first contact that starts after the first
        sample (bounce apexes; the default): a body that starts in contact (launched from
        the surface) has its launch flight left out, as no bounce has happened yet.
      free_fall: ``g dt_s^2`` (m; ``dt_s`` the save interval), the second difference of
        free-flight samples: with it, contacts shorter than the save interval count as
        contacts (:func:`hidden_contacts`; before, the first bounce apexes reported were
        those after the first contact a sample caught, or none), and three samples around
        such a contact are no apex. None: only sampled contacts count. ``scale``: as
        :func:`hidden_contacts` takes it.
    Returns:
      (heights (n,), valid (n,) bool); heights of missing apexes are nan.
    """
    if h.shape[0] < 3:                  # no sample has two neighbours: no apex to find
        return jnp.full((n,), jnp.nan, h.dtype), jnp.zeros((n,), bool)
    kink = None if free_fall is None else _kinks(h, free_fall, flight_gap, scale)
    return _apexes(h, n, flight_gap, after_contact, kink)


def _apexes(h, n: int, flight_gap, after_contact: bool, kink):
    """:func:`apex_heights` of ``h`` (S >= 3 samples) given its kink mask (:func:`_kinks`,
    or None: only sampled contacts count), which :func:`ball_metrics` computes once."""
    hm, hp = h[:-2], h[2:]
    h0, q, flying = _triples(h, flight_gap)                 # q < 0 at a top
    is_top = flying & (hm <= h0) & (h0 > hp) & (q < 0.0)
    entry = _first((h[1:] <= flight_gap) & (h[:-1] > flight_gap)) + 1
    if kink is not None:
        is_top = is_top & ~kink
        entry = jnp.minimum(entry, _first(kink) + 1)   # hidden around sample i: triples from i
    if after_contact:
        # since the first contact that starts after t = 0 (one in progress at t = 0 is the
        # launch, not a bounce)
        touched = jnp.arange(h.shape[0] - 2) >= entry
        is_top = is_top & touched
    q_safe = jnp.where(is_top, q, -1.0)
    vertex = h0 - (hp - hm) ** 2 / (8.0 * q_safe)
    return _rank_select(vertex, is_top, n)


def initial_apex(h0, v0, g: float):
    """Energy height of the initial free flight from height ``h0`` (m) and normal velocity
    ``v0`` (m/s): ``h0 + v0^2 / (2 g)`` whatever the sign of ``v0``. Thrown up, it is the
    apex; thrown down, the height a drop from rest would need for the same first impact
    speed; the drop height when released at rest."""
    return h0 + jnp.asarray(v0) ** 2 / (2.0 * g)


def restitutions(apexes, first_apex):
    """Restitution of each bounce from consecutive free-flight apexes.

    With free flight before and after an impact, the impact and rebound speeds at the surface
    are ``sqrt(2 g H)`` of the apexes around it, so ``e_n = sqrt(H_n / H_{n-1})`` exactly.

    Args:
      apexes: (n,) bounce apex heights, m (nan where absent).
      first_apex: height of the apex before the first impact (the drop height), m.
    Returns:
      (n,) restitution of bounces 1..n (nan where absent).
    """
    prev = jnp.concatenate([jnp.reshape(first_apex, (1,)).astype(apexes.dtype), apexes[:-1]])
    ok = (prev > 0.0) & (apexes >= 0.0)
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, apexes / jnp.where(ok, prev, 1.0), 1.0)),
                     jnp.nan)


def crossings(t, h, level: float, n: int, direction: int, *, flight: bool = False):
    """Times at which ``h`` crosses ``level`` going down (``direction=-1``) or up (``+1``).

    By default interpolated linearly between the two straddling samples. With
    ``flight=True`` (uniform samples of a body that is in free flight on the far side of
    each crossing, as a bouncing body) the crossing is located on the free-flight parabola
    through the three samples on the flight side, ``i-2, i-1, i`` before a downward crossing
    between ``i`` and ``i+1`` and ``i+2, i+3, i+4`` after an upward one: exact for a free
    flight under constant gravity (symplectic Euler's samples lie on one) and untouched by
    how the contact acts inside the step, where linear interpolation between a flight sample
    and a contact sample is off by ``a dt^2 / (8 v)``. The samples next to the crossing are
    skipped after an upward crossing because a step-averaged contact still acts within one
    step of it. Falls back to linear interpolation where those samples are missing or not
    on the flight side.

    Args:
      t: (S,) s.  h: (S,) m.  level: m.  n: how many (static).
    Returns:
      (times (n,), valid (n,) bool); nan where absent.
    """
    a, b = h[:-1] - level, h[1:] - level
    if direction < 0:
        hit = (a >= 0.0) & (b < 0.0)
    else:
        hit = (a < 0.0) & (b >= 0.0)
    den = jnp.where(hit, a - b, 1.0)
    frac = jnp.where(hit, a / den, 0.0)
    tc = t[:-1] + frac * (t[1:] - t[:-1])
    if flight and h.shape[0] >= 5:
        s = h.shape[0]
        i = jnp.arange(s - 1)
        first = i - 2 if direction < 0 else i + 2          # first of the three samples
        ok = (first >= 0) & (first + 2 <= s - 1)
        f0 = jnp.clip(first, 0, s - 3)
        y0, y1, y2 = h[f0] - level, h[f0 + 1] - level, h[f0 + 2] - level
        ok = ok & (y0 >= 0.0) & (y1 >= 0.0) & (y2 >= 0.0)
        q = y2 - 2.0 * y1 + y0
        qa, qb = 0.5 * q, (y1 - y0) - 0.5 * q                # p(tau) = qa tau^2 + qb tau + y0
        disc = qb * qb - 4.0 * qa * y0
        ok = ok & (disc > 0.0) & (jnp.abs(qb) > 0.0)
        root = jnp.sqrt(jnp.where(ok, disc, 1.0))
        # the root nearest the samples, without cancellation: 2 C / (-B -+ sqrt(D))
        den_q = jnp.where(ok, -qb - jnp.sign(qb) * root, 1.0)
        tau = 2.0 * y0 / den_q
        step = t[1] - t[0]
        tq = t[f0] + tau * step
        use = hit & ok
        tc = jnp.where(use, tq, tc)
    return _rank_select(tc, hit, n)


def contact_durations(t, h, n: int, *, level: float = 0.0, flight: bool = False):
    """Durations of the first ``n`` completed contacts (``h < level``), s.

    Each contact runs from a downward crossing of ``level`` to the next upward one: the time
    the body overlaps the surface (``h < level``; ``level`` is 0 in :func:`ball_metrics`),
    whatever the contact law's force does inside it. With a law that cannot pull, such as
    ``no_tension``, the force reaches zero before the overlap ends, so the force-based
    contact time of :func:`diffpen.physical.contact_time` is shorter (about 10% at
    e = 0.667). A contact already in progress at the first sample (a body that starts in
    contact) is not a full contact and is left out: the first duration is that of the first
    contact that starts after t = 0. A contact still open at the end is nan.
    ``flight``: locate the crossings on the adjacent free flights (:func:`crossings`).

    Returns: (durations (n,), valid (n,) bool).
    """
    down, up, valid = _contacts(t, h, n, level, flight)
    return jnp.where(valid, up - down, jnp.nan), valid


def _contacts(t, h, n: int, level, flight: bool):
    """``(starts (n,), ends (n,), valid (n,))`` of :func:`contact_durations`' contacts, s."""
    down, vd = crossings(t, h, level, n, -1, flight=flight)
    up, vu = crossings(t, h, level, n + 1, +1, flight=flight)
    # starting in contact, the first upward crossing ends the contact in progress
    start_in = h[0] < level
    up, vu = jnp.where(start_in, up[1:], up[:-1]), jnp.where(start_in, vu[1:], vu[:-1])
    return down, up, vd & vu


def max_penetration(h):
    """Largest penetration depth ``max(-h)``, m (0 when never in contact), refined by the
    parabola through the deepest sample and its neighbours."""
    d = -h
    i = _first(d == jnp.max(d))              # argmax, as two vectorised reductions
    i = jnp.clip(i, 1, d.shape[0] - 2)
    dm, d0, dp = d[i - 1], d[i], d[i + 1]
    q = dm - 2.0 * d0 + dp
    ok = (q < 0.0) & (d0 >= dm) & (d0 >= dp)
    refined = jnp.where(ok, d0 - (dp - dm) ** 2 / (8.0 * jnp.where(ok, q, -1.0)), d0)
    return jnp.maximum(jnp.maximum(refined, jnp.max(d)), 0.0)


def resting_height(k, mass: float, g: float, radius: float, *, law="linear",
                   exponent: float = 1.0, width: float = 0.0):
    """Centre height (m) of a sphere resting on a horizontal plane at z = 0 (static balance):
    ``radius - law.resting_depth(m g, k, width)`` (:class:`diffpen.laws.ContactLaw`; ``law``
    a record or a name, ``exponent`` for ``"hunt_crossley"``).

    Args:
      k: contact stiffness, N/m (N/m^n).  mass: kg.  g: |gravity|, m/s^2.  radius: m.
      width: the simulator's smoothing width, m.
    """
    return radius - dp.laws.get(law, exponent).resting_depth(mass * g, k, width)


def settling_time(t, z, rest, tol: float = 1e-3):
    """Settling time: the last time ``|z - rest| > tol``, interpolated, s.

    Exactly the definition (no soft maximum): find the last sample outside the band and
    interpolate where ``|z - rest|`` comes down to ``tol`` between it and the next sample. The
    value is continuous in the samples within each piece and jumps where an excursion's peak
    passes through the band, as the exact definition does (the last excursion then changes:
    in k and c this happens wherever a small late bounce just reaches the band). Next to such
    a jump the exact crossing time has an unbounded slope (the peak is tangent to the band);
    the interpolation's divisor is kept >= ``tol / 1000`` so that its gradient stays bounded
    (by ``1000 dt / tol`` per metre of the samples; a crossing at any speed above
    ``tol / (1000 dt)`` is untouched) instead of exploding. Away from the jumps its derivative
    is the continuous one (quick-start ball at dt = 1e-4 s, tol 1 mm: d/dc -0.1120 against
    -0.1106 s per N s/m). For a measure that
    is smooth in k and c use :func:`energy_decay_time`.

    Args:
      t: (S,) s, increasing, including the start.  z: (S,) m.  rest: resting value, m.
      tol: band half-width, m.
    Returns:
      (time, settled): ``t[0]`` if always inside the band; ``nan`` with ``settled=False`` if
      still outside at the last sample.
    """
    e = jnp.abs(z - rest)
    s = e.shape[0]
    idx = jnp.arange(s)
    out = e > tol
    last = jnp.max(jnp.where(out, idx, -1))
    settled = last < s - 1
    i = jnp.clip(last, 0, s - 2)
    ei, ej = e[i], e[i + 1]
    den = jnp.maximum(ei - ej, 1e-3 * tol)
    frac = jnp.clip((ei - tol) / den, 0.0, 1.0)
    tc = t[i] + frac * (t[i + 1] - t[i])
    tc = jnp.where(last < 0, t[0], tc)
    return jnp.where(settled, tc, jnp.nan), settled


def energy_decay_time(t, energy):
    """Energy-decay time ``int E dt / E(0)`` over the samples (trapezoids), s.

    ``energy``: (S,) the mechanical energy above rest, J (>= 0, decaying to 0). For an
    exponential decay ``E0 exp(-t / tau)`` sampled long enough it is ``tau``; for a bouncing
    body it is the time the initial energy would last at its initial level. Unlike the
    settling time (the last exit from a band, which jumps when a late bounce passes through
    the band) it is a smooth function of k and c wherever the trajectory is, so its exact
    gradient is the continuous system's (up to the integrator's error): use it where a fit
    needs a settling measure. It is the integral over the samples only: a record that ends
    with energy left gives a value cut short (:func:`ball_metrics` reports nan then, see
    :data:`DECAY_TAIL`). Args: t (S,) s.  Returns: s.
    """
    e = jnp.asarray(energy)
    area = jnp.sum(0.5 * (e[1:] + e[:-1]) * (t[1:] - t[:-1]))
    return area / e[0]


def ball_energy(sim, position, velocity, params, *, body: int = 0, plane: int = 0):
    """Mechanical energy above static rest of a sphere on a plane, J, per sample:
    ``m v^2 / 2 + m g (h - h_rest) + (E_c(d) - E_c(d_rest))`` with the contact law's elastic
    energy ``E_c`` (:attr:`diffpen.laws.ContactLaw.energy`). position, velocity: (S, 3).
    Heights are above the plane's offset in ``params`` (:func:`plane_offset`). Raises
    ValueError for a body the model leaves things out of (:func:`ball_model_gaps`)."""
    check_ball_model(sim.scene, body)
    pl = sim.scene.planes[plane]
    radius, mass = float(sim.radius[body]), float(sim.mass[body])
    n = np.asarray(pl.normal, float)
    g = float(-np.dot(np.asarray(sim.scene.gravity), n))
    law = sim.contact_law
    k = params.contact[pl.material].k
    h = height_above_plane(position, radius, pl.normal, plane_offset(pl, params))
    d_rest = law.resting_depth(mass * g, k, sim.smoothing)
    kinetic = 0.5 * mass * jnp.sum(velocity * velocity, axis=-1)
    potential = mass * g * (h + d_rest) + (law.energy(-h, k, sim.smoothing)
                                           - law.energy(d_rest, k, sim.smoothing))
    return kinetic + potential


class BallMetrics(NamedTuple):
    """Metrics of one sphere bouncing on a plane (all exact; see the module docstring).

    apex_heights: (n_apex,) m, lowest point above the surface at the top of each rebound.
    apex_valid: (n_apex,) bool.
    restitution: (n_apex,) per bounce.
    contact_durations: (n_apex,) s, the overlap time ``h < 0`` of each contact that starts
      after t = 0 (:func:`contact_durations`; not where the force ends).
    max_penetration: m.
    resting_height: centre height at static rest, m.
    settling_time: s (nan if not settled within the rollout).
    settled: bool.
    drop_height: apex before the first impact (lowest point), m: the energy height
      ``h0 + v0^2 / (2 g)`` (:func:`initial_apex`), or for a body that starts in contact
      (launched from the surface) the apex of its launch flight.
    decay_time: energy-decay time ``int E dt / E(0)``, s (:func:`energy_decay_time`;
      smooth in k and c); 0 for a body at rest from the start (no energy above rest), nan
      when the record ends with more than :data:`DECAY_TAIL` of the start energy left (cut
      short: roll out longer).
    decay_valid: bool, False where ``decay_time`` is nan.
    """
    apex_heights: object
    apex_valid: object
    restitution: object
    contact_durations: object
    max_penetration: object
    resting_height: object
    settling_time: object
    settled: object
    drop_height: object
    decay_time: object = None
    decay_valid: object = None

    def as_dict(self) -> dict:
        """Plain Python numbers/lists (nan for absent events), for printing and JSON."""
        def conv(v):
            a = np.asarray(v)
            return a.tolist() if a.ndim else a.item()
        return {name: conv(getattr(self, name)) for name in self._fields}


def ball_model_gaps(scene: dp.Scene, body: int) -> list:
    """What the ball metrics (:func:`ball_metrics`: a free sphere on a plane under gravity)
    leave out of ``body``'s motion in ``scene``, in words: springs (plain, anchored,
    plastic) attached to it, drag on it; empty where the model holds."""
    springs = sum(int(body in (s.a, s.b)) for group in (
        scene.springs, scene.anchored_springs, scene.plastic_springs) for s in group)
    drags = sum(int(d.body == body) for d in scene.drags)
    return ([f"{springs} spring(s) attached"] if springs else []) + (
        [f"drag on it ({drags})"] if drags else [])


def check_ball_model(scene, body: int) -> None:
    """Raise ValueError naming what :func:`ball_model_gaps` finds on ``body``."""
    gaps = ball_model_gaps(scene, body)
    if gaps:
        raise ValueError(f"ball metrics model a free sphere bouncing on a plane, and body "
                         f"{body} has {' and '.join(gaps)}: its resting height and energy "
                         "would leave them out (a sphere hung on a spring settled 5% late, "
                         "silently). Fit such a scene to records (diffpen fit SCENE.toml "
                         "--data), or compute the metrics it needs from its trajectory.")


def ball_metrics(sim, traj, params, *, body: int = 0, n_apex: int = 3, settle_tol: float = 1e-3,
                 plane: int = 0, state0=None, decay_cut: str = "nan") -> BallMetrics:
    """All metrics of ``body`` (a sphere) bouncing on plane ``plane`` of ``sim``'s scene.

    The initial state (``state0`` or ``sim.init_state()``) is prepended to the saved samples,
    so the trajectory starts at t = 0. Traceable: use it inside ``jit``/``vmap``/``grad``.

    Args:
      sim: a compiled :class:`diffpen.Simulator`.  traj: its :class:`diffpen.Trajectory`.
      params: the :class:`diffpen.Params` of the rollout (k sets the resting height; a named
        plane's offset is ``params.extra["plane_offset"][name]``, :func:`plane_offset`).
      body: body index.  n_apex: number of bounces reported (static).
      settle_tol: settling band, m.  plane: plane index.
      decay_cut: a decay time cut short by the rollout (``decay_valid`` False) is ``"nan"``,
        or ``"bound"``: the integral over the rollout, a lower bound that still moves with k
        and c (what a fit's optimiser takes; never a reached target, see
        :func:`tuning.bounce.fit_bounce`).
    Returns:
      :class:`BallMetrics`.
    Raises: ValueError for a body the model leaves forces out of (:func:`ball_model_gaps`:
      springs, drag), before anything is traced.
    """
    if decay_cut not in ("nan", "bound"):
        raise ValueError(f"decay_cut must be 'nan' or 'bound', got {decay_cut!r}.")
    if not (isinstance(settle_tol, (int, float, np.integer, np.floating))
            and np.isfinite(settle_tol) and settle_tol > 0.0):  # NaN: all "settled" at t = 0
        raise ValueError(f"settle_tol (the settling band, m) must be a finite number > 0, "
                         f"got {settle_tol!r}.")
    if isinstance(n_apex, bool) or not isinstance(n_apex, (int, np.integer)) or n_apex < 1:
        raise ValueError(f"n_apex must be a positive integer (bounces reported), got "
                         f"{n_apex!r}.")
    scene = sim.scene
    check_ball_model(scene, body)
    pl = scene.planes[plane]
    radius = float(sim.radius[body])
    mass = float(sim.mass[body])
    gvec = np.asarray(scene.gravity)
    g = float(-np.dot(gvec, pl.normal))
    if g <= 0.0:
        raise ValueError("ball metrics need gravity pointing into the plane.")
    s0 = sim.init_state() if state0 is None else state0
    t = jnp.concatenate([jnp.reshape(s0.time, (1,)), traj.time])
    pos = jnp.concatenate([s0.position[None, body], traj.position[:, body]])
    offset = plane_offset(pl, params)
    h = height_above_plane(pos, radius, pl.normal, offset)
    n = jnp.asarray(pl.normal, dtype=h.dtype)
    v0n = jnp.dot(s0.velocity[body], n)
    gap = 0.5 * sim.smoothing
    # free-flight samples' second difference: contacts shorter than the save interval (a
    # stiff contact, substeps) are found by their kink (hidden_contacts)
    enough = h.shape[0] >= 3            # samples with two neighbours: apexes and kinks
    kink = _kinks(h, g * (t[1] - t[0]) ** 2, gap, radius + jnp.abs(offset)) if enough \
        else None
    nothing = (jnp.full((n_apex,), jnp.nan, h.dtype), jnp.zeros((n_apex,), bool))
    apex, valid = _apexes(h, n_apex, gap, True, kink) if enough else nothing
    # starting in contact (launched from the surface), the launch flight's apex
    launch, launched = _apexes(h, 1, gap, False, kink) if enough else nothing
    h_energy = initial_apex(h[0], v0n, g)
    # (no launch flight, e.g. at rest on the plane: the energy height, as before)
    h_drop = jnp.where((h[0] <= gap) & launched[0], launch[0], h_energy)
    k = params.contact[pl.material].k
    rest_z = resting_height(k, mass, g, radius, law=sim.contact_law, width=sim.smoothing)
    centre = h + radius                                          # centre height above plane
    ts, settled = settling_time(t, centre, rest_z, settle_tol)
    down, up, ok = _contacts(t, h, n_apex, 0.0, True)      # contact_durations(flight=True)
    dur = jnp.where(ok, up - down, jnp.nan)
    # a contact no sample caught has no duration or depth, and the sampled ones after it are
    # not the bounces their rank says: theirs are nan (the first contact is the deepest)
    if enough:
        t_hidden = jnp.min(jnp.where(kink, t[1:-1], jnp.inf))
        dur = jnp.where(down < t_hidden, dur, jnp.nan)
        depth = jnp.where(jnp.isfinite(t_hidden) & ~(down[0] < t_hidden), jnp.nan,
                          max_penetration(h))
    else:
        depth = max_penetration(h)
    if traj.velocity is not None:
        vel = jnp.concatenate([s0.velocity[None, body], traj.velocity[:, body]])
        e = ball_energy(sim, pos, vel, params, body=body, plane=plane)
        # a start energy within rounding of rest: at rest from the start, decay time 0
        noise = 100.0 * jnp.finfo(e.dtype).eps * mass * g * (jnp.abs(pos[0] @ n) + radius)
        at_rest = e[0] <= noise
        decay_valid = at_rest | (e[-1] <= DECAY_TAIL * e[0])
        decay = jnp.where(at_rest, 0.0, energy_decay_time(t, jnp.where(at_rest, 1.0, e)))
        if decay_cut == "nan":
            decay = jnp.where(decay_valid, decay, jnp.nan)
    else:
        decay = jnp.full((), jnp.nan, h.dtype)
        decay_valid = jnp.zeros((), bool)
    return BallMetrics(
        apex_heights=apex, apex_valid=valid, restitution=restitutions(apex, h_drop),
        contact_durations=dur, max_penetration=depth,
        resting_height=rest_z + offset, settling_time=ts, settled=settled,
        drop_height=h_drop, decay_time=decay, decay_valid=decay_valid)


#: jitted :func:`ball_metrics` programs by (simulator, options), the last 8
_BALL_METRICS_JIT = ProgramCache()


def ball_metrics_dict(sim, traj, params, **options) -> dict:
    """:func:`ball_metrics` ``(sim, traj, params, **options)`` run compiled and returned as a
    dict (:meth:`BallMetrics.as_dict`): one program per simulator, options and trajectory
    shape, reused by later calls with new values (a ``jax.jit`` built at each call compiled
    again every time: 0.8-1.5 s a call). ``options`` are :func:`ball_metrics`' static
    keywords (body, n_apex, settle_tol, plane, decay_cut)."""
    f = _BALL_METRICS_JIT.get((sim, tuple(sorted(options.items()))), lambda: jax.jit(
        lambda tr, p: ball_metrics(sim, tr, p, **options)))
    return f(traj, params).as_dict()
