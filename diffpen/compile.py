"""Scene -> simulator: static index arrays, the Params/State pytrees, and a step built from
ONLY the force terms the scene has.

``diffpen.compile(scene, dt)`` assembles a :class:`Simulator`, a frozen holder of pure,
jitted functions ``step(params, state)``, ``rollout(params, steps)`` and
``forces(params, state)``. The scene's structure (bodies, pairs, springs, law, smoothing
width, integrator) is static: changing it means compiling a new simulator. Parameter values
are call-time arguments: changing them, or vmapping and differentiating over them, never
recompiles.

The force terms come from ``BUILTIN_TERMS`` (= :data:`diffpen.terms.BUILTIN`), one fixed
tuple of term builders, one module per kind in :mod:`diffpen.terms` (or from the builders
given as ``compile(..., terms=...)``): its order is the force summation order. A term the
scene does not need is never built, so it is never traced (each term runs under its own
``jax.named_scope``, which tests use to prove it). Compile assembles what the terms declare:
the ``Params.contact`` / ``Params.springs`` keys are the union of the contact materials and
spring groups the builders say they read (asked before any term is built), the
``Params.extra`` defaults and the ``State.aux`` entries and updates come from the built
Terms. Each term carries its stability bound, which :mod:`diffpen.stability` sums; the pure
rollout is :func:`diffpen.rollout.rollout`. Term assembly lives in :mod:`diffpen.assembly`,
the step built from the terms in :mod:`diffpen.stepping`, parameters in :mod:`diffpen.params`,
start states in :mod:`diffpen.start_state`; the Simulator's ``params``, ``init_state``,
``state_from`` and ``step_function`` delegate to them.
"""
from __future__ import annotations

import math
import types
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import assembly as _assembly
from . import broadphase as _broadphase
from . import checks as _checks
from . import laws, rigid
from . import layout as _layout
from . import motion as _motion
from . import params as _params
from . import precision as _precision
from . import rollout as _rollout
from . import stability as _stability
from . import start_energy as _start_energy
from .stability import depth as _depth
from . import start_state as _start_state
from . import stepping as _stepping
from . import terms as _terms
from .errors import SceneError, StabilityError
from .integrators import kick_then_drift
from .scene import Scene
from .params import _is_concrete
from .state import Params, State, Trajectory
from .terms import CompileContext, Term

__all__ = ["compile", "Simulator", "Term", "CompileContext", "BUILTIN_TERMS"]

#: Every built-in term builder, in force summation order (fixed; nothing is appended on
#: import). Each returns a Term (carrying its stability bound) or None when the scene does
#: not need it.
BUILTIN_TERMS: tuple = _terms.BUILTIN


# --------------------------------------------------------------------------- simulator
class Simulator:
    """A compiled scene: a frozen holder of pure, jitted functions. Build it with
    :func:`compile`; its attributes cannot be reassigned.

    Attributes:
      scene: a copy of the Scene it was built from (:meth:`diffpen.Scene.snapshot`; compile
        again to simulate later edits of it).  dt: time step, s.  n_bodies: int.
      law: contact law name.  contact_law: its :class:`diffpen.laws.ContactLaw` record.
      exponent: the law's exponent (Hunt-Crossley).  smoothing: smoothing width used, m.
      integrator: the integrator's name.  substeps: int or "auto".
      dtype: float32 or float64.  unroll: ``lax.scan`` unroll of a rollout's loop.
      broadphase: the broad phase record (:mod:`diffpen.broadphase`), or None (all pairs).
      materials: contact material names some term reads (``Params.contact`` keys): the
        union of the term builders' declarations, in builder order.
      spring_groups: spring group names (``Params.springs`` keys), declared the same way.
      terms: names of the force terms this simulator evaluates, in summation order
        (:meth:`term` gives the :class:`diffpen.terms.Term` records).
      mass: (n_bodies,) kg.  radius: (n_bodies,) m.  pinned: (n_bodies,) bool.
      context: the :class:`diffpen.terms.CompileContext` the terms were built from.
      analysis: the :class:`diffpen.stability.Analysis` (the integrator record, the terms'
        stability bounds).
      gate_cache: the :class:`diffpen.stability.GateCache` of up-front stability verdicts.
      layout: ``"rows"`` or ``"columns"``, how rollouts hold positions and velocities while
        they step (:mod:`diffpen.layout`; results are the same either way; the ``"auto"``
        given to :func:`compile` is resolved to one of them).
      columns: ``layout == "columns"``.
    """

    def __init__(self, scene: Scene, dt: float, *, integrator="semi_implicit_euler",
                 law: str | laws.ContactLaw = "linear", smoothing: float | str = "auto",
                 exponent: float = 1.0, dtype=None, unroll: int = 1,
                 substeps: int | str = 1, broadphase=None, terms=None,
                 layout: str = "auto"):
        if not isinstance(scene, Scene):
            raise SceneError(f"compile expects a diffpen.Scene, got {type(scene).__name__}.")
        if not scene.bodies:
            raise SceneError("the scene has no bodies: add one with scene.add_sphere(...) or "
                             "scene.add_particle(...).")
        _checks.check_pairs(scene, broadphase)
        builders = _assembly.builders(terms)
        builtin_terms = all(b in _terms.BUILTIN for b in builders)
        # terms that give no energy back beyond the start's (diffpen.stability.depth)
        passive_terms = all(b in _terms.BUILTIN or getattr(b, "passive", False)
                            for b in builders)
        dt, method, contact_law, width = _checks.compile_arguments(
            scene, dt, integrator, law, exponent, smoothing, unroll, substeps,
            builtin_terms=builtin_terms)
        exponent = float(contact_law.exponent)

        self.scene = scene = scene.snapshot()   # later edits of ``scene`` do not reach it
        self.dt = dt
        self.integrator = method.name
        self.law = contact_law.name
        self.contact_law = contact_law
        self.smoothing = width
        self.exponent = exponent
        self.unroll = int(unroll)
        try:
            self.dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
        except TypeError:
            raise SceneError(f"dtype must be float32 or float64, got {dtype!r}.") from None
        if self.dtype not in (jnp.float32, jnp.float64):
            raise SceneError(f"dtype must be float32 or float64, got {self.dtype.name}: the "
                             "step's contact windows and stability checks need at least "
                             "float32's precision (integers cannot carry a state).")
        if self.dtype == jnp.float64 and not jax.config.jax_enable_x64:
            raise SceneError("dtype float64 needs jax.config.update('jax_enable_x64', True) "
                             "before compiling.")

        _precision.check_dtype_range(scene, self.dtype)
        _precision.check_coordinates(scene, self.dtype)
        bodies = scene.bodies
        self.n_bodies = len(bodies)
        self.mass = np.array([b.mass for b in bodies])
        self.radius = np.array([b.radius for b in bodies])
        self.pinned = np.array([b.pinned for b in bodies])
        collide = self._collide = np.array([b.collide for b in bodies])

        ctx = CompileContext(
            scene=scene, dtype=self.dtype, law=contact_law, width=width,
            mass=self.mass, radius=self.radius, pinned=self.pinned, collide=collide,
            broadphase=broadphase, step=dt,
            velocity_lag=0.5 if kick_then_drift(method) else 0.0)
        # the params keys: what the term builders declare they read, before any is built
        self.materials = _assembly.declared(builders, ctx, "materials", scene.materials,
                                   "contact material", "scene.add_material({!r}, k=..., c=...)")
        self.spring_groups = _assembly.declared(builders, ctx, "groups", scene.spring_groups,
                                       "spring group", "scene.add_spring_group({!r}, k=...)")
        ctx.material_index.update({m: i for i, m in enumerate(self.materials)})
        ctx.group_index.update({g: i for i, g in enumerate(self.spring_groups)})
        if broadphase is not None:
            _broadphase.check(broadphase, ctx)
        self.context = ctx
        self.broadphase = broadphase
        self._rigid = rigid.RigidDynamics(ctx, method) if scene.has_rotation else None
        # (n, 3) body-frame principal moments, kg m^2 (0: no rotation), for the start energy
        self._moments = np.array([rigid.inertia_diagonal(b) if b.rigid else np.zeros(3)
                                  for b in bodies]).reshape(-1, 3)
        self._terms: tuple[Term, ...] = _assembly.build_terms(builders, ctx)
        self.terms = tuple(t.name for t in self._terms)
        self._searching = tuple(t for t in self._terms if t.search is not None)
        self._reporting = tuple(t for t in self._terms if t.report is not None)
        self._extra_defaults = dict(ctx.extra_defaults)
        self._extra_checks = dict(ctx.extra_checks)
        self._aux_updates = tuple(ctx.aux_updates)
        self._inv_mass = ctx.const(np.where(self.pinned, 0.0, 1.0 / self.mass)[:, None])
        g = np.array(scene.gravity)
        self._gravity = None
        if np.any(g != 0.0):
            free = (~self.pinned).astype(float)[:, None]
            self._gravity = ctx.const(free * g[None, :] if self.pinned.any() else g[None, :])

        self.layout = _layout.check(layout, self._terms, method, rigid=self._rigid is not None,
                                    searching=bool(self._searching),
                                    aux_updates=bool(self._aux_updates))
        self.columns = self.layout == "columns"
        self.substeps = substeps if substeps == "auto" else int(substeps)
        self.analysis = _stability.Analysis(
            integrator=method, dt=dt, substeps=self.substeps, mass=self.mass.astype(float),
            pinned=self.pinned.copy(), d_ref=np.maximum(np.maximum(
                self.radius.astype(float), _depth.start_depths(scene)), 1e-3),
            bounds=tuple(b for t in self._terms for b in t.bound),
            contact_scale=contact_law.stiffness, dtype=self.dtype,
            gravity=float(np.linalg.norm(np.asarray(scene.gravity, float))),
            contact_wh=contact_law.safe_wh or _stability.SAFE_WH,
            depth_exponent=(float(contact_law.exponent) if _depth.qualifies(
                scene, contact_law, passive_terms) else None),
            min_step=_precision.min_resolved_step(scene, self.dtype), extra_ranges=_stability
            .bounds.extra_ranges(self._extra_defaults, self._extra_checks),
            events_step=(_precision.events_min_step(scene, self.dtype)   # warned in the gate
                         if contact_law.one_contact == "events" else 0.0))
        self.gate_cache, self._steps = _stability.GateCache(), {}   # substeps -> pure step
        self._forces_jit = jax.jit(self._forces, static_argnames=("h",))
        self._search_aux_jit = jax.jit(self._search_aux)
        self._rollout_traces = [0]          # programs traced (rollout_cache_size)
        self._validated: dict = {}          # params values checked (diffpen.params.validate)
        self._spin_kappa = _motion.spin_anisotropy(scene)   # (n,) inertia anisotropy
        self._tunnel_table = _motion.tunnelling_table(scene)  # spheres that can meet
        self._rollout_jit = jax.jit(self._rollout_impl,
                                    static_argnames=("steps", "save_every", "checkpoint",
                                                     "substeps", "observe"))
        with jax.ensure_compile_time_eval():            # concrete even if compiled in a trace
            self._init = _start_state.init_state(self)  # arrays are immutable: shared
        self._frozen = True

    def __setattr__(self, name, value):
        if getattr(self, "_frozen", False):
            raise AttributeError(f"Simulator is frozen: compile a new one instead of setting "
                                 f"{name!r}.")
        object.__setattr__(self, name, value)

    def term(self, name: str) -> Term:
        """The :class:`diffpen.terms.Term` record named ``name`` (see :attr:`terms`)."""
        for t in self._terms:
            if t.name == name:
                return t
        raise KeyError(f"this simulator has no term {name!r}; terms: {list(self.terms)}.")

    # ------------------------------------------------------------------ parameters
    def params(self, k=None, c=None, *, contact: dict | None = None, spring_k=None,
               spring_c=None, springs: dict | None = None, extra: dict | None = None) -> Params:
        """Build the differentiable parameter pytree.

        Args:
          k, c: contact stiffness (N/m) and damping (N s/m) for EVERY contact material.
          contact: ``{material: (k, c)}`` per material (overrides ``k``/``c``).
          spring_k, spring_c: stiffness (N/m) and damping (N s/m) for EVERY spring group.
          springs: ``{group: (k, c)}`` per spring group (overrides ``spring_k``/``spring_c``).
          extra: parameters of extension terms.
        Values not given come from the scene's material / spring group defaults. Values may be
        floats, 0-d arrays or tracers; they are cast to the simulator's dtype.
        Returns: :class:`diffpen.Params`.
        """
        return _params.build(self, k, c, contact=contact, spring_k=spring_k,
                             spring_c=spring_c, springs=springs, extra=extra)

    def _cast(self, v):
        return _params.cast(self.dtype, v)

    # ------------------------------------------------------------------ state
    def init_state(self) -> State:
        """The scene's initial state (time 0, positions and velocities as added).

        ``aux`` holds the terms' entries (plastic rest lengths, the broad-phase overflow
        flag) and ``aux["unstable"]`` (False), the traced stability flag a rollout sets
        (:mod:`diffpen.stability`)."""
        # new arrays (a donated one deleted the default start); host copies: jnp.copy compiles
        return jax.tree_util.tree_map(lambda a: jax.device_put(np.array(a)), self._init)

    def state_from(self, state: State | None = None, *, body=0, position=None, velocity=None,
                   orientation=None, angular_velocity=None, frame: str | None = None) -> State:
        """A start state with the given bodies' pose and velocities replaced.

        Pure array updates (no recompilation, no scene rebuild): works under ``jax.jit``,
        ``jax.vmap`` (e.g. one start state per measured record) and ``jax.grad``.

        Args:
          state: the state to start from (default :meth:`init_state`).
          body: a body index, or a sequence of b indices.
          position: (3,) or (b, 3) centres, m.  velocity: (3,) or (b, 3) m/s, world frame.
          orientation: (4,) or (b, 4) quaternions (w, x, y, z), body to world (normalised
            here); rigid bodies only.
          angular_velocity: (3,) or (b, 3) rad/s, with ``frame`` saying in which frame:
            ``frame="body"`` (as gyroscopes and most pose trackers give it) or
            ``frame="world"`` (as ``add_box`` and ``add_rigid_sphere`` take it); rigid
            bodies only. ``frame`` has no default: one would silently turn the other's spin.
        Returns: :class:`State` (None arguments leave that part unchanged).
        """
        return _start_state.state_from(self, state, body=body, position=position,
                                       velocity=velocity, orientation=orientation,
                                       angular_velocity=angular_velocity, frame=frame)

    # ------------------------------------------------------------------ dynamics
    def forces(self, params: Params, state: State, *, h: float | None = None):
        """Total force on each body, (n_bodies, 3) newtons, gravity excluded; plus torques
        (n_bodies, 3) N m, or None for scenes without rotating bodies. Pure; jitted.

        ``h``: the integrator's inner step, s. None (default): the instantaneous, pointwise
        forces. Given: contacts apply their force averaged over the window ``s in [-h, h]``
        around this state, weighted by the hat ``1 - |s| / h`` of the step grid
        (``diffpen.laws.ContactLaw.averaged``, ``diffpen.window``), which is what the step
        integrates (static: a new value recompiles). With a broad phase and concrete
        values, a search past its static capacity warns
        (:class:`diffpen.broadphase.BroadPhaseOverflowWarning`), as a rollout does: the
        forces then miss contacts."""
        _checks.check_params(self, params, "sim.forces")
        if h is not None:
            try:
                ok = not isinstance(h, (bool, str)) and math.isfinite(float(h)) and h > 0.0
            except (TypeError, ValueError):
                ok = False
            if not ok:      # NaN gave NaN forces and a negative step was taken as given
                raise SceneError(f"h must be a positive, finite inner step in s (or None for "
                                 f"the instantaneous forces), got {h!r}.")
            h = float(h)
        out = self._forces_jit(jax.tree_util.tree_map(self._cast, params), state, h=h)
        if self._reporting and all(map(_is_concrete, jax.tree_util.tree_leaves(
                (params, state)))):
            view = types.SimpleNamespace(aux=self._search_aux_jit(params, state))
            for term in self._reporting:
                term.report(view)
        return out

    def _search_aux(self, params: Params, state: State) -> dict:
        """The ``State.aux`` entries the terms' searches record for ``state`` (e.g. the broad
        phase's overflow flag)."""
        aux = {}
        for term in self._searching:
            if term.record is not None:
                # this state's search alone: the term's entries start cleared (not sticky)
                fresh = {**state.aux, **{k: jnp.zeros_like(jnp.asarray(v))
                                         for k, v in (term.aux or {}).items()}}
                aux.update(term.record(fresh, term.search(params, state)))
        return aux

    def _forces(self, params: Params, state: State, found: dict | None = None, *,
                h: float | None = None, columns: bool = False):
        """``forces`` unjitted. ``found``: ``{term name: search result}`` already found for
        this very state (a step passes its own searches); the terms with a search not in it
        search themselves. ``columns``: return F as :class:`diffpen.layout.Columns`."""
        f = None
        tau = None
        for term in self._terms:
            with jax.named_scope(term.name):
                kw = {"h": h} if (h is not None and term.step_aware) else {}
                if found is not None and term.name in found:
                    ft, tt = term.force(params, state, found[term.name], **kw)
                else:
                    ft, tt = term.force(params, state, **kw)
            f = ft if f is None else _layout.add(f, ft)
            if tt is not None:
                tau = tt if tau is None else tau + tt
        if f is None:
            f = jnp.zeros_like(state.position)
        return (_layout.columns(f) if columns else _layout.rows(f)), tau

    def acceleration(self, params: Params, state: State, found: dict | None = None, *,
                     h: float | None = None):
        """``(a, alpha)``: linear accelerations (n_bodies, 3) m/s^2 with gravity, and angular
        accelerations (n_bodies, 3) rad/s^2 (None without rotating bodies). Pure, not jitted:
        what the integrators integrate (``accel_fn`` of :mod:`diffpen.integrators`), so under
        (semi-)implicit Euler a body with unequal moments gets ``I_w^-1 tau`` alone (the step
        carries its angular momentum: :meth:`diffpen.rigid.RigidDynamics.transport`), else
        Euler's equations. In the columns layout (:mod:`diffpen.layout`; only when
        :attr:`columns`) ``a`` is :class:`diffpen.layout.Columns` and ``alpha`` None."""
        if _layout.is_columns(state.position):
            # the columns layout (diffpen.layout): terms read rows, forces come back as
            # columns, each component gets the rows' operations in the same order
            f, _ = self._forces(params, _layout.rows_state(state), found, h=h, columns=True)
            a = _layout.Columns(*(fj * self._inv_mass[:, 0] for fj in f))
            if self._gravity is not None:
                with jax.named_scope("gravity"):
                    a = _layout.Columns(*(aj + self._gravity[:, j] for j, aj in enumerate(a)))
            return a, None
        f, tau = self._forces(params, state, found, h=h)
        a = f * self._inv_mass
        if self._gravity is not None:
            with jax.named_scope("gravity"):
                a = a + self._gravity
        if self._rigid is None:
            return a, None
        with jax.named_scope("rigid_dynamics"):
            return a, self._rigid.alpha(state, tau)

    def step(self, params: Params, state: State, *, check_stability: bool = True) -> State:
        """Advance ``state`` by one time step ``dt``. Pure; jitted. Arguments are checked as
        a rollout's are (:class:`SceneError`; :func:`diffpen.checks.check_step`), params cast
        to the simulator's dtype; with concrete params the rollout's stability gate runs
        (:class:`StabilityError` past the safe step; "auto" takes the substeps it picks),
        unless ``check_stability=False`` (then 1 substep for "auto", and no flag). In your own
        jitted scan each step sets ``aux["unstable"]``: from traced params as a rollout does
        (a law stiffening with depth bounds it by the state's energy, every step: a
        Hunt-Crossley cloth 2.4-4x the step), else where the state is not finite."""
        _checks.check_step(self, params, state)
        n = _stability.step_gate(self, params, state, check_stability)
        new, ok = _stepping.jitted(self, n, flag=_stepping.flag_mode(
            params, state, check_stability))(
            jax.tree_util.tree_map(self._cast, params), state)
        if isinstance(ok, jax.core.Tracer) or not bool(ok):   # traced: its concrete fields
            _checks.check_state_values(self, state)     # raises, naming what is wrong
        return new

    def step_function(self, substeps: int | None = None):
        """The pure (unjitted) step ``step(params, state) -> state`` over ``dt`` in
        ``substeps`` inner steps (default: the simulator's; 1 for "auto"), built once per
        count: what :meth:`step` jits and :meth:`rollout` scans."""
        n = substeps if substeps is not None else (
            self.substeps if isinstance(self.substeps, int) else 1)
        if n not in self._steps:
            self._steps[n] = _stepping.build(self, n)
        return self._steps[n]

    def stability(self, params: Params, state: State | None = None):
        """Largest stable step of this integrator for ``params`` and the current margin:
        a :class:`diffpen.stability.StabilityReport` (``stable_dt`` in s, ``margin`` =
        stable_dt / inner step, ``substeps_needed``, ``omega_max`` rad/s, what limits it).
        Params must be concrete (not jit tracers): inside jit the rollout's
        ``State.aux["unstable"]`` flag says the same. ``state``: the start state a rollout
        would take (default the scene's): its energy bounds a law stiffening with depth
        (:mod:`diffpen.stability.depth`), its spin has a limit (:mod:`diffpen.motion`)."""
        _checks.check_params(self, params, "sim.stability")
        state = self._init if state is None else state
        rep = _stability.report(self.analysis, params, energy=self.start_energy(state, params))
        if rep is None:
            raise SceneError("sim.stability(params) needs concrete parameter values, not "
                             "jit tracers.")
        return _motion.with_spin(self, rep, state)     # a start spin's limit, if tighter

    # ------------------------------------------------------------------ rollout
    def _rollout_impl(self, params, state, steps, save_every, checkpoint=None, substeps=1,
                      observe=None, energy=None):
        self._rollout_traces[0] += 1           # runs only when JAX traces a new program
        params = jax.tree_util.tree_map(self._cast, params)
        # the traced stability flag (energy: the up-front gate's, diffpen.stability.depth)
        state = _stepping.flagged(self, params, state, self.dt / substeps, energy, add=True)
        # per-contact step constants of the law (ContactLaw.step_factors), once, outside
        # the loop (a rematerialised step would recompute them and their derivatives)
        params = self.context.with_step_factors(params, self.dt / substeps)
        state = _stepping.hold_pins(self, state)    # pins stay put whatever state says
        view = None
        if self.columns:                    # step in columns, save rows (diffpen.layout)
            state, view = _layout.columns_state(state), _layout.rows_state
        traj = _rollout.rollout(self.step_function(substeps), params, state, steps=steps,
                                save_every=save_every, dt=self.dt, checkpoint=checkpoint,
                                unroll=self.unroll, observe=observe, dtype=self.dtype,
                                view=view)
        # the finite check's flag, from this program (unused outputs are dropped by XLA)
        return traj, _checks.last_state_finite(traj)

    def rollout_cache_size(self) -> int:
        """How many times this simulator's rollout has been traced (once per static
        combination of steps, save_every, checkpoint, substeps, observe and the shapes and
        dtypes of one rollout's arguments; new values never add one): a test hook for "does
        not recompile". ``jax.vmap`` at a new batch size compiles the batched program again
        without adding to it (the rollout is traced once per example shape); params are cast
        to the simulator's dtype first, so Python floats and arrays share one program."""
        return self._rollout_traces[0]

    def start_energy(self, state, params: Params | None = None) -> float | None:
        """The energy (J) with which a rollout from ``state`` bounds the reference depth of a
        contact law that stiffens with depth (:mod:`diffpen.stability.depth`: kinetic,
        rotation included, potential, and the springs' stored energy with their stiffness
        from ``params``), as the up-front check counts it; None where the radii bound it
        instead: the law's stiffness does not grow with depth, the scene does not qualify, the
        state is traced (under jit or vmap), a body starts in contact, a named plane's offset
        is not given by concrete ``params`` (its ``params.extra["plane_offset"]``), or,
        without ``params``, a spring starts stretched or compressed. The traced flag of a
        rollout counts the same energy from traced values too (:func:`diffpen.start_energy.traced`)."""
        return _start_energy.host(self, state, params)

    def rollout(self, params: Params, steps: int, state: State | None = None, *,
                save_every: int | None = None, check_finite: bool = True,
                checkpoint: int | None = None, check_stability: bool = True,
                observe: Callable | None = None, substeps: int | None = None) -> Trajectory:
        """Run ``steps`` steps with ``lax.scan``, saving every ``save_every``-th state.

        Pure and jitted: works under ``jax.jit``, ``jax.vmap`` and ``jax.grad``. Changing
        parameter values never recompiles; a new ``steps`` or ``save_every`` does.

        Args:
          params: from :meth:`params`.
          steps: number of steps (static int > 0), a multiple of ``save_every``.
          state: start state (default :meth:`init_state`).
          save_every: keep one state every this many steps (default None: every state).
            Under ``jax.vmap`` with neither this nor ``observe`` given, a rollout of 64
            steps or more warns (:class:`diffpen.PerformanceWarning`): recording every
            state of every rollout to keep a few numbers is several times slower than
            ``save_every=steps`` or ``observe=``; pass ``save_every=1`` to keep the whole
            trajectory without the warning.
          checkpoint: block size in steps for gradient checkpointing (``jax.checkpoint`` of
            each block): reverse mode then stores one state per block and recomputes inside
            it, so memory goes from O(steps) to O(steps / checkpoint + checkpoint); choose
            ~sqrt(steps). Must divide ``steps`` and be a multiple or a divisor of
            ``save_every`` (a divisor: saved intervals are checkpointed too, three levels).
            Same values and gradients as without it.
          check_finite: when called with concrete values, raise :class:`NonFiniteError` naming
            the first step and body at which the state became NaN/inf.
          check_stability: with concrete params, raise :class:`StabilityError` before running
            when an explicit integrator's step is past its safe step (:meth:`stability`);
            ``substeps="auto"`` picks the substeps here instead. With traced params (jit,
            vmap, grad) nothing is raised: the rollout sets ``State.aux["unstable"]``
            (saved in ``Trajectory.aux``) instead, whatever ``check_stability`` says.
          observe: ``observe(state) -> pytree``: save only this at each saved step (in
            ``Trajectory.observed``) instead of whole states, e.g.
            ``lambda s: s.position[:, 2]``: less memory and, for batched sweeps, several
            times faster. Static: pass the same function object each call, a new one
            recompiles.
          substeps: inner steps per step for this call (static int >= 1; default the
            simulator's, or the pick of ``substeps="auto"``). A traced rollout of an "auto"
            simulator needs it.
        Returns:
          :class:`Trajectory`; ``position`` has shape (steps // save_every, n_bodies, 3)
          (with ``observe``: None, and ``observed`` holds what it returned at each saved
          step).
        """
        given, save_every = save_every, (1 if save_every is None else save_every)
        _checks.check_rollout(self, params, steps, state, save_every, observe)
        _checks.check_rollout_options(steps, save_every, substeps, checkpoint,
                                      check_stability=check_stability,
                                      check_finite=check_finite)
        _checks.warn_batched_recording(params, state, steps, given, observe)
        if state is None:
            state = self._init
        energy = self.start_energy(state, params)
        try:
            n = _stability.gate(self.analysis, params, check=check_stability,
                                substeps=None if substeps is None else int(substeps),
                                cache=self.gate_cache, energy=energy)  # host-side only
        except StabilityError as exc:
            if energy is None and _start_energy.left_to_flag(self, state, params):
                raise _start_energy.with_hint(exc) from None
            raise
        if check_stability and all(map(_is_concrete, jax.tree_util.tree_leaves(params))):
            # a start spin past the integrator's limit: "auto" substeps, else refused
            n = _motion.check_spin(self, state, int(n),
                                   auto=substeps is None and self.substeps == "auto")
            if self._tunnel_table is not None and all(map(_is_concrete, (state.position,
                                                                         state.velocity))):
                _motion.check_tunnelling(self, params, state)
        typed = jax.tree_util.tree_map(self._cast, params)   # Python floats: no 2nd program
        traj, finite = self._rollout_jit(
            typed, state, steps=int(steps), save_every=int(save_every),
            checkpoint=None if checkpoint is None else int(checkpoint), substeps=int(n),
            observe=observe, energy=None if energy is None else jnp.asarray(energy, self.dtype))
        if check_finite:
            _checks.check_finite_trajectory(traj, save_every, self.dt, finite)
        if _is_concrete(traj.time if observe is not None else traj.position):
            for term in self._reporting:        # host-side, e.g. the broad phase's overflow
                term.report(traj)
            _motion.warn_spun_up(self, traj, check_stability, state)  # spun past the limit
        return traj

    def __repr__(self) -> str:
        return (f"Simulator(n_bodies={self.n_bodies}, dt={self.dt}, integrator="
                f"{self.integrator!r}, law={self.law!r}, smoothing={self.smoothing}, "
                f"terms={list(self.terms)})")


def compile(scene: Scene, dt: float, *, integrator="semi_implicit_euler",
            law: str | laws.ContactLaw = "linear", smoothing: float | str = "auto",
            exponent: float = 1.0, dtype=None, unroll: int = 1, substeps: int | str = 1,
            broadphase=None, terms=None, layout: str = "auto") -> Simulator:
    """Compile a scene into a simulator whose step holds only the terms the scene has.

    Args:
      scene: a :class:`diffpen.Scene`.
      dt: time step, s, > 0.
      integrator: a name in ``diffpen.integrators.INTEGRATORS`` or an
        :class:`diffpen.integrators.Integrator` record (e.g. one made outside the package:
        rollouts and the stability analysis use its own step factory and amplification).
      law: contact law: a :class:`diffpen.laws.ContactLaw` record (used as given) or a name,
        ``"linear"`` (default; may pull at separation), ``"no_tension"`` or
        ``"hunt_crossley"``. A name takes the law's centred damping (``centred=True``: the
        damper at the step window's centre speed, not semi-implicit Euler's half-step-old
        velocity) on a scene where no body can feel more than one contact and nothing else
        (one sphere or particle on one plane or fixed sphere, or two free spheres; no
        springs, drag or added terms: :func:`diffpen.checks.one_contact_per_body`), and
        the plain step average elsewhere (exact rest on several contacts);
        ``Simulator.contact_law`` is the record used.
      smoothing: width (m) of the C1 penetration ramp; 0 = exact ``max(d, 0)``; ``"auto"``
        (default) = 0: the step applies each contact's force averaged over the step
        (``diffpen.laws``), continuous through contact start and end, so no band is needed.
        A width > 0 selects the smoothed pointwise law instead (no step averaging). Static:
        changing it recompiles.
      exponent: Hunt-Crossley exponent n (1.5 = Hertz); other laws refuse any but 1.
      dtype: float dtype of the state (default: JAX's default float).
      unroll: ``lax.scan`` unroll factor of rollouts (a speed knob; no effect on results).
      substeps: inner steps of ``dt / substeps`` per step (int >= 1), or ``"auto"``: each
        rollout with concrete params picks the smallest count that is stable
        (``diffpen.stability``). With a fixed count, a rollout of an explicit integrator past
        its stability limit raises :class:`diffpen.StabilityError` naming the stable dt and
        the substeps that would make it stable. Static: changing it recompiles.
      broadphase: how sphere-sphere and sphere-box pairs are found: None (default) evaluates
        every pair that can move (exact, cost ~ pairs); ``diffpen.broadphase.AABB(max_pairs)``
        prunes them by bounding boxes, ``diffpen.broadphase.Grid(...)`` by a neighbour grid
        (near-linear cost). Static capacities; overflow is reported in
        ``State.aux["broadphase_overflow"]``.
      terms: the term builders, in force summation order (default ``BUILTIN_TERMS``); e.g.
        ``(*diffpen.terms.BUILTIN, my_builder)`` adds a term made outside the package
        (:class:`diffpen.terms.TermBuilder`: its Term's force, stability bound, extra params
        and aux state, and the contact materials and spring groups it reads).
      layout: how rollouts hold positions and velocities while they step
        (:mod:`diffpen.layout`; users always see (n, 3) rows): ``"auto"`` (default):
        ``"columns"`` where the scene allows it, else ``"rows"``; ``"columns"``: three
        (n,) arrays, which XLA CPU vectorises along a ``jax.vmap`` batch (1024 balls: the
        recording rollout 1.06x the plain floor against 1.48x in rows); the same values
        up to rounding (XLA may fuse the two layouts differently). Columns need a scene
        whose every force term returns columns (sphere and particle contacts with planes)
        and an explicit integrator; asked for otherwise, :class:`SceneError` says why.
    Returns:
      :class:`Simulator`.
    """
    return Simulator(scene, dt, integrator=integrator, law=law, smoothing=smoothing,
                     exponent=exponent, dtype=dtype, unroll=unroll, substeps=substeps,
                     broadphase=broadphase, terms=terms, layout=layout)
