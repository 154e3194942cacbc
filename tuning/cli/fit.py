"""``diffpen fit``: fit contact k and c of the built-in ball scene (or a TOML scene file) to
bounce targets or to a measured trajectory.

With no arguments it fits the ball (radius 0.1 m, mass 1 kg, centre dropped from 1 m onto the
plane z = 0) to the default targets: first apex of the lowest point ``DEFAULT_APEX`` m and
settling time ``DEFAULT_SETTLE`` s (band 1 mm).
"""
from __future__ import annotations

import math
import os
import time

from ..stable import law_units  # noqa: F401  (the units this command prints)
from ._common import (CLIError, add_start_state_arguments, count, dump_json, fail, fmt,
                      law_name, positive, setup_jax)
from .record_fit_report import print_record_fit

UNITS = {"apex_heights": "m", "settling_time": "s", "contact_durations": "s",
         "max_penetration": "m", "restitution": "", "rms_residual": "m"}

#: Default targets of ``diffpen fit`` (feasible: reached at k ~ 2.2e3 N/m, c ~ 11 N s/m).
DEFAULT_APEX = 0.40
DEFAULT_SETTLE = 2.6
#: Default learning rate of ``--method adam|sgd``.
DEFAULT_LR = 0.05


def add_arguments(p) -> None:
    p.add_argument("scene", nargs="?", metavar="SCENE.toml",
                   help="a scene file with [fit] targets (default: the built-in ball)")
    p.add_argument("--radius", type=positive("--radius"), help="ball radius, m "
                   "(default 0.1)")
    p.add_argument("--mass", type=positive("--mass"), help="ball mass, kg "
                   "(default 1)")
    p.add_argument("--drop", type=positive("--drop"),
                   help="initial centre height, m (default 1)")
    p.add_argument("--target-apex", type=positive("--target-apex"), nargs="+", metavar="M",
                   help="apex heights of the lowest point above the plane, m, bounce by "
                        f"bounce (default {DEFAULT_APEX} with the default settling target)")
    p.add_argument("--target-settle", type=positive("--target-settle"), metavar="S",
                   help=f"settling time, s (default {DEFAULT_SETTLE} when no target is given)")
    p.add_argument("--target-decay", type=positive("--target-decay"), metavar="S",
                   help="energy-decay time int E dt / E(0), s: a settling measure smooth in k "
                        "and c (tuning.metrics; the rollout covers tuning.bounce.DECAY_MARGIN "
                        "(8) x S + 0.2 s)")
    p.add_argument("--target-contact", type=positive("--target-contact"), metavar="S",
                   help="duration of the first contact, s: the time the ball overlaps the "
                   "plane (lowest point below the surface); with --law no_tension the force "
                   "ends before the overlap does (about 10%% sooner at e = 0.667), so this is "
                   "longer than dp.physical.contact_time")
    p.add_argument("--settle-tol", type=positive("--settle-tol"), metavar="M",
                   help="settling band: |z - rest| <= tol, m (default 1e-3)")
    p.add_argument("--data", metavar="FILE.csv", nargs="+",
                   help="fit to measured records: without a scene file, one CSV with columns "
                        "t (s), z (ball centre height, m); with SCENE.toml, any number of "
                        "motion records (t, x, y, z[, qw, qx, qy, qz][, vx..][, wx..]) fitted "
                        "jointly")
    p.add_argument("--out", metavar="FITTED.toml", help="with SCENE.toml --data: write the "
                   "scene with the fitted values; the fit's progress is kept beside it "
                   "(FITTED.toml.fit-progress.json, removed once FITTED.toml is written), so "
                   "an interrupted fit resumes when the same command runs again; a "
                   "FITTED.toml already there is replaced once the fit ends (atomically)")
    p.add_argument("--fresh", action="store_true", help="with --out: start the fit afresh "
                   "instead of resuming the progress kept beside it (needed when that "
                   "progress is of a fit with other settings)")
    add_start_state_arguments(p, "with SCENE.toml --data: ")
    p.add_argument("--no-step-check", action="store_true", help="with SCENE.toml --data: "
                   "leave out the time step's error (step_shift: the residuals at dt / 2, "
                   "one more compile and evaluation); the standard errors then cover the "
                   "records' noise only")
    p.add_argument("--loss", choices=["l2", "l1"], default="l2",
                   help="with SCENE.toml --data: squared pose error (default) or its norm")
    p.add_argument("--horizon", type=positive("--horizon"), nargs="+", metavar="S",
                   help="with SCENE.toml --data: fit the first S seconds of every record "
                        "first, then longer (growing horizon), the whole records last "
                        "(default: the scene file's [fit] horizon, else 1/8, 1/4 and 1/2 of "
                        "the longest record)")
    p.add_argument("--starts", type=count("--starts", minimum=0), default=0, metavar="N",
                   help="with SCENE.toml --data: N more start points drawn around the scene "
                        "file's values (a factor 3 for log-space leaves, 1/10 of the bounds "
                        "for linear ones), screened by one rollout each (default 0)")
    p.add_argument("--keep", type=count("--keep"), default=1, metavar="M",
                   help="with --starts: run LM from the M best screened starts and keep the "
                        "fit of lowest cost (default 1)")
    p.add_argument("--dt", type=positive("--dt"), help="time step, s (default 1e-3 for "
                   "targets; chosen from the data with --data)")
    p.add_argument("--duration", type=positive("--duration"), metavar="S",
                   help="rollout length of the built-in ball's fit, s (default: covers the "
                        "targets with margin)")
    p.add_argument("--law", type=law_name,
                   help="contact law, a name in diffpen.laws.CONTACT_LAWS (default linear)")
    p.add_argument("--exponent", type=positive("--exponent"), metavar="N",
                   help="with --law hunt_crossley: the exponent n of F = max(k - c vn, 0) d^n "
                        "(1.5: Hertz; default 1); k is then in N/m^n and c in N s/m^(n+1)")
    p.add_argument("--events", action="store_true", default=None,
                   help="fit the built-in ball with the law's event-exact record "
                        "(diffpen.laws.get(LAW, events=True): its steps land on the "
                        "continuous motion through contact start and end, so the fitted k "
                        "and c are the continuous system's; about 1.1-1.8x the step's cost "
                        "on a bouncing ball)")
    p.add_argument("--method", choices=["lm", "adam", "sgd"], default="lm",
                   help="lm (Levenberg-Marquardt, default) or a first-order optax optimiser")
    p.add_argument("--lr", type=positive("--lr"), default=DEFAULT_LR,
                   help="learning rate on log-parameters for adam/sgd (default 0.05)")
    p.add_argument("--maxiter", type=count("--maxiter"),
                   help="iteration limit: of the whole fit for targets (default 40 with lm, "
                        "400 with adam/sgd); per horizon stage for records (t,z records: "
                        "default 15, the last stage twice as many; position records: default "
                        "30, or the scene file's [fit] maxiter)")
    p.add_argument("--k0", type=positive("--k0"),
                   help="start stiffness, N/m (Hunt-Crossley: N/m^n)")
    p.add_argument("--c0", type=positive("--c0"),
                   help="start damping, N s/m (Hunt-Crossley: N s/m^(n+1))")
    p.add_argument("--plot", metavar="FILE.png", help="the built-in ball's fits only: its "
                   "trajectory against the targets and the loss curve (needs matplotlib); for "
                   "scene files use diffpen evaluate ... --plot DIR")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def run(args) -> int:
    try:
        return _run(args)
    except CLIError as exc:
        return fail("fit", str(exc))
    except ImportError as exc:
        return fail("fit", str(exc))
    except ValueError as exc:       # FitError, SceneError: bad input, said before compiling
        return fail("fit", str(exc))


def _targets(args) -> dict:
    tg = {}
    if args.target_apex:
        tg["apex_heights"] = list(args.target_apex)
    if args.target_settle:
        tg["settling_time"] = args.target_settle
    if args.target_contact:
        tg["contact_durations"] = [args.target_contact]
    if args.target_decay:
        tg["decay_time"] = args.target_decay
    if not tg:
        tg = {"apex_heights": [DEFAULT_APEX], "settling_time": DEFAULT_SETTLE}
    return tg


def _check_plot(args) -> None:
    """--plot: a writable path and matplotlib present, checked before anything is fitted."""
    if args.plot:
        from ..io import check_plot
        from ..plots import require_matplotlib
        check_plot(args.plot, what="--plot")
        require_matplotlib()


#: The built-in ball's flags and their defaults: a scene file has its own values.
BALL_FLAGS = {"radius": 0.1, "mass": 1.0, "drop": 1.0, "settle_tol": 1e-3, "law": "linear",
              "dt": None, "k0": None, "c0": None, "target_apex": None,
              "target_settle": None, "target_contact": None, "target_decay": None,
              "events": False, "duration": None,
              "exponent": 1.0}


def _refuse_ball_flags(args, why: str) -> None:
    """A scene file sets the ball's geometry, law, step, start values and targets itself:
    say so rather than ignore the flags given."""
    given = ["--" + n.replace("_", "-") for n in BALL_FLAGS if getattr(args, n) is not None]
    if given:
        raise CLIError(f"{' '.join(given)} set the built-in ball's fit; {why} takes them from "
                       "the scene file (edit its values, targets or [fit] table)")


def _refuse_data_flags(args) -> None:
    """--data REC.csv (no scene file) fits k and c with Levenberg-Marquardt from the record's
    own start: say so rather than ignore the flags it does not read."""
    given = [f for f, on in (("--drop", args.drop is not None),
                             ("--settle-tol", args.settle_tol is not None),
                             ("--method", args.method != "lm"),
                             ("--events", args.events is not None),
                             ("--duration", args.duration is not None),
                             ("--lr", args.lr != DEFAULT_LR)) if on]
    if given:
        raise CLIError(f"--data {args.data[0]} does not read {' '.join(given)}: a t,z record "
                       "is fitted by Levenberg-Marquardt from its own start height (it reads "
                       "--radius, --mass, --law, --exponent, --dt, --k0, --c0 and --maxiter); drop them")


def _run(args) -> int:
    if args.maxiter is not None and args.maxiter < 1:
        raise CLIError("--maxiter must be a positive integer")
    _check_plot(args)
    if args.scene is not None:
        _refuse_ball_flags(args, f"a fit of {args.scene}")
    elif args.data:
        _refuse_data_flags(args)
    for name, default in BALL_FLAGS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    if args.exponent != 1.0 and not _takes_exponent(args.law):
        raise CLIError(f"--exponent sets Hunt-Crossley's exponent: give --law hunt_crossley "
                       f"with it (got --law {args.law})")
    if args.exponent < 1.0:
        raise CLIError(f"--exponent must be >= 1 (Hertz: 1.5), got {args.exponent:g}")
    from ..errors import check_starts_keep    # before anything is read or compiled
    check_starts_keep(args.starts, args.keep, ("--starts", "--keep"))
    if args.fresh and not args.out:
        raise CLIError("--fresh restarts a fit that --out keeps the progress of: give it with "
                       "SCENE.toml --data FILES... --out FITTED.toml")
    in_file = _records_in_file(args.scene) if args.scene is not None and not args.data else None
    if in_file == "height" and args.out:
        raise CLIError(f"--out writes the fitted scene of a fit to position records (x, y, z "
                       f"columns); {args.scene} names t,z height records, which the ball's "
                       "trajectory fit reads and prints k and c for: drop --out, or give the "
                       "records x, y, z columns")
    if args.scene is not None and (args.data or in_file == "positions"):
        return _run_records(args)
    if (args.out or args.horizon or args.starts or args.keep != 1
            or args.flight_frames is not None or args.first_state is not None
            or args.loss != "l2" or args.no_step_check):
        opts = ("--out, --horizon, --starts, --keep, --flight-frames, --first-state, "
                "--no-step-check and --loss are options of fits to position records (diffpen fit SCENE.toml "
                "--data FILES... with x, y, z columns)")
        if args.scene is None:
            raise CLIError(opts + "; the built-in ball takes none of them")
        raise CLIError(f"{opts}; {args.scene} is fitted to its [fit] targets or a t,z record, "
                       "a fit that prints the fitted values: drop those options (and copy the "
                       "values into the file to keep them)")
    if args.scene is None and args.method == "lm" and args.lr != DEFAULT_LR:
        # it was accepted and unused
        raise CLIError("--lr is the learning rate of the optax optimisers (--method adam or "
                       "sgd); Levenberg-Marquardt (--method lm, the default) does not read it")
    if args.data and len(args.data) > 1:
        raise CLIError("without a scene file --data reads one t,z record of the ball; give "
                       "SCENE.toml to fit several records")
    if args.data:
        args.data = args.data[0]
    if args.scene is not None:
        if args.plot:       # refused before fitting (it was a note after it, and no file)
            raise CLIError("--plot draws fits of the built-in ball (targets or --data t,z); "
                           f"{args.scene}'s fit prints its fitted values (a scene file fitted "
                           "to position records is drawn by diffpen evaluate FITTED.toml "
                           "--data FILES... --plot DIR)")
        from .. import scenefile
        setup_jax()
        return _report(args, *scenefile.fit_file(args.scene, progress=None if not args.json
                                                 else False, method=args.method,
                                                 lr=args.lr, maxiter=args.maxiter))
    if args.data:
        return _run_data(args)
    if not args.drop > args.radius:
        raise CLIError(f"--drop {args.drop} m must exceed --radius {args.radius} m (the ball "
                       "would start in contact)")
    setup_jax()
    import optax

    from ..bounce import fit_bounce
    from ..scenes import ball_scene
    targets = _targets(args)
    scene = ball_scene(radius=args.radius, mass=args.mass, height=args.drop)
    dt = args.dt or 1e-3
    method, opt = "lm", None
    if args.method != "lm":
        method = "optax"
        opt = (optax.adam(args.lr) if args.method == "adam" else optax.sgd(args.lr))
    t0 = time.perf_counter()
    law = _law(args)
    res = fit_bounce(scene, targets, dt=dt, law=law, settle_tol=args.settle_tol,
                     k0=args.k0, c0=args.c0, method=method, optimizer=opt,
                     maxiter=args.maxiter, progress=False if args.json else None,
                     duration=args.duration)
    seconds = time.perf_counter() - t0
    from diffpen.checks import one_contact_per_body
    centred = (", event-exact steps" if args.events else ", damping at the step's centre"
               if one_contact_per_body(scene) else "")
    desc = (f"ball r={args.radius:g} m, m={args.mass:g} kg, centre dropped from "
            f"z={args.drop:g} m onto the plane z=0 (dt={dt:g} s, {_law_label(args)}{centred}, "
            f"settling band {args.settle_tol * 1e3:g} mm)")
    k = res.params.contact["default"].k
    c = res.params.contact["default"].c
    zeta = damping_ratio_or_none(_law(args), k, c, args.mass)
    out = {"scene": desc, "k": float(k), "c": float(c), "targets": res.targets,
           "achieved": res.achieved, "rel_error": res.rel_error, "reached": res.reached,
           "iterations": res.iterations, "evaluations": res.evaluations, "seconds": seconds,
           "message": res.message,
           "notes": res.notes, "dt": dt, "law": args.law, "exponent": args.exponent,
           "events": bool(args.events), "zeta": zeta}
    return _drawn(args, lambda: _plot_targets(args, scene, res, dt),
                  lambda: _print(args, out))


def _law(args):
    """The contact law of the built-in ball's fits: the ``--law`` name, or where ``--events``
    or ``--exponent`` asks for another record, that record (with ``--exponent`` alone the
    centred one, which the name resolves to on the ball's one contact:
    ``diffpen.checks.compile_arguments``)."""
    import diffpen as dp
    if args.events or args.exponent != 1.0:
        return dp.laws.get(args.law, args.exponent, centred=not args.events,
                           events=bool(args.events))
    return args.law


def _takes_exponent(name: str) -> bool:
    """Whether the contact law ``name`` is built for a given exponent (its record says so:
    ``ContactLaw.takes_exponent``)."""
    import diffpen as dp
    return dp.laws.get(name).takes_exponent


def _law_label(args) -> str:
    """``"linear law"``, ``"hunt_crossley law (n = 1.5)"``, ... for the output's scene line."""
    return f"{args.law} law" + (f" (n = {args.exponent:g})" if _takes_exponent(args.law)
                                else "")


def damping_ratio_or_none(law, k, c, mass) -> float | None:
    """The damping ratio ``c / (2 sqrt(k m))`` (dimensionless) of a ball of ``mass`` (kg) on
    contact stiffness ``k`` (N/m) and damping ``c`` (N s/m), or None for a law whose force is
    not ``k d - c vn`` (Hunt-Crossley: k and c have other units and the ratio is not
    defined)."""
    import diffpen as dp
    rec = dp.laws.get(law or "linear")
    if rec.exponent != 1.0 or rec.damping_exponent != 0.0:
        return None
    # dp.physical.damping_ratio's formula on the fitted floats: its eager jax operations (a
    # check and a select) compiled seven more programs on every cold start of diffpen fit
    return float(c) / (2.0 * math.sqrt(float(k) * float(mass)))


def _report(args, out: dict, plot_fn=None) -> int:
    if args.plot and plot_fn is None:
        import sys
        sys.stderr.write("diffpen fit: note: --plot is drawn for the built-in ball and "
                         "--data fits only, not for scene files\n")
        return _print(args, out)
    return _drawn(args, plot_fn and (lambda: plot_fn(args.plot)), lambda: _print(args, out))


def _drawn(args, draw, report) -> int:
    """``draw()`` the --plot figure (when asked for), then ``report()`` the fit (its exit
    status). A figure that cannot be written (a full disk, a folder that passed the check
    but takes no file) is said after the fitted values, with exit status 2: it ended the
    command with a traceback before they were printed, and the fit was lost."""
    error = None
    if args.plot and draw is not None:
        try:
            draw()
        except (OSError, RuntimeError, ValueError) as exc:
            error = (f"--plot {args.plot} could not be written ({type(exc).__name__}: {exc}); "
                     "the fitted values are printed above")
    status = report()
    if error is None:
        return status
    import sys
    sys.stderr.write(f"diffpen fit: error: {error}\n")
    return 2


def _print(args, out: dict) -> int:
    if args.json:
        dump_json(out)
        return 0 if out.get("reached", True) else 1
    print(f"diffpen fit: {out['scene']}")
    if "targets" in out:            # metric values, or a record's name (a str: no :g)
        print("targets:   " + "   ".join(
            f"{n} = {v if isinstance(v, str) else fmt(v, UNITS.get(n, ''))}"
            for n, v in out["targets"].items()))
    kse = out.get("k_stderr")
    ku, cu = law_units(out.get("law"), out.get("exponent", 1.0))
    if kse is not None:
        print(f"fitted:    k = {out['k']:.6g} +- {kse:.2g} {ku}   c = {out['c']:.6g} +- "
              f"{out['c_stderr']:.2g} {cu}   (standard errors)")
    else:
        print(f"fitted:    k = {out['k']:.6g} {ku}   c = {out['c']:.6g} {cu}"
              + (f"   (damping ratio {out['zeta']:.4g})" if out.get("zeta") is not None
                 else ""))
    if "achieved" in out:
        parts = []
        for n, v in out["achieved"].items():
            err = out.get("rel_error", {}).get(n)
            # an infinite error is a metric that is no result (a settling time at the
            # rollout's end): "inf% off" read as a number
            note = ("" if err is None else f" ({err * 100:.2g}% off)" if math.isfinite(err)
                    else " (not settled within the rollout: its end)" if "settl" in n
                    else " (no such event in the rollout)")
            parts.append(f"{n} = {fmt(v, UNITS.get(n, ''), 6)}{note}")
        print("achieved:  " + "   ".join(parts))
    for key, label in (("rms", "residual rms (m)"), ("noise", "record noise (m)"),
                       ("first_guess", "first guess (k, c)")):
        if key in out:
            print(f"{label}: {fmt(out[key])}")
    for note in out.get("notes", []):
        print(f"note:      {note}")
    status = "targets reached" if out.get("reached", True) else "TARGETS NOT REACHED"
    if out.get("message") == status:
        out = dict(out, message="within tolerance")
    ev = (f" after the start search ({out['evaluations']} simulations with gradients in all)"
          if "evaluations" in out else "")
    print(f"status:    {status} -- {out.get('message', '')}; {out['iterations']} LM/optimiser "
          f"iterations{ev}; {out['seconds']:.2f} s wall time")
    return 0 if out.get("reached", True) else 1


def _plot_targets(args, scene, res, dt) -> None:
    import jax.numpy as jnp
    import numpy as np

    import diffpen as dp

    from ..metrics import resting_height
    from ..plots import fit_figure
    sim = dp.compile(scene, dt, law=_law(args))
    dur = res.targets.get("settling_time", 3.0)
    steps = int(math.ceil(1.3 * dur / dt))
    s0 = sim.init_state()
    traj = sim.rollout(res.params, steps, s0)
    t = np.concatenate([[0.0], np.asarray(traj.time)])
    z = np.concatenate([[args.drop], np.asarray(traj.position[:, 0, 2])])
    k = float(res.params.contact["default"].k)
    rest = float(resting_height(jnp.asarray(k), args.mass, 9.81, args.radius, law=args.law,
                                exponent=args.exponent, width=sim.smoothing))
    ku, cu = law_units(args.law, args.exponent)
    fit_figure(args.plot, t, z, targets=res.targets, achieved=res.achieved,
               loss_history=(res.eval_history if res.eval_history is not None
                             and len(res.eval_history) else res.loss_history),
               evaluations=res.eval_history is not None and len(res.eval_history) > 0,
               radius=args.radius, settle_tol=args.settle_tol,
               rest=rest, title=f"k={k:.4g} {ku}, "
                                f"c={float(res.params.contact['default'].c):.4g} {cu}")


def _run_data(args) -> int:
    ku, cu = law_units(args.law, args.exponent)
    if any(v is not None for v in (args.target_apex, args.target_settle, args.target_contact,
                                   args.target_decay)):
        raise CLIError("--data fits a measured trajectory; drop the --target-* flags")
    from ..errors import FitError
    from ..problem import RESIDUAL_FACTOR, residual_reached
    from ..sysid import fit_trajectory, load_csv
    t, z = load_csv(args.data)           # validated before anything is compiled
    setup_jax()
    from diffpen import SceneError
    try:
        res = fit_trajectory(t, z, radius=args.radius, mass=args.mass, law=_law(args),
                             dt=args.dt, k0=args.k0, c0=args.c0, maxiter=args.maxiter or 15,
                             progress=False if args.json else None)
    except (FitError, SceneError) as exc:    # a valid file the ball model cannot explain
        msg = f"the model does NOT explain {args.data}: {exc}"
        if args.json:
            dump_json({"reached": False, "message": msg, "data": args.data})
        else:
            print(f"status:    RECORD NOT EXPLAINED -- {msg}")
        return 1
    out = {"scene": f"ball r={args.radius:g} m, m={args.mass:g} kg fitted to {args.data} "
                    f"({len(t)} samples, {t[-1] - t[0]:.3g} s; dt={res.dt:.3g} s, "
                    f"{_law_label(args)})",
           "k": res.k, "c": res.c,
           "zeta": damping_ratio_or_none(_law(args), res.k, res.c, args.mass),
           "k_stderr": res.k_stderr, "c_stderr": res.c_stderr,
           "k_lower_bound": res.k_lower_bound, "targets": {"data": args.data}, "achieved": {"rms_residual": res.rms},
           "first_guess": list(res.first_guess), "rms": res.rms, "noise": res.noise,
           "dt": res.dt, "iterations": res.iterations, "seconds": res.seconds,
           "message": res.message, "notes": res.notes, "law": args.law,
           "exponent": args.exponent, "reached": residual_reached(res.rms, res.noise, res.dt_error),
           "residual_limit": RESIDUAL_FACTOR * math.hypot(res.noise, res.dt_error)}
    if not out["reached"]:
        out["message"] = (f"the model does NOT explain the record: residual rms "
                          f"{res.rms:.3g} m > {RESIDUAL_FACTOR:g} x the expected "
                          f"{math.hypot(res.noise, res.dt_error):.3g} m (noise and time step). "
                          "Check the units (t in s, z in m), --radius and --mass, and that "
                          "the record is a ball bouncing on the ground")
    def draw():
        from ..plots import trajectory_fit_figure
        trajectory_fit_figure(args.plot, t, z, res.z_fit, res.history,
                              title=(f"k={res.k:.5g}+-{res.k_stderr:.2g} {ku}, "
                                     if res.k_lower_bound is None else
                                     f"k={res.k:.5g} {ku} (held, lower bound), ")
                                    + f"c={res.c:.5g}+-{res.c_stderr:.2g} {cu}")
    return _drawn(args, draw, lambda: _print_trajectory(args, out, res, ku, cu))


def _print_trajectory(args, out, res, ku, cu) -> int:
    """The ball trajectory fit's summary (or JSON), its exit status."""
    if args.json:
        dump_json(out)
        return 0 if out["reached"] else 1
    print(f"diffpen fit: {out['scene']}")
    if res.k_lower_bound is None:
        print(f"fitted:    k = {res.k:.6g} +- {res.k_stderr:.2g} {ku}   c = {res.c:.6g} +- "
              f"{res.c_stderr:.2g} {cu}   (standard errors, Gauss-Newton)")
    else:
        print(f"fitted:    k = {res.k:.6g} {ku} HELD (a lower bound: the record does not "
              f"resolve the contact time)   c = {res.c:.6g} +- {res.c_stderr:.2g} {cu}   "
              "(standard error, Gauss-Newton)")
    if out["zeta"] is not None:
        print(f"damping ratio {out['zeta']:.4g}")
    print(f"first guess from the record's events: k = {res.first_guess[0]:.5g} {ku}, "
          f"c = {res.first_guess[1]:.5g} {cu}")
    print(f"residual rms {res.rms * 1e3:.3g} mm against record noise {res.noise * 1e3:.3g} mm")
    for note in res.notes:
        print(f"note:      {note}")
    status = ("record explained" if out["reached"] else "RECORD NOT EXPLAINED -- "
              + out["message"])
    print(f"status:    {status}; LM: {res.message}; {res.iterations} LM iterations over "
          f"{len(res.horizons)} horizons, {res.seconds:.2f} s wall time")
    return 0 if out["reached"] else 1


def _records_in_file(path: str) -> str | None:
    """What scene file ``path`` names in ``[fit] data``: None (nothing), ``"height"`` (t,z
    records of a bouncing ball: the ball's trajectory fit reads them) or ``"positions"``
    (records with position columns, of any body: the record fit reads them, as --data
    records, with or without --out; a ball's x,y,z records went to the trajectory fit
    without --out and to the record fit with it, two fits of one file)."""
    from ..scenefile import load_scene_file
    sf = load_scene_file(path)
    if sf.spec is None or not sf.spec.data:
        return None
    if sf.setup.metrics is not None and not any(_position_record(p) for p in sf.spec.data):
        return "height"
    return "positions"


def _position_record(path: str) -> bool:
    """Whether the record ``path`` has position columns (``x``, or ``NAME.x``) in its header
    (:func:`tuning.records.header_columns`: blank and comment lines before it skipped, as the
    reader skips them); a t,z height record has none, and one that cannot be read counts as
    none (the ball's reader then says why, naming its line)."""
    from ..records import header_columns
    return any(c == "x" or c.endswith(".x") for c in header_columns(path) or [])


def _run_records(args) -> int:
    """SCENE.toml --data FILES...: the scene file's [fit] params fitted to all records."""
    if args.method != "lm":
        raise CLIError("fits to records use Levenberg-Marquardt (--method lm)")
    if args.lr != DEFAULT_LR:
        raise CLIError("--lr is the learning rate of the optax optimisers; fits to records use "
                       "Levenberg-Marquardt, which does not read it")
    if args.plot:
        raise CLIError("--plot draws ball fits; for records run diffpen evaluate FITTED.toml "
                       "--data FILES... --plot DIR on the scene written by --out")
    setup_jax()
    from ..scene_fit import fit_files
    horizons = tuple(sorted(args.horizon)) + (None,) if args.horizon else None
    try:
        out = fit_files(args.scene, args.data, out=args.out, estimate=args.first_state,
                        loss=args.loss, horizons=horizons, maxiter=args.maxiter,
                        starts=args.starts, keep=args.keep, max_frames=args.flight_frames,
                        progress=False if args.json else None, fresh=args.fresh,
                        keep_progress=True, step_check=False if args.no_step_check else None)
    except OSError as exc:          # e.g. a full disk while saving the fit's progress
        where = f" ({exc.filename})" if exc.filename else ""
        raise CLIError(f"{exc.strerror or exc}{where}"
                       + ("; the progress saved before it is kept: rerun the same command "
                          "(without --fresh) to resume" if args.out else "")) from None
    status = print_record_fit(args, out)
    if out["out"] is not None:
        # the fitted scene and the summary are out: the progress is no longer needed (removed
        # only now, so that a Ctrl-C before the summary still resumes at once)
        from ..fit_checkpoint import checkpoint_path
        try:
            os.unlink(checkpoint_path(out["out"]))
        except FileNotFoundError:
            pass
    return status
