"""Speed benchmarks of diffpen against baselines measured in the same process.

For every standard scene this measures, after compilation and as the median of several runs
(``jax.block_until_ready``):

* ``compile_s``: wall time to lower and compile diffpen's forward rollout;
* ``forward_s`` and ``steps_per_s`` (the case's ``work`` per second: ball-steps, batch x
  steps / forward_s, for batched balls; sphere-steps, spheres x steps / forward_s, for the
  many-sphere cases; steps / forward_s for the spring networks);
* ``grad_s``: one gradient of a scalar loss of the rollout w.r.t. the scene's (k, c)
  (per batch element under ``vmap`` for batched scenes), and ``grad_over_forward``;
* ``memory_bytes``: XLA's memory analysis of the compiled forward and gradient executables
  (arguments + outputs + temporaries; the peak a device must hold);
* ``floor_s`` / ``vs_floor``: a plain hand-written ``lax.scan`` of the same physics with no
  generality (:mod:`tuning.reports.floors`): for the ball, scalar ``z`` and ``v`` per ball
  and a hard ``max(d, 0)`` contact, so a batch is one vector per component; for the spring
  networks, x, y and z as separate arrays, a gather of each spring's ends and a
  ``segment_sum`` of the forces per node;
* spring networks only: ``band_floor_s`` / ``vs_band_floor``: the same physics hand-written
  in diffpen's own lattice layout (dense slices added in place,
  :func:`tuning.reports.floors.network_floor`), the fastest form found: what diffpen's
  generality costs on top of its layout;
* ``floor_grad_s`` / ``grad_vs_floor`` and ``floor_grad_reverse_s`` / ``reverse_vs_floor``:
  the floor's gradient taken as diffpen's (``grad_s``) and in reverse mode (``grad_reverse_s``),
  timed in turns with diffpen's;
* ``numpy_s`` / ``vs_numpy``: the same physics in vectorised NumPy;
* ball cases only: ``stepping_s`` / ``stepping_per_s`` / ``stepping_vs_floor``: the same
  rollout returning only its final state (nothing recorded), against the floor doing the
  same: the workload of a stepping rate, the figure simulators quote and the peers' anchors
  measure; ``natural_s`` / ``natural_vs_floor``: the code a user writes first,
  ``sim.rollout(params, steps).position[-1, 0, 2]`` (every state recorded, the last height
  kept), against the same floor.

Forward workloads return what a tuning metric needs: the ball's full height trajectory, the
final node positions of spring networks. The functions here compute; ``tuning.cli.bench``
prints.
"""
from __future__ import annotations

import time
import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp
from diffpen import builders

from ..scenes import ball_scene
from .floors import G, network_floor, network_parts, plain_ball_floor, plain_network_floor
from .timing import interleaved_times, median_time, memory_bytes

__all__ = ["Case", "CASES", "run_case", "run", "sphere_scaling", "gradient_memory",
           "spheres_in_box"]


def _gradients(loss: Callable, floor_loss: Callable | None, *, batched: bool) -> dict:
    """Jitted gradients of ``loss(k, c)`` w.r.t. (k, c): ``grad`` with
    ``diffpen.value_and_grad`` (its automatic choice: forward mode for these two scalars),
    ``grad_reverse`` with reverse mode, and ``floor_grad`` / ``floor_grad_reverse`` of the
    floor's loss the same two ways (so ``grad_vs_floor`` and ``reverse_vs_floor`` compare
    like with like). Per batch row under ``vmap`` when ``batched``."""
    def make(fn, mode):
        g = dp.value_and_grad(fn, (0, 1), mode=mode)
        return jax.jit(jax.vmap(g) if batched else g)
    return dict(grad=make(loss, "auto"), grad_reverse=make(loss, "reverse"),
                floor_grad=None if floor_loss is None else make(floor_loss, "auto"),
                floor_grad_reverse=None if floor_loss is None else make(floor_loss, "reverse"),
                grad_mode=dp.autodiff.resolve_mode("auto", 2))


class Case(NamedTuple):
    """One benchmark configuration. ``build(dtype, quick)`` returns a dict with keys
    ``forward``, ``grad``, ``floor``, ``numpy`` (callables or None), ``args`` (JAX inputs of
    forward/grad/floor), ``work`` (body-steps per forward call), ``steps``, ``batch``."""
    name: str
    build: Callable[[object, bool], dict]


# --------------------------------------------------------------------------- ball
def _ball(batch: int, quick: bool, layout: str = "auto"):
    def build(dtype, quick_=quick):
        steps = 2000 if not quick_ else 500
        b = batch if not quick_ else min(batch, 256)
        dt, k0, c0 = 1e-3, 1e4, 20.0
        sim = dp.compile(ball_scene(radius=0.1, mass=1.0, height=1.0, gravity=G), dt=dt,
                         dtype=dtype, unroll=1 if b == 1 else 4, layout=layout)

        def height(state):
            return state.position[0, 2]

        def heights(k, c):
            return sim.rollout(sim.params(k=k, c=c), steps=steps, observe=height).observed

        def final_position(k, c):
            return sim.rollout(sim.params(k=k, c=c), steps=steps, save_every=steps).position

        def natural(k, c):
            # what a user writes first: the whole trajectory, then its last height (measured
            # as written, so its PerformanceWarning is expected here)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", dp.PerformanceWarning)
                return sim.rollout(sim.params(k=k, c=c), steps=steps).position[-1, 0, 2]

        # the floor's fastest form measured here: the scan unrolled 8 times at batch 1 (10-15%
        # faster), not unrolled under vmap (unrolling made 1024 balls 1.2-1.5x slower) nor
        # in its gradient (unrolled, the forward-mode gradient at batch 1 was 6x slower)
        floor_unroll = 8 if b == 1 else 1

        def floor_heights(k, c, unroll=floor_unroll):
            return plain_ball_floor(k, c, steps=steps, dt=dt, unroll=unroll)

        def floor_final(k, c):
            return plain_ball_floor(k, c, steps=steps, dt=dt, record=False,
                                    unroll=floor_unroll)

        def loss(fn):
            return lambda k, c: jnp.sum(fn(k, c) ** 2)

        ks = jnp.asarray(np.geomspace(5e3, 2e4, b), dtype)
        cs = jnp.full((b,), c0, dtype)
        grads = _gradients(loss(heights), loss(lambda k, c: floor_heights(k, c, 1)),
                           batched=b > 1)
        lift = (lambda f: jax.jit(f)) if b == 1 else (lambda f: jax.jit(jax.vmap(f)))
        fwd, flr = lift(heights), lift(floor_heights)
        stepping = dict(stepping=lift(final_position), floor_stepping=lift(floor_final),
                        natural=lift(natural))
        args = ((jnp.asarray(k0, dtype), jnp.asarray(c0, dtype)) if b == 1 else (ks, cs))
        npdt = np.dtype(dtype)
        kn, cn = np.asarray(args[0], npdt), np.asarray(args[1], npdt)

        def numpy_heights():
            z = np.ones_like(kn) if kn.ndim else np.ones((), npdt)
            v = np.zeros_like(z)
            out = np.empty((steps,) + z.shape, npdt)
            for i in range(steps):
                d = 0.1 - z
                f = kn * np.maximum(d, 0.0) - cn * (d > 0.0) * v
                v = v + dt * (f - G)
                z = z + dt * v
                out[i] = z
            return out
        return dict(forward=fwd, floor=flr, numpy=numpy_heights, args=args, work=b * steps,
                    steps=steps, batch=b, **grads, **stepping)
    return build


# --------------------------------------------------------------------------- spring networks
def _network_case(make_scene: Callable[[], dp.Scene], steps: int, quick_steps: int, dt: float):
    def build(dtype, quick):
        n_steps = quick_steps if quick else steps
        scene = make_scene()
        sim = dp.compile(scene, dt=dt, dtype=dtype)
        p0 = sim.params()
        state = sim.init_state()
        groups = sim.spring_groups

        def fwd_kc(k, c):
            # scale every spring group's (k, c) by the same factors: 2 differentiable scalars
            springs = {g: (p0.springs[g].k * k, p0.springs[g].c * c) for g in groups}
            p = sim.params(springs=springs)
            return sim.rollout(p, steps=n_steps, state=state, save_every=n_steps).position[-1]

        floor_final, kvec, cvec, _ = plain_network_floor(sim, p0, n_steps, dtype)
        band_final = network_floor(sim, p0, n_steps, dtype)[0]

        def floor_kc(k, c):
            return floor_final(kvec * k, cvec * c, state.position, state.velocity)

        def band_floor_kc(k, c):
            return band_final(kvec * k, cvec * c, state.position, state.velocity)

        def loss(fn):
            return lambda k, c: jnp.sum(fn(k, c)[:, 2])
        args = (jnp.asarray(1.0, dtype), jnp.asarray(1.0, dtype))
        npdt = np.dtype(dtype)
        # the same springs, masses, gravity and drag as the floors read (network_parts)
        ia, ib, rest, gi, _, inv_m, grav, drag_c, _, _ = network_parts(sim, p0, dtype)
        kn = np.asarray(kvec, npdt)[gi]
        cn = np.asarray(cvec, npdt)[gi]
        inv_m = inv_m[:, None].astype(npdt)
        grav = grav.astype(npdt)
        drag_np = drag_c[:, None].astype(npdt)
        x0, v0 = np.asarray(state.position, npdt), np.asarray(state.velocity, npdt)
        rest_n = np.asarray(rest, npdt)
        n = sim.n_bodies

        def numpy_final():
            x, v = x0.copy(), v0.copy()
            for _ in range(n_steps):
                dx = x[ia] - x[ib]
                dv = v[ia] - v[ib]
                length = np.sqrt(np.sum(dx * dx, -1))
                u = dx / length[:, None]
                f = (-kn * (length - rest_n) - cn * np.sum(u * dv, -1))[:, None] * u
                # np.bincount sums in float64: back to the case's dtype
                force = np.stack([np.bincount(ia, f[:, j], n) - np.bincount(ib, f[:, j], n)
                                  for j in range(3)], -1).astype(npdt)
                v = v + dt * ((force - drag_np * v) * inv_m + grav)
                x = x + dt * v
            return x
        has_only_springs = set(sim.terms) <= {"springs", "drag"}
        grads = _gradients(loss(fwd_kc), loss(floor_kc) if has_only_springs else None,
                           batched=False)
        return dict(forward=jax.jit(fwd_kc), floor=jax.jit(floor_kc) if has_only_springs else None,
                    band_floor=jax.jit(band_floor_kc) if has_only_springs else None,
                    numpy=numpy_final if has_only_springs else None, **grads,
                    args=args, work=n_steps, steps=n_steps, batch=1,
                    bodies=sim.n_bodies, springs=len(ia))
    return build


def _cloth_scene(n: int) -> dp.Scene:
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    # 0.1 m spacing, 0.1 kg per node: stable at dt = 1e-3 with k = 1e3 on every group
    # (Gershgorin: 2 x 12 springs x 1e3 / 0.1 x dt^2 = 0.24 < 4)
    builders.add_cloth(scene, n, n, 0.1, mass=0.1 * n * n, origin=(0.0, 0.0, 1.0),
                       structural=(1e3, 0.1), shear=(1e3, 0.1), bend=(1e3, 0.1),
                       pinned=[(0, 0), (n - 1, 0), (0, n - 1), (n - 1, n - 1)],
                       collide=False)
    return scene


def _jelly_scene(n: int) -> dp.Scene:
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    builders.add_jelly(scene, n, n, n, 0.05, mass=0.1 * n ** 3, origin=(0.0, 0.0, 0.5),
                       pinned=[(0, 0, n - 1), (n - 1, n - 1, n - 1)], collide=False)
    return scene


def _chain_scene() -> dp.Scene:
    scene, _ = builders.paper_chain()
    return scene


def spheres_in_box(n: int, *, radius: float = 0.05, mass: float = 0.1, seed: int = 0):
    """``n`` spheres on a jittered lattice (spacing 2.4 radii) in a square box: a floor and
    four walls, gravity. Returns ``(scene, side_length_m)``."""
    rng = np.random.default_rng(seed)
    spacing = 2.4 * radius
    side = max(2, int(round((n / 2.0) ** (1.0 / 3.0))))        # columns twice as tall as wide
    layers = -(-n // (side * side))
    length = side * spacing
    scene = dp.Scene(gravity=(0.0, 0.0, -G))
    for m in range(n):
        i, j, l = m % side, (m // side) % side, m // (side * side)
        pos = ((i + 0.5) * spacing, (j + 0.5) * spacing, radius + 0.01 + l * spacing)
        jitter = rng.uniform(-0.1, 0.1, 3) * radius
        scene.add_sphere(radius, mass, tuple(np.add(pos, jitter)))
    scene.add_plane((0.0, 0.0, 1.0), 0.0)
    scene.add_plane((1.0, 0.0, 0.0), 0.0)
    scene.add_plane((-1.0, 0.0, 0.0), -length)
    scene.add_plane((0.0, 1.0, 0.0), 0.0)
    scene.add_plane((0.0, -1.0, 0.0), -length)
    assert layers >= 1
    return scene, length


def _spheres(n: int, steps: int):
    """``n`` spheres in a box for ``steps`` steps (a tenth of them, at least 5, with quick): a
    per-step rate, so a few dozen steps measure it (10000 spheres take ~0.2 s per step here)."""
    full = steps

    def build(dtype, quick):
        from diffpen.broadphase import Grid
        steps = max(5, full // 10) if quick else full
        scene, _ = spheres_in_box(n)
        sim = dp.compile(scene, dt=5e-4, dtype=dtype,
                         broadphase=Grid(max_per_cell=8, max_pairs=8 * n))
        state = sim.init_state()

        def final(k, c):
            p = sim.params(k=k, c=c)
            return sim.rollout(p, steps=steps, state=state, save_every=steps,
                               check_stability=False).position[-1]

        def loss(k, c):
            return jnp.sum(final(k, c)[:, 2])
        args = (jnp.asarray(5e3, dtype), jnp.asarray(2.0, dtype))
        return dict(forward=jax.jit(final), floor=None, numpy=None, args=args,
                    **_gradients(loss, None, batched=False), work=n * steps, steps=steps,
                    batch=1, bodies=n)
    return build


def sphere_scaling(sizes=(1000, 2000, 4000, 8000, 16000), *, steps: int = 100,
                   repeats: int = 3, dtype=jnp.float32) -> dict:
    """Per-step forward time of ``spheres_in_box`` with the grid neighbour search for each
    size, and the least-squares exponent of time against size (1 = linear). The sizes are
    timed in turns (``interleaved_times``), so a change of machine load hits all of them."""
    from diffpen.broadphase import Grid
    fns = {}
    for n in sizes:
        scene, _ = spheres_in_box(n)
        sim = dp.compile(scene, dt=5e-4, dtype=dtype,
                         broadphase=Grid(max_per_cell=8, max_pairs=8 * n))
        state = sim.init_state()
        fns[n] = jax.jit(lambda k, c, sim=sim, state=state: sim.rollout(
            sim.params(k=k, c=c), steps=steps, state=state, save_every=steps,
            check_stability=False).position[-1])
    t = interleaved_times(fns, (jnp.asarray(5e3, dtype), jnp.asarray(2.0, dtype)),
                          repeats=repeats)
    per_step = [t[n] / steps for n in sizes]
    return dict(sizes=list(sizes), seconds_per_step=per_step,
                exponent=_scaling_exponent(sizes, per_step))


CASES: dict[str, Case] = {
    "ball_b1": Case("ball_b1", _ball(1, False)),
    "ball_b1024": Case("ball_b1024", _ball(1024, False)),
    "ball_b65536": Case("ball_b65536", _ball(65536, False)),
    # the same balls stepped in the rows layout (the default, "auto", steps them in columns;
    # diffpen.layout)
    "ball_b1024_rows": Case("ball_b1024_rows", _ball(1024, False, "rows")),
    "ball_b65536_rows": Case("ball_b65536_rows", _ball(65536, False, "rows")),
    "chain": Case("chain", _network_case(_chain_scene, 2000, 500, 0.1)),
    "cloth32": Case("cloth32", _network_case(lambda: _cloth_scene(32), 1000, 200, 1e-3)),
    "cloth64": Case("cloth64", _network_case(lambda: _cloth_scene(64), 1000, 100, 1e-3)),
    "jelly10": Case("jelly10", _network_case(lambda: _jelly_scene(10), 1000, 100, 1e-3)),
    "spheres1000": Case("spheres1000", _spheres(1000, 100)),
    "spheres10000": Case("spheres10000", _spheres(10000, 20)),
}

#: Cases run by ``--quick`` (CI-sized).
QUICK = ("ball_b1", "ball_b1024", "chain", "cloth32")


def run_case(name: str, *, dtype=jnp.float32, quick: bool = False, repeats: int = 5,
             baselines: bool = True) -> dict:
    """Measure one case; returns a flat dict of figures (see the module docstring)."""
    case = CASES[name]
    spec = case.build(dtype, quick)
    args = spec["args"]
    t0 = time.perf_counter()
    compiled = spec["forward"].lower(*args).compile()
    compile_s = time.perf_counter() - t0
    grad_compiled = spec["grad"].lower(*args).compile()
    # diffpen and its floor run alternately, so both see the same machine load: the ratios
    # are taken within the same few seconds
    with_floor = baselines and spec.get("floor") is not None
    with_floor_grad = with_floor and spec.get("floor_grad") is not None
    t = interleaved_times({"forward": spec["forward"], "grad": spec["grad"],
                           "floor": spec["floor"] if with_floor else None,
                           "floor_grad": spec["floor_grad"] if with_floor_grad else None,
                           "band_floor": spec.get("band_floor") if with_floor else None},
                          args, repeats=repeats)
    fwd, grad = t["forward"], t["grad"]
    # reverse mode is shown for comparison: beside the floor's reverse mode in turns where
    # there is one, else one timed run when a forward takes > 0.2 s
    floor_rev = spec.get("floor_grad_reverse") if with_floor_grad else None
    if floor_rev is not None:
        tr = interleaved_times({"rev": spec["grad_reverse"], "floor_rev": floor_rev}, args,
                               repeats=max(3, repeats // 2))
        grad_rev = tr["rev"]
    else:
        grad_rev = median_time(spec["grad_reverse"], *args,
                               repeats=1 if fwd > 0.2 else max(1, repeats // 2))
    # quick: a CI-sized run of the case (batch <= 256, fewer steps): the row says so, so that
    # nothing reading the JSON by case name takes it for the full-size figures
    out = dict(case=name, quick=bool(quick), dtype=np.dtype(dtype).name, batch=spec["batch"],
               steps=spec["steps"],
               compile_s=compile_s, forward_s=fwd, steps_per_s=spec["work"] / fwd,
               grad_s=grad, grad_over_forward=grad / fwd, grad_mode=spec["grad_mode"],
               grad_reverse_s=grad_rev, reverse_over_forward=grad_rev / fwd,
               memory_bytes=memory_bytes(compiled), grad_memory_bytes=memory_bytes(grad_compiled))
    for key in ("bodies", "springs"):
        if key in spec:
            out[key] = spec[key]
    if with_floor:
        out.update(floor_s=t["floor"], vs_floor=fwd / t["floor"])
    if "band_floor" in t:
        out.update(band_floor_s=t["band_floor"], vs_band_floor=fwd / t["band_floor"])
    if with_floor_grad:
        out.update(floor_grad_s=t["floor_grad"], grad_vs_floor=grad / t["floor_grad"])
    if floor_rev is not None:
        out.update(floor_grad_reverse_s=tr["floor_rev"],
                   reverse_vs_floor=grad_rev / tr["floor_rev"])
    if spec.get("stepping") is not None:
        # the same rollout returning only the final state: the workload of stepping-rate
        # figures (a simulator advancing its state, nothing recorded), e.g. the peers' anchors
        ts = interleaved_times({"stepping": spec["stepping"], "natural": spec.get("natural"),
                                "floor": spec["floor_stepping"] if with_floor else None},
                               args, repeats=repeats)
        out.update(stepping_s=ts["stepping"], stepping_per_s=spec["work"] / ts["stepping"])
        if "natural" in ts:
            out.update(natural_s=ts["natural"])
        if with_floor:
            out.update(floor_stepping_s=ts["floor"],
                       stepping_vs_floor=ts["stepping"] / ts["floor"])
            if "natural" in ts:
                out.update(natural_vs_floor=ts["natural"] / ts["floor"])
    if baselines and spec.get("numpy") is not None:
        nrep = 1 if spec["work"] > 2e6 else 3
        t_np = median_time(spec["numpy"], repeats=nrep)
        out.update(numpy_s=t_np, vs_numpy=fwd / t_np)
    return out


def run(names=None, *, dtypes=(jnp.float32,), quick: bool = False, repeats: int = 5,
        progress: Callable[[str], None] | None = None) -> list[dict]:
    """Run the named cases (default: all, or ``QUICK`` with ``quick=True``) for each dtype."""
    names = list(names or (QUICK if quick else CASES))
    for n in names:
        if n not in CASES:
            raise ValueError(f"unknown benchmark case {n!r}; choose from {sorted(CASES)}.")
    rows = []
    for dtype in dtypes:
        if jnp.dtype(dtype) == jnp.float64 and not jax.config.jax_enable_x64:
            raise ValueError("float64 benchmarks need jax_enable_x64 (the CLI sets it).")
        for n in names:
            if progress:
                progress(f"{n} ({jnp.dtype(dtype).name})")
            rows.append(run_case(n, dtype=dtype, quick=quick, repeats=repeats))
    return rows


def gradient_memory(n: int = 32, steps: int = 100_000, save_every: int = 1000,
                    checkpoint: int | None = 100, *, dtype=jnp.float32,
                    compare: bool = False) -> dict:
    """Memory of backprop through a long cloth rollout with checkpointing.

    Forward: ``rollout(steps, save_every)`` of the ``n`` x ``n`` cloth; loss = mean height of
    the saved states; gradient w.r.t. the structural (k, c). Memory is XLA's analysis of each
    compiled executable (arguments + outputs + temporaries). With ``compare=True`` it also runs
    both gradients (plain backprop and checkpointed) and reports their largest relative
    difference (use float64 for the 1e-6 check).
    """
    scene = _cloth_scene(n)
    sim = dp.compile(scene, dt=1e-3, dtype=dtype)
    state = sim.init_state()
    group = "cloth.structural"

    def loss(k, c, ck):
        p = sim.params(springs={group: (k, c)})
        traj = sim.rollout(p, steps=steps, state=state, save_every=save_every, checkpoint=ck,
                           check_stability=False)
        return jnp.mean(traj.position[..., 2])
    args = (jnp.asarray(1e3, dtype), jnp.asarray(0.1, dtype))
    fwd = jax.jit(lambda k, c: loss(k, c, None))
    g_ck = jax.jit(jax.grad(lambda k, c: loss(k, c, checkpoint), (0, 1)))
    g_plain = jax.jit(jax.grad(lambda k, c: loss(k, c, None), (0, 1)))
    out = dict(case=f"cloth{n}_memory", steps=steps, save_every=save_every,
               checkpoint=checkpoint, dtype=np.dtype(dtype).name,
               forward_bytes=memory_bytes(fwd.lower(*args).compile()),
               grad_checkpoint_bytes=memory_bytes(g_ck.lower(*args).compile()),
               grad_plain_bytes=memory_bytes(g_plain.lower(*args).compile()))
    if out["forward_bytes"] and out["grad_checkpoint_bytes"]:
        out["checkpoint_over_forward"] = out["grad_checkpoint_bytes"] / out["forward_bytes"]
    if compare:
        t0 = time.perf_counter()
        a = jax.block_until_ready(g_ck(*args))
        out["grad_checkpoint_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        b = jax.block_until_ready(g_plain(*args))
        out["grad_plain_s"] = time.perf_counter() - t0
        out["max_rel_diff"] = max(float(abs(x - y) / abs(y)) for x, y in zip(a, b))
    return out


def _scaling_exponent(sizes, times) -> float:
    """Least-squares slope of log(time) against log(size)."""
    return float(np.polyfit(np.log(sizes), np.log(times), 1)[0])
