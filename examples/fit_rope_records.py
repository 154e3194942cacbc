"""Fit a rope's spring stiffness and damping to marker records, the way the cube tosses are fitted.

A 6-node rope hangs from one end and swings. Four records of it (three swings fitted, one
held out) are made here by a more accurate model than the fit uses (classical Runge-Kutta at
a quarter of the step) with 0.2 mm of noise on its five free nodes, written as CSV, and
fitted jointly through the same function as ``diffpen fit SCENE.toml --data FILES...``
(``tuning.scene_fit.fit_files``: each record starts from its own first state, Levenberg-
Marquardt over a growing horizon). The held-out swing is then evaluated with the fitted scene
(``diffpen evaluate``). Measured records work the same way: name the observed bodies in the
scene file and give the columns ``NAME.x, NAME.y, NAME.z`` (``rope[3].x`` for a builder's
node).

With ``--markers`` the records hold positions only (no velocity columns, as marker systems
record), and the fit refines each record's start state with the parameters
(``--first-state refine``, :mod:`tuning.start_refine`).

Run:  python examples/fit_rope_records.py [--out DIR] [--markers]
"""
from __future__ import annotations

import argparse
import os
import tempfile

import jax

# record fits in float64, as diffpen fit runs them (in float32 the library warns that record
# fits are less reliable)
jax.config.update("jax_enable_x64", True)

from tuning import trajfit as tf  # noqa: E402
from tuning.scene_fit import fit_files  # noqa: E402
from tuning.synthetic import synthetic_record  # noqa: E402
from tuning.evaluate import evaluate_files  # noqa: E402
from tuning.records import write_record  # noqa: E402
from tuning.scenefile import load_scene_file  # noqa: E402

SCENE = """
description = "a rope of 6 nodes hanging from one end"
dt = 1e-3
[[ropes]]
n = 6
start = [0.0, 0.0, 1.0]
end = [0.5, 0.0, 1.0]
mass = 0.3
k = 150.0                       # N/m, the fit's start value (the truth is 400)
c = 0.1                         # N s/m (the truth is 0.6)
pinned = [0]
velocity = [0.0, {vy}, 0.0]
[fit]
params = ["springs.rope.stretch.k", "springs.rope.stretch.c"]
observe = ["rope[1]", "rope[2]", "rope[3]", "rope[4]", "rope[5]"]
"""
TRUTH = {"springs.rope.stretch.k": 400.0, "springs.rope.stretch.c": 0.6}
SWINGS = (0.0, 0.5, -1.0, 0.8)           # sideways start speeds, m/s; the last is held out


def make_records(folder: str, velocities: bool = True) -> list:
    """One record per swing: rk4 at 0.25 ms, 5 ms frames, 0.2 mm noise, 1 s (``velocities``:
    with velocity columns)."""
    paths = []
    for i, vy in enumerate(SWINGS):
        path = os.path.join(folder, f"swing{i}.toml")
        with open(path, "w") as fh:
            fh.write(SCENE.format(vy=vy))
        sf = load_scene_file(path)
        sim = sf.compile(integrator="rk4", dt=2.5e-4)
        params = tf.with_leaves(sf.params(sim), TRUTH)
        bodies = {name: sf.names[name] for name in sf.spec.observe}
        rec = synthetic_record(sim, params, 1.0, 5e-3, bodies, noise=2e-4, seed=i,
                               velocities=velocities)
        csv = os.path.join(folder, f"swing{i}.csv")
        write_record(csv, rec)
        paths.append(csv)
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--out", default=None, help="folder for the scene, records and fitted "
                    "scene (default: a temporary folder)")
    ap.add_argument("--markers", action="store_true", help="records of positions only, "
                    "fitted with the start states refined (--first-state refine)")
    args = ap.parse_args(argv)
    folder = args.out or tempfile.mkdtemp(prefix="rope-records-")
    os.makedirs(folder, exist_ok=True)
    records = make_records(folder, velocities=not args.markers)
    scene = os.path.join(folder, "rope.toml")          # the scene the fit starts from
    with open(scene, "w") as fh:
        fh.write(SCENE.format(vy=0.0))
    fitted = os.path.join(folder, "rope_fitted.toml")
    out = fit_files(scene, records[:-1], out=fitted,
                    estimate="refine" if args.markers else None)
    print(f"fitted {out['records']} records in {out['fit_seconds']:.1f} s "
          f"({out['iterations']} LM iterations, horizons {out['horizons']}):")
    for name, v in out["fitted"].items():
        print(f"  {name} = {v:.5g} +- {out['stderr'][name]:.2g}   (truth {TRUTH[name]:g}, "
              f"{100 * (v / TRUTH[name] - 1):+.2f}%)")
    pe = out["after"]["position_error_pct"]["mean"]
    print(f"  position error on the fitted records: {pe:.3f}% of the observed nodes' extent")
    held = evaluate_files(fitted, records[-1:])
    print(f"held-out swing: {held['position_error_pct']['mean']:.3f}% "
          f"(start values: {evaluate_files(scene, records[-1:])['position_error_pct']['mean']:.3f}%)")
    print(f"files in {folder}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
