"""Independent reference solutions for the trust reports, and the measurements on sampled
trajectories that are compared with them.

References never use the simulator: closed forms (damped spring), or
``scipy.integrate.solve_ivp(method="DOP853", rtol=1e-12)`` on a right-hand side written here
in numpy, with every contact start and end located as an event (ball), never the same
integrator at a smaller dt. :func:`apex_heights` and :func:`settling_time` measure a sampled
trajectory (numpy), so that a simulated run and a reference are judged by the same rule.

Units: SI throughout (m, kg, s, N/m, N s/m).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "G", "spring_closed_form", "BallReference", "ball_reference",
    "ball_reference_derivatives", "chain_reference",
    "apex_heights", "settling_time", "BoxCornerReference", "rotation_angle", "quat_matrix",
]

G = 9.81


def _scipy_integrate():
    try:
        from scipy import integrate
    except ImportError:
        raise ImportError("reference solutions need scipy: pip install -e '.[report]' (or "
                          "pip install scipy).") from None
    return integrate



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


def _law_facts(law, exponent: float = 1.0):
    """The :class:`diffpen.laws.ContactLaw` record of ``law`` (a name or a record), whose
    facts (``pulls``, ``exponent``, ``damping_exponent``) say which force the references
    write out; the force itself is written here in numpy."""
    from diffpen.laws import get
    return get(law, exponent)


class BallReference:
    """Hard-contact ball on the plane z = 0, solved phase by phase with DOP853 at rtol 1e-12;
    every contact start and end (centre height = radius) is an event, and so is every switch
    of a clamped law (``no_tension``: ``k d - c v`` through 0; ``hunt_crossley``: ``k - c v``
    through 0), so each phase has a smooth right-hand side.

    Laws (``d = r - z`` penetration, ``v = dz/dt`` the separating speed), written here in
    numpy from the facts of the law's record (``pulls``, ``exponent``, ``damping_exponent``
    of :class:`diffpen.laws.ContactLaw`; ``law`` is a name or a record), not from its
    force functions:

    * ``linear``: ``F = k d - c v`` while ``d > 0``;
    * ``no_tension``: ``F = max(k d - c v, 0)`` while ``d > 0``;
    * ``hunt_crossley``: ``F = max(k - c v, 0) d^n`` while ``d > 0`` (``exponent`` n).

    Attributes: ``state(t) -> (z, v)``; ``contacts``: list of (t_start, t_end) (geometric
    contact, ``d > 0``); ``apexes``: apex centre heights after each contact (exact:
    ``z + v^2 / (2 g)`` at the end of contact); ``max_penetration``: the largest depth of each
    contact, m (located as the event ``v = 0`` inside it)."""

    def __init__(self, *, k: float, c: float, m: float, r: float, z0: float, v0: float = 0.0,
                 T: float, g: float = G, law: str = "linear", exponent: float = 1.0):
        integrate = _scipy_integrate()
        rec = _law_facts(law, exponent)
        self.k, self.c, self.m, self.r, self.g = k, c, m, r, g
        self.law, self.exponent = rec.name, float(rec.exponent)
        self.T = T
        n, mexp, pulls = self.exponent, float(rec.damping_exponent), rec.pulls

        def switch(y):
            """The clamped quantity of the law, ``F / d^m`` (its sign says whether the contact
            pushes; 1 for a law that may pull)."""
            d, v = r - y[0], y[1]
            if pulls:
                return 1.0
            return k * (d if n - mexp == 1.0 else max(d, 0.0) ** (n - mexp)) - c * v

        def rhs_for(mode):
            contact, pushing = mode

            def rhs(_, y):
                if not (contact and pushing):
                    return [y[1], -g]
                d, v = r - y[0], y[1]
                # F = (k d^(n-m) - c v) d^m: k d - c v for the linear laws, (k - c v) d^n
                # for Hunt-Crossley
                stiff = d if n - mexp == 1.0 else max(d, 0.0) ** (n - mexp)
                f = (k * stiff - c * v) * (1.0 if mexp == 0.0 else max(d, 0.0) ** mexp)
                return [y[1], f / m - g]
            return rhs

        def surface(_, y):
            return y[0] - r

        def clamp(_, y):
            return switch(y)

        def turn(_, y):
            return y[1]
        segs, contacts, apexes, deepest = [], [], [], []
        t, y = 0.0, np.array([z0, v0], float)
        contact = z0 < r
        pushing = contact and switch(y) > 0.0
        start = 0.0                                  # starting overlapped: in contact from 0
        depth = max(r - z0, 0.0)
        while t < T:
            surface.terminal, clamp.terminal, turn.terminal = True, True, False
            surface.direction = 1.0 if contact else -1.0
            clamp.direction = -1.0 if pushing else 1.0
            turn.direction = 0.0
            events = [surface] + ([clamp, turn] if contact else [])
            sol = integrate.solve_ivp(rhs_for((contact, pushing)), (t, T), y,
                                      method="DOP853", rtol=1e-12, atol=1e-14,
                                      events=events, dense_output=True)
            segs.append((t, sol.t[-1], sol.sol, contact and pushing))
            if contact:
                for yz in sol.y_events[2]:
                    depth = max(depth, r - float(yz[0]))
                depth = max(depth, float(np.max(r - sol.y[0])))
            if sol.status != 1:
                if contact:
                    contacts.append((start, T))
                    deepest.append(depth)
                t = T
                break
            hit = [(float(te[0]), i) for i, te in enumerate(sol.t_events[:2]) if len(te)]
            t_e, which = min(hit)
            y = np.array(sol.y_events[which][0], float)
            t = t_e
            if which == 0:                           # contact starts or ends
                y[0] = r
                if contact:
                    contacts.append((start, t_e))
                    deepest.append(depth)
                    # no apex without gravity: the ball leaves for good
                    apexes.append(r + y[1] ** 2 / (2.0 * g) if g > 0.0 else np.inf)
                else:
                    start, depth = t_e, 0.0
                contact = not contact
                pushing = contact and (switch(y) > 0.0 or (not pulls and y[1] < 0))
            else:                                    # the clamp switches inside contact
                pushing = not pushing
            if len(contacts) > 200:
                break
        self._segs = segs
        self.contacts = contacts
        self.apexes = apexes
        self.max_penetration = deepest

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
        n = self.exponent
        return (0.5 * self.m * v * v + self.m * self.g * (z - self.r)
                + self.k * d ** (n + 1.0) / (n + 1.0))

    def settling_time(self, frac: float = 0.01) -> float:
        """First time the energy falls to ``frac`` of its initial value (s); energy decreases
        only while the contact pushes, so the crossing is located in such a phase with
        brentq."""
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


    def decay_time(self, T: float | None = None) -> float:
        """Energy-decay time ``int_0^T E dt / E(0)`` (s) with ``E`` the energy above static
        rest (``energy`` minus its value at rest); by quadrature of the dense solution on
        each phase (the phases are smooth)."""
        from scipy.integrate import quad
        T = self.T if T is None else T
        n = self.exponent
        d_rest = (self.m * self.g / self.k) ** (1.0 / n)
        z_rest = self.r - d_rest
        e_rest = float(self.energy(np.array([z_rest]), np.array([0.0]))[0])

        def e(t, sol):
            z, v = sol(t)
            return float(self.energy(np.array([z]), np.array([v]))[0]) - e_rest
        total = 0.0
        for (t0, t1, sol, _) in self._segs:
            if t0 >= T:
                break
            total += quad(e, t0, min(t1, T), args=(sol,), epsabs=0.0, epsrel=1e-11,
                          limit=200)[0]
        z0, v0 = self.state([0.0])
        return total / (float(self.energy(z0, v0)[0]) - e_rest)


def ball_reference(**kw) -> BallReference:
    """See :class:`BallReference`."""
    return BallReference(**kw)


def ball_reference_derivatives(*, k: float, c: float, rel_step: float = 1e-5, n: int = 3,
                               decay: bool = False, **kw) -> dict:
    """Values and derivatives w.r.t. k and c of the reference ball's metrics, by central
    differences of :class:`BallReference` (relative step ``rel_step``; a parameter at 0, such
    as ``c = 0``, takes a forward difference of absolute step ``rel_step`` in SI units).

    Metrics (arrays of length ``n``): ``apex`` (apex heights of the lowest point above the
    plane, m), ``duration`` (contact durations, s), ``penetration`` (max depth of each
    contact, m); with ``decay`` also ``decay_time`` ((1,), s: :meth:`BallReference.decay_time`
    over ``[0, T]``). Returns ``{"value": {metric: (n,)}, "dk": {...}, "dc": {...}}``."""
    def metrics(kk, cc):
        ref = BallReference(k=kk, c=cc, **kw)
        r = ref.r
        out = {"apex": np.array(ref.apexes[:n]) - r,
               "duration": np.array([b - a for a, b in ref.contacts[:n]]),
               "penetration": np.array(ref.max_penetration[:n])}
        out = {key: np.concatenate([v, np.full(n - len(v), np.nan)]) for key, v in out.items()}
        if decay:
            out["decay_time"] = np.array([ref.decay_time()])
        return out
    out = {"value": metrics(k, c)}
    for name, base in (("dk", k), ("dc", c)):
        step = rel_step * base if base > 0 else rel_step
        up = metrics(k + step, c) if name == "dk" else metrics(k, c + step)
        if base > 0:
            dn = metrics(k - step, c) if name == "dk" else metrics(k, c - step)
            out[name] = {key: (up[key] - dn[key]) / (2.0 * step) for key in up}
        else:       # at 0 (an undamped ball): one-sided, no negative parameter
            out[name] = {key: (up[key] - out["value"][key]) / step for key in up}
    return out


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



# --------------------------------------------------------------------------- box corners
def quat_matrix(q):
    """Rotation matrix (3, 3) of the quaternion q (4,) = (w, x, y, z), normalised here."""
    w, x, y, z = np.asarray(q, float) / math.sqrt(float(np.dot(q, q)))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _cross(a, b):
    """``np.cross`` of (..., 3) arrays, written out (numpy's is slow on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def rotation_angle(q, q0) -> float:
    """Angle (rad, in [0, pi]) of the rotation taking orientation ``q0`` to ``q`` (unit
    quaternions (4,), (w, x, y, z)): ``2 atan2(|vec(p)|, |w(p)|)`` of ``p = q conj(q0)``."""
    q = np.asarray(q, float) / np.linalg.norm(q)
    q0 = np.asarray(q0, float) / np.linalg.norm(q0)
    w0, v0 = q0[0], -q0[1:]
    pw = q[0] * w0 - np.dot(q[1:], v0)
    pv = q[0] * v0 + w0 * q[1:] + np.cross(q[1:], v0)
    return 2.0 * math.atan2(float(np.linalg.norm(pv)), abs(float(pw)))


class BoxCornerReference:
    """A rigid box on the plane z = 0 with penalty contact at each of its 8 corners and
    smooth Coulomb friction, solved phase by phase with DOP853; each corner's contact start
    and end and each sign change of its normal force are located as terminal events, so
    every phase has a smooth right-hand side. Written here in numpy, independently of
    :mod:`diffpen` (the same model as diffpen's ``contact_box_plane`` term, in continuous
    time).

    Model (SI units; world z up, gravity ``-g`` along z). State: centre ``x`` (3,) m,
    velocity ``v`` (3,) m/s, orientation quaternion ``q`` (4,) (w, x, y, z; body to world,
    ``R`` its rotation matrix), body-frame angular velocity ``W`` (3,) rad/s. Corner ``i``
    (body frame ``c_i = (+-hx, +-hy, +-hz)``) is at ``p_i = x + R c_i``, its depth is
    ``d_i = -p_i,z`` and its velocity ``u_i = v + R (W x c_i)``, separating speed
    ``vn_i = u_i,z``. While ``d_i > 0``:

    * normal force ``F_i = k d_i - c vn_i`` (``law="linear"``: it may pull at the end of a
      contact) or ``max(k d_i - c vn_i, 0)`` (``"no_tension"``), along +z;
    * friction ``-mu max(F_i, 0) u_t / sqrt(|u_t|^2 + s^2)``, ``u_t`` the horizontal part of
      ``u_i``, ``s`` the slip speed (m/s);

    both act at ``p_i``; the torque about the centre is ``(R c_i) x f_i``. Newton's and
    Euler's equations: ``m dv/dt = sum f_i - m g e_z``; ``I dW/dt = tau_b - W x I W`` with
    ``I`` the body-frame principal moments (solid box ``m/3 (hy^2 + hz^2)``, ...) and
    ``tau_b = R^T tau``; ``dq/dt = q (0, W) / 2``.

    Args:
      k: N/m, c: N s/m, mu: friction coefficient, slip_speed: m/s.
      mass: kg; half: (3,) half extents, m; inertia: (3,) kg m^2 (default: solid box).
      x0, v0: (3,) m, m/s; q0: (4,) unit quaternion; w0: (3,) world angular velocity, rad/s
        (as ``diffpen.Scene.add_box`` takes them).
      T: end time, s; rtol, atol: DOP853 tolerances (atol on every state component).

    Attributes: ``events`` list of ``(t, corner, kind)`` with kind ``"start"``, ``"end"``
    (``d_i`` through 0), ``"push"``, ``"pull"`` (``F_i`` through 0 inside a contact);
    ``contacts``: per corner, the list of ``(t_start, t_end)`` (``t_end = T`` if still in
    contact). :meth:`state` gives ``(x, v, q, w_world)`` at any time."""

    def __init__(self, *, k: float, c: float, mu: float, slip_speed: float, mass: float,
                 half, x0, v0=(0.0, 0.0, 0.0), q0=(1.0, 0.0, 0.0, 0.0),
                 w0=(0.0, 0.0, 0.0), T: float, g: float = G, law: str = "linear",
                 inertia=None, rtol: float = 1e-10, atol: float = 1e-13,
                 max_events: int = 5000,
                 guard: float = 1e-10):
        integrate = _scipy_integrate()
        rec = _law_facts(law)
        if rec.exponent != 1.0 or rec.damping_exponent != 0.0:
            raise ValueError(f"the box reference writes F = k d - c vn (the linear and "
                             f"no_tension laws), not {rec.name!r}.")
        pulls = rec.pulls
        law = rec.name
        half = np.asarray(half, float)
        self.k, self.c, self.mu, self.s, self.m, self.g = k, c, mu, slip_speed, mass, g
        self.half, self.law, self.T = half, law, T
        hx, hy, hz = half
        inertia = (mass / 3.0 * np.array([hy * hy + hz * hz, hx * hx + hz * hz,
                                          hx * hx + hy * hy]) if inertia is None
                   else np.asarray(inertia, float))
        self.inertia = inertia
        signs = np.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)
                          for sz in (-1.0, 1.0)])
        self.corners = corners = signs * half                     # same order as diffpen
        q0 = np.asarray(q0, float) / np.linalg.norm(q0)
        w_body = quat_matrix(q0).T @ np.asarray(w0, float)
        y0 = np.concatenate([np.asarray(x0, float), np.asarray(v0, float), q0, w_body])

        memo = {}

        def kinematics(y):
            # the event functions ask for the same state one after the other: computed once
            key = y.tobytes()
            if key not in memo:
                rot = quat_matrix(y[6:10])
                r = corners @ rot.T                               # (8, 3) lever arms, world
                w = rot @ y[10:13]
                u = y[3:6] + _cross(w, r)                       # corner velocities
                memo.clear()
                memo[key] = rot, r, u, -(y[2] + r[:, 2])
            return memo[key]

        def normal(d, vn):
            return k * d - c * vn

        def rhs_for(touch, push):
            touch, push = np.array(touch), np.array(push)

            def rhs(_, y):
                q = y[6:10]
                W = y[10:13]
                dq = 0.5 * np.array([-q[1] * W[0] - q[2] * W[1] - q[3] * W[2],
                                     q[0] * W[0] + q[2] * W[2] - q[3] * W[1],
                                     q[0] * W[1] + q[3] * W[0] - q[1] * W[2],
                                     q[0] * W[2] + q[1] * W[1] - q[2] * W[0]])
                acc = np.array([0.0, 0.0, -g])
                dW = -_cross(W, inertia * W) / inertia
                if touch.any():
                    rot, r, u, d = kinematics(y)
                    sel = np.flatnonzero(touch)
                    fn = normal(d[sel], u[sel, 2])
                    on = push[sel]
                    fz = np.where(on, fn, fn if pulls else 0.0)
                    ut = u[sel, :2]
                    sp = np.sqrt(np.sum(ut * ut, axis=1) + slip_speed * slip_speed)
                    ft = -mu * np.where(on, fn, 0.0)[:, None] * ut / sp[:, None]
                    f = np.column_stack([ft, fz])
                    acc = acc + f.sum(axis=0) / mass
                    tau_b = rot.T @ _cross(r[sel], f).sum(axis=0)
                    dW = dW + tau_b / inertia
                return np.concatenate([y[3:6], acc, dq, dW])
            return rhs

        def guarded(fun, direction, until):
            # an event function that just switched is ~0 at the restart, with either sign:
            # for ``guard`` seconds it reports the side it leaves from, so that the root
            # just located is not found again (a corner that truly grazes the plane within
            # that time is recorded ``guard`` late)
            def ev(t, y):
                return -direction if t < until else fun(y)
            ev.terminal, ev.direction = True, direction
            return ev

        def depth(i):
            return lambda y: kinematics(y)[3][i]

        def force(i):
            def fun(y):
                _, _, u, d = kinematics(y)
                return normal(d[i], u[i, 2])
            return fun

        _, _, u, d = kinematics(y0)
        touch = [bool(x > 0.0) for x in d]
        push = [bool(t and normal(di, ui) > 0.0) for t, di, ui in zip(touch, d, u[:, 2])]
        start = [0.0 if t else None for t in touch]
        contacts = [[] for _ in range(8)]
        segs, events = [], []
        t, y = 0.0, y0
        until = {}                                   # (corner, kind) -> end of its guard
        while t < T:
            evs, what = [], []
            for i in range(8):
                evs.append(guarded(depth(i), -1.0 if touch[i] else 1.0,
                                   until.get((i, "d"), -1.0)))
                what.append((i, "d"))
                if touch[i]:
                    evs.append(guarded(force(i), -1.0 if push[i] else 1.0,
                                       until.get((i, "f"), -1.0)))
                    what.append((i, "f"))
            sol = integrate.solve_ivp(rhs_for(touch, push), (t, T), y, method="DOP853",
                                      rtol=rtol, atol=atol, events=evs, dense_output=True)
            if sol.status == -1:
                raise RuntimeError(f"BoxCornerReference: DOP853 failed at t = {t}: "
                                   f"{sol.message}")
            segs.append((t, float(sol.t[-1]), sol.sol))
            if sol.status != 1:
                break
            hits = [(float(te[0]), j) for j, te in enumerate(sol.t_events) if len(te)]
            t, j = min(hits)
            y = np.array(sol.y_events[j][0], float)
            i, kind = what[j]
            until = {(i, kind): t + guard}
            if kind == "d":
                if touch[i]:
                    contacts[i].append((start[i], t))
                    touch[i], push[i] = False, False
                    events.append((t, i, "end"))
                else:
                    touch[i], start[i] = True, t
                    _, _, u, _ = kinematics(y)
                    push[i] = bool(u[i, 2] < 0.0)      # F = -c vn at d = 0
                    if push[i]:
                        until[(i, "f")] = t + guard
                    events.append((t, i, "start"))
            else:
                push[i] = not push[i]
                events.append((t, i, "push" if push[i] else "pull"))
            if len(events) > max_events:
                raise RuntimeError(f"BoxCornerReference: more than {max_events} events "
                                   f"before t = {t} s (chattering contact?).")
        for i in range(8):
            if touch[i]:
                contacts[i].append((start[i], T))
        self._segs = segs
        self.events = events
        self.contacts = contacts

    def _y(self, t: float):
        t = float(t)
        for t0, t1, sol in self._segs:
            if t <= t1:
                return sol(min(max(t, t0), t1))
        t0, t1, sol = self._segs[-1]
        return sol(t1)

    def state(self, t):
        """``(x (3,) m, v (3,) m/s, q (4,) unit quaternion, w (3,) world rad/s)`` at time
        ``t`` (s, 0 <= t <= T)."""
        y = self._y(t)
        q = y[6:10] / np.linalg.norm(y[6:10])
        return y[:3].copy(), y[3:6].copy(), q, quat_matrix(q) @ y[10:13]

    def energy(self, t) -> float:
        """Kinetic + gravitational (from z = 0) + the corners' elastic energy, J."""
        y = self._y(t)
        rot = quat_matrix(y[6:10])
        d = np.maximum(-(y[2] + (self.corners @ rot.T)[:, 2]), 0.0)
        W = y[10:13]
        return float(0.5 * self.m * y[3:6] @ y[3:6] + 0.5 * W @ (self.inertia * W)
                     + self.m * self.g * y[2] + 0.5 * self.k * np.sum(d * d))

    def angular_momentum(self, t):
        """Angular momentum about the centre of mass, world frame (3,) kg m^2/s."""
        y = self._y(t)
        return quat_matrix(y[6:10]) @ (self.inertia * y[10:13])
