"""The extreme-case stability matrix: a ball and a sphere chain dropped onto the plane with each
factor (stiffness, mass, damping, speed, initial overlap, gravity, dt, dtype, integrator) pushed
to its extremes, alone and at combined corners. Every case must run sane (finite, energy not
growing, penetration bounded, restitution <= 1, finite gradients) or be refused with a clear
error whose advice then works.

Everything here computes and returns plain data (dicts, lists); ``tuning.cli.report`` prints.
The ball is :func:`tuning.scenes.ball_scene`, also the problem of
:mod:`tuning.reports.accuracy` and :mod:`tuning.reports.gradient_check`.

Units: SI throughout (m, kg, s, N/m, N s/m).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp
from diffpen import stability as _stab

from ..scenes import ball_scene
from .reference import G

__all__ = [
    "INTEGRATORS", "chain_scene", "Case", "extreme_cases", "case_smoothing",
    "ENERGY_TOL", "run_case", "stability_matrix", "summarize_matrix",
]

INTEGRATORS = ("semi_implicit_euler", "verlet", "rk4", "implicit_euler")


# --------------------------------------------------------------------------- scenes
def chain_scene(*, n: int = 4, mass: float = 1.0, radius: float = 0.05, spacing: float = 0.2,
                height: float = 0.5, speed: float = 0.0, overlap: bool = False,
                gravity: bool = True, k: float = 1e4, c: float = 0.0) -> dp.Scene:
    """A horizontal chain of ``n`` spheres joined by springs (group ``"chain"``), above the
    ground plane, falling onto it. ``mass`` per sphere, kg; the springs start at rest length.
    ``overlap``: the first sphere starts centred on the plane (overlapped by its radius)."""
    scene = dp.Scene(gravity=(0.0, 0.0, -G if gravity else 0.0), allow_overlap=overlap)
    prev = None
    for i in range(n):
        z0 = 0.0 if (overlap and i == 0) else height
        b = scene.add_sphere(radius=radius, mass=mass, position=(spacing * i, 0.0, z0),
                             velocity=(0.0, 0.0, -speed))
        if prev is not None:
            scene.add_spring(prev, b, k=k, c=c, group="chain")
        prev = b
    scene.add_plane()
    return scene


# --------------------------------------------------------------------------- energy
def _energy(sim, k, sk, position, velocity):
    """Mechanical energy (J) per saved state: kinetic + gravity + springs + contact (the
    contact law's elastic energy, :attr:`diffpen.laws.ContactLaw.energy`).

    position, velocity: (S, n, 3). k: contact stiffness, sk: spring stiffness (N/m).
    Returns (E (S,), max penetration (S,) m).
    """
    m = np.asarray(sim.mass)[None, :]
    r = np.asarray(sim.radius)[None, :]
    x, v = np.asarray(position, float), np.asarray(velocity, float)
    e = 0.5 * np.sum(m * np.sum(v * v, axis=-1), axis=-1)
    g = np.asarray(sim.scene.gravity)
    e -= np.sum(m * (x @ g), axis=-1)
    d = r - x[..., 2]                                        # plane z = 0, normal +z
    # one compiled program per shape (eagerly, each of the law's operations compiled its own)
    energy = jax.jit(sim.contact_law.energy, static_argnums=2)
    e += np.sum(np.asarray(energy(d, k, sim.smoothing)), axis=-1)
    for s in sim.scene.springs:
        xb = x[:, s.b] if s.b is not None else np.asarray(s.anchor)[None]
        ext = np.linalg.norm(x[:, s.a] - xb, axis=-1) - s.rest_length
        e += 0.5 * sk * ext ** 2
    return e, np.max(d, axis=-1)


# --------------------------------------------------------------------------- extreme cases
@dataclasses.dataclass(frozen=True)
class Case:
    """One extreme case. k: N/m (contact, and springs for the chain); mass: kg per body;
    zeta: damping ratio (c = 2 zeta sqrt(k m)); speed: initial downward speed, m/s; overlap:
    start overlapped by a full radius; gravity: on/off; dt: s; duration: simulated time, s."""
    scene: str = "ball"
    dtype: str = "float64"
    integrator: str = "semi_implicit_euler"
    k: float = 1e4
    mass: float = 1.0
    zeta: float = 0.1
    speed: float = 0.0
    overlap: bool = False
    gravity: bool = True
    dt: float = 1e-3
    duration: float = 0.6
    label: str = "nominal"

    @property
    def c(self) -> float:
        return 2.0 * self.zeta * math.sqrt(self.k * self.mass)


def extreme_cases(*, scenes=("ball", "chain"), dtypes=("float32", "float64"),
                  integrators=INTEGRATORS, quick: bool = False) -> list[Case]:
    """The extreme-case matrix: each factor varied alone from a nominal case (k = 1e4 N/m,
    m = 1 kg, zeta = 0.1, at rest 0.4 m above the plane, gravity, dt = 1e-3 s), plus corners
    that combine extremes. ``quick`` keeps only the corners and the ends of each range."""
    one = [("k", [1e1, 1e3, 1e5, 1e7, 1e9]), ("mass", [1e-4, 1e-2, 1e2, 1e4]),
           ("zeta", [0.0, 1.0, 10.0, 100.0]), ("speed", [10.0, 100.0]),
           ("overlap", [True]), ("gravity", [False]), ("dt", [1e-5, 1e-4, 1e-2, 1e-1])]
    corners = [
        dict(k=1e9, mass=1e-4, dt=1e-1, label="stiffest, lightest, largest dt"),
        dict(k=1e9, mass=1e-4, dt=1e-5, speed=100.0, label="stiffest, lightest, 100 m/s"),
        dict(k=1e1, mass=1e4, zeta=0.0, dt=1e-1, label="softest, heaviest, undamped"),
        dict(k=1e9, zeta=100.0, speed=100.0, overlap=True, label="stiff, overdamped, "
                                                                 "overlapped, 100 m/s"),
        dict(k=1e7, zeta=0.0, gravity=False, speed=100.0, dt=1e-5,
             label="undamped 100 m/s impact, no gravity"),
    ]
    if quick:
        one = [(f, sorted({vals[0], vals[-1]}, key=vals.index)) for f, vals in one]
    specs = [dict(label="nominal")]
    for field, vals in one:
        for v in vals:
            specs.append({field: v, "label": f"{field}={v:g}" if not isinstance(v, bool)
                          else f"{field}={v}"})
    specs += corners
    out = []
    for scene in scenes:
        for dtype in dtypes:
            for integ in integrators:
                for spec in specs:
                    out.append(Case(scene=scene, dtype=dtype, integrator=integ, **spec))
    return out


_SIM_CACHE: dict = {}


def case_smoothing(case: Case, radius: float) -> float:
    """Smoothing width (m) of a case: diffpen's default (1e-3 x radius) where it keeps
    docs/physics-notes.md section 5's rule sigma < m g / k, else 0 (the exact ramp max(d, 0))."""
    g = G if case.gravity else 0.0
    width = 1e-3 * radius
    return width if width < case.mass * g / case.k else 0.0


#: the most states a case's checks keep (its rollout saves every n-th inner step above it)
MAX_SAVED = 200_000


def _case_sim(case: Case, substeps, integrator=None):
    integrator = integrator or case.integrator
    key = (case.scene, case.dtype, integrator, case.mass, case.gravity, case.dt, substeps,
           case_smoothing(case, 0.1 if case.scene == "ball" else 0.05))
    if key not in _SIM_CACHE:
        if case.scene == "ball":
            scene = ball_scene(mass=case.mass, height=0.5, gravity=G if case.gravity else 0.0)
        else:
            scene = chain_scene(mass=case.mass, gravity=case.gravity)
        width = case_smoothing(case, scene.bodies[0].radius)
        # substeps N: the same physics as N steps of dt / N, compiled so, so that the checks
        # see every inner state (a contact shorter than dt is invisible in the outer states);
        # at most MAX_SAVED states are kept
        sim = dp.compile(scene, case.dt / substeps, integrator=integrator,
                         dtype=jnp.dtype(case.dtype), smoothing=width)
        steps = max(2, int(round(case.duration / case.dt))) * substeps
        save_every = -(-steps // MAX_SAVED)          # every state, or every n-th past the cap
        steps = -(-steps // save_every) * save_every  # (then < save_every inner steps more)

        def loss(kc, state):
            k, c = kc[0], kc[1]
            params = (sim.params(k=k, c=c, spring_k=k, spring_c=c) if case.scene == "chain"
                      else sim.params(k=k, c=c))
            traj = sim.rollout(params, steps, state, check_finite=False,
                               save_every=save_every)
            return jnp.mean(traj.position[..., 2]), traj
        # forward mode: d(loss)/d(k, c) and the trajectory in one pass (compiles faster than
        # reverse mode for two parameters)
        _SIM_CACHE[key] = (sim, steps, jax.jit(jax.jacfwd(loss, has_aux=True)))
    return _SIM_CACHE[key]


def _initial_state(sim, case: Case):
    s = sim.init_state()
    pos = np.asarray(s.position, float).copy()
    vel = np.zeros_like(pos)
    vel[:, 2] = -case.speed
    if case.overlap:
        pos[0, 2] = 0.0
    return s._replace(position=jnp.asarray(pos, sim.dtype), velocity=jnp.asarray(vel, sim.dtype))


#: Stated tolerances of the sanity checks (see run_case).
ENERGY_TOL = {"float64": 0.02, "float32": 0.02}


def run_case(case: Case, *, remedy: bool = True, max_inner_steps: int = 2_000_000) -> dict:
    """Run one extreme case and judge it.

    Outcomes: ``"ok"`` (sane, see below); ``"refused"`` (a clear StabilityError before running:
    the explicit step is past its limit) -- with ``remedy``, the case is then re-run with the
    substeps the error names and the row records that run's verdict as ``remedy``;
    ``"error"`` (another clear error, e.g. NonFiniteError naming step and body);
    ``"FAIL"`` (a sanity check failed, or a NaN was produced without an error).

    Sanity checks (every state saved):
      * finite positions and velocities, and finite d(loss)/dk, d(loss)/dc (loss = mean height
        of the bodies over the run);
      * energy does not grow: in states out of contact (penetration <= 2 m g / k + smoothing,
        i.e. resting contact counts as out of contact), energy <= E0 + tol |E0| with
        tol = ENERGY_TOL (2%) plus the step's own first-order energy error w h / 2 for explicit
        integrators (0 for implicit_euler), E0 the initial energy including any initial overlap;
      * penetration bounded: <= d_E + v_E h + smoothing, d_E the depth at which the contact
        spring would hold all of E0 + the work of gravity over it, v_E the speed all of E0
        would give one body, h the inner step (one step of travel into the contact);
      * restitution <= 1 within the same tolerance: the largest upward speed after the first
        impact is <= the largest downward speed before it times sqrt(1 + tol).
    """
    row = dataclasses.asdict(case)
    row["c"] = case.c
    try:
        out = _run_case(case, 1, max_inner_steps)
    except dp.StabilityError as e:
        row.update(outcome="refused", detail=str(e).split(":")[0] + (
                   f": safe step {e.stable_dt:.3g} s, needs substeps={e.substeps}"
                   if e.stable_dt is not None else ": asks for float64"),
                   substeps=e.substeps, stable_dt=e.stable_dt)
        steps = max(2, int(round(case.duration / case.dt)))
        if remedy:
            # the error's advice: the substeps it names, or implicit_euler when those would
            # be too many inner steps
            use_substeps = e.substeps is not None and e.substeps * steps <= max_inner_steps
            try:
                r = (_run_case(case, e.substeps, max_inner_steps) if use_substeps else
                     _run_case(case, 1, max_inner_steps, integrator="implicit_euler"))
                row["remedy"] = r["outcome"]
                row["remedy_detail"] = (f"substeps={e.substeps}" if use_substeps
                                        else "implicit_euler") + (
                    f": {r['detail']}" if r.get("detail") else "")
                row.update({f"remedy_{k}": v for k, v in r.items()
                            if k not in ("outcome", "detail")})
            except (dp.StabilityError, dp.NonFiniteError, dp.SceneError) as e2:
                row["remedy"] = "error"
                row["remedy_detail"] = f"{type(e2).__name__}: {e2}"
        return row
    except (dp.NonFiniteError, dp.SceneError) as e:
        row.update(outcome="error", detail=f"{type(e).__name__}: {e}")
        return row
    row.update(out)
    return row


def _run_case(case: Case, substeps: int, max_inner_steps: int, integrator=None) -> dict:
    integrator = integrator or case.integrator
    sim, steps, vg = _case_sim(case, substeps, integrator)
    params = (sim.params(k=case.k, c=case.c, spring_k=case.k, spring_c=case.c)
              if case.scene == "chain" else sim.params(k=case.k, c=case.c))
    rep = sim.stability(params)
    if substeps == 1:
        _stab.gate(sim, params)                      # raises StabilityError past the limit
    state = _initial_state(sim, case)
    grad, traj = vg(jnp.asarray([case.k, case.c], sim.dtype), state)
    gk, gc = np.asarray(grad, float)
    pos = np.asarray(traj.position, float)
    vel = np.asarray(traj.velocity, float)
    out = dict(outcome="ok", detail="", substeps=substeps, stable_dt=rep.stable_dt,
               margin=rep.margin * 1.0, grad_k=float(gk), grad_c=float(gc))
    bad = ~(np.isfinite(pos).all(axis=-1) & np.isfinite(vel).all(axis=-1))
    if bad.any():
        # what the user's rollout does with it: a NonFiniteError naming step and body is a
        # clear error; anything else is a silent NaN
        try:
            sim.rollout(params, steps, state)
        except dp.NonFiniteError as e:
            out.update(outcome="error", detail=f"NonFiniteError: {e}")
            return out
        s, b = (int(v) for v in np.argwhere(bad)[0])
        out.update(outcome="FAIL", detail=f"non-finite state at step {s + 1}, body {b} "
                   "without an error")
        return out
    problems = []
    if not (np.isfinite(gk) and np.isfinite(gc)):
        problems.append(f"non-finite gradient (dk {float(gk):.3g}, dc {float(gc):.3g})")
    x0 = np.asarray(state.position, float)[None]
    v0 = np.asarray(state.velocity, float)[None]
    e0, d0 = _energy(sim, case.k, case.k, x0, v0)
    e, d = _energy(sim, case.k, case.k, pos, vel)
    e0, d0 = float(e0[0]), float(d0[0])
    h = case.dt / substeps
    explicit = integrator not in dp.integrators.IMPLICIT
    tol = ENERGY_TOL[case.dtype] + (0.5 * rep.omega_max * h if explicit else 0.0)
    g = G if case.gravity else 0.0
    m = case.mass
    rest = 2.0 * m * g / case.k * (4 if case.scene == "chain" else 1) + sim.smoothing
    free = d <= rest
    # energy scale: |E0| + the drop's potential + the rounding floor of the springs' energy
    eps = float(np.finfo(np.dtype(case.dtype)).eps)
    scale = (abs(e0) + m * g * 0.5 * len(sim.mass)
             + len(sim.mass) * 0.5 * case.k * (100 * eps * 0.2) ** 2 + 1e-300)
    growth = float(np.max(e[free]) - e0) / scale if free.any() else 0.0
    out["energy_growth"] = growth
    if growth > tol:
        problems.append(f"energy grew by {growth:.3g} of its scale (> {tol:.3g})")
    # penetration bound
    e_avail = max(e0, 0.0) + m * g * 1.0 * len(sim.mass) + 1e-300
    d_e = (m * g + math.sqrt((m * g) ** 2 + 2.0 * case.k * e_avail)) / case.k
    v_e = math.sqrt(2.0 * e_avail / m)
    bound = max(d0, d_e + v_e * h + sim.smoothing)
    out["max_penetration"] = float(np.max(d))
    out["penetration_bound"] = bound
    if np.max(d) > bound:
        problems.append(f"penetration {np.max(d):.3g} m > bound {bound:.3g} m")
    # restitution of the first impact (body 0)
    vz = vel[:, 0, 2]
    # the step-averaged contact (smoothing 0) acts from a gap of |v| h on
    touching = np.flatnonzero(d > (sim.smoothing if sim.smoothing else -np.abs(vz) * h))
    if touching.size and case.overlap is False:
        first = touching[0]
        v_in = max(case.speed, float(-np.min(np.concatenate([[-case.speed], vz[:first + 1]]))))
        v_out = float(np.max(vz[first:])) if first < len(vz) else 0.0
        if v_in > 0:
            e_rest = max(v_out, 0.0) / v_in
            out["restitution"] = e_rest
            if e_rest > math.sqrt(1.0 + tol) and case.scene == "ball":
                problems.append(f"restitution {e_rest:.4g} > 1")
    if problems:
        out.update(outcome="FAIL", detail="; ".join(problems))
    return out


def stability_matrix(cases: list[Case] | None = None, *, progress: Callable | None = None,
                     remedy: bool = True) -> list[dict]:
    """Run every case (default :func:`extreme_cases`); one result dict per case."""
    cases = extreme_cases() if cases is None else cases
    rows = []
    for i, case in enumerate(cases):
        rows.append(run_case(case, remedy=remedy))
        if progress is not None:
            progress(i + 1, len(cases), rows[-1])
    _SIM_CACHE.clear()
    return rows


def summarize_matrix(rows: list[dict]) -> dict:
    """Counts of outcomes, overall and of the remedies of refused cases."""
    out = {"cases": len(rows)}
    for r in rows:
        out[r["outcome"]] = out.get(r["outcome"], 0) + 1
        if r["outcome"] == "refused" and "remedy" in r:
            key = f"refused->remedy {r['remedy']}"
            out[key] = out.get(key, 0) + 1
    return out
