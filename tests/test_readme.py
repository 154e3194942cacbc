"""The README's quick start runs as written."""
import pathlib
import re

import numpy as np

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_quick_start_runs_as_written():
    text = README.read_text()
    block = re.search(r"## Quick start\s+```python\n(.*?)```", text, re.S).group(1)
    env: dict = {}
    import warnings

    import diffpen as dp
    with warnings.catch_warnings():
        warnings.simplefilter("error", dp.PerformanceWarning)     # it shows the fast form
        exec(compile(block, "README quick start", "exec"), env)
    assert env["traj"].position.shape == (2000, 1, 3)
    assert env["traj"].time.shape == (2000,)
    z = np.asarray(env["z"])
    assert z.shape == (2000,) and z.max() <= 1.0 and z.min() > 0.0   # bounces off the ground
    assert np.isfinite(float(env["dz_dk"]))
    z_end = np.asarray(env["z_end"])
    assert z_end.shape == (1024,)
    sim = env["sim"]
    one = sim.rollout(sim.params(k=float(env["ks"][0]), c=20.0), steps=2000)
    np.testing.assert_allclose(z_end[0], one.position[-1, 0, 2], rtol=1e-5)


def test_sharding_snippet_runs_as_written():
    text = README.read_text()
    quick = re.search(r"## Quick start\s+```python\n(.*?)```", text, re.S).group(1)
    snippet = re.search(r"## Beyond one machine.*?```python\n(.*?)```", text, re.S).group(1)
    env: dict = {}
    exec(compile(quick.split("dz_dk")[0], "README quick start", "exec"), env)
    exec(compile(snippet, "README sharding", "exec"), env)
    heights = np.asarray(env["heights"])
    assert heights.shape == (64,) and np.all(np.isfinite(heights))


def test_gradient_snippet_runs_as_written():
    import jax
    text = README.read_text()
    quick = re.search(r"## Quick start\s+```python\n(.*?)```", text, re.S).group(1)
    snippet = re.search(r"\*\*Gradients: forward or reverse\.\*\*.*?```python\n(.*?)```",
                        text, re.S).group(1)
    env: dict = {}
    exec(compile(quick.split("dz_dk")[0], "README quick start", "exec"), env)
    exec(compile(snippet, "README gradients", "exec"), env)
    ref_value, ref_grad = jax.value_and_grad(env["loss"], (0, 1))(1e4, 20.0)
    np.testing.assert_allclose(float(env["value"]), float(ref_value), rtol=1e-12)
    np.testing.assert_allclose([float(env["dk"]), float(env["dc"])],
                               [float(g) for g in ref_grad], rtol=1e-6)


def test_batched_fit_snippet_runs_as_written(capsys):
    text = README.read_text()
    snippet = re.search(r"### Batched fits.*?```python\n(.*?)```", text, re.S).group(1)
    env: dict = {}
    exec(compile(snippet, "README batched fits", "exec"), env)
    res = env["res"]
    assert len(res) == 3 and bool(np.all(res.converged))
    np.testing.assert_allclose(res.achieved["apex_heights"][:, 0], env["apexes"], rtol=2e-3)
    assert "target 0.50 m" in capsys.readouterr().out


def test_readme_scene_file_runs(tmp_path):
    """The README's scene file with every kind of table was unstable at its own dt (a rope
    node of 20 g on a 2e4 N/m board, the box at 1 ms): it now loads, compiles and steps."""
    import os
    import shutil

    import numpy as np

    from tuning.scenefile import load_scene_file
    root = os.path.join(os.path.dirname(__file__), "..")
    text = open(os.path.join(root, "README.md")).read()
    start = text.index("```toml\ndt = 5e-4")
    block = text[start + len("```toml\n"):text.index("```", start + 8)]
    (tmp_path / "scene.toml").write_text(block)
    for name in ("toss_003.csv", "toss_006.csv"):
        shutil.copy(os.path.join(root, "examples", "data", "cube-toss", name), tmp_path)
    sf = load_scene_file(str(tmp_path / "scene.toml"))
    sim = sf.compile()
    traj = sim.rollout(sf.params(sim), 100, save_every=100)
    assert np.isfinite(np.asarray(traj.position)).all()
