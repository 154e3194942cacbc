"""``diffpen simulate SCENE``: roll out a built-in scene (``tuning.scenes.SCENES``) or a TOML
scene file, print its metrics, and optionally write the trajectory (.npz)."""
from __future__ import annotations

from types import SimpleNamespace

from ._common import (CLIError, count, dump_json, fail, finite, fmt, law_name, positive,
                      setup_jax)


def add_arguments(p) -> None:
    p.add_argument("scene", metavar="SCENE",
                   help="a built-in scene name (see tuning.scenes.SCENES, e.g. 'ball') or a "
                        ".toml scene file")
    p.add_argument("--k", type=positive("--k"), help="contact stiffness, N/m (every material)")
    p.add_argument("--c", type=finite("--c"), help="contact damping, N s/m (every material)")
    p.add_argument("--steps", type=count("--steps", None), help="number of steps (default: the "
                   "scene's)")
    p.add_argument("--duration", type=positive("--duration"), metavar="S",
                   help="simulated time, s, as fit and sweep take it (default: the scene's; "
                        "or give --steps)")
    p.add_argument("--dt", type=positive("--dt"), help="time step, s (default: the scene's)")
    p.add_argument("--law", type=law_name,
                   help="contact law, a name in diffpen.laws.CONTACT_LAWS (default: the "
                        "scene's)")
    p.add_argument("--exponent", type=positive("--exponent"), metavar="N",
                   help="with --law hunt_crossley: its exponent n (1.5: Hertz; default: the "
                        "scene's), as diffpen fit takes it")
    p.add_argument("--integrator", metavar="NAME",
                   help="semi_implicit_euler, verlet, rk4 or implicit_euler (default: the "
                        "scene's; a scene file's integrator = ...)")
    p.add_argument("--out", metavar="FILE.npz", help="write time, position and velocity")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def run(args) -> int:
    try:
        return _run(args)
    except (CLIError, ValueError, KeyError, OSError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
        return fail("simulate", str(msg))


def _stability_advice(message: str, args) -> str:
    """The library's StabilityError ``message`` with its advice in this command's options:
    ``--dt`` here, the substeps and the integrator in a scene file (the command has no flags
    for them)."""
    from ..scenefile import is_scene_path
    head, sep, tail = message.partition(" Use dt <= ")
    if not sep:             # no practical step: the integrator is the file's to change
        implicit = "use integrator='implicit_euler'"      # (too many substeps, or "auto"'s)
        if implicit in message and is_scene_path(args.scene):
            return message.replace(implicit, 'set integrator = "implicit_euler" at the top '
                                   f"of {args.scene}")
        return message
    dt = tail.split(" s,", 1)[0]
    if is_scene_path(args.scene):
        n = _substeps(tail)
        sub = f'substeps = {n} (or "auto")' if n else 'substeps = "auto"'
        more = f'or set {sub} or integrator = "implicit_euler" at the top of {args.scene}'
    else:
        more = ("or write the scene as a scene file, which can set substeps and "
                "integrator = \"implicit_euler\"")
    return f"{head} Use --dt {dt} or smaller, {more}."


def _substeps(text: str) -> int | None:
    """The substep count a StabilityError's advice names (``substeps=N``), else None."""
    import re
    m = re.search(r"substeps=(\d+)", text)
    return int(m.group(1)) if m else None


def _load(args):
    from ..scenefile import is_scene_path, load_scene_file
    if is_scene_path(args.scene):             # ball.TOML is a file, not the built-in "ball"
        return load_scene_file(args.scene).setup
    from ..scenes import get_scene
    return get_scene(args.scene)


def _check_size(sim, steps: int, write: bool, given: str) -> None:
    """Refuse a rollout whose saved trajectory cannot fit in memory (every step of every body
    is kept), with the library's own estimate (``diffpen.checks.estimate``, twice over with
    --out), before the rollout is compiled. ``sim``: the simulator, or before compiling a
    stand-in in the rows layout (the least the library counts). ``given``: what set the step
    count, named in the message (``--steps N``, or ``--dt`` over the scene's duration)."""
    from diffpen.checks import STEP_RATE, estimate, human_bytes, human_time, memory_bytes
    n = max(sim.n_bodies, 1)
    stored, seconds = estimate(sim, steps)
    stored *= 2 if write else 1
    mem = memory_bytes()
    if stored > 0.5 * mem:
        count = f"{steps}" if steps < 10 ** 12 else f"{steps:.3g}"    # not 300 digits
        raise CLIError(f"{given} keeps {count} states of {n} bodies: about "
                       f"{human_bytes(stored)}, more than half of this machine's "
                       f"{human_bytes(mem)} (and about {human_time(seconds)} of compute "
                       f"at ~{STEP_RATE:.0e} body-steps/s): lower --steps or raise --dt")


def _run(args) -> int:
    if args.steps is not None and args.steps < 1:
        raise CLIError("--steps must be a positive integer")
    if args.steps is not None and args.duration is not None:
        raise CLIError("--steps and --duration both set the rollout's length: give one")
    if args.c is not None and not args.c >= 0.0:
        raise CLIError("--c must be >= 0 (N s/m)")
    if args.out:
        from ..io import check_distinct, check_output
        from ..scenefile import is_scene_path
        check_output(args.out, what="--out")
        check_distinct({"--out": args.out},
                       inputs=[args.scene] if is_scene_path(args.scene) else [])
        if not args.out.lower().endswith(".npz"):
            raise CLIError(f"--out {args.out} must end in .npz (the trajectory is written as "
                           "a NumPy .npz archive)")
    setup = _load(args)                       # scene built and validated: nothing compiled yet
    dt = args.dt or setup.dt
    duration = args.duration if args.duration is not None else setup.steps * setup.dt
    steps = args.steps or max(1, int(round(duration / dt)))
    given = (f"--steps {steps}" if args.steps else
             f"--dt {dt:g} over --duration {duration:g} s" if args.duration is not None else
             f"--dt {dt:g} over the scene's {duration:g} s")
    # before compiling, as the rows layout; then as the simulator holds it (columns: more)
    _check_size(SimpleNamespace(n_bodies=setup.scene.n_bodies, scene=setup.scene,
                                dtype=setup.compile_options.get("dtype") or "float64",
                                columns=False), steps, bool(args.out), given)
    setup_jax()
    import numpy as np

    import diffpen as dp
    options = {**setup.compile_options, "law": args.law or setup.law}
    if args.exponent is not None:       # dp.compile refuses it for a law that does not read it
        options["exponent"] = args.exponent
    if args.integrator is not None:     # an unknown name: dp.compile's SceneError lists them
        options["integrator"] = args.integrator
    sim = dp.compile(setup.scene, dt, **options)
    _check_size(sim, steps, bool(args.out), given)
    if not sim.materials and (args.k is not None or args.c is not None):
        given = " and ".join(f for f, v in (("--k", args.k), ("--c", args.c)) if v is not None)
        raise CLIError(f"{given} set contact materials, but {args.scene} has no contact "
                       "materials (nothing in it makes contact): drop "
                       + ("it" if " and " not in given else "them"))
    # each material its own declared k and c (the scene's k / c where it declares none);
    # --k / --c, when given, set every material's (they once replaced every material's values
    # with the first material's)
    contact = {}
    for name in sim.materials:
        mat = setup.scene.materials[name]
        contact[name] = (args.k if args.k is not None else mat.k if mat.k is not None
                         else setup.k,
                         args.c if args.c is not None else mat.c if mat.c is not None
                         else setup.c)
    params = sim.params(contact=contact) if contact else sim.params()
    ks = {v[0] for v in contact.values()}
    cs = {v[1] for v in contact.values()}
    s0 = sim.init_state()
    try:
        traj = sim.rollout(params, steps, s0)
    except dp.StabilityError as exc:
        raise CLIError(_stability_advice(str(exc), args)) from None
    out = {"scene": args.scene, "description": setup.description, "dt": dt, "steps": steps,
           "duration": steps * dt, "law": sim.law, "exponent": sim.exponent,
           "integrator": sim.integrator,
           "k": ks.pop() if len(ks) == 1 else None, "c": cs.pop() if len(cs) == 1 else None,
           "n_bodies": sim.n_bodies}
    if len(contact) > 1:
        out["materials"] = {name: {"k": kc[0], "c": kc[1]} for name, kc in contact.items()}
    if setup.metrics is not None:
        out.update(setup.metrics(sim, traj, params))
    else:
        out["final_position"] = np.asarray(traj.position[-1]).tolist()
    if args.out:
        from ..io import atomic_write
        arrays = {"time": np.concatenate([[0.0], np.asarray(traj.time)]),
                  "position": np.concatenate([np.asarray(s0.position)[None],
                                              np.asarray(traj.position)]),
                  "velocity": np.concatenate([np.asarray(s0.velocity)[None],
                                              np.asarray(traj.velocity)])}
        atomic_write(args.out, lambda fh: np.savez(fh, **arrays))
        out["out"] = args.out
    if args.json:
        dump_json(out)
        return 0
    print(f"diffpen simulate: {setup.description or args.scene}")
    from ..stable import law_units
    ku, cu = law_units(sim.contact_law)         # Hunt-Crossley: N/m^n, N s/m^(n+1)
    if "materials" in out:
        kc = "; ".join(f"{name}: k={v['k']:g} {ku}, c={v['c']:g} {cu}"
                       for name, v in out["materials"].items())
    elif sim.materials:
        kc = f"k={out['k']:g} {ku}, c={out['c']:g} {cu}"
    else:
        kc = ""
    centred = ", damping at the step's centre" if sim.contact_law.centred is not None else ""
    law = sim.law + (f" (n {sim.exponent:g})" if sim.contact_law.takes_exponent else "")
    print(f"  {steps} steps of dt={dt:g} s ({steps * dt:g} s), {sim.integrator}, {law} "
          f"law{centred}" + (f", {kc}" if kc else ""))
    skip = {"scene", "description", "dt", "steps", "duration", "law", "exponent", "integrator",
            "k", "c", "n_bodies", "out", "materials"}
    for key, val in out.items():
        if key not in skip:
            print(f"  {key}: {fmt(val)}")
    if args.out:
        print(f"  trajectory written to {args.out} (time (S,), position/velocity (S, n, 3))")
    return 0
