"""The gradient report: the error of jax.grad of the ball's apex height and of its height at a
fixed time w.r.t. k and c, against dt and smoothing width, measured against the derivative of
the continuous hard-contact model (:mod:`tuning.reference`), and the largest
finite-difference step at which central differences of the simulator agree with jax.grad.

Returns plain data (a list of dicts); ``tuning.cli.report`` prints.

Units: SI throughout (m, kg, s, N/m, N s/m).
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .accuracy import BallSpec
from .extreme import ball_scene
from .reference import G, ball_reference

__all__ = ["gradient_report"]


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

