"""jax derivatives outside the one-contact ball against the continuous physics: the cases
behind the README's "Gradients outside the one-contact ball" table (the sphere pairs, the
chain of particles on springs, the sliding particle; the box rows came from a planar
rigid-body reference not shipped here).

    python benchmarks/gradients_beyond_ball.py [spheres] [chain] [slide] [--integrator NAME]

Each case is a diffpen scene with the library's defaults (``dp.compile(scene, dt)``, the
linear law named) and a scipy DOP853 reference of the same model at rtol 1e-12 that stops at
every contact start and end (and, sliding, where the normal force reaches 0): located events.
The continuous derivative is the reference's central difference at a relative step of 1e-5.
Printed per metric, parameter and dt (1e-3, 3e-4, 1e-4 s): the jax derivative
(``jax.jacfwd``), the library's own central differences at relative steps 1e-2, 1e-3, 1e-4,
the continuous derivative and the jax one's relative error against it. float64. Needs scipy.
``--integrator verlet`` (or ``rk4``, any name of ``diffpen.integrators.INTEGRATORS``)
compiles the scenes with that integrator instead of the default semi-implicit Euler.
"""
from __future__ import annotations

import sys

import numpy as np

import diffpen as dp
import jax
import jax.numpy as jnp
from scipy.integrate import solve_ivp

jax.config.update("jax_enable_x64", True)

DTS = (1e-3, 3e-4, 1e-4)
RTOL = dict(method="DOP853", rtol=1e-12, atol=1e-14)
INTEGRATOR = "semi_implicit_euler"          # --integrator NAME


def compare(name, metrics, params, simulated, reference) -> None:
    """Print jax, the library's central differences and the continuous derivative of
    ``simulated(dt)(p)`` (a jax function of the parameter vector ``p``) per dt."""
    p = np.asarray([v for _, v in params], float)
    ref_val = reference(p)
    cont = np.stack([(reference(p + e) - reference(p - e)) / (2 * e[i])
                     for i, e in enumerate(np.diag(1e-5 * p))], axis=1)
    for dt in DTS:
        f = jax.jit(simulated(dt))
        val, jac = np.asarray(f(jnp.asarray(p))), np.asarray(jax.jacfwd(f)(jnp.asarray(p)))
        fd = {s: np.stack([(np.asarray(f(jnp.asarray(p + e))) - np.asarray(f(jnp.asarray(p - e))))
                           / (2 * e[i]) for i, e in enumerate(np.diag(s * p))], axis=1)
              for s in (1e-2, 1e-3, 1e-4)}
        for m, metric in enumerate(metrics):
            print(f"{name} dt {dt:.0e} {metric}: {val[m]:+.6e} (continuous {ref_val[m]:+.6e})")
            for i, (pname, _) in enumerate(params):
                err = abs(jac[m, i] - cont[m, i]) / abs(cont[m, i])
                diffs = " ".join(f"{fd[s][m, i]:+.4e}" for s in fd)
                print(f"    d/d{pname}: jax {jac[m, i]:+.5e}  differences {diffs}  continuous "
                      f"{cont[m, i]:+.5e}  error {100 * err:.2f}%")
        sys.stdout.flush()


# --------------------------------------------------------------------------- sphere pairs
M1, M2, RADIUS, V1, V2, GAP, T_PAIR = 1.0, 3.0, 0.1, 0.75, -0.25, 0.050377, 0.12


def pair_start(b):
    """Centres of the two spheres at rest distance, ``b`` the offset across the motion."""
    dx = np.sqrt((2 * RADIUS) ** 2 - b ** 2) + GAP
    return np.array([0.0, 0.0, 1.0]), np.array([dx, b, 1.0])


def pair_entry(b):
    """Time and relative position where the free approach reaches contact."""
    xa, xb = pair_start(b)
    r0, v = (xb - xa)[:2], np.array([V2 - V1, 0.0])
    aa, bb, cc = v @ v, 2 * r0 @ v, r0 @ r0 - (2 * RADIUS) ** 2
    t0 = (-bb - np.sqrt(bb * bb - 4 * aa * cc)) / (2 * aa)
    return t0, r0 + v * t0, v


def pair_reference(b):
    def ref(p):
        k, c = p
        mu = M1 * M2 / (M1 + M2)
        _, r1, v0 = pair_entry(b)

        def rate(t, y):
            r, v = y[:2], y[2:]
            length = np.sqrt(r @ r)
            n = r / length
            force = k * (2 * RADIUS - length) - c * (v @ n)
            return np.concatenate([v, force * n / mu])

        def leaves(t, y):
            return np.sqrt(y[0] ** 2 + y[1] ** 2) - 2 * RADIUS
        leaves.terminal, leaves.direction = True, 1
        sol = solve_ivp(rate, (0, 1.0), np.concatenate([r1, v0]), events=leaves, **RTOL)
        te, ye = sol.t_events[0][0], sol.y_events[0][0]
        vcm = (M1 * np.array([V1, 0.0]) + M2 * np.array([V2, 0.0])) / (M1 + M2)
        va = vcm - M2 / (M1 + M2) * ye[2:]
        e = -(ye[2:] @ (ye[:2] / (2 * RADIUS))) / (v0 @ (r1 / (2 * RADIUS)))
        return np.array([te, va[0], va[1], e])
    return ref


def pair_simulated(b):
    def make(dt):
        xa, xb = pair_start(b)
        scene = dp.Scene(gravity=(0.0, 0.0, 0.0))
        scene.add_sphere(radius=RADIUS, mass=M1, position=tuple(xa), velocity=(V1, 0, 0))
        scene.add_sphere(radius=RADIUS, mass=M2, position=tuple(xb), velocity=(V2, 0, 0))
        sim = dp.compile(scene, dt, integrator=INTEGRATOR)
        steps = int(round(T_PAIR / dt))
        t0, r1, v0 = pair_entry(b)

        def f(p):
            tr = sim.rollout(sim.params(k=p[0], c=p[1]), steps=steps, save_every=steps)
            r = tr.position[-1, 1, :2] - tr.position[-1, 0, :2]
            v = tr.velocity[-1, 1, :2] - tr.velocity[-1, 0, :2]
            # the free line back to the exit: |r + v s| = 2 R, the root s < 0 nearest 0
            aa, bb, cc = v @ v, 2 * r @ v, r @ r - (2 * RADIUS) ** 2
            s = (-bb + jnp.sqrt(bb * bb - 4 * aa * cc)) / (2 * aa)
            n = (r + v * s) / (2 * RADIUS)
            e = -(v @ n) / (v0 @ (r1 / (2 * RADIUS)))
            return jnp.stack([tr.time[-1] + s - t0, tr.velocity[-1, 0, 0],
                              tr.velocity[-1, 0, 1], e])
        return f
    return make


# --------------------------------------------------------------------------- chain
N, M_NODE, SPACING, G = 4, 0.25, 0.1, 9.81
Z0 = [0.3 + 0.0213 * i for i in range(N)]
X0 = [SPACING * i for i in range(N)]
T_CHAIN = (0.30, 0.42)


def chain_reference(p):
    kc, cc, ks, cs = p
    rest = [np.hypot(X0[i + 1] - X0[i], Z0[i + 1] - Z0[i]) for i in range(N - 1)]

    def rate(t, y, inside):
        x, z, vx, vz = y[:N], y[N:2 * N], y[2 * N:3 * N], y[3 * N:]
        fx, fz = np.zeros(N), -G * M_NODE * np.ones(N)
        for i in range(N - 1):
            dx, dz = x[i + 1] - x[i], z[i + 1] - z[i]
            length = np.hypot(dx, dz)
            ux, uz = dx / length, dz / length
            f = -ks * (length - rest[i]) - cs * ((vx[i + 1] - vx[i]) * ux
                                                 + (vz[i + 1] - vz[i]) * uz)
            fx[i + 1] += f * ux
            fz[i + 1] += f * uz
            fx[i] -= f * ux
            fz[i] -= f * uz
        for i in range(N):
            if inside[i]:
                fz[i] += -kc * z[i] - cc * vz[i]
        return np.concatenate([vx, vz, fx / M_NODE, fz / M_NODE])

    def crossing(i, inside):
        def ev(t, y, *_):
            return y[N + i]
        ev.terminal, ev.direction = True, (1 if inside[i] else -1)
        return ev
    y = np.concatenate([X0, Z0, np.zeros(N), np.zeros(N)]).astype(float)
    t, inside, out = 0.0, [False] * N, []
    for t_end in T_CHAIN:
        while True:
            sol = solve_ivp(rate, (t, t_end), y, events=[crossing(i, inside) for i in range(N)],
                            args=(inside,), **RTOL)
            hits = [(sol.t_events[i][0], i) for i in range(N) if len(sol.t_events[i])]
            if sol.status == 1 and hits:
                t, i = min(hits)
                y = sol.y_events[i][0].copy()
                y[N + i] = 0.0
                inside[i] = not inside[i]
            else:
                y, t = sol.y[:, -1], t_end
                break
        out += [y[N], y[2 * N - 1], y[0]]
    return np.array(out)


def chain_simulated(dt):
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    for i in range(N):
        scene.add_particle(mass=M_NODE, position=(X0[i], 0.0, Z0[i]))
    scene.add_spring_group("rope", k=2e3, c=1.0)
    for i in range(N - 1):
        scene.add_spring(i, i + 1, group="rope")
    scene.add_plane()
    sim = dp.compile(scene, dt, integrator=INTEGRATOR)
    rows = [int(round(t / dt)) - 1 for t in T_CHAIN]

    def f(p):
        tr = sim.rollout(sim.params(k=p[0], c=p[1], springs={"rope": (p[2], p[3])}),
                         steps=rows[-1] + 1, save_every=1)
        return jnp.stack([v for j in rows for v in (tr.position[j, 0, 2],
                                                    tr.position[j, N - 1, 2],
                                                    tr.position[j, 0, 0])])
    return f


# --------------------------------------------------------------------------- slide
M_SLIDE, V_SLIDE, Z_SLIDE, SLIP, T_SLIDE = 1.0, 2.0, 0.02, 0.01, 1.0


def slide_reference(p):
    mu, k, c = p

    def normal(y):
        return -k * y[1] - c * y[3]

    def rate(t, y, inside):
        fz, fx = -M_SLIDE * G, 0.0
        if inside[0]:
            fn = normal(y)
            fz += fn
            fx = -mu * max(fn, 0.0) * y[2] / np.sqrt(y[2] ** 2 + SLIP ** 2)
        return np.array([y[2], y[3], fx / M_SLIDE, fz / M_SLIDE])
    y, t, inside = np.array([0.0, Z_SLIDE, V_SLIDE, 0.0]), 0.0, [False]
    while True:
        def surface(t, y, *_):
            return y[1]
        surface.terminal, surface.direction = True, (1 if inside[0] else -1)

        def release(t, y, *_):
            return normal(y) if inside[0] else 1.0
        release.terminal = True
        sol = solve_ivp(rate, (t, T_SLIDE), y, events=[surface, release], args=(inside,),
                        **RTOL)
        if sol.status != 1:
            return np.array([sol.y[0, -1]])
        if len(sol.t_events[0]) and (not len(sol.t_events[1])
                                     or sol.t_events[0][0] <= sol.t_events[1][0]):
            t, y = sol.t_events[0][0], sol.y_events[0][0].copy()
            y[1] = 0.0
            inside[0] = not inside[0]
        else:                           # the normal force's kink: restart just past it
            t, y = sol.t_events[1][0], sol.y_events[1][0]
            step = solve_ivp(rate, (t, t + 1e-9), y, args=(inside,), **RTOL)
            t, y = step.t[-1], step.y[:, -1]


def slide_simulated(dt):
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    scene.add_material("rough", k=1e4, c=20.0, friction=0.3, slip_speed=SLIP)
    scene.add_particle(mass=M_SLIDE, position=(0.0, 0.0, Z_SLIDE), velocity=(V_SLIDE, 0, 0))
    scene.add_plane(material="rough")
    sim = dp.compile(scene, dt, integrator=INTEGRATOR)
    steps = int(round(T_SLIDE / dt))

    def f(p):
        params = sim.params(contact={"rough": (p[1], p[2])}, extra={"friction": {"rough": p[0]}})
        return sim.rollout(params, steps=steps, save_every=steps).position[-1, 0, :1]
    return f


def main() -> None:
    global INTEGRATOR
    args = sys.argv[1:]
    if "--integrator" in args:
        at = args.index("--integrator")
        INTEGRATOR = args[at + 1]
        del args[at:at + 2]
    print(f"integrator: {INTEGRATOR}")
    cases = args or ["spheres", "chain", "slide"]
    if "spheres" in cases:
        for b, label in ((0.0, "spheres head-on"), (0.1, "spheres at 60 deg")):
            compare(label, ["duration", "vA_x", "vA_y", "restitution"],
                    [("k", 3e4), ("c", 30.0)], pair_simulated(b), pair_reference(b))
    if "chain" in cases:
        compare("chain", [f"{q}@{t}" for t in T_CHAIN for q in ("z0", "z3", "x0")],
                [("k_contact", 1e4), ("c_contact", 10.0), ("k_spring", 2e3), ("c_spring", 1.0)],
                chain_simulated, chain_reference)
    if "slide" in cases:
        compare("slide", ["x_stop"], [("mu", 0.3), ("k", 1e4), ("c", 20.0)], slide_simulated,
                slide_reference)


if __name__ == "__main__":
    main()
