"""Time integrators: one step factory per method, all with the same signature, and the
:class:`Integrator` record that carries everything else about a method.

``make(accel_fn, h) -> step(params, state) -> state``

``accel_fn(params, state) -> (a, alpha)`` returns the linear acceleration ``a`` (n, 3) in
m/s^2 and the angular acceleration ``alpha`` (n, 3) in rad/s^2 (``None`` for scenes without
rotating bodies). Integrators only move the state with :func:`kick` (velocities) and
:func:`drift` (positions and orientations), so they work for particles and rigid bodies alike.

An :class:`Integrator` holds the step factory, the amplification matrix of one step on a
damped linear mode (what :mod:`diffpen.stability` analyses; ``None`` for unconditionally
stable methods) and the number of force evaluations per step. ``BUILTIN`` holds the built-in
records and ``INTEGRATORS`` maps their names (accepted by ``diffpen.compile(...,
integrator=NAME)``) to them; a record made elsewhere is passed to ``compile`` as it is (no
registration).
"""
from __future__ import annotations

import functools
import math
import types
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
import numpy as np

from . import layout
from .state import State

__all__ = ["Integrator", "kick", "drift", "semi_implicit_euler", "verlet", "rk4", "kick_then_drift",
           "implicit_euler", "backward_euler_amplification", "substepped", "build_step",
           "resolve", "BUILTIN", "INTEGRATORS", "IMPLICIT", "DENSE_MAX_DOF",
           "implicit_euler_with", "solves_iteratively", "carries_momentum"]


def kick(state: State, acc, h) -> State:
    """Advance velocities by ``h`` seconds of acceleration ``acc = (a, alpha)``."""
    a, alpha = acc
    w = state.angular_velocity
    if w is not None and alpha is not None:
        w = w + h * alpha
    return state._replace(velocity=layout.axpy(h, a, state.velocity), angular_velocity=w)


def quat_rate(q, w):
    """``dq/dt = 1/2 (0, w) * q`` of quaternions ``q`` (n, 4; w, x, y, z) turning at world
    angular velocity ``w`` (n, 3) rad/s."""
    qw, qv = q[..., :1], q[..., 1:]
    dqw = -0.5 * jnp.sum(w * qv, axis=-1, keepdims=True)
    dqv = 0.5 * (qw * w + jnp.cross(w, qv))
    return jnp.concatenate([dqw, dqv], axis=-1)


def _unit(q):
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def quat_integrate(q, w, h):
    """Rotate unit quaternions ``q`` (n, 4; w, x, y, z) by world angular velocity ``w`` (n, 3)
    over ``h`` seconds (first order, renormalised)."""
    return _unit(q + h * quat_rate(q, w))


def drift(state: State, h) -> State:
    """Advance positions (and orientations) by ``h`` seconds at the current velocities."""
    q = state.orientation
    if q is not None:
        q = quat_integrate(q, state.angular_velocity, h)
    return state._replace(time=state.time + h,
                          position=layout.axpy(h, state.velocity, state.position), orientation=q)


def semi_implicit_euler(accel_fn: Callable, dt: float):
    """Symplectic (semi-implicit) Euler: ``v += h a(x, v)``, then ``x += h v``.

    One force evaluation per step. Stable for an undamped spring when ``w h < 2``; with
    explicit damping when ``k h^2 + 2 c h < 4 m`` (docs/physics-notes.md section 4).
    """
    def step(params, state: State) -> State:
        return drift(kick(state, accel_fn(params, state), dt), dt)
    return step


# --------------------------------------------------------------------------- helpers
def _with_velocity(state: State, velocity, angular_velocity) -> State:
    return state._replace(velocity=velocity, angular_velocity=angular_velocity)


def _axpy(h, acc, base):
    """``base + h * acc`` for (linear, angular) pairs, angular may be None."""
    a, alpha = acc
    v, w = base
    return (layout.axpy(h, a, v), None if (w is None or alpha is None) else w + h * alpha)


# --------------------------------------------------------------------------- explicit
def verlet(accel_fn: Callable, dt: float):
    """Velocity Verlet (kick-drift-kick leapfrog).

    ``v+ = v + h/2 a(x, v)``; ``x' = x + h v+``; ``v' = v+ + h/2 a(x', v*)`` with the
    predicted end velocity ``v* = 2 v+ - v`` (so dampers stay second order). Two force
    evaluations per step (the state carries no acceleration). Second order; symplectic for
    position-only forces; stable for an undamped spring when ``w h < 2`` (docs/physics-notes.md
    section 4).
    """
    half = 0.5 * dt

    def step(params, state: State) -> State:
        s = drift(kick(state, accel_fn(params, state), half), dt)
        w = s.angular_velocity
        pred = s._replace(velocity=jax.tree_util.tree_map(lambda a, b: 2.0 * a - b,
                                                          s.velocity, state.velocity),
                          angular_velocity=None if w is None
                          else 2.0 * w - state.angular_velocity)
        return kick(s, accel_fn(params, pred), half)
    return step


def rk4(accel_fn: Callable, dt: float):
    """Classical fourth-order Runge-Kutta on ``(x, v)``; four force evaluations per step.

    Stable for an undamped spring when ``w h < 2.83`` (docs/physics-notes.md section 4). For
    rigid bodies the orientation ``q`` is a fourth variable of the same Runge-Kutta step,
    ``dq/dt = 1/2 (0, w) * q``: its stages ``q0 + h k`` (unnormalised, so the scheme is
    exactly RK4; the forces see them normalised) and ``q0 + h/6 (k1 + 2 k2 + 2 k3 + k4)``
    normalised at the end, so rotations converge at fourth order too.
    """
    half = 0.5 * dt

    def stage(state, vel, h, q):
        # position x + h * vel, velocity = vel's own stage value; orientation q (unit)
        s = drift(_with_velocity(state, *vel), h)
        return s if q is None else s._replace(orientation=_unit(q))

    def step(params, state: State) -> State:
        q0 = state.orientation
        v0 = (state.velocity, state.angular_velocity)
        a1 = accel_fn(params, state)
        v1 = v0
        k1 = None if q0 is None else quat_rate(q0, v1[1])
        v2 = _axpy(half, a1, v0)
        q2 = None if q0 is None else q0 + half * k1
        s2 = _with_velocity(stage(state, v1, half, q2), *v2)
        a2 = accel_fn(params, s2)
        k2 = None if q0 is None else quat_rate(q2, v2[1])
        v3 = _axpy(half, a2, v0)
        q3 = None if q0 is None else q0 + half * k2
        s3 = _with_velocity(stage(state, v2, half, q3), *v3)
        a3 = accel_fn(params, s3)
        k3 = None if q0 is None else quat_rate(q3, v3[1])
        v4 = _axpy(dt, a3, v0)
        q4 = None if q0 is None else q0 + dt * k3
        s4 = _with_velocity(stage(state, v3, dt, q4), *v4)
        a4 = accel_fn(params, s4)

        def weighted(parts):
            if parts[0] is None:
                return None
            return jax.tree_util.tree_map(lambda p0, p1, p2, p3: (p0 + 2.0 * p1 + 2.0 * p2 + p3)
                                          / 6.0, *parts)

        def comb(i):
            return weighted([p[i] for p in (v1, v2, v3, v4)])

        def comb_a(i):
            return weighted([p[i] for p in (a1, a2, a3, a4)])
        s = drift(_with_velocity(state, comb(0), comb(1)), dt)
        if q0 is not None:
            k4 = quat_rate(q4, v4[1])
            s = s._replace(orientation=_unit(q0 + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)))
        return kick(_with_velocity(s, *v0), (comb_a(0), comb_a(1)), dt)
    return step


# --------------------------------------------------------------------------- implicit
#: Largest number of degrees of freedom (3 x bodies) solved densely by ``implicit_euler``
#: under ``solver="auto"``; larger scenes use GMRES on Jacobian-vector products.
DENSE_MAX_DOF = 96

#: the linear solvers of :func:`implicit_euler`
IMPLICIT_SOLVERS = ("auto", "dense", "gmres", "cg")


def solves_iteratively(integrator, ndof: int, *, rigid: bool = False) -> bool:
    """Whether ``integrator`` (a record or name) solves its implicit system of ``ndof``
    unknowns (3 x bodies) by GMRES or CG (whose miss sets ``State.aux["unstable"]``, see
    :func:`_checked_solve`) rather than densely. Rigid-body scenes always solve densely;
    explicit integrators solve nothing."""
    rec = integrator if isinstance(integrator, Integrator) else INTEGRATORS.get(integrator)
    make = getattr(rec, "make", None)
    base = getattr(make, "func", make)
    if base is not implicit_euler or rigid:
        return False
    return _iterative(getattr(make, "keywords", {}).get("solver", "auto"), ndof)


def _iterative(solver: str, ndof: int) -> bool:
    """Whether implicit_euler's ``solver`` takes GMRES or CG for ``ndof`` unknowns."""
    return solver in ("cg", "gmres") or (solver == "auto" and ndof > DENSE_MAX_DOF)


def implicit_euler(accel_fn: Callable, dt: float, *, inv_mass=None, solver: str = "auto",
                   cg_tol: float = 1e-10, cg_maxiter: int | None = None):
    """Linearised backward Euler (Baraff & Witkin 1998), one linear solve per step.

    With ``a = accel_fn(params, state)`` and its Jacobians ``A_x = da/dx``, ``A_v = da/dv``
    (3n x 3n) at the current state::

        (I - h A_v - h^2 A_x) dv = h (a + h A_x v),   v' = v + dv,   x' = x + h v'

    which is docs/physics-notes.md section 4's
    ``(M - h df/dv - h^2 df/dx) dv = h (f0 + h df/dx v0)`` divided by the mass. Unconditionally stable on linear springs and contacts (it adds
    numerical damping ``zeta_num ~ w h / 2``, so a fitted ``c`` depends on ``h``).

    Args:
      accel_fn, dt: as for every integrator (dt in s).
      inv_mass: (n,) 1/kg, 0 for pinned bodies. Needed by the iterative solvers, which work
        on the mass-weighted system ``M (I - h A_v - h^2 A_x)`` restricted to free bodies.
      solver: ``"dense"`` (Jacobians by forward mode, ``jnp.linalg.solve``), ``"gmres"``
        (matrix-free GMRES on Jacobian-vector products, any system), ``"cg"`` (conjugate
        gradients: faster, but only right when that system is symmetric, as for conservative
        springs and contacts; a damper with relative motion across its axis makes it
        non-symmetric and CG's answer wrong), or ``"auto"``: dense up to ``DENSE_MAX_DOF``
        degrees of freedom, else GMRES. Gradients through an iterative solve use a second
        solve on the transposed operator, from vector-Jacobian products.
      cg_tol: relative residual tolerance of the iterative solve.  cg_maxiter: its
        iteration cap (default 3n). Each iterative solve is checked with one more product;
        a relative residual past ``max(1e3 cg_tol, sqrt(eps))`` sets the state's stability
        flag (``State.aux["unstable"]``): see :func:`_checked_solve` for the miss it guards.
    Differentiable with respect to params (and state) through either solve.

    Rigid bodies (states with orientations): the same step on generalised coordinates. The
    velocity is ``u = (v, w)`` (6n) and a configuration change is ``(dx, dtheta)``, a
    translation and a world-frame rotation vector (the orientation becomes ``q`` rotated by
    ``dtheta``); ``A_x`` and ``A_v`` are the Jacobians of ``(a, alpha)`` with respect to them.
    After the solve, ``x' = x + h v'`` and ``q`` turns by ``h w'`` (a body with unequal moments
    then takes its angular momentum's turn and speed, :func:`carries_momentum`, its
    gyroscopic term left out of the solve). Rigid scenes use the dense solve (the iterative
    solvers are refused there).
    """
    from .errors import SceneError

    if solver not in IMPLICIT_SOLVERS:
        raise SceneError(f"implicit_euler solver must be 'auto', 'dense', 'gmres' or 'cg', "
                         f"got {solver!r}.")
    h = dt

    def step(params, state: State) -> State:
        if state.orientation is not None:
            if solver in ("cg", "gmres"):
                raise SceneError(
                    f"implicit_euler with solver={solver!r} supports particle and sphere "
                    "scenes only (this scene has rotating rigid bodies, solved on generalised "
                    "coordinates): use integrator='implicit_euler' or "
                    "implicit_euler_with('dense').")
            return _rigid_step(accel_fn, h, params, state)
        x0, v0 = state.position, state.velocity
        shape = x0.shape
        ndof = x0.size
        a0 = accel_fn(params, state)[0]

        def acc_xv(x, v):
            return accel_fn(params, state._replace(position=x.reshape(shape),
                                                   velocity=v.reshape(shape)))[0].reshape(-1)
        xf, vf = x0.reshape(-1), v0.reshape(-1)
        if not _iterative(solver, ndof):
            jx, jv = _jacobians(acc_xv, xf, vf)
            eye = jnp.eye(ndof, dtype=xf.dtype)
            mat = eye - h * jv - (h * h) * jx
            rhs = h * (a0.reshape(-1) + h * (jx @ vf))
            dv = jnp.linalg.solve(mat, rhs)
        else:
            if inv_mass is None:
                raise SceneError("implicit_euler with an iterative solver needs inv_mass "
                                 "(n,) 1/kg; diffpen.compile passes it.")
            im = jnp.repeat(jnp.asarray(inv_mass, xf.dtype).reshape(-1), shape[-1])
            free = (im > 0.0).astype(xf.dtype)
            w = jnp.where(im > 0.0, 1.0 / jnp.where(im > 0.0, im, 1.0), 1.0)  # mass, kg

            def jvp_x(z):
                return jax.jvp(lambda x: acc_xv(x, vf), (xf,), (z,))[1]

            def jvp_v(z):
                return jax.jvp(lambda v: acc_xv(xf, v), (vf,), (z,))[1]

            def matvec(z):
                zp = free * z
                az = zp - h * jvp_v(zp) - (h * h) * jvp_x(zp)
                return free * (w * az) + (1.0 - free) * z

            rhs = free * w * h * (a0.reshape(-1) + h * jvp_x(vf))
            maxiter = cg_maxiter if cg_maxiter is not None else max(3 * ndof, 20)

            def cg_solve(mv, b):
                if solver == "cg":
                    return jax.scipy.sparse.linalg.cg(mv, b, tol=cg_tol, atol=0.0,
                                                      maxiter=maxiter)[0]
                return jax.scipy.sparse.linalg.gmres(mv, b, tol=cg_tol, atol=0.0,
                                                     restart=min(30, ndof),
                                                     maxiter=maxiter)[0]

            def transpose_solve(vecmat, b):
                return cg_solve(vecmat, b)

            def solve(b):
                return lax.custom_linear_solve(matvec, b, solve=cg_solve,
                                               transpose_solve=transpose_solve)
            dv, state = _checked_solve(solve, matvec, rhs, cg_tol, state)
        v1 = (vf + dv).reshape(shape)
        return state._replace(time=state.time + h, position=x0 + h * v1, velocity=v1)
    return step


def _checked_solve(solve: Callable, matvec: Callable, rhs, tol: float, state: State):
    """``(dv, state)``: ``solve(rhs)`` checked with one more product, ``matvec(dv)``. Where its
    relative residual is past ``max(1e3 tol, sqrt(eps))`` the state's stability flag
    (``State.aux["unstable"]``) is set: an iterative solve that returns a wrong answer is
    never silent (a refinement step, ``dv + solve(residual)``, was tried and not kept: it
    also moved right answers). (Seen in JAX 0.10 on CPU: GMRES and CG inside a rollout's ``lax.scan`` of
    two or more steps returned a relative residual of 3.7e-3 at a cloth's first contact,
    against 1e-10 asked, where the same step alone solved to 1e-16; the rollout left its own
    step loop by 2e-4 m and its gradients by up to 5%.)"""
    limit = max(1e3 * tol, float(jnp.finfo(rhs.dtype).eps) ** 0.5)

    dv = solve(rhs)
    bad = jnp.linalg.norm(rhs - matvec(dv)) > limit * jnp.linalg.norm(rhs)
    from .stability.bounds import FLAG      # (diffpen.stability imports this module)
    flag = state.aux.get(FLAG) if isinstance(state.aux, dict) else None
    if flag is not None:
        state = state._replace(aux={**state.aux, FLAG: flag | lax.stop_gradient(bad)})
    return dv, state


def _jacobians(fn: Callable, x, v):
    """``(d fn / dx, d fn / dv)`` at ``(x, v)`` (flat vectors of one length), from one forward-mode
    Jacobian over the stacked ``(x, v)``: one traced copy of ``fn`` instead of two."""
    m = x.size

    def stacked(z):
        return fn(z[:m], z[m:])
    jac = jax.jacfwd(stacked)(jnp.concatenate([x, v]))
    return jac[:, :m], jac[:, m:]


def _rigid_step(accel_fn: Callable, h: float, params, state: State) -> State:
    """Linearised backward Euler on generalised coordinates (see :func:`implicit_euler`):
    unknowns ``u = (v, w)`` (n, 6), configuration changes ``(dx, dtheta)``."""
    x0, v0 = state.position, state.velocity
    q0, w0 = state.orientation, state.angular_velocity
    n = x0.shape[0]

    def acc(e, u):
        e, u = e.reshape(n, 6), u.reshape(n, 6)
        s = state._replace(position=x0 + e[:, :3], orientation=quat_integrate(q0, e[:, 3:], 1.0),
                           velocity=u[:, :3], angular_velocity=u[:, 3:])
        a, alpha = accel_fn(params, s)
        return jnp.concatenate([a, alpha], axis=-1).reshape(-1)

    a, alpha = accel_fn(params, state)          # the step's own state (searches reused)
    a0 = jnp.concatenate([a, alpha], axis=-1).reshape(-1)
    u0 = jnp.concatenate([v0, w0], axis=-1).reshape(-1)
    e0 = jnp.zeros_like(u0)
    jx, jv = _jacobians(acc, e0, u0)
    mat = jnp.eye(u0.size, dtype=u0.dtype) - h * jv - (h * h) * jx
    u1 = (u0 + jnp.linalg.solve(mat, h * (a0 + h * (jx @ u0)))).reshape(n, 6)
    v1, w1 = u1[:, :3], u1[:, 3:]
    return state._replace(time=state.time + h, position=x0 + h * v1, velocity=v1,
                          orientation=quat_integrate(q0, w1, h), angular_velocity=w1)


# --------------------------------------------------------------------------- substeps
def substepped(step_fn: Callable, n: int):
    """Run ``step_fn`` (built for ``dt / n``) ``n`` times per call, with ``lax.scan``.

    ``n == 1`` returns ``step_fn`` itself, so nothing extra is traced.
    """
    if n == 1:
        return step_fn

    def step(params, state: State) -> State:
        def body(s, _):
            return step_fn(params, s), None
        return lax.scan(body, state, None, length=n)[0]
    return step


def build_step(integrator, accel_fn: Callable, dt: float, *, substeps: int = 1,
               inv_mass=None):
    """The step of ``integrator`` (a name or an :class:`Integrator`) for a saved step ``dt``
    (s) split into ``substeps`` inner steps.

    ``inv_mass`` ((n,) 1/kg, 0 = pinned) goes to integrators that take it (implicit_euler).
    With ``substeps == 1`` this is exactly ``integrator.make(accel_fn, dt)``.
    """
    rec = resolve(integrator)
    h = dt / substeps if substeps != 1 else dt
    if rec.takes_inv_mass:
        inner = rec.make(accel_fn, h, inv_mass=inv_mass)
    else:
        inner = rec.make(accel_fn, h)
    return substepped(inner, substeps)


# --------------------------------------------------------------------------- analysis
def _mode_matrix(K, C, xp):
    """``A`` (..., 2, 2) of ``d/dt (x, v) = A (x, v)`` for ``x'' = -K x - C v``."""
    zero, one = xp.zeros_like(K), xp.ones_like(K)
    return xp.stack([xp.stack([zero, one], axis=-1), xp.stack([-K, -C], axis=-1)], axis=-2)


def _broadcast(K, C, h, xp):
    if xp is np:
        return np.broadcast_arrays(np.asarray(K, float), np.asarray(C, float),
                                   np.asarray(h, float))
    K, C, h = (xp.asarray(a) for a in (K, C, h))
    dtype = xp.result_type(K, C, h, float)
    shape = xp.broadcast_shapes(K.shape, C.shape, h.shape)
    return tuple(xp.broadcast_to(a.astype(dtype), shape) for a in (K, C, h))


def _columns(x1, v1, x2, v2, xp):
    """Matrix (..., 2, 2) with columns (x1, v1) and (x2, v2)."""
    return xp.stack([xp.stack([x1, x2], axis=-1), xp.stack([v1, v2], axis=-1)], axis=-2)


def semi_implicit_euler_amplification(K, C, h, xp=np):
    """One semi-implicit Euler step on ``x'' = -K x - C v`` (K 1/s^2, C 1/s, h s; arrays that
    broadcast): ``v' = v + h a(x, v)``, ``x' = x + h v'``. Returns (..., 2, 2)."""
    K, C, h = _broadcast(K, C, h, xp)
    vx, vv = -h * K, 1.0 - h * C                 # v' = vx x + vv v
    return _columns(1.0 + h * vx, vx, h * vv, vv, xp)


def semi_implicit_euler_stable_dt(K, C, xp=np):
    """Closed-form limit of semi-implicit Euler: the root of ``K h^2 + 2 C h = 4``, written
    ``4 / (C + sqrt(C^2 + 4 K))`` (``2 / C`` without stiffness; ``inf`` for K = C = 0): the
    textbook ``(-C + sqrt(C^2 + 4 K)) / K`` cancels where ``4 K << C^2`` (a safe step of 0
    for an overdamped spring) and, with its squares, overflowed in float32 from C ~ 2e19 1/s
    or K ~ 9e37 1/s^2 (a limit of inf: a traced rollout past it was not flagged); the
    square root is taken as a ``hypot``, which does not overflow."""
    if xp is np:
        if math.isnan(float(K)) or math.isnan(float(C)):
            return math.nan             # no limit is known, not "no limit" (inf)
        K, C = max(float(K), 0.0), max(float(C), 0.0)
        den = C + math.hypot(C, 2.0 * math.sqrt(K))
        return 4.0 / den if den > 0.0 else math.inf
    K, C = xp.maximum(K, 0.0), xp.maximum(C, 0.0)
    return 4.0 / (C + xp.hypot(C, 2.0 * xp.sqrt(K)))


def verlet_amplification(K, C, h, xp=np):
    """One velocity-Verlet step (:func:`verlet`, predicted end velocity) on
    ``x'' = -K x - C v``. Returns (..., 2, 2)."""
    K, C, h = _broadcast(K, C, h, xp)
    cols = []
    for x, v in ((1.0, 0.0), (0.0, 1.0)):
        vh = v + 0.5 * h * (-K * x - C * v)
        x1 = x + h * vh
        v1 = vh + 0.5 * h * (-K * x1 - C * (2.0 * vh - v))
        cols.append((x1, v1))
    return _columns(*cols[0], *cols[1], xp)


def rk4_amplification(K, C, h, xp=np):
    """One classical RK4 step on ``x'' = -K x - C v``: ``sum_{j<=4} (h A)^j / j!``."""
    K, C, h = _broadcast(K, C, h, xp)
    A = _mode_matrix(K, C, xp)
    eye = xp.broadcast_to(xp.eye(2, dtype=A.dtype), A.shape)
    hA = h[..., None, None] * A
    hA2 = hA @ hA
    hA3 = hA2 @ hA
    return eye + hA + hA2 / 2.0 + hA3 / 6.0 + hA3 @ hA / 24.0


def backward_euler_amplification(K, C, h, xp=np):
    """One linearised backward Euler step (:func:`implicit_euler`) on ``x'' = -K x - C v``:
    ``(1 + h C + h^2 K) dv = -h (K x + C v + h K v)``, ``x' = x + h v'``. Its spectral
    radius is below 1 for every h > 0 when K, C >= 0 (no step limit), which is why the
    :class:`Integrator` record of implicit Euler has no amplification."""
    K, C, h = _broadcast(K, C, h, xp)
    Kx, Cv = -K, -C
    denom = 1.0 - h * Cv - h * h * Kx
    dvx = h * Kx / denom
    dvv = h * (Cv + h * Kx) / denom
    return _columns(1.0 + h * dvx, dvx, h * (1.0 + dvv), 1.0 + dvv, xp)


class Integrator(NamedTuple):
    """Everything about one time integration method (a record; no registration needed).

    name: shown in reports and errors.
    make: ``make(accel_fn, h, **options) -> step(params, state) -> state``, the step of one
      inner step of ``h`` seconds (:func:`semi_implicit_euler` is the model).
    amplification: ``amplification(K, C, h, xp=numpy) -> (..., 2, 2)``: the matrix mapping
      ``(x, v)`` through one step of ``h`` s on the damped mode ``x'' = -K x - C v`` (K in
      1/s^2, C in 1/s; arrays that broadcast; ``xp`` is numpy or ``jax.numpy``). What
      :mod:`diffpen.stability` analyses (step limit, traced stability flag). ``None`` for
      methods stable at every step (implicit ones): no limit, no contact tightening.
    evaluations: force evaluations per step (``None`` when it varies, e.g. Jacobian products).
    stable_dt: optional closed form ``stable_dt(K, C, xp=numpy) -> h``, the largest stable
      step on one mode (else found by bisection on ``amplification``).
    takes_inv_mass: ``make`` accepts ``inv_mass=`` ((n,) 1/kg, 0 for pinned bodies).
    columns: the step moves positions and velocities with :func:`kick` and :func:`drift` (or
      ``jax.tree_util.tree_map``) only, so it also steps states whose vectors are
      :class:`diffpen.layout.Columns` (the batch-friendly layout; :mod:`diffpen.layout`).
    """
    name: str
    make: Callable
    amplification: Callable | None
    evaluations: int | None = 1
    stable_dt: Callable | None = None
    takes_inv_mass: bool = False
    columns: bool = False

    @property
    def explicit(self) -> bool:
        """Whether the method has a step limit (an amplification matrix to analyse)."""
        return self.amplification is not None


#: The built-in integrators, built once.
BUILTIN: tuple[Integrator, ...] = (
    Integrator("semi_implicit_euler", semi_implicit_euler, semi_implicit_euler_amplification,
               1, stable_dt=semi_implicit_euler_stable_dt, columns=True),
    Integrator("verlet", verlet, verlet_amplification, 2, columns=True),
    Integrator("rk4", rk4, rk4_amplification, 4, columns=True),
    Integrator("implicit_euler", implicit_euler, None, None, takes_inv_mass=True),
)

#: Built-in integrators by name, for ``diffpen.compile(..., integrator=NAME)`` (read-only).
INTEGRATORS = types.MappingProxyType({rec.name: rec for rec in BUILTIN})

#: Names of the built-in integrators that are unconditionally stable on linear springs.
IMPLICIT = frozenset(rec.name for rec in BUILTIN if not rec.explicit)


def implicit_euler_with(solver: str) -> Integrator:
    """The ``implicit_euler`` record with its linear solver chosen, for
    ``diffpen.compile(scene, dt, integrator=implicit_euler_with("gmres"))``: ``"auto"`` (the
    built-in record's choice: dense up to :data:`DENSE_MAX_DOF` degrees of freedom, GMRES
    above), ``"dense"``, ``"gmres"`` (matrix-free, on Jacobian-vector products) or ``"cg"``
    (conjugate gradients: faster, but right only for a symmetric system; dampers with
    relative motion across their axis make it non-symmetric). The iterative solvers take
    particle and sphere scenes (rigid bodies solve densely). The record is named
    ``implicit_euler[SOLVER]`` (plain ``implicit_euler`` for ``"auto"``), so that
    ``Simulator.integrator`` and the keys of saved sweeps and fits tell the solvers apart. An
    unknown solver raises :class:`diffpen.SceneError` here, before anything is compiled."""
    if solver not in IMPLICIT_SOLVERS:
        from .errors import SceneError
        raise SceneError(f"implicit_euler solver must be one of {list(IMPLICIT_SOLVERS)}, "
                         f"got {solver!r}.")
    name = "implicit_euler" if solver == "auto" else f"implicit_euler[{solver}]"
    return INTEGRATORS["implicit_euler"]._replace(
        name=name, make=functools.partial(implicit_euler, solver=solver))


def kick_then_drift(integrator) -> bool:
    """Whether ``integrator`` (a name or a record) steps as semi-implicit Euler, by its step
    factory, not its name (a renamed record steps the same): its velocity lags its position
    by ``h / 2`` (what the centred contact laws take back); it carries the angular momentum
    of bodies with unequal moments (:func:`carries_momentum`)."""
    return resolve(integrator).make is semi_implicit_euler


def carries_momentum(integrator) -> bool:
    """Whether ``integrator`` (a name or a record) steps as a kick (its velocities) then a
    drift at the new velocities, semi-implicit Euler and implicit Euler, by their step
    factories: the step then carries the angular momentum of bodies with unequal moments
    (:meth:`diffpen.rigid.RigidDynamics.transport`) instead of their gyroscopic term."""
    make = resolve(integrator).make
    return getattr(make, "func", make) in (semi_implicit_euler, implicit_euler)


def resolve(integrator) -> Integrator:
    """The :class:`Integrator` for a built-in name or a record (returned as it is)."""
    if isinstance(integrator, Integrator):
        return integrator
    from .errors import SceneError
    if isinstance(integrator, str) and integrator in INTEGRATORS:
        return INTEGRATORS[integrator]
    raise SceneError(f"unknown integrator {integrator!r}; choose one of {sorted(INTEGRATORS)} "
                     "or pass a diffpen.integrators.Integrator record.")
