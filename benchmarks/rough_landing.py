"""A box landing on a rough floor against an event-located reference: the case behind the
README's "friction under an impact's load" (what the safe step does not cover).

    python benchmarks/rough_landing.py [--slip 0.01 0.1] [--time 0.6]

A 2 kg box (half extents 0.1, 0.15, 0.2 m, the uniform box's inertia) starts tilted
(quaternion (0.95, 0.2, 0.15, 0.05), normalised) with its centre at 0.45 m, moving at (0.5,
0.2, 0) m/s and turning at (0.5, -1.0, 0.8) rad/s (world frame), and lands on a plane of k
2e4 N/m, c 60 N s/m, mu 0.5 with smooth Coulomb friction of slip speed s. The reference
integrates the same model (each corner's force ``k d - c v_n`` along the normal and ``-mu
max(f_n, 0) v_t / sqrt(|v_t|^2 + s^2)`` along the plane while it is below the plane) with
scipy's DOP853 at rtol 1e-12, stopping at every corner's contact start and end (located
events). diffpen steps it with semi-implicit Euler at dt 4e-4 ... 5e-5 s in float64 (its
step-averaged contact, the default); printed: the largest error of the centre's position (m)
and of the angular velocity (rad/s) after ``--time`` s, and the order between steps. Needs
scipy (the ``test`` or ``report`` extra).
"""
from __future__ import annotations

import argparse

import numpy as np

import diffpen as dp
import jax

jax.config.update("jax_enable_x64", True)

HALF = np.array([0.1, 0.15, 0.2])
MASS, G, K, C, MU = 2.0, 9.81, 2e4, 60.0, 0.5
INERTIA = MASS / 3 * np.array([HALF[1] ** 2 + HALF[2] ** 2, HALF[0] ** 2 + HALF[2] ** 2,
                               HALF[0] ** 2 + HALF[1] ** 2])
Q0 = np.array([0.95, 0.2, 0.15, 0.05]) / np.linalg.norm([0.95, 0.2, 0.15, 0.05])
X0, V0, W0 = np.array([0.0, 0.0, 0.45]), np.array([0.5, 0.2, 0.0]), np.array([0.5, -1.0, 0.8])
CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * HALF


def rotation(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def reference(duration: float, slip: float):
    """The state (x, v, q, w) after ``duration`` s, integrated between located events."""
    from scipy.integrate import solve_ivp

    def rate(t, y):
        x, v, q, w = y[0:3], y[3:6], y[6:10], y[10:13]
        r_mat = rotation(q)
        force, torque = np.array([0.0, 0.0, -MASS * G]), np.zeros(3)
        for corner in CORNERS:
            r = r_mat @ corner
            d = -(x[2] + r[2])
            if d > 0:
                vp = v + np.cross(w, r)
                fn = K * d - C * vp[2]
                vt = vp - np.array([0.0, 0.0, vp[2]])
                f = np.array([0.0, 0.0, fn]) - MU * max(fn, 0.0) * vt / np.sqrt(vt @ vt
                                                                                + slip ** 2)
                force, torque = force + f, torque + np.cross(r, f)
        inertia = r_mat @ np.diag(INERTIA) @ r_mat.T
        alpha = np.linalg.solve(inertia, torque - np.cross(w, inertia @ w))
        qdot = np.concatenate([[-0.5 * w @ q[1:]], 0.5 * (q[0] * w + np.cross(w, q[1:]))])
        return np.concatenate([v, force / MASS, qdot, alpha])

    def event(j):
        def crossing(t, y):
            return y[2] + (rotation(y[6:10]) @ CORNERS[j])[2]
        crossing.terminal = True
        return crossing
    events = [event(j) for j in range(8)]
    y, t = np.concatenate([X0, V0, Q0, W0]), 0.0
    while t < duration - 1e-15:
        sol = solve_ivp(rate, (t, duration), y, method="DOP853", rtol=1e-12, atol=1e-13,
                        events=events)
        if sol.status == 1:             # a corner starts or ends its contact: restart there
            t = min(te[0] for te in sol.t_events if len(te))
            j = next(i for i, te in enumerate(sol.t_events) if len(te) and te[0] == t)
            y = sol.y_events[j][0]
            step = solve_ivp(rate, (t, min(t + 1e-10, duration)), y, method="DOP853",
                             rtol=1e-12, atol=1e-13)
            y, t = step.y[:, -1], step.t[-1]
        else:
            y, t = sol.y[:, -1], duration
    return y


def simulated(duration: float, slip: float, dt: float):
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_material("floor", k=K, c=C, friction=MU, slip_speed=slip)
    scene.add_box(tuple(HALF), MASS, tuple(X0), tuple(V0), orientation=tuple(Q0),
                  angular_velocity=tuple(W0))
    scene.add_plane(material="floor")
    sim = dp.compile(scene, dt, dtype=jax.numpy.float64)
    report = sim.stability(sim.params())
    n = int(round(duration / dt))
    final = sim.rollout(sim.params(), n, save_every=n)
    return (np.asarray(final.position[-1, 0]), np.asarray(final.angular_velocity[-1, 0]),
            report)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--slip", type=float, nargs="+", default=[0.01, 0.1], help="slip speeds")
    ap.add_argument("--time", type=float, default=0.6, help="compared after this time, s")
    args = ap.parse_args()
    for slip in args.slip:
        ref = reference(args.time, slip)
        print(f"slip speed {slip:g} m/s: reference spin {np.linalg.norm(ref[10:13]):.3f} rad/s")
        errors = []
        for dt in (4e-4, 2e-4, 1e-4, 5e-5):
            x, w, report = simulated(args.time, slip, dt)
            ex, ew = np.abs(x - ref[0:3]).max(), np.abs(w - ref[10:13]).max()
            errors.append(ex)
            print(f"  dt {dt:.0e} s ({'within' if report.stable else 'past'} the safe step "
                  f"{report.safe_dt:.2g} s): "
                  f"position {ex * 1e3:.3g} mm, angular velocity {ew:.3g} rad/s")
        orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
        print("  orders between steps: " + ", ".join(f"{o:.2f}" for o in orders))


if __name__ == "__main__":
    main()
