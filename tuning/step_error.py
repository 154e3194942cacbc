"""The time step's own error in a bounce: the restitution of one impact simulated at the
fit's ``dt`` against the continuous model's (a closed form, or Richardson extrapolation),
and the note a bounce fit adds when it is large (:func:`tuning.bounce.fit_bounce`)."""
from __future__ import annotations

import math

import jax

import diffpen as dp

__all__ = ["STEP_ERROR_NOTE", "step_error_note", "step_restitution_error"]

#: :func:`fit_bounce` notes the time step's own restitution error at the fitted point
#: (:func:`step_restitution_error`) when it is larger than this.
STEP_ERROR_NOTE = 0.01


def step_error_note(contact, *, dt: float, law, mass: float, radius: float, speed: float,
                     compile_kw: dict) -> str | None:
    """The note :func:`tuning.bounce.fit_bounce` adds when the time step's own restitution error at the
    fitted ``contact`` (k, c) is above :data:`STEP_ERROR_NOTE`; None otherwise (or when it
    cannot be measured: no rebound)."""
    try:
        err = step_restitution_error(float(contact.k), float(contact.c), mass=mass,
                                     radius=radius, speed=speed, dt=dt, law=law, **compile_kw)
    except (ValueError, FloatingPointError):      # SceneError, StabilityError, NonFiniteError
        return None
    if err is None or not abs(err) > STEP_ERROR_NOTE:
        return None
    rec = dp.laws.get(law, compile_kw.get("exponent", 1.0)) if isinstance(law, str) else law
    lag = (compile_kw.get("integrator", "semi_implicit_euler") == "semi_implicit_euler"
           and compile_kw.get("smoothing", "auto") in ("auto", 0, 0.0))
    centred = {"linear": "laws.linear(centred=True)",
               "no_tension": "laws.no_tension(centred=True)",
               "hunt_crossley": f"laws.hunt_crossley({rec.exponent:g}, centred=True)"}
    fix = "use a smaller dt"
    if lag and rec.centred is None and rec.name in centred:
        fix += f" or {centred[rec.name]}"
    return (f"the time step's own restitution error at the fitted point is {100 * err:+.3g}%: "
            f"the fitted k, c are those of the discrete model at this dt ({dt:g} s); {fix}")


#: Impact simulators of :func:`step_restitution_error`, by everything they are compiled from.
_IMPACT_SIMS: dict = {}


def _impact_restitution(k: float, c: float, h: float, *, mass: float, radius: float,
                        speed: float, gap: float, t_contact: float, law,
                        compile_kw: dict) -> float | None:
    """Restitution of one gravity-free impact at ``speed`` m/s simulated at step ``h`` s
    (the ball starts ``gap`` m above the plane): its speed after the contact over its speed
    before; None when the contact has not ended after ``4 t_contact`` s."""
    key = (mass, radius, speed, gap, h, law, tuple(sorted(compile_kw.items())))
    try:
        sim = _IMPACT_SIMS.get(key)
    except TypeError:                  # an option that cannot key a cache: compile anew
        key, sim = None, None
    if sim is None:
        from .scenes import ball_scene
        sim = dp.compile(ball_scene(radius=radius, mass=mass, height=radius + gap,
                                    velocity=-speed, gravity=0.0), h, law=law, **compile_kw)
        if key is not None:
            if len(_IMPACT_SIMS) >= 16:
                _IMPACT_SIMS.clear()
            _IMPACT_SIMS[key] = sim
    # a power of two: few distinct rollout lengths, so few compiled programs
    steps = 2 ** max(4, math.ceil(math.log2((gap / speed + 4.0 * t_contact) / h + 2.0)))
    tr = sim.rollout(sim.params(k=k, c=c), steps, save_every=steps)
    z, v = (float(a) for a in jax.device_get((tr.position[-1, 0, 2], tr.velocity[-1, 0, 2])))
    return v / speed if z > radius and v > 0.0 else None


#: :func:`diffpen.physical.restitution` as one compiled program (eagerly it is a dozen).
_closed_form_restitution = jax.jit(dp.physical.restitution, static_argnames="law")


def step_restitution_error(k: float, c: float, *, mass: float, speed: float, dt: float,
                           radius: float = 0.1, law="linear", **compile_kw) -> float | None:
    """The time step's own error in the restitution at contact ``k``, ``c``: ``e_dt / e - 1``
    for one gravity-free impact of a sphere (``mass`` kg, ``radius`` m) at ``speed`` m/s on
    a plane, simulated at ``dt`` s with ``law`` and ``compile_kw`` (as in
    :func:`diffpen.compile`).

    ``e`` is the continuous model's: the law's closed form
    (:func:`diffpen.physical.restitution`, linear and no_tension without smoothing) where it
    has one and rebounds, else the same impact at ``dt / 8`` extrapolated to ``dt -> 0``
    (Richardson, first order: ``e_8 + (e_8 - e_dt) / 7``). One small compile and rollout
    (two without a closed form). Returns None when the simulated ball does not rebound.
    """
    rec = dp.laws.get(law, compile_kw.get("exponent", 1.0)) if isinstance(law, str) else law
    n = float(rec.exponent)
    # the undamped contact's duration, pi sqrt(m / k) for n = 1 (Hertz-like for n > 1, at
    # the stiffness of the deepest point): the rollouts last 4 of them (zeta up to ~0.97)
    d_max = ((n + 1.0) * mass * speed ** 2 / (2.0 * k)) ** (1.0 / (n + 1.0))
    t_contact = math.pi * math.sqrt(mass / (n * k * d_max ** (n - 1.0)))
    kw = dict(mass=mass, radius=radius, speed=speed, gap=0.5 * speed * dt,
              t_contact=t_contact, law=law, compile_kw=compile_kw)
    e_dt = _impact_restitution(k, c, dt, **kw)
    if e_dt is None:
        return None
    e = None
    if rec.closed_form is not None and compile_kw.get("smoothing", "auto") in ("auto", 0, 0.0):
        e = float(_closed_form_restitution(k, c, mass, law=rec))
    if not (e is not None and e > 0.0):
        e_8 = _impact_restitution(k, c, dt / 8.0, **kw)
        if e_8 is None:
            return None
        e = e_8 + (e_8 - e_dt) / 7.0
    return e_dt / e - 1.0
