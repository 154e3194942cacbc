"""Trust reports: the extreme-case stability matrix, error against run time (work-precision)
of every integrator, and the error of gradients against dt and smoothing width.

Everything here computes and returns plain data (dicts, lists); ``tuning.cli.report`` prints
and plots. References are independent of the simulator: closed forms (damped spring), or
``scipy.integrate.solve_ivp(method="DOP853", rtol=1e-12)`` on a right-hand side written here
in numpy, with every contact start and end located as an event (ball), never the same
integrator at a smaller dt. Times are medians of several runs after compilation, measured with
``jax.block_until_ready``.

Units: SI throughout (m, kg, s, N/m, N s/m).
"""
from __future__ import annotations

import dataclasses
import math
import statistics
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp
from diffpen import stability as _stab

__all__ = [
    "G", "INTEGRATORS", "ball_scene", "chain_scene", "Case", "extreme_cases", "run_case",
    "stability_matrix", "summarize_matrix", "ball_reference", "chain_reference",
    "spring_closed_form", "apex_heights", "settling_time", "accuracy", "recommend",
    "gradient_report", "time_call", "plot_accuracy", "BallSpec", "case_smoothing",
]

G = 9.81
INTEGRATORS = ("semi_implicit_euler", "verlet", "rk4", "implicit_euler")


def _scipy_integrate():
    try:
        from scipy import integrate
    except ImportError:
        raise ImportError("reference solutions need scipy: pip install -e '.[report]' (or "
                          "pip install scipy).") from None
    return integrate


# --------------------------------------------------------------------------- scenes
def ball_scene(*, mass: float = 1.0, radius: float = 0.1, height: float = 1.0,
               speed: float = 0.0, overlap: bool = False, gravity: bool = True) -> dp.Scene:
    """One sphere above the ground plane z = 0.

    height: initial centre height, m (ignored with ``overlap``: the centre then starts ON the
    plane, i.e. overlapped by its full radius).  speed: initial downward speed, m/s.
    """
    scene = dp.Scene(gravity=(0.0, 0.0, -G if gravity else 0.0))
    z0 = 0.0 if overlap else height
    scene.add_sphere(radius=radius, mass=mass, position=(0.0, 0.0, z0),
                     velocity=(0.0, 0.0, -speed))
    scene.add_plane()
    return scene


def chain_scene(*, n: int = 4, mass: float = 1.0, radius: float = 0.05, spacing: float = 0.2,
                height: float = 0.5, speed: float = 0.0, overlap: bool = False,
                gravity: bool = True, k: float = 1e4, c: float = 0.0) -> dp.Scene:
    """A horizontal chain of ``n`` spheres joined by springs (group ``"chain"``), above the
    ground plane, falling onto it. ``mass`` per sphere, kg; the springs start at rest length.
    ``overlap``: the first sphere starts centred on the plane (overlapped by its radius)."""
    scene = dp.Scene(gravity=(0.0, 0.0, -G if gravity else 0.0))
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
def _ramp_potential(d, width: float):
    """Integral of diffpen.laws.ramp from -inf to d (m^2): contact energy / k."""
    d = np.asarray(d, float)
    if width == 0.0:
        return 0.5 * np.maximum(d, 0.0) ** 2
    h = 0.5 * width
    band = (np.clip(d, -h, h) + h) ** 3 / (6.0 * width)
    return np.where(d >= h, 0.5 * d * d + h * h / 6.0, np.where(d <= -h, 0.0, band))


def _energy(sim, k, sk, position, velocity):
    """Mechanical energy (J) per saved state: kinetic + gravity + springs + contact.

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
    e += k * np.sum(_ramp_potential(d, sim.smoothing), axis=-1)
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
    physics-notes.md section 5's rule sigma < m g / k, else 0 (the exact ramp max(d, 0))."""
    g = G if case.gravity else 0.0
    width = 1e-3 * radius
    return width if width < case.mass * g / case.k else 0.0


def _case_sim(case: Case, substeps, integrator=None):
    integrator = integrator or case.integrator
    key = (case.scene, case.dtype, integrator, case.mass, case.gravity, case.dt, substeps,
           case_smoothing(case, 0.1 if case.scene == "ball" else 0.05))
    if key not in _SIM_CACHE:
        if case.scene == "ball":
            scene = ball_scene(mass=case.mass, height=0.5, gravity=case.gravity)
        else:
            scene = chain_scene(mass=case.mass, gravity=case.gravity)
        width = case_smoothing(case, scene.bodies[0].radius)
        sim = dp.compile(scene, case.dt, integrator=integrator, substeps=substeps,
                         dtype=jnp.dtype(case.dtype), smoothing=width)
        steps = max(2, int(round(case.duration / case.dt)))

        def loss(kc, state):
            k, c = kc[0], kc[1]
            params = (sim.params(k=k, c=c, spring_k=k, spring_c=c) if case.scene == "chain"
                      else sim.params(k=k, c=c))
            traj = sim.rollout(params, steps, state, check_finite=False)
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
        row.update(outcome="refused", detail=str(e).split(":")[0] + f": safe step "
                   f"{e.stable_dt:.3g} s, needs substeps={e.substeps}", substeps=e.substeps,
                   stable_dt=e.stable_dt)
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
    touching = np.flatnonzero(d > sim.smoothing)
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


# --------------------------------------------------------------------------- references
def spring_closed_form(t, *, k: float, c: float, m: float, x0: float):
    """Free damped oscillator x'' = -(k x + c x') / m from (x0, 0): position x(t), m.
    Under-, critically and over-damped cases."""
    t = np.asarray(t, float)
    w0 = math.sqrt(k / m)
    z = c / (2.0 * math.sqrt(k * m))
    if z < 1.0:
        wd = w0 * math.sqrt(1.0 - z * z)
        return x0 * np.exp(-z * w0 * t) * (np.cos(wd * t) + z * w0 / wd * np.sin(wd * t))
    if z == 1.0:
        return x0 * np.exp(-w0 * t) * (1.0 + w0 * t)
    s = w0 * math.sqrt(z * z - 1.0)
    r1, r2 = -z * w0 + s, -z * w0 - s
    return x0 * (r2 * np.exp(r1 * t) - r1 * np.exp(r2 * t)) / (r2 - r1)


class BallReference:
    """Hard-contact ball on the plane z = 0 (linear law, no smoothing), solved phase by phase
    with DOP853 at rtol 1e-12; each contact start and end (centre height = radius) is an
    event. ``state(t) -> (z, v)``; ``contacts``: list of (t_start, t_end); ``apexes``: apex
    centre heights after each contact (exact: z + v^2 / (2 g) at the end of contact)."""

    def __init__(self, *, k: float, c: float, m: float, r: float, z0: float, v0: float = 0.0,
                 T: float, g: float = G):
        integrate = _scipy_integrate()
        self.k, self.c, self.m, self.r, self.g = k, c, m, r, g
        self.T = T
        segs, contacts, apexes = [], [], []
        t, y = 0.0, np.array([z0, v0], float)
        in_contact = z0 < r

        def flight(_, y):
            return [y[1], -g]

        def contact(_, y):
            d = r - y[0]
            return [y[1], (k * d - c * y[1]) / m - g]

        def surface(_, y):
            return y[0] - r
        while t < T:
            surface.terminal = True
            surface.direction = 1.0 if in_contact else -1.0
            sol = integrate.solve_ivp(contact if in_contact else flight, (t, T), y,
                                      method="DOP853", rtol=1e-12, atol=1e-14,
                                      events=surface, dense_output=True)
            segs.append((t, sol.t[-1], sol.sol, in_contact))
            if sol.status == 1:                      # event: contact starts or ends
                t_e = float(sol.t_events[0][0])
                y = np.array(sol.y_events[0][0], float)
                y[0] = r
                if in_contact:
                    contacts.append((contacts_start, t_e))
                    # no apex without gravity: the ball leaves for good
                    apexes.append(r + y[1] ** 2 / (2.0 * g) if g > 0.0 else np.inf)
                else:
                    contacts_start = t_e
                t = t_e
                in_contact = not in_contact
                if len(contacts) > 200:
                    break
            else:
                if in_contact:
                    contacts.append((contacts_start if contacts else 0.0, T))
                t = T
        self._segs = segs
        self.contacts = contacts
        self.apexes = apexes

    def state(self, t):
        """(z (S,), v (S,)) at times t (S,) s."""
        t = np.atleast_1d(np.asarray(t, float))
        z, v = np.empty_like(t), np.empty_like(t)
        starts = np.array([s[0] for s in self._segs])
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(self._segs) - 1)
        for i in np.unique(idx):
            sel = idx == i
            y = self._segs[i][2](np.clip(t[sel], self._segs[i][0], self._segs[i][1]))
            z[sel], v[sel] = y[0], y[1]
        return z, v

    def energy(self, z, v):
        """Energy above rest on the plane, J: kinetic + m g (z - r) + contact spring."""
        d = np.maximum(self.r - z, 0.0)
        return 0.5 * self.m * v * v + self.m * self.g * (z - self.r) + 0.5 * self.k * d * d

    def settling_time(self, frac: float = 0.01) -> float:
        """First time the energy falls to ``frac`` of its initial value (s); energy decreases
        only during contact, so the crossing is located in a contact phase with brentq."""
        from scipy.optimize import brentq
        z0, v0 = self.state([0.0])
        target = frac * float(self.energy(z0, v0)[0])
        for (t0, t1, sol, contact) in self._segs:
            if not contact:
                continue
            e1 = float(self.energy(*sol(t1)))
            if e1 <= target:
                return brentq(lambda t: float(self.energy(*sol(t))) - target, t0, t1,
                              xtol=1e-13)
        return math.nan


def ball_reference(**kw) -> BallReference:
    """See :class:`BallReference`."""
    return BallReference(**kw)


def chain_reference(t_eval, *, x0, m: float, k: float, c: float, rest: float, g: float = G):
    """Chain of particles hanging from a pinned first particle: springs between neighbours
    (F = -k x - c x_dot along the axis), gravity -z. DOP853 at rtol 1e-12 on a numpy
    right-hand side. x0: (n, 3) initial positions (row 0 pinned), at rest.
    Returns positions (S, n, 3) at t_eval."""
    integrate = _scipy_integrate()
    x0 = np.asarray(x0, float)
    n = len(x0)

    def rhs(_, y):
        x = np.concatenate([x0[:1], y[:3 * (n - 1)].reshape(n - 1, 3)])
        v = np.concatenate([np.zeros((1, 3)), y[3 * (n - 1):].reshape(n - 1, 3)])
        d = x[1:] - x[:-1]
        L = np.linalg.norm(d, axis=1)
        u = d / L[:, None]
        rate = np.sum(u * (v[1:] - v[:-1]), axis=1)
        f = (-k * (L - rest) - c * rate)[:, None] * u       # on the lower end of each spring
        acc = np.zeros((n, 3))
        acc[1:] += f / m
        acc[:-1] -= f / m
        acc[:, 2] -= g
        return np.concatenate([y[3 * (n - 1):], acc[1:].ravel()])
    y0 = np.concatenate([x0[1:].ravel(), np.zeros(3 * (n - 1))])
    sol = integrate.solve_ivp(rhs, (0.0, float(t_eval[-1])), y0, method="DOP853",
                              rtol=1e-12, atol=1e-12, t_eval=t_eval)
    pos = sol.y[:3 * (n - 1)].T.reshape(len(t_eval), n - 1, 3)
    return np.concatenate([np.broadcast_to(x0[:1], (len(t_eval), 1, 3)), pos], axis=1)


# --------------------------------------------------------------------------- metrics
def apex_heights(t, z, radius: float, n: int):
    """Centre heights of the first ``n`` apexes after the first contact, m (NaN if missing).

    Each flight (z > radius) after a contact contributes its highest sample refined by a
    parabola through it and its neighbours (exact for samples of a parabola, which is what
    every integrator here produces in free flight up to its own error)."""
    z = np.asarray(z, float)
    air = z > radius
    out = []
    i = int(np.argmax(~air)) if (~air).any() else len(z)   # first contact sample
    while len(out) < n and i < len(z):
        starts = np.flatnonzero(air[i:])
        if not starts.size:
            break
        s = i + starts[0]
        ends = np.flatnonzero(~air[s:])
        e = s + ends[0] if ends.size else len(z)
        if e == len(z):
            break                                             # flight not finished
        j = s + int(np.argmax(z[s:e]))
        if 0 < j < len(z) - 1:
            a, b, cc = z[j - 1], z[j], z[j + 1]
            den = a - 2 * b + cc
            out.append(b - (a - cc) ** 2 / (8 * den) if den < 0 else b)
        else:
            out.append(z[j])
        i = e
    return np.array(out + [math.nan] * (n - len(out)))


def settling_time(t, energy, frac: float = 0.01) -> float:
    """First time the energy (J, per sample) falls to ``frac`` of its first value, linearly
    interpolated between samples (s); NaN if it never does."""
    t, energy = np.asarray(t, float), np.asarray(energy, float)
    e0 = energy[0]
    below = np.flatnonzero(energy <= frac * e0)
    if not below.size:
        return math.nan
    i = below[0]
    if i == 0:
        return float(t[0])
    a, b = energy[i - 1], energy[i]
    return float(t[i - 1] + (a - frac * e0) / (a - b) * (t[i] - t[i - 1]))


def time_call(fn: Callable, repeats: int = 5) -> float:
    """Median wall time (s) of ``fn()`` over ``repeats`` runs after one warm-up (compile) run;
    ``fn`` returns arrays, waited for with jax.block_until_ready."""
    jax.block_until_ready(fn())
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


# --------------------------------------------------------------------------- accuracy
@dataclasses.dataclass
class BallSpec:
    """The ball problem: k (N/m), c (N s/m), mass (kg), radius (m), drop height of the centre
    (m), simulated time T (s), apexes compared, settling energy fraction."""
    k: float = 1e4
    c: float = 20.0
    mass: float = 1.0
    radius: float = 0.1
    height: float = 1.0
    T: float = 3.0
    n_apex: int = 3
    settle_frac: float = 0.01


def _ball_errors(spec: BallSpec, ref: BallReference, t, z, v):
    ap = apex_heights(t, z, spec.radius, spec.n_apex)
    ap_ref = np.array(ref.apexes[:spec.n_apex])
    rel = np.abs(ap - ap_ref) / (ap_ref - spec.radius)
    d = np.maximum(spec.radius - z, 0.0)
    e = (0.5 * spec.mass * v * v + spec.mass * G * (z - spec.radius)
         + 0.5 * spec.k * d * d)
    e_all = np.concatenate([[spec.mass * G * (spec.height - spec.radius)], e])
    t_all = np.concatenate([[0.0], t])
    ts = settling_time(t_all, e_all, spec.settle_frac)
    ts_ref = ref.settling_time(spec.settle_frac)
    return {"apex_rel_error": float(np.max(rel)) if np.all(np.isfinite(rel)) else math.inf,
            "apexes": ap.tolist(), "settling_time": ts,
            "settling_error": abs(ts - ts_ref) if math.isfinite(ts) else math.inf}


def _dts(coarse: float, n: int):
    return [coarse / 2 ** i for i in range(n)]


def accuracy(*, ball: BallSpec | None = None, integrators=INTEGRATORS, n_dt: int = 6,
             coarse_dt: float = 4e-3, widths=(0.0, 1e-5, 1e-4, 1e-3, 1e-2),
             width_dt: float = 1.25e-4, repeats: int = 5, problems=("ball", "spring", "chain"),
             default_dtypes=("float32", "float64"), progress: Callable | None = None,
             dts=None) -> dict:
    """Error against run time for each integrator and a ladder of dt (halving from
    ``coarse_dt``), on three problems, against independent references:

    * ``ball``: drop onto the plane (linear law, smoothing 0): max relative error of the first
      apex heights (above the plane) against the DOP853 reference with located contact
      events; settling time (energy to 1%) error in s.
    * ``spring``: particle on a damped world spring (k = 100 N/m, m = 1 kg, zeta = 0.1,
      x0 = 0.1 m, 2 s): max |x - x_exact| / x0 against the closed form.
    * ``chain``: 6 particles hanging from a pinned one (k = 200 N/m, c = 0.5 N s/m, 0.1 kg),
      released sideways, 1.5 s: max tip position error / chain length against DOP853.

    Plus the ball's smoothing-width ladder (semi-implicit Euler at ``width_dt``) and the
    default configuration (semi-implicit Euler, dt = 1e-3 s, default smoothing) in each of
    ``default_dtypes``. Times: median of ``repeats`` rollouts of the whole problem after
    compilation. ``dts`` (s), when given, replaces the halving ladder for every problem.
    Returns a JSON-able dict: ``{"problems": {name: {integrator: [points]}}, "widths":
    [...], "default": [...], "ball": spec}``; a point is ``{"dt", "error", "time", ...}``.
    """
    spec = ball or BallSpec()
    say = progress or (lambda *_: None)
    out = {"ball": dataclasses.asdict(spec), "problems": {}, "widths": [], "default": []}
    ref = ball_reference(k=spec.k, c=spec.c, m=spec.mass, r=spec.radius, z0=spec.height,
                         T=spec.T)
    if "ball" in problems:
        scene = ball_scene(mass=spec.mass, radius=spec.radius, height=spec.height)
        res = {}
        for integ in integrators:
            pts = []
            for dt in dts or _dts(coarse_dt, n_dt):
                sim = dp.compile(scene, dt, integrator=integ, smoothing=0.0,
                                 dtype=jnp.float64, substeps="auto")
                params = sim.params(k=spec.k, c=spec.c)
                steps = int(round(spec.T / dt))
                try:
                    traj = sim.rollout(params, steps)
                except (dp.StabilityError, dp.NonFiniteError) as e:
                    pts.append({"dt": dt, "error": math.inf, "time": math.nan,
                                "note": type(e).__name__})
                    continue
                t = np.asarray(traj.time)
                z, v = (np.asarray(traj.position[:, 0, 2]), np.asarray(traj.velocity[:, 0, 2]))
                errs = _ball_errors(spec, ref, t, z, v)
                wall = time_call(lambda: sim.rollout(params, steps).position, repeats)
                pts.append({"dt": dt, "error": errs["apex_rel_error"], "time": wall,
                            "settling_error": errs["settling_error"],
                            "substeps": getattr(sim, "_auto_last", 1)})
                say("ball", integ, pts[-1])
            res[integ] = pts
        out["problems"]["ball"] = res
        out["reference"] = {"apexes": ref.apexes[:spec.n_apex],
                            "settling_time": ref.settling_time(spec.settle_frac)}
        # smoothing width ladder and the default configuration
        for w in widths:
            sim = dp.compile(scene, width_dt, smoothing=w, dtype=jnp.float64)
            steps = int(round(spec.T / width_dt))
            traj = sim.rollout(sim.params(k=spec.k, c=spec.c), steps)
            errs = _ball_errors(spec, ref, np.asarray(traj.time),
                                np.asarray(traj.position[:, 0, 2]),
                                np.asarray(traj.velocity[:, 0, 2]))
            out["widths"].append({"width": w, "dt": width_dt, "error": errs["apex_rel_error"],
                                  "settling_error": errs["settling_error"]})
            say("width", w, out["widths"][-1])
        for dtype in default_dtypes:
            sim = dp.compile(scene, 1e-3, dtype=jnp.dtype(dtype))
            params = sim.params(k=spec.k, c=spec.c)
            steps = int(round(spec.T / 1e-3))
            traj = sim.rollout(params, steps)
            errs = _ball_errors(spec, ref, np.asarray(traj.time, float),
                                np.asarray(traj.position[:, 0, 2], float),
                                np.asarray(traj.velocity[:, 0, 2], float))
            wall = time_call(lambda: sim.rollout(params, steps).position, repeats)
            out["default"].append({"dtype": dtype, "dt": 1e-3, "smoothing": sim.smoothing,
                                   "steps": steps, "error": errs["apex_rel_error"],
                                   "settling_error": errs["settling_error"], "time": wall,
                                   "time_per_step": wall / steps})
            say("default", dtype, out["default"][-1])
    if "spring" in problems:
        k, c, m, x0, T = 100.0, 2.0, 1.0, 0.1, 2.0
        scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
        p = scene.add_particle(mass=m, position=(0.0, 0.0, 1.0 + x0))
        scene.add_spring(p, (0.0, 0.0, 0.0), k=k, c=c, rest_length=1.0)
        res = {}
        for integ in integrators:
            pts = []
            for dt in dts or _dts(coarse_dt * 2.5, n_dt):
                sim = dp.compile(scene, dt, integrator=integ, dtype=jnp.float64)
                params = sim.params()
                steps = int(round(T / dt))
                traj = sim.rollout(params, steps)
                x = np.asarray(traj.position[:, 0, 2]) - 1.0
                err = float(np.max(np.abs(x - spring_closed_form(np.asarray(traj.time), k=k,
                                                                 c=c, m=m, x0=x0)))) / x0
                wall = time_call(lambda: sim.rollout(params, steps).position, repeats)
                pts.append({"dt": dt, "error": err, "time": wall})
                say("spring", integ, pts[-1])
            res[integ] = pts
        out["problems"]["spring"] = res
    if "chain" in problems:
        n, k, c, m, L, T = 6, 200.0, 0.5, 0.1, 0.2, 1.5
        scene = dp.Scene(gravity=(0.0, 0.0, -G))
        prev = scene.add_particle(mass=m, position=(0.0, 0.0, 0.0), pinned=True)
        for i in range(1, n + 1):
            b = scene.add_particle(mass=m, position=(L * i, 0.0, 0.0))
            scene.add_spring(prev, b, k=k, c=c, rest_length=L, group="chain")
            prev = b
        x0 = np.array([[L * i, 0.0, 0.0] for i in range(n + 1)])
        res = {}
        refs = {}
        for integ in integrators:
            pts = []
            for dt in dts or _dts(coarse_dt, n_dt):
                sim = dp.compile(scene, dt, integrator=integ, dtype=jnp.float64)
                params = sim.params()
                steps = int(round(T / dt))
                traj = sim.rollout(params, steps)
                tt = np.asarray(traj.time)
                if dt not in refs:
                    refs[dt] = chain_reference(tt, x0=x0, m=m, k=k, c=c, rest=L)
                tip = np.asarray(traj.position[:, -1])
                err = float(np.max(np.linalg.norm(tip - refs[dt][:, -1], axis=-1))) / (n * L)
                wall = time_call(lambda: sim.rollout(params, steps).position, repeats)
                pts.append({"dt": dt, "error": err, "time": wall})
                say("chain", integ, pts[-1])
            res[integ] = pts
        out["problems"]["chain"] = res
    return out


def recommend(result: dict, tol: float, problem: str = "ball"):
    """Cheapest (integrator, dt) of ``result["problems"][problem]`` whose error <= tol, as a
    point dict with its integrator, or None when none meets it."""
    best = None
    for integ, pts in result["problems"].get(problem, {}).items():
        for p in pts:
            if p["error"] <= tol and math.isfinite(p["time"]):
                if best is None or p["time"] < best["time"]:
                    best = dict(p, integrator=integ)
    return best


# --------------------------------------------------------------------------- gradients
def gradient_report(*, spec: BallSpec | None = None, dts=(1e-3, 2.5e-4), widths=(0.0, 1e-4,
                    1e-3, 1e-2), t_height: float = 2.0,
                    rel_steps=tuple(10.0 ** -np.arange(1, 8.5, 0.5)), agree: float = 0.01,
                    progress: Callable | None = None) -> list[dict]:
    """Gradient error of the ball's apex height and of its height at ``t_height`` s w.r.t.
    k and c, against dt and smoothing width.

    For each (dt, width): jax.grad of
      * ``apex``: z + v^2 / (2 g) at the sample nearest the middle of the first rebound's
        flight (the first apex height, exact in free flight), and
      * ``z_T``: the centre height at ``t_height`` s,
    its relative error against the derivative of the continuous hard-contact model (central
    differences of the DOP853 reference, relative step 1e-5), and the largest relative
    finite-difference step (from ``rel_steps``) at which central differences of the
    simulator agree with jax.grad within ``agree`` (relative), with every smaller step down
    to 1e-5 agreeing too.
    Returns one dict per (dt, width, quantity, parameter).
    """
    spec = spec or BallSpec(T=t_height)
    say = progress or (lambda *_: None)
    T = t_height

    def ref_quantities(k, c):
        ref = ball_reference(k=k, c=c, m=spec.mass, r=spec.radius, z0=spec.height, T=T)
        (t0, t1), t2 = ref.contacts[0], ref.contacts[1][0]
        z, v = ref.state([T])
        return ref.apexes[0], float(z[0]), 0.5 * (t1 + t2)
    apex0, zT0, t_mid = ref_quantities(spec.k, spec.c)
    ref_d = {}
    for name, i in (("k", 0), ("c", 1)):
        base = [spec.k, spec.c]
        h = 1e-5 * base[i]
        up, dn = list(base), list(base)
        up[i] += h
        dn[i] -= h
        qu, qd = ref_quantities(*up), ref_quantities(*dn)
        ref_d[("apex", name)] = (qu[0] - qd[0]) / (2 * h)
        ref_d[("z_T", name)] = (qu[1] - qd[1]) / (2 * h)
    scene = ball_scene(mass=spec.mass, radius=spec.radius, height=spec.height)
    rows = []
    for dt in dts:
        steps = int(round(T / dt))
        i_mid = int(round(t_mid / dt)) - 1
        for w in widths:
            sim = dp.compile(scene, dt, smoothing=w, dtype=jnp.float64)

            @jax.jit
            def quantities(k, c, sim=sim, steps=steps, i_mid=i_mid):
                traj = sim.rollout(sim.params(k=k, c=c), steps)
                z, v = traj.position[:, 0, 2], traj.velocity[:, 0, 2]
                return jnp.stack([z[i_mid] + v[i_mid] ** 2 / (2 * G), z[-1]])
            jac = jax.jit(jax.jacrev(quantities, (0, 1)))
            dk, dc = (np.asarray(a) for a in jac(spec.k, spec.c))
            for qi, qname in enumerate(("apex", "z_T")):
                for pname, g, base in (("k", dk[qi], spec.k), ("c", dc[qi], spec.c)):
                    fds = []
                    for s in rel_steps:
                        h = s * base
                        if pname == "k":
                            a, b = quantities(base + h, spec.c), quantities(base - h, spec.c)
                        else:
                            a, b = quantities(spec.k, base + h), quantities(spec.k, base - h)
                        fds.append(float((a[qi] - b[qi]) / (2 * h)))
                    fds = np.array(fds)
                    ok = np.abs(fds - g) <= agree * abs(g)
                    largest = None
                    for j, s in enumerate(rel_steps):
                        if all(ok[j:][np.array(rel_steps[j:]) >= 1e-5]):
                            largest = float(s)
                            break
                    r = ref_d[(qname, pname)]
                    rows.append({"dt": dt, "width": w, "quantity": qname, "param": pname,
                                 "grad": float(g), "reference": float(r),
                                 "grad_rel_error": abs(float(g) - r) / abs(r),
                                 "largest_agreeing_rel_step": largest,
                                 "fd": fds.tolist(), "rel_steps": [float(s) for s in rel_steps]})
                    say(rows[-1])
    return rows


# --------------------------------------------------------------------------- plot
def plot_accuracy(result: dict, path: str) -> None:
    """Log-log work-precision diagram: x = error, y = wall time, one curve per integrator,
    one panel per problem; the default configuration is starred. matplotlib is imported here
    (the ``plot`` extra)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError("--plot needs matplotlib: pip install 'diffpen[plot]' (or pip "
                          "install matplotlib).") from None
    names = list(result["problems"])
    titles = {"ball": "ball drop: apex heights (rel.)", "spring": "damped spring (rel.)",
              "chain": "hanging chain: tip (rel. to length)"}
    fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 4.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        for i, (integ, pts) in enumerate(result["problems"][name].items()):
            pts = [p for p in pts if math.isfinite(p["error"]) and math.isfinite(p["time"])
                   and p["error"] > 0]
            if not pts:
                continue
            x = [p["error"] for p in pts]
            y = [p["time"] for p in pts]
            ax.loglog(x, y, "o-", color=f"C{i}", label=integ, ms=4)
            ax.annotate(f"{pts[0]['dt']:.0e}", (x[0], y[0]), fontsize=7, color=f"C{i}",
                        xytext=(3, 3), textcoords="offset points")
        if name == "ball":
            for d in result.get("default", []):
                ax.loglog([d["error"]], [d["time"]], "*", ms=12,
                          color="k" if d["dtype"] == "float64" else "0.5",
                          label=f"default ({d['dtype']}, dt 1e-3)")
        ax.set_xlabel("error against reference")
        ax.set_ylabel("wall time of the rollout (s)")
        ax.set_title(titles.get(name, name), fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("diffpen work-precision (lower left is better; label = coarsest dt)",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
