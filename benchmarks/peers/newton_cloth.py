"""Optional peer comparison: Newton (on Warp's CPU backend) running the cloth benchmark.

Not a dependency of diffpen. Run it in its own environment:

    python3 -m venv /tmp/peer-venv && /tmp/peer-venv/bin/pip install newton==1.8.0
    /tmp/peer-venv/bin/python benchmarks/peers/newton_cloth.py --n 32 --steps 1000

Scene (as ``diffpen bench cloth32``, structural + shear springs only, as measured for the
issue's anchor): an n x n particle grid, 0.1 m spacing, 0.1 kg per particle, springs with
k = 1e3 N/m, c = 0.1 N s/m, four pinned corners, gravity, semi-implicit Euler at dt = 1e-3 s.
Prints JSON: forward steps/s (median of runs after the first) and the time of one gradient of
the mean final height w.r.t. the spring stiffnesses through ``wp.Tape``.
"""
import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

import newton


def build(n: int, requires_grad: bool):
    b = newton.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_cloth_grid(pos=wp.vec3(0.0, 0.0, 1.0), rot=wp.quat_identity(), vel=wp.vec3(0.0),
                     dim_x=n - 1, dim_y=n - 1, cell_x=0.1, cell_y=0.1, mass=0.1,
                     tri_ke=0.0, tri_ka=0.0, tri_kd=0.0, tri_drag=0.0, tri_lift=0.0,
                     edge_ke=0.0, edge_kd=0.0, add_springs=True, spring_ke=1e3,
                     spring_kd=0.1, particle_radius=0.01)
    for idx in (0, n - 1, n * (n - 1), n * n - 1):            # pin the four corners
        b.particle_mass[idx] = 0.0
        b.particle_flags[idx] = b.particle_flags[idx] & ~int(newton.ParticleFlags.ACTIVE)
    model = b.finalize(device="cpu", requires_grad=requires_grad)
    model.particle_grid = None
    return model


def rollout(model, solver, steps: int, dt: float, tape_states=None):
    states = tape_states or [model.state() for _ in range(2)]
    control = model.control()
    if tape_states is None:
        s0, s1 = states
        for _ in range(steps):
            s1.clear_forces()
            solver.step(s0, s1, control, None, dt)
            s0, s1 = s1, s0
        return s0
    for i in range(steps):
        states[i].clear_forces()
        solver.step(states[i], states[i + 1], control, None, dt)
    return states[steps]


@wp.kernel
def mean_z(q: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    i = wp.tid()
    wp.atomic_add(out, 0, q[i][2] / float(q.shape[0]))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    wp.init()
    dt = 1e-3
    model = build(args.n, requires_grad=False)
    solver = newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
    n_springs = int(model.spring_count)
    rollout(model, solver, 10, dt)                      # compile kernels
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        final = rollout(model, solver, args.steps, dt)
        wp.synchronize()
        times.append(time.perf_counter() - t0)
    fwd = statistics.median(times)
    z = final.particle_q.numpy()[:, 2]

    gmodel = build(args.n, requires_grad=True)
    gsolver = newton.solvers.SolverSemiImplicit(gmodel, enable_tri_contact=False)
    states = [gmodel.state(requires_grad=True) for _ in range(args.steps + 1)]
    loss = wp.zeros(1, dtype=float, requires_grad=True, device="cpu")
    gtimes = []
    for _ in range(2):
        loss.zero_()
        t0 = time.perf_counter()
        tape = wp.Tape()
        with tape:
            last = rollout(gmodel, gsolver, args.steps, dt, tape_states=states)
            wp.launch(mean_z, dim=gmodel.particle_count, inputs=[last.particle_q],
                      outputs=[loss], device="cpu")
        tape.backward(loss)
        g = gmodel.spring_stiffness.grad.numpy()
        wp.synchronize()
        gtimes.append(time.perf_counter() - t0)
        tape.zero()
    print(json.dumps({"peer": f"newton {newton.__version__} / warp {wp.__version__} (cpu)",
                      "n": args.n, "particles": int(model.particle_count),
                      "springs": n_springs, "steps": args.steps, "forward_s": fwd,
                      "steps_per_s": args.steps / fwd, "grad_s": gtimes[-1],
                      "mean_final_z": float(np.mean(z)),
                      "grad_finite": bool(np.all(np.isfinite(g)))}))


if __name__ == "__main__":
    main()
