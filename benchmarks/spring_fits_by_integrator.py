"""Spring k and c fitted from records by each integrator: the README's figures for the box hung
on two anchored springs and the rope (*Fitting measured motion*, "Other bodies, same
command").

    python benchmarks/spring_fits_by_integrator.py

Each record is made by rk4 at a quarter of the fit's 1 ms step, 5 ms frames, 0.6 s, with
noise (rope 0.1 mm, box 0.2 mm; seeds 1-3), by the tests' scene files
(tests/record_scenes.py); each fit is `diffpen fit SCENE.toml --data REC.csv --first-state
refine` with the scene file's `integrator` set to semi-implicit Euler, then to verlet. Printed:
the fitted k and c against the truth, in %. About 15 s.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import pathlib
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from record_scenes import BOX, ROPE, record_file  # noqa: E402
from tuning import scene_fit  # noqa: E402
from tuning.cli import main  # noqa: E402

CASES = {
    "rope": (ROPE.format(k=200.0, c=0.3),
             {"springs.rope.stretch.k": 300.0, "springs.rope.stretch.c": 0.5},
             ["rope[1]", "rope[2]", "rope[3]"], 1e-4),
    "box": (BOX.format(k=250.0, c=1.0), {"springs.hang.k": 400.0, "springs.hang.c": 2.0},
            ["box"], 2e-4),
}


def fit(folder: pathlib.Path, name: str, integrator: str, seed: int) -> dict:
    """``{leaf: error in %}`` of one refined fit."""
    text, truth, bodies, noise = CASES[name]
    text = text.replace("dt = 1e-3", f'dt = 1e-3\nintegrator = "{integrator}"')
    scene, rec = record_file(folder, text, truth, bodies, name, integrator="rk4", dt=2.5e-4,
                             every=5e-3, duration=0.6, noise=noise, seed=seed)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        main(["fit", scene, "--data", rec, "--json", "--first-state", "refine"])
    out = json.loads(buf.getvalue())
    return {n.split(".")[-1]: round(100.0 * (out["fitted"][n] / v - 1.0), 2)
            for n, v in truth.items()}


def main_() -> None:
    scene_fit.STEP_CHECK = False            # the fitted values only
    with tempfile.TemporaryDirectory() as tmp:
        for name in CASES:
            for integrator in ("semi_implicit_euler", "verlet"):
                for seed in (1, 2, 3):
                    folder = pathlib.Path(tmp) / f"{name}-{integrator}-{seed}"
                    folder.mkdir()
                    print(f"{name:4} {integrator:19} seed {seed}: error % "
                          f"{fit(folder, name, integrator, seed)}", flush=True)


if __name__ == "__main__":
    main_()
