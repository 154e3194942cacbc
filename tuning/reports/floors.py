"""The hand-written floors the benchmarks compare diffpen with: the plain JAX an expert
would write first for the same physics, with no generality (for the ball the fastest form
of it measured; for spring networks diffpen is faster than it, see ``network_floor``). The
ball's is a ``lax.scan`` of scalar height and velocity per ball with a hard ``max(d, 0)``
contact; the spring networks' (:func:`plain_network_floor`) keeps x, y and z as separate
arrays, gathers each spring's ends and sums the forces per node with ``jax.ops.segment_sum``.
Independent of diffpen's step (they read a compiled simulator's scene and parameters only).

:func:`network_floor` is a second reference for the spring networks, not a plain one: it
writes lattice springs on dense slices added back in place, diffpen's own layout
(:func:`diffpen.terms.spring_bands`), the fastest form found; diffpen over it is the cost of
diffpen's generality on top of that layout."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

__all__ = ["G", "plain_ball_floor", "plain_network_floor", "network_floor", "network_parts"]

#: gravity of the benchmark scenes, m/s^2
G = 9.81


def plain_ball_floor(k, c, *, steps: int, dt: float = 1e-3, radius: float = 0.1,
                     drop: float = 1.0, record: bool = True, unroll: int = 8):
    """The plain floor of the ball workloads: a ``lax.scan`` of the scalar height ``z`` (m)
    and vertical velocity ``v`` (m/s) of one ball of unit mass dropped from rest at ``drop``
    onto the plane z = 0, hard contact ``f = k max(d, 0) - c [d > 0] v`` with
    ``d = radius - z``, symplectic Euler. Scalars, no (3,) vectors, no generality: under
    ``jax.vmap`` the carry is one (B,) array per component, which XLA vectorises along the
    batch. ``unroll``: of the ``lax.scan``. Returns (steps,) heights when ``record``, else
    the final ``z``."""
    def step(s, _):
        z, v = s
        d = radius - z
        f = k * jnp.maximum(d, 0.0) - c * (d > 0.0) * v
        v = v + dt * (f - G)
        z = z + dt * v
        return (z, v), (z if record else None)
    z0 = jnp.full_like(k, drop)
    (z, _), zs = jax.lax.scan(step, (z0, jnp.zeros_like(z0)), None, length=steps,
                              unroll=unroll)
    return zs if record else z



def network_parts(sim: dp.Simulator, params: dp.Params, dtype):
    """What both network floors read from a simulator: the springs' ends, rest lengths and
    groups, each group's (k, c), inverse masses, gravity and drag per node."""
    springs = [s for s in sim.scene.springs if s.b is not None]
    ia = np.array([s.a for s in springs])
    ib = np.array([s.b for s in springs])
    rest = np.array([s.rest_length for s in springs])
    group = [s.group for s in springs]
    names = sorted(set(group))
    gi = np.array([names.index(g) for g in group])
    n = sim.n_bodies
    inv_m = np.where(sim.pinned, 0.0, 1.0 / sim.mass)
    grav = np.asarray(sim.scene.gravity)[None, :] * (~sim.pinned)[:, None]
    drag_c = np.zeros(n)
    for d in sim.scene.drags:
        if not sim.pinned[d.body]:
            drag_c[d.body] += sim.scene.drag_groups[d.group]
    kvec = jnp.asarray([params.springs[g].k for g in names], dtype)
    cvec = jnp.asarray([params.springs[g].c for g in names], dtype)
    return ia, ib, rest, gi, names, inv_m, grav, drag_c, kvec, cvec


def plain_network_floor(sim: dp.Simulator, params: dp.Params, steps: int, dtype):
    """The plain floor for spring networks: per-spring k and c (``k (L - rest) + c rate``
    along the spring), symplectic Euler, gravity, drag, pinned nodes; no contact (the network
    scenes have none). x, y and z are separate (n,) arrays; each step gathers every spring's
    two ends and sums the spring forces per node with ``jax.ops.segment_sum``: what an expert
    writes first, with no knowledge of the lattice. Returns ``(final, kvec, cvec, meta)``
    as :func:`network_floor`: ``final(kvec, cvec, x0, v0) -> (n, 3)`` positions (m) after
    ``steps`` steps."""
    ia, ib, rest_np, gi, names, inv_m_np, grav_np, drag_np, kvec, cvec = network_parts(
        sim, params, dtype)
    n, dt = sim.n_bodies, sim.dt
    rest = jnp.asarray(rest_np, dtype)
    inv_m = jnp.asarray(inv_m_np, dtype)
    grav = [jnp.asarray(grav_np[:, j], dtype) for j in range(3)]
    drag = jnp.asarray(drag_np, dtype)
    has_drag = bool(np.any(drag_np))

    def final(kv, cv, x0, v0):
        k, c = kv[gi], cv[gi]

        def step(s, _):
            x, v = s            # each a tuple of three (n,) arrays
            dx = [x[j][ia] - x[j][ib] for j in range(3)]
            dv = [v[j][ia] - v[j][ib] for j in range(3)]
            length = jnp.sqrt(dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2])
            u = [d / length for d in dx]
            rate = u[0] * dv[0] + u[1] * dv[1] + u[2] * dv[2]
            f = -k * (length - rest) - c * rate
            new_v, new_x = [], []
            for j in range(3):
                fj = f * u[j]
                force = (jax.ops.segment_sum(fj, ia, n) - jax.ops.segment_sum(fj, ib, n))
                if has_drag:
                    force = force - drag * v[j]
                vj = v[j] + dt * (force * inv_m + grav[j])
                new_v.append(vj)
                new_x.append(x[j] + dt * vj)
            return (tuple(new_x), tuple(new_v)), None
        split = [tuple(a[:, j] for j in range(3)) for a in (x0, v0)]
        (x, _), _ = jax.lax.scan(step, tuple(split), None, length=steps)
        return jnp.stack(x, -1)
    return final, kvec, cvec, (ia, ib, rest_np, gi, names)


def network_floor(sim: dp.Simulator, params: dp.Params, steps: int, dtype):
    """Hand-written spring-network reference in diffpen's own layout (not a plain floor:
    :func:`plain_network_floor` is): the same physics, with lattice springs (one index offset
    per family, :func:`diffpen.terms.spring_bands`) on dense slices added back in place
    (``lax.dynamic_update_slice``), the fastest way found to write them in JAX; the other
    springs a gather and, per node, a sum of static row picks."""
    from diffpen.terms import spring_bands
    ia, ib, rest_np, gi, names, inv_m_np, grav_np, drag_np, kvec, cvec = network_parts(
        sim, params, dtype)
    inv_m = jnp.asarray(inv_m_np[:, None], dtype)
    grav = jnp.asarray(grav_np, dtype)
    dt, n = sim.dt, sim.n_bodies
    drag_c = jnp.asarray(drag_np[:, None], dtype)
    has_drag = bool(np.any(drag_np))
    bands, other = spring_bands(ia, ib)
    dense = []
    for d, lo, hi, ids in bands:             # slot j holds the spring from lo + j to lo + j + d
        slot = np.minimum(ia[ids], ib[ids]) - lo
        on, rest_b, grp = np.zeros(hi - lo), np.zeros(hi - lo), np.zeros(hi - lo, int)
        on[slot], rest_b[slot], grp[slot] = 1.0, rest_np[ids], gi[ids]
        dense.append((d, lo, hi, jnp.asarray(on, dtype), jnp.asarray(rest_b, dtype), grp))
    rest = jnp.asarray(rest_np[other], dtype)
    oa, ob, og = ia[other], ib[other], gi[other]

    def node_sum(f, idx):
        # per node, the sum of its springs' rows: a few static row picks (a segment sum is an
        # XLA scatter, which keeps XLA CPU from compiling the loop into one kernel)
        picks = [[] for _ in range(n)]
        for p, node in enumerate(idx):
            picks[node].append(p)
        ext = jnp.concatenate([f, jnp.zeros((1, 3), f.dtype)])
        out = 0.0
        for r in range(max(len(q) for q in picks)):
            out = out + ext[np.array([q[r] if r < len(q) else len(idx) for q in picks])]
        return out

    def tension(dx, dv, rest_len, k, c):
        length = jnp.sqrt(jnp.sum(dx * dx, -1))
        u = dx / length[:, None]
        return (-k * (length - rest_len) - c * jnp.sum(u * dv, -1))[:, None] * u

    def final(kvec, cvec, x0, v0):
        def step(s, _):
            x, v = s
            force = jnp.zeros_like(x)
            for d, lo, hi, on, rest_b, grp in dense:
                f = tension(x[lo + d:hi + d] - x[lo:hi], v[lo + d:hi + d] - v[lo:hi], rest_b,
                            kvec[grp], cvec[grp]) * on[:, None]
                # in place, as diffpen does (.at[].add would be an XLA scatter, which keeps
                # XLA CPU from compiling the loop into one kernel)
                force = jax.lax.dynamic_update_slice(force, force[lo + d:hi + d] + f,
                                                     (lo + d, 0))
                force = jax.lax.dynamic_update_slice(force, force[lo:hi] - f, (lo, 0))
            if len(other):
                f = tension(x[oa] - x[ob], v[oa] - v[ob], rest, kvec[og], cvec[og])
                force = force + node_sum(f, oa) - node_sum(f, ob)
            if has_drag:
                force = force - drag_c * v
            v = v + dt * (force * inv_m + grav)
            return (x + dt * v, v), None
        (x, _), _ = jax.lax.scan(step, (x0, v0), None, length=steps)
        return x
    return final, kvec, cvec, (ia, ib, rest_np, gi, names)
