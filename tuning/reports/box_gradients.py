"""Gradients of a box landing on a corner against the continuous system (issue item: friction
and corner contact): a cube dropped tilted so one corner lands first, metrics a fit would use
(pose at two times, distance travelled, the first contact's end), diffpen's derivatives
w.r.t. k, c and mu by ``jax.jacfwd`` against central differences of
:class:`tuning.reports.reference.BoxCornerReference`.

Returns plain data; ``docs/gradients.txt`` holds the table. Units: SI.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .reference import G

__all__ = ["BoxCornerCase", "BOX_CASES", "BOX_METRICS", "box_corner_scene",
           "box_corner_metrics_fn", "box_corner_reference_metrics", "box_corner_reference",
           "box_corner_rows", "box_corner_table", "box_corner_phase_errors"]


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
        from .reference import quat_matrix
        return (dp.geometry.box_corners((self.half,) * 3) @ quat_matrix(
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
