"""The gradient report: the error of jax.grad of the ball's apex height and of its height at a
fixed time w.r.t. k and c, against dt and smoothing width, measured against the derivative of
the continuous hard-contact model (:mod:`tuning.reports.reference`), and the largest
finite-difference step at which central differences of the simulator agree with jax.grad.

Returns plain data (a list of dicts); ``tuning.cli.report`` prints.

Units: SI throughout (m, kg, s, N/m, N s/m).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from ..scenes import ball_scene
from .accuracy import BallSpec
from .reference import G, ball_reference

__all__ = ["gradient_report", "largest_agreeing_step", "SMALLEST_CHECKED_STEP", "GradientCase", "EVENT_CASES", "EVENT_METRICS",
           "event_metrics_fn", "event_reference", "event_gradient_rows", "event_gradient_table",
           "event_phase_errors", "cube_toss_gradients"]


#: the smallest relative step :func:`largest_agreeing_step` requires to agree (below it,
#: central differences of a float64 rollout are rounding noise)
SMALLEST_CHECKED_STEP = 1e-5


def largest_agreeing_step(rel_steps, fds, g, agree: float = 0.01) -> float | None:
    """The largest relative step ``s`` of ``rel_steps`` (descending) whose central difference
    ``fds`` agrees with the derivative ``g`` within ``agree`` (relative), with every smaller
    step down to :data:`SMALLEST_CHECKED_STEP` agreeing too; None if there is none. Steps
    below that floor are never returned (nothing is checked there), and the floor is
    compared with a relative tolerance: ``10.0 ** -5`` computed as ``9.999999999999999e-06``
    is the floor."""
    steps = np.asarray(rel_steps, float)
    ok = np.abs(np.asarray(fds, float) - g) <= agree * abs(g)
    checked = steps >= SMALLEST_CHECKED_STEP * (1 - 1e-9)
    for j in np.flatnonzero(checked):
        if ok[j:][checked[j:]].all():
            return float(steps[j])
    return None


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
    Returns one dict per (dt, width, quantity, parameter). Raises ValueError when a (dt,
    width) is past the simulator's safe step at ``spec``'s k and c.
    """
    spec = spec or BallSpec(T=t_height)
    if not (spec.k > 0 and spec.c > 0):
        raise ValueError(f"the gradient report steps k and c both ways (central differences "
                         f"of relative size down to 1e-8): give k > 0 and c > 0, got "
                         f"k = {spec.k:g}, c = {spec.c:g}")
    say = progress or (lambda *_: None)
    T = t_height
    scene = ball_scene(mass=spec.mass, radius=spec.radius, height=spec.height)
    for dt in dts:          # the rollouts below run jitted, with no concrete stability check
        for w in widths:
            sim = dp.compile(scene, dt, smoothing=w, dtype=jnp.float64)
            rep = sim.stability(sim.params(k=spec.k, c=spec.c))
            if not rep.safe:
                raise ValueError(
                    f"the ball (k {spec.k:g} N/m, c {spec.c:g} N s/m, {spec.mass:g} kg) is "
                    f"past the safe step of {rep.integrator} at the report's dt = {dt:g} s "
                    f"(safe step {rep.safe_dt:.3g} s, set by {rep.limiting or 'the contact'}): "
                    "its gradients would be those of an unstable rollout; lower --k or --c, "
                    "or raise --mass")

    def ref_quantities(k, c):
        ref = ball_reference(k=k, c=c, m=spec.mass, r=spec.radius, z0=spec.height, T=T)
        if len(ref.contacts) < 2:
            raise ValueError(f"the ball (k {k:g} N/m, c {c:g} N s/m, {spec.mass:g} kg, "
                             f"dropped from {spec.height:g} m) does not land twice within "
                             f"{T:g} s, which the report's first-apex and z_T quantities "
                             "need: lower the drop height or the damping c")
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
                    largest = largest_agreeing_step(rel_steps, fds, g, agree)
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
                     smoothing="auto", dtype=None, centred: bool | None = None, record=None):
    """``f(k, c) -> (7,)`` the metrics :data:`EVENT_METRICS` of ``case`` simulated at ``dt``
    (s): apex heights of the lowest point (m), contact durations (s) and the largest
    penetration (m), from :func:`tuning.metrics.ball_metrics`. Jitted; differentiable.
    ``centred``: True / False the law's record with / without its damping at the step
    window's centre speed (``diffpen.laws``, e.g. ``linear(centred=True)``); None (default)
    the law's name, as ``diffpen.compile`` resolves it for this one-contact ball (centred).
    ``record``: a ``diffpen.laws.ContactLaw`` to use instead (e.g. ``linear(events=True)``)."""
    import jax
    import jax.numpy as jnp

    from diffpen import laws

    from ..metrics import ball_metrics
    scene = ball_scene(mass=case.mass, radius=case.radius, height=case.drop)
    law = (record if record is not None else case.law if centred is None
           else laws.get(case.law, case.exponent, centred=centred))
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
                        smoothing="auto", fd_steps=(), progress: Callable | None = None,
                        centred: bool | None = None, events: bool = False) -> list[dict]:
    """jax derivatives of the event metrics w.r.t. k and c against the continuous system's.

    One row per (case, integrator, dt, metric, parameter): ``grad`` (jax.jacfwd of the
    simulated metric), ``reference`` (central differences of the DOP853 event-located
    reference), ``rel_error`` = |grad - reference| / |reference|, ``value`` and
    ``value_reference`` (the metric itself), and, for each relative step in ``fd_steps``, the
    library's own central difference (``fd``) and its relative gap to ``grad``
    (``fd_gap``; item 4 of the gradient issue: the landscape has no jumps). ``centred``:
    the law's record as :func:`event_metrics_fn` takes it (None: the name, as compiled);
    ``events``: each case's law's event-exact record instead (``diffpen.laws.get(law,
    exponent, events=True)``; semi-implicit Euler only).
    """
    from diffpen import laws
    import jax
    say = progress or (lambda *_: None)
    rows = []
    for case in cases:
        ref = event_reference(case)
        for integ in integrators:
            for dt in dts:
                record = laws.get(case.law, case.exponent, events=True) if events else None
                f, _ = event_metrics_fn(case, dt, integrator=integ, smoothing=smoothing,
                                        centred=centred, record=record)
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
                       centred: bool | None = None, record=None) -> dict:
    """Errors of the event metrics against the continuous system over where the impacts fall
    in the step: ``case`` dropped from ``drop + j v dt / phases`` (j = 0 .. phases - 1; v the
    first impact speed, so the impacts move through one step), the reference recomputed for
    each drop. Returns ``{"value", "dk", "dc"}``, each a (phases, 7) array in
    :data:`EVENT_METRICS` order: signed ``value / reference - 1`` and
    ``|jax / continuous - 1|`` of the derivatives. (The gradient table evaluates one phase;
    at dt 1e-3 the apex 2-3 derivatives ripple with it.) ``centred``, ``record``: as
    :func:`event_metrics_fn` takes them."""
    import jax
    v = np.sqrt(2.0 * G * (case.drop - case.radius))
    out = {"value": [], "dk": [], "dc": []}
    for j in range(phases):
        cj = case._replace(drop=case.drop + j * v * dt / phases)
        ref = event_reference(cj)
        f, _ = event_metrics_fn(cj, dt, centred=centred, record=record)
        val = np.asarray(f(cj.k, cj.c))
        jk, jc = (np.asarray(a) for a in jax.jit(jax.jacfwd(f, (0, 1)))(cj.k, cj.c))
        out["value"].append(val / ref["value"] - 1.0)
        out["dk"].append(np.abs(jk / ref["dk"] - 1.0))
        out["dc"].append(np.abs(jc / ref["dc"] - 1.0))
    return {key: np.array(a) for key, a in out.items()}


def cube_toss_gradients(path, *, frames: int | None = None, k: float = 2e4, c: float = 20.0,
                        mu: float = 0.18, dt: float = 1e-3, dtype=None,
                        rel_steps=(1e-6, 1e-4, 0.03, 0.1)) -> dict:
    """Pose-loss gradient of a recorded cube toss (``examples/data/cube-toss`` format:
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
