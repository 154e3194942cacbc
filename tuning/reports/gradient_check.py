"""The gradient report: the error of jax.grad of the ball's apex height and of its height at a
fixed time w.r.t. k and c, against dt and smoothing width, measured against the derivative of
the continuous hard-contact model (:mod:`tuning.reports.reference`), and the largest
finite-difference step at which central differences of the simulator agree with jax.grad.

Returns plain data (a list of dicts); ``tuning.cli.report`` prints.

Units: SI throughout (m, kg, s, N/m, N s/m).
"""
from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from ..scenes import ball_scene
from .accuracy import BallSpec
from .reference import G, ball_reference

__all__ = ["gradient_report", "GradientCase", "EVENT_CASES", "EVENT_METRICS",
           "event_metrics_fn", "event_reference", "event_gradient_rows", "event_gradient_table",
           "event_phase_errors", "cube_toss_gradients", "two_point_window_law",
           "BoxCornerCase", "BOX_CASES", "BOX_METRICS", "box_corner_scene",
           "box_corner_metrics_fn", "box_corner_reference_metrics", "box_corner_reference",
           "box_corner_rows", "box_corner_table", "box_corner_phase_errors"]


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
        (_, t1), t2 = ref.contacts[0], ref.contacts[1][0]
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



# --------------------------------------------------------------------------- events
class GradientCase(NamedTuple):
    """A ball dropped from rest onto the plane z = 0, for the event-gradient table.

    name: label.  law: contact law name.  exponent: Hunt-Crossley n.  mass: kg.  radius: m.
    drop: initial centre height, m.  k: N/m (N/m^n).  c: N s/m.  T: rollout length, s.
    """
    name: str
    law: str
    mass: float
    k: float
    c: float
    exponent: float = 1.0
    radius: float = 0.1
    drop: float = 1.0
    T: float = 3.0


#: The cases of the gradient table: the quick-start ball (tuning.scenes.ball), a light stiff
#: ball, a heavy no_tension ball and a Hertz (Hunt-Crossley n = 1.5) ball.
EVENT_CASES = (
    GradientCase("quick-start ball", "linear", 1.0, 1e4, 20.0),
    GradientCase("0.3 kg ball", "linear", 0.3, 3e4, 15.0),
    GradientCase("2 kg no_tension", "no_tension", 2.0, 5e4, 60.0),
    GradientCase("Hertz ball", "hunt_crossley", 1.0, 1e6, 3e4, exponent=1.5),
)

#: The metrics compared, in the order of :func:`event_metrics_fn`'s output.
EVENT_METRICS = ("apex1", "apex2", "apex3", "duration1", "duration2", "duration3",
                 "penetration")


def event_metrics_fn(case: GradientCase, dt: float, *, integrator: str = "semi_implicit_euler",
                     smoothing="auto", dtype=None, centred: bool = False):
    """``f(k, c) -> (7,)`` the metrics :data:`EVENT_METRICS` of ``case`` simulated at ``dt``
    (s): apex heights of the lowest point (m), contact durations (s) and the largest
    penetration (m), from :func:`tuning.metrics.ball_metrics`. Jitted; differentiable.
    ``centred``: the law's record with its damping at the step window's centre speed
    (``diffpen.laws``, e.g. ``linear(centred=True)``)."""
    import jax
    import jax.numpy as jnp

    from diffpen import laws

    from ..metrics import ball_metrics
    scene = ball_scene(mass=case.mass, radius=case.radius, height=case.drop)
    law = laws.get(case.law, case.exponent, centred=centred)
    sim = dp.compile(scene, dt, law=law, exponent=case.exponent, smoothing=smoothing,
                     integrator=integrator, dtype=dtype or jnp.float64)
    steps = int(round(case.T / dt))

    def f(k, c):
        p = sim.params(k=k, c=c)
        bm = ball_metrics(sim, sim.rollout(p, steps, check_stability=False), p, n_apex=3)
        return jnp.concatenate([bm.apex_heights, bm.contact_durations,
                                jnp.reshape(bm.max_penetration, (1,))])
    return jax.jit(f), sim


def event_reference(case: GradientCase, rel_step: float = 1e-5) -> dict:
    """The continuous system's metrics and derivatives for ``case``
    (:func:`tuning.reports.reference.ball_reference_derivatives`): ``{"value", "dk", "dc"}`` each a
    (7,) array in :data:`EVENT_METRICS` order."""
    from .reference import ball_reference_derivatives
    ref = ball_reference_derivatives(k=case.k, c=case.c, m=case.mass, r=case.radius,
                                     z0=case.drop, T=case.T, law=case.law,
                                     exponent=case.exponent, rel_step=rel_step)

    def flat(d):
        return np.concatenate([d["apex"], d["duration"], d["penetration"][:1]])
    return {key: flat(ref[key]) for key in ("value", "dk", "dc")}


def event_gradient_rows(cases=EVENT_CASES, dts=(1e-3,), *, integrators=("semi_implicit_euler",),
                        smoothing="auto", fd_steps=(), progress: Callable | None = None
                        ) -> list[dict]:
    """jax derivatives of the event metrics w.r.t. k and c against the continuous system's.

    One row per (case, integrator, dt, metric, parameter): ``grad`` (jax.jacfwd of the
    simulated metric), ``reference`` (central differences of the DOP853 event-located
    reference), ``rel_error`` = |grad - reference| / |reference|, ``value`` and
    ``value_reference`` (the metric itself), and, for each relative step in ``fd_steps``, the
    library's own central difference (``fd``) and its relative gap to ``grad``
    (``fd_gap``; item 4 of the gradient issue: the landscape has no jumps).
    """
    import jax
    say = progress or (lambda *_: None)
    rows = []
    for case in cases:
        ref = event_reference(case)
        for integ in integrators:
            for dt in dts:
                f, _ = event_metrics_fn(case, dt, integrator=integ, smoothing=smoothing)
                val = np.asarray(f(case.k, case.c))
                jk, jc = (np.asarray(a) for a in jax.jit(jax.jacfwd(f, (0, 1)))(case.k, case.c))
                fds = {}
                for s in fd_steps:
                    hk, hc = s * case.k, s * case.c
                    fds[s] = ((np.asarray(f(case.k + hk, case.c))
                               - np.asarray(f(case.k - hk, case.c))) / (2 * hk),
                              (np.asarray(f(case.k, case.c + hc))
                               - np.asarray(f(case.k, case.c - hc))) / (2 * hc))
                for i, metric in enumerate(EVENT_METRICS):
                    for p, (g, r) in enumerate((("k", (jk[i], ref["dk"][i])),
                                                ("c", (jc[i], ref["dc"][i])))[j][1]
                                               for j in range(2)):
                        pname = "kc"[p]
                        row = {"case": case.name, "law": case.law, "integrator": integ,
                               "dt": dt, "metric": metric, "param": pname,
                               "grad": float(g), "reference": float(r),
                               "rel_error": abs(float(g) - float(r)) / abs(float(r)),
                               "value": float(val[i]),
                               "value_reference": float(ref["value"][i])}
                        if fd_steps:
                            row["fd"] = [float(fds[s][p][i]) for s in fd_steps]
                            row["fd_gap"] = [abs(float(fds[s][p][i]) - float(g)) / abs(float(g))
                                             for s in fd_steps]
                            row["fd_steps"] = list(fd_steps)
                        rows.append(row)
                        say(row)
    return rows


def event_phase_errors(case: GradientCase, dt: float = 1e-3, phases: int = 6, *,
                       centred: bool = False) -> dict:
    """Errors of the event metrics against the continuous system over where the impacts fall
    in the step: ``case`` dropped from ``drop + j v dt / phases`` (j = 0 .. phases - 1; v the
    first impact speed, so the impacts move through one step), the reference recomputed for
    each drop. Returns ``{"value", "dk", "dc"}``, each a (phases, 7) array in
    :data:`EVENT_METRICS` order: signed ``value / reference - 1`` and
    ``|jax / continuous - 1|`` of the derivatives. (The gradient table evaluates one phase;
    at dt 1e-3 the apex 2-3 derivatives ripple with it.)"""
    import jax
    v = np.sqrt(2.0 * G * (case.drop - case.radius))
    out = {"value": [], "dk": [], "dc": []}
    for j in range(phases):
        cj = case._replace(drop=case.drop + j * v * dt / phases)
        ref = event_reference(cj)
        f, _ = event_metrics_fn(cj, dt, centred=centred)
        val = np.asarray(f(cj.k, cj.c))
        jk, jc = (np.asarray(a) for a in jax.jit(jax.jacfwd(f, (0, 1)))(cj.k, cj.c))
        out["value"].append(val / ref["value"] - 1.0)
        out["dk"].append(np.abs(jk / ref["dk"] - 1.0))
        out["dc"].append(np.abs(jc / ref["dc"] - 1.0))
    return {key: np.array(a) for key, a in out.items()}


def cube_toss_gradients(path, *, frames: int | None = None, k: float = 2e4, c: float = 20.0,
                        mu: float = 0.18, dt: float = 1e-3, dtype=None,
                        rel_steps=(1e-6, 1e-4, 0.03, 0.1)) -> dict:
    """Pose-loss gradient of a recorded cube toss (``/work/shared/data/cube-toss`` format:
    columns t, x, y, z, qw..qz, vx..vz, wx..wz with the angular velocity in the body frame):
    a 0.37 kg cube of half-width 0.0524 m (inertia 8.1e-4 kg m^2) started from row 0 on a
    rough plane (material ``board``: ``k`` N/m, ``c`` N s/m, friction ``mu``), loss = mean
    over the first ``frames`` frames of |p_sim - p_data| / 0.1048 (edge lengths).

    Returns ``{"loss", "ad": (3,), "fd": {step: (3,)}}``: jax.grad w.r.t. (log k, log c,
    log mu) and central differences of the same loss at each relative step of ``rel_steps``
    (in log space, so absolute steps of the log)."""
    import jax
    import jax.numpy as jnp
    data = np.genfromtxt(path, delimiter=",", names=True)
    n = len(data["t"]) if frames is None else int(frames)
    t = data["t"][:n]
    pos = np.stack([data["x"], data["y"], data["z"]], 1)[:n]
    q0 = [float(data[a][0]) for a in ("qw", "qx", "qy", "qz")]
    w, x, y, z = q0
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    w_world = rot @ np.array([data[a][0] for a in ("wx", "wy", "wz")])
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_material("board", k=k, c=c, friction=mu, slip_speed=0.01)
    scene.add_plane(material="board")
    scene.add_box((0.0524,) * 3, 0.37, tuple(pos[0]),
                  tuple(float(data[a][0]) for a in ("vx", "vy", "vz")), orientation=tuple(q0),
                  angular_velocity=tuple(w_world), inertia=(8.1e-4,) * 3)
    dtype = dtype or jnp.float64
    sim = dp.compile(scene, dt, dtype=dtype)
    steps = int(round(t[-1] / dt))
    idx = np.clip(np.round(t / dt).astype(int) - 1, 0, steps - 1)
    target = jnp.asarray(pos, dtype)

    def loss(lk, lc, lmu):
        base = sim.params()
        con = dict(base.contact)
        con["board"] = con["board"]._replace(k=jnp.exp(lk), c=jnp.exp(lc))
        extra = dict(base.extra)
        extra["friction"] = {"board": jnp.exp(lmu)}
        traj = sim.rollout(base._replace(contact=con, extra=extra), steps,
                           check_stability=False)
        return jnp.mean(jnp.linalg.norm(traj.position[idx, 0] - target, axis=-1)) / 0.1048
    x0 = [jnp.asarray(np.log(v), dtype) for v in (k, c, mu)]
    f = jax.jit(loss)
    ad = np.array([float(a) for a in jax.jit(jax.grad(loss, (0, 1, 2)))(*x0)])
    fd = {}
    for s in rel_steps:
        row = []
        for i in range(3):
            up, dn = list(x0), list(x0)
            up[i], dn[i] = up[i] + s, dn[i] - s
            row.append((float(f(*up)) - float(f(*dn))) / (2 * s))
        fd[s] = np.array(row)
    return {"loss": float(f(*x0)), "ad": ad, "fd": fd}


def two_point_window_law(mass: float, gravity: float = G):
    """PROTOTYPE (measurement only; not used by any simulator unless passed as ``law=``): the
    linear law whose step window follows the continuous path instead of a straight line.

    The window's past half is the true motion through ``d_{n-1} = d_n + h vn`` and ``d_n``
    (semi-implicit Euler's last two positions): damped harmonic about ``m g / k`` when both
    are in contact, a gravity parabola when both are apart, parabola then contact (or contact
    then parabola) when the last step crossed, the crossing speed found by Newton's method;
    its future half continues from ``d_n`` with that path's slope. The force ``k d + c d'``
    along the path is integrated with the hat weight by 16-point Gauss-Legendre on the pieces
    between crossings. With it the positions are exact samples of the continuous motion, so
    contact events carry their exact derivative terms (docs/gradients.txt).

    Only for ONE free body of ``mass`` kg on a horizontal plane with gravity ``gravity``
    m/s^2 along -normal (the ball cases). Costs ~100 force evaluations and 20 Newton steps per
    contact and step. Returns a ``diffpen.laws.ContactLaw``."""
    from diffpen import laws
    m = float(mass)
    G0 = float(gravity)
    GX, GW = (jnp.asarray(a) for a in np.polynomial.legendre.leggauss(16))

    def avg(dn, vn, k, c, h):
        w0sq = k / m; sg = c / (2 * m); w = jnp.sqrt(w0sq - sg * sg); de = m * G0 / k
        def contact(t, d0, D0):
            x0 = d0 - de
            return de + jnp.exp(-sg * t) * (x0 * jnp.cos(w * t)
                                            + ((D0 + sg * x0) / w) * jnp.sin(w * t))
        def free(t, d0, D0):
            return d0 + D0 * t + 0.5 * G0 * t * t
        dp_ = dn + h * vn
        # 0: both in contact, 1: both apart, 2: entered during the last step, 3: left it
        case = jnp.where((dp_ > 0) & (dn > 0), 0,
                         jnp.where((dp_ <= 0) & (dn <= 0), 1, jnp.where(dn > 0, 2, 3)))
        # case 2: entering
        dn2, dp2 = jnp.where(case == 2, dn, 1e-4), jnp.where(case == 2, dp_, -1e-4)
        def tau0_of(U):
            return -2 * dp2 / (U + jnp.sqrt(U * U - 2 * G0 * dp2))
        def r2(U):
            t0 = tau0_of(U)
            return contact(h - t0, 0.0, U + G0 * t0) - dn2
        U = (dn2 - dp2) / h
        for _ in range(8):
            U = U - r2(U) / jax.grad(r2)(U)
        tau0 = tau0_of(U); Uc = U + G0 * tau0
        # case 3: exiting
        dn3, dp3 = jnp.where(case == 3, dn, -1e-4), jnp.where(case == 3, dp_, 1e-4)
        def rfree(Ue):
            return -2 * dn3 / (-Ue + jnp.sqrt(jnp.maximum(Ue * Ue + 2 * G0 * dn3, 1e-30)))
        def r3(Ue):
            return contact(-(h - rfree(Ue)), 0.0, Ue) - dp3
        Ue = (dn3 - dp3) / h
        for _ in range(8):
            Ue = Ue - r3(Ue) / jax.grad(r3)(Ue)
        tau1 = h - rfree(Ue)
        # case 0
        A = dn - de
        B = (A * jnp.cos(w * h) - (dp_ - de) * jnp.exp(-sg * h)) / jnp.sin(w * h)
        D_free = (dn - dp_) / h + 0.5 * G0 * h
        tc0 = h - tau0
        D_in = jax.grad(lambda t: contact(t, 0.0, Uc))(tc0)
        D0 = jnp.select([case == 0, case == 1, case == 2], [-sg * A + w * B, D_free, D_in],
                        Ue + G0 * rfree(Ue))
        def back(s):
            t = s + h
            p0 = de + jnp.exp(-sg * s) * (A * jnp.cos(w * s) + B * jnp.sin(w * s))
            p1 = free(s, dn, D_free)
            p2 = jnp.where(t < tau0, free(t, dp_, U), contact(t - tau0, 0.0, Uc))
            p3 = jnp.where(t < tau1, contact(t - tau1, 0.0, Ue), free(t - tau1, 0.0, Ue))
            return jnp.select([case == 0, case == 1, case == 2], [p0, p1, p2], p3)
        # forward crossings
        S = jnp.sqrt(jnp.maximum(D0 * D0 - 2 * G0 * jnp.minimum(dn, 0.0), 0.0))
        s0 = jnp.where(D0 > 0, -2 * jnp.minimum(dn, 0.0) / jnp.where(D0 + S > 0, D0 + S, 1.0),
                       (-D0 + S) / G0)
        s0 = jnp.where(dn > 0, h, s0)
        Dc = D0 + G0 * s0
        inside = dn > 0
        exits = inside & (contact(h, jnp.where(inside, dn, 1e-4), D0) < 0)
        s1 = jnp.clip(jnp.where(exits, dn / jnp.maximum(-D0, 1e-9), 0.5 * h), 0.0, h)
        dni = jnp.where(exits, dn, 1e-4); D0i = jnp.where(exits, D0, -1.0)
        for _ in range(6):
            f_ = contact(s1, dni, D0i); fp = jax.grad(lambda q: contact(q, dni, D0i))(s1)
            s1 = jnp.clip(s1 - f_ / fp, 0.0, h)
        def fwd(s):
            pin = contact(s, dn, D0)
            pout = jnp.where(s < s0, free(s, dn, D0), contact(s - s0, 0.0, Dc))
            return jnp.where(inside, pin, pout)
        sb = jnp.where(case == 2, tau0 - h, jnp.where(case == 3, tau1 - h, -0.5 * h))
        sb = jnp.clip(sb, -h, 0.0)
        sf = jnp.where(inside, jnp.where(exits, s1, 0.5 * h), jnp.clip(s0, 0.0, h))
        tot = 0.0
        for a, b, fn in ((-h, sb, back), (sb, 0.0, back), (0.0, sf, fwd), (sf, h, fwd)):
            s = 0.5 * (a + b) + 0.5 * (b - a) * GX
            dd = jax.vmap(fn)(s); dv = jax.vmap(jax.grad(fn))(s)
            fs = jnp.where(dd > 0, k * dd + c * dv, 0.0) * (1 - jnp.abs(s) / h)
            tot = tot + 0.5 * (b - a) * jnp.sum(GW * fs)
        return tot / h
    def vec(d, vn, k, c, h):
        return jax.vmap(lambda a, b: avg(a, b, k, c, h))(
            jnp.atleast_1d(d), jnp.atleast_1d(vn)).reshape(jnp.shape(d))
    return dataclasses.replace(laws.linear(), averaged=vec)


def event_gradient_table(rows: list[dict], before: list[dict] | None = None) -> str:
    """Plain-text table of :func:`event_gradient_rows` (one line per case, integrator, dt and
    metric: value error, d/dk and d/dc against the continuous derivatives, relative errors),
    with the same rows of an earlier run (``before``) side by side when given."""
    old = {(r["case"], r["integrator"], r["dt"], r["metric"], r["param"]): r
           for r in (before or [])}
    head = (f"{'case':18} {'dt (s)':>7} {'metric':12} {'value err':>9} "
            f"{'d/dk':>11} {'continuous':>11} {'err':>7} "
            f"{'d/dc':>11} {'continuous':>11} {'err':>7}")
    if before is not None:
        head += f" | {'before: d/dk':>12} {'err':>7} {'d/dc':>11} {'err':>7} {'value err':>9}"
    lines = [head]
    by = {}
    for r in rows:
        by.setdefault((r["case"], r["integrator"], r["dt"], r["metric"]), {})[r["param"]] = r
    for (case, integ, dt, metric), pr in by.items():
        k, c = pr["k"], pr["c"]
        verr = (k["value"] - k["value_reference"]) / k["value_reference"]
        line = (f"{case:18} {dt:7.1e} {metric:12} {verr:+9.2%} "
                f"{k['grad']:+11.4e} {k['reference']:+11.4e} {k['rel_error']:7.2%} "
                f"{c['grad']:+11.4e} {c['reference']:+11.4e} {c['rel_error']:7.2%}")
        if before is not None:
            ok, oc = (old.get((case, integ, dt, metric, p)) for p in "kc")
            if ok is not None and oc is not None:
                overr = (ok["value"] - ok["value_reference"]) / ok["value_reference"]
                line += (f" | {ok['grad']:+12.4e} {ok['rel_error']:7.2%} "
                         f"{oc['grad']:+11.4e} {oc['rel_error']:7.2%} {overr:+9.2%}")
        lines.append(line)
    return "\n".join(lines)


# --------------------------------------------------------------------------- box on a corner
class BoxCornerCase(NamedTuple):
    """A cube dropped tilted onto a rough plane (z = 0) so that one corner lands first, with
    a horizontal and an angular velocity; it bounces on that corner and another, then lands
    on an edge and a face and settles.

    name: label.  k: N/m, c: N s/m, mu: friction coefficient, slip_speed: m/s (the plane's
    material ``rough``, linear law).  mass: kg.  half: half edge, m.  axis, angle: the
    initial orientation (rotation of ``angle`` rad about ``axis``).  gap: height of the
    lowest corner above the plane at t = 0, m.  v0: (3,) m/s.  w0: (3,) world rad/s.
    times: (2,) s, when the pose is measured (the second is the rollout's end)."""
    name: str
    k: float = 2e4
    c: float = 20.0
    mu: float = 0.18
    slip_speed: float = 0.01
    mass: float = 0.37
    half: float = 0.025
    axis: tuple = (1.0, 0.6, 0.2)
    angle: float = 0.7
    gap: float = 0.02
    v0: tuple = (0.3, 0.1, 0.0)
    w0: tuple = (1.0, -2.0, 3.0)
    times: tuple = (0.15, 0.3)

    def orientation(self) -> np.ndarray:
        """The initial unit quaternion (4,) (w, x, y, z)."""
        a = np.asarray(self.axis, float)
        a = a / np.linalg.norm(a)
        return np.r_[np.cos(0.5 * self.angle), np.sin(0.5 * self.angle) * a]

    def corner_heights(self) -> np.ndarray:
        """Heights (8,) m of the corners above the centre at t = 0 (diffpen's order)."""
        from .reference import _quat_matrix
        return (dp.geometry.box_corners((self.half,) * 3) @ _quat_matrix(
            self.orientation()).T)[:, 2]

    def first_corner(self) -> int:
        """Index of the corner that lands first (the lowest at t = 0)."""
        return int(np.argmin(self.corner_heights()))

    def x0(self) -> tuple:
        """The initial centre (3,) m."""
        return (0.0, 0.0, self.gap - float(self.corner_heights().min()))


#: The box cases: a 5 cm, 0.37 kg cube with the cube toss's friction (mu 0.18, slip speed
#: 1 cm/s) at the cube toss's contact (k 2e4 N/m, c 20 N s/m; one corner: effective mass
#: m / 4, w h = 0.47 at dt 1e-3), a medium (k 5e3, c 10; w h = 0.23) and a soft one
#: (k 2e3, c 6; w h = 0.15). All three pass diffpen's stability check at dt 1e-3 (mu 0.4 at
#: slip speed 1 cm/s does not: the friction's viscous regime needs 2 substeps).
BOX_CASES = (
    BoxCornerCase("k 2e4"),
    BoxCornerCase("k 5e3", k=5e3, c=10.0),
    BoxCornerCase("k 2e3", k=2e3, c=6.0),
)

#: The box metrics, in the order of :func:`box_corner_metrics_fn`'s output: the centre's
#: x, y, z (m) and the rotation angle from the start (rad) at ``times[0]`` (during the
#: bounces) and ``times[1]`` (settled), the horizontal distance travelled by ``times[1]`` (m)
#: and the end of the first corner's first contact (s).
BOX_METRICS = ("x@T1", "y@T1", "z@T1", "angle@T1", "x@T2", "y@T2", "z@T2", "angle@T2",
               "distance@T2", "t_end1")


def box_corner_scene(case: BoxCornerCase):
    """The :class:`diffpen.Scene` of ``case`` (material ``rough`` on the plane)."""
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_material("rough", k=case.k, c=case.c, friction=case.mu,
                       slip_speed=case.slip_speed)
    scene.add_plane(material="rough")
    scene.add_box((case.half,) * 3, case.mass, case.x0(), case.v0,
                  orientation=tuple(case.orientation()), angular_velocity=case.w0)
    return scene


def box_corner_metrics_fn(case: BoxCornerCase, dt: float, *, dtype=None,
                          integrator: str = "semi_implicit_euler", law="linear"):
    """``f(k, c, mu) -> (10,)`` the metrics :data:`BOX_METRICS` of ``case`` simulated at
    ``dt`` (s) with the default contact settings (linear law, step-averaged contact; ``law``
    a name or a :class:`diffpen.laws.ContactLaw` record) and ``integrator`` (default: the
    default one). The end of the first corner's contact is its height's first upward crossing of
    0 on the parabola through the three samples after it (:func:`tuning.metrics.crossings`
    with ``flight=True``; the cube is not in free flight then, a second corner is down or
    about to land, so this is a local extrapolation, exact as dt -> 0). Jitted;
    differentiable (``jax.jacfwd(f, (0, 1, 2))``)."""
    from diffpen.rigid import quat_to_matrix

    from ..metrics import crossings
    dtype = dtype or jnp.float64
    sim = dp.compile(box_corner_scene(case), dt, dtype=dtype, integrator=integrator, law=law)
    steps = int(round(case.times[1] / dt))
    idx = [int(round(T / dt)) - 1 for T in case.times]
    corner = jnp.asarray(dp.geometry.box_corners((case.half,) * 3)[case.first_corner()],
                         dtype)
    q0 = jnp.asarray(case.orientation(), dtype)
    x0 = jnp.asarray(case.x0(), dtype)
    t = jnp.arange(1, steps + 1, dtype=dtype) * dt

    def angle(q):
        # rotation angle of q conj(q0): 2 atan2(|vec|, |w|)
        w0, v0 = q0[0], -q0[1:]
        pw = q[0] * w0 - jnp.dot(q[1:], v0)
        pv = q[0] * v0 + w0 * q[1:] + jnp.cross(q[1:], v0)
        return 2.0 * jnp.arctan2(jnp.linalg.norm(pv), jnp.abs(pw))

    def f(k, c, mu):
        p = sim.params(k=k, c=c, extra={"friction": {"rough": mu}})
        traj = sim.rollout(p, steps, check_stability=False)
        x, q = traj.position[:, 0], traj.orientation[:, 0]
        height = x[:, 2] + (quat_to_matrix(q) @ corner)[:, 2]
        t_end = crossings(t, height, 0.0, 1, +1, flight=True)[0][0]
        out = []
        for i in idx:
            out += [x[i, 0], x[i, 1], x[i, 2], angle(q[i])]
        out += [jnp.linalg.norm(x[idx[1], :2] - x0[:2]), t_end]
        return jnp.stack(out)
    return jax.jit(f), sim


def box_corner_reference_metrics(case: BoxCornerCase, k=None, c=None, mu=None, *,
                                 rtol: float = 1e-12):
    """The metrics :data:`BOX_METRICS` (10,) of the continuous system
    (:class:`tuning.reports.reference.BoxCornerReference`) at ``k``, ``c``, ``mu`` (default the
    case's)."""
    from .reference import BoxCornerReference, rotation_angle
    k, c, mu = (case.k if k is None else k, case.c if c is None else c,
                case.mu if mu is None else mu)
    q0 = case.orientation()
    x0 = np.asarray(case.x0())
    ref = BoxCornerReference(k=k, c=c, mu=mu, slip_speed=case.slip_speed, mass=case.mass,
                             half=(case.half,) * 3, x0=x0, v0=case.v0, q0=q0, w0=case.w0,
                             T=case.times[1], rtol=rtol)
    out = []
    for T in case.times:
        x, _, q, _ = ref.state(T)
        out += [x[0], x[1], x[2], rotation_angle(q, q0)]
    x, _, _, _ = ref.state(case.times[1])
    out += [float(np.linalg.norm(x[:2] - x0[:2])), ref.contacts[case.first_corner()][0][1]]
    return np.array(out, float), ref


def box_corner_reference(case: BoxCornerCase, rel_step: float = 1e-4, *,
                         rtol: float = 1e-12, params=("k", "c", "mu")) -> dict:
    """Values and derivatives of the continuous system's metrics: ``{"value": (10,),
    "dk", "dc", "dmu": (10,)}`` by central differences at relative step ``rel_step`` of
    :func:`box_corner_reference_metrics` (only w.r.t. the names in ``params``).

    At rtol 1e-12 these derivatives agree with rtol 1e-13 to ~1e-10 relative, with rtol
    1e-10 to ~1e-7. For :data:`BOX_CASES` steps 1e-4 and 3e-4 agree within 0.02% (the
    ``spread`` of :func:`box_corner_rows`). With mu 0.4 (which diffpen's stability check
    refuses at dt 1e-3) the pose after the settling is curved at the scale of 1e-3 relative:
    steps 1e-3 and 1e-4 differ by up to 6% there, 3e-4 and 1e-4 by up to 0.5%."""
    base = {"k": case.k, "c": case.c, "mu": case.mu}
    out = {"value": box_corner_reference_metrics(case, rtol=rtol)[0]}
    for name in params:
        val = base[name]
        step = rel_step * val
        up = box_corner_reference_metrics(case, **{**base, name: val + step}, rtol=rtol)[0]
        dn = box_corner_reference_metrics(case, **{**base, name: val - step}, rtol=rtol)[0]
        out["d" + name] = (up - dn) / (2.0 * step)
    return out


def box_corner_rows(cases=BOX_CASES, dts=(1e-3, 1e-4), dtypes=("float64", "float32"), *,
                    rel_step: float = 1e-4, progress: Callable | None = None) -> list[dict]:
    """One row per (case, dt, dtype, metric): the simulated value and ``jax.jacfwd``
    derivatives w.r.t. k, c, mu against the continuous system's (:func:`box_corner_reference`
    at ``rel_step``), with the reference's own spread (``d*_spread``: relative change of its
    derivative when the step is 3x larger)."""
    rows = []
    for case in cases:
        ref = box_corner_reference(case, rel_step)
        wide = box_corner_reference(case, 3.0 * rel_step)
        for dt in dts:
            for dtype in dtypes:
                f, _ = box_corner_metrics_fn(case, dt, dtype=getattr(jnp, dtype))
                args = [getattr(jnp, dtype)(v) for v in (case.k, case.c, case.mu)]
                value = np.asarray(f(*args), float)
                jac = [np.asarray(j, float) for j in jax.jit(jax.jacfwd(f, (0, 1, 2)))(*args)]
                for m, name in enumerate(BOX_METRICS):
                    row = {"case": case.name, "dt": dt, "dtype": dtype, "metric": name,
                           "value": value[m], "ref": ref["value"][m]}
                    for p, key in enumerate(("dk", "dc", "dmu")):
                        row[key], row[key + "_ref"] = jac[p][m], ref[key][m]
                        row[key + "_spread"] = (abs(wide[key][m] - ref[key][m])
                                                / abs(ref[key][m]))
                    rows.append(row)
                if progress is not None:
                    progress(f"{case.name} dt {dt:g} {dtype}")
    return rows


def box_corner_table(rows: list[dict]) -> str:
    """The rows of :func:`box_corner_rows` as a text table, one line per (case, dt, metric)
    from the float64 rows: the value's error (simulated minus continuous, in the metric's
    unit) and per parameter the jax derivative, the continuous one, the relative error
    ``|jax / continuous - 1|`` and, where float32 rows exist, float32's relative gap to
    float64 (``!`` when the signs differ)."""
    f32 = {(r["case"], r["dt"], r["metric"]): r for r in rows if r["dtype"] == "float32"}
    head = (f"{'case':6s} {'dt':>5s} {'metric':11s} {'value':>10s} {'err':>8s} |"
            + " |".join(f" {'d/d' + p:>10s} {'continuous':>10s} {'err':>7s} {'f32':>6s}"
                        for p in ("k", "c", "mu")))
    lines = [head]
    for r in rows:
        if r["dtype"] != "float64":
            continue
        other = f32.get((r["case"], r["dt"], r["metric"]))
        cells = []
        for p in ("dk", "dc", "dmu"):
            ref = r[p + "_ref"]
            err = abs(r[p] - ref) / abs(ref) if ref != 0.0 else float("nan")
            gap = "      "
            if other is not None:
                flip = "!" if np.sign(other[p]) != np.sign(r[p]) else " "
                gap = f"{100 * abs(other[p] / r[p] - 1.0):4.1f}%{flip}"
            cells.append(f" {r[p]:+10.3e} {ref:+10.3e} {100 * err:6.1f}% {gap}")
        lines.append(f"{r['case']:6s} {r['dt']:5.0e} {r['metric']:11s} {r['value']:+10.3e} "
                     f"{r['value'] - r['ref']:+8.1e} |" + " |".join(cells))
    return "\n".join(lines)


def box_corner_phase_errors(case: BoxCornerCase, dt: float = 1e-3, phases: int = 6, *,
                            rel_step: float = 1e-4) -> np.ndarray:
    """Relative errors ``|jax / continuous - 1|`` (phases, 3, 10) of d/dk, d/dc, d/dmu of
    :data:`BOX_METRICS` (float64, ``dt`` s) with the drop moved through one step: the gap
    of the first corner raised by ``j / phases`` of the distance it falls in one step at
    impact (``j = 0 .. phases - 1``; the continuous system recomputed for each)."""
    fall = np.sqrt(2.0 * G * case.gap) * dt
    out = []
    for j in range(phases):
        shifted = case._replace(gap=case.gap + j * fall / phases)
        ref = box_corner_reference(shifted, rel_step)
        f, _ = box_corner_metrics_fn(shifted, dt)
        args = [jnp.float64(v) for v in (case.k, case.c, case.mu)]
        jac = jax.jit(jax.jacfwd(f, (0, 1, 2)))(*args)
        out.append([np.abs(np.asarray(jac[p]) / ref[key] - 1.0)
                    for p, key in enumerate(("dk", "dc", "dmu"))])
    return np.array(out)
