"""TOML scene files: every bad file is refused with the file, the key and the fix before anything
is compiled (regressions of issue 13's bad inputs); the CLI's handling of scene files with
records."""
import math
import os
import shutil

import numpy as np
import pytest

import diffpen as dp
from tuning.cli import main
from tuning.scenefile import SceneFileError, is_scene_path, load_scene_file, param_leaves


# --------------------------------------------------------------------------- bad input
BALL = """
[materials.rubber]
k = 1e4
c = 10.0
[[spheres]]
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 1.0]
material = "rubber"
[[planes]]
material = "rubber"
"""
FIT = "[fit]\nparams = [\"contact.rubber.k\"]\n[fit.targets]\napex_heights = [0.3]\n"


def _spheres(n):
    rows = "".join(f"{{radius = 0.01, mass = 0.1, position = [{i % 100 * 0.03:.2f}, "
                   f"{i // 100 * 0.03:.2f}, 1.0]}},\n" for i in range(n))
    return f"spheres = [\n{rows}]\n"


BAD = [
    # types without coercion
    (BALL.replace("radius = 0.1", 'radius = "0.1"'),
     r"spheres\[0\]\.radius must be a number \(m\), got a string '0.1'; write it without "
     r"quotes, e\.g\. radius = 0\.1"),
    # an array's element: the fix quotes the element (it said "position = 1")
    (BALL.replace("position = [0.0, 0.0, 1.0]", 'position = [0.0, 0.0, "1"]'),
     r"spheres\[0\]\.position\[2\] must be a number, got a string '1'; write it without "
     r"quotes: 1\."),
    (BALL.replace("mass = 1.0", "mass = true"),
     r"spheres\[0\]\.mass must be a number \(kg\), got a boolean True"),
    (BALL.replace("[[spheres]]", "[spheres]"),
     r"spheres must be an array of tables: write each entry as \[\[spheres\]\]"),
    ("materials = 5\n" + BALL.split("[[spheres]]")[1].join(["[[spheres]]", ""]),
     r"materials must be a table, got an integer 5"),
    (BALL.replace("k = 1e4", 'k = "stiff"'),
     r"materials\.rubber\.k must be a number \(N/m\), got a string 'stiff'"),
    (BALL + FIT.replace("apex_heights = [0.3]", "").replace("[fit.targets]",
                                                              'targets = "lots"'),
     r"fit\.targets must be a table, got a string 'lots'"),
    (BALL + FIT + "", None),
    (BALL + FIT.replace("[fit]", "[fit]\nsettle_tol = -1"), r"fit\.settle_tol must be > 0"),
    (BALL + FIT.replace("[fit]", '[fit]\nbody = "zero"'),
     r"fit\.body names body 'zero', which the scene does not have"),
    (BALL + '[fit]\ndata = 42\n', r"fit\.data must be a file name or an array of file names"),
    (BALL + FIT.replace("[fit]", '[fit]\nweights = "heavy"'),
     r"fit\.weights must be a table, got a string 'heavy'"),
    (BALL + FIT.replace("[fit]", '[fit]\nmaxiter = "many"'),
     r"fit\.maxiter must be an integer, got a string 'many'"),
    (BALL + FIT.replace("[fit]", "[fit]\nmaxiter = 2.0"), r"fit\.maxiter must be an integer"),
    (BALL + FIT.replace("[fit]", '[fit]\nfirst_state = "guess"'),
     r"fit\.first_state must be one of 'record', 'fit'"),
    (BALL + FIT.replace("[fit]", "[fit]\nflight_frames = 2"),
     r"fit\.flight_frames must be an integer >= 3"),
    (BALL + FIT.replace("[fit]", "[fit]\nhorizon = [0.5, -1]"), r"fit\.horizon\[1\] must be > 0"),
    # settings the fit does not read were accepted and ignored (and params = [] fitted the
    # contact's k and c)
    (BALL + FIT.replace("[fit]", "[fit]\nlr = 0.1"),
     r"fit\.lr is the learning rate of the optax optimisers .*method = \"lm\" does not"),
    (BALL + FIT.replace("[fit]", "[fit]\nhorizon = [0.5]"),
     r"fit\.horizon is read by fits to motion records"),
    (BALL + FIT.replace("[fit]", '[fit]\nfirst_state = "record"'),
     r"fit\.first_state is read by fits to motion records"),
    (BALL + FIT.replace('params = ["contact.rubber.k"]', "params = []"),
     r"fit\.params is empty: name the leaves to fit"),
    ("duration = 1e9\n" + BALL,
     r"duration = 1e\+09 s at dt = 0\.001 s is 1e\+12 steps: a rollout saving every step "
     r"would hold about .* TiB and run for roughly .* days.*max_steps=.*the diffpen "
     r"commands keep the limit"),
    ("dt = 0\n" + BALL, r"dt must be > 0 \(s\), got 0"),
    (BALL + "[[springs]]\na = 0\nb = 7\nk = 1.0\n",
     r"springs\[0\]\.b is body 7, but the scene has 1 bodies"),
    (BALL + "[[springs]]\na = 0\nb = [0, 0]\nk = 1.0\n",
     r"springs\[0\]\.b must be 3 numbers \[x, y, z\]"),
    (BALL.replace('material = "rubber"\n[[planes]]', 'material = "steel"\n[[planes]]'),
     r"spheres\[0\]\.material names material 'steel', which is not declared; add a "
     r"\[materials\.steel\] table"),
    (BALL.replace("mass = 1.0", "mass = 1.0\nangular_velocity = [0, 0, 1]"),
     r"unknown key\(s\) \['angular_velocity'\] in \[spheres\[0\]\]"),
    (BALL + "[[boxes]]\nhalf_extents = [0.1, 0.1, 0.1]\nmass = 1.0\nposition = [2, 0, 1]\n"
     "orientation = [0, 0, 0, 0]\n", r"boxes\[0\]\.orientation is the zero quaternion"),
    (BALL + "[[boxes]]\nhalf_extents = [0.1, 0.1]\nmass = 1.0\nposition = [2, 0, 1]\n",
     r"boxes\[0\]\.half_extents must be 3 numbers"),
    (BALL + "[[ropes]]\nn = 1\nstart = [0, 1, 1]\nend = [1, 1, 1]\nmass = 0.1\nk = 10.0\n",
     r"ropes\[0\]\.n must be an integer >= 2, got 1"),
    (BALL + "[[cloths]]\nnx = 3\nny = 3\nspacing = 0.1\nmass = 0.1\npinned = [[0, 7]]\n",
     r"cloths\[0\] cloth pinned: pinned node \(0, 7\) is outside the grid"),
    (BALL + "[[ropes]]\nn = 3\nstart = [0, 1, 1]\nend = [1, 1, 1]\nmass = 0.1\nk = 10.0\n"
     "[[springs]]\na = \"rope[3]\"\nb = 0\nk = 1.0\n",
     r"springs\[0\]\.a 'rope\[3\]' is outside 'rope', whose nodes have shape \(3,\)"),
    (BALL + "[[spheres]]\nname = \"1st\"\nradius = 0.1\nmass = 1.0\nposition = [1, 0, 1]\n",
     r"spheres\[1\]\.name '1st' is not a valid name"),
    (BALL + FIT.replace("[fit]", '[fit]\nmethod = "newton"'),
     r"fit\.method must be one of 'lm', 'adam', 'sgd'"),
    (BALL + FIT.replace("apex_heights = [0.3]", "apex_heights = [-0.3]"),
     r"fit\.targets\.apex_heights\[0\] must be > 0"),
    (BALL + FIT + "[fit.bounds]\n\"contact.rubber.k\" = [0, 1e5]\n",
     r"fit\.bounds\.contact\.rubber\.k has lo = 0 <= 0 for a leaf fitted in log space"),
    (BALL + FIT + "[fit.bounds]\n\"contact.rubber.k\" = [1e5, 1e6]\n",
     r"does not contain the start value 10000"),
    (BALL + FIT + "[fit.bounds]\n\"contact.rubber.c\" = [1, 100]\n",
     r"bounds 'contact.rubber.c', which is not in \[fit\] params"),
    ('broadphase = { kind = "octree" }\n' + BALL,
     r"broadphase\.kind must be one of 'aabb', 'grid'"),
    # regression: grid bounds with lo >= hi passed the file and failed in compile, naming
    # neither the file nor the key
    ('broadphase = { kind = "grid", bounds = [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]] }\n' + BALL,
     r"broadphase\.bounds = \[\[1\.0, 1\.0, 1\.0\], \[0\.0, 0\.0, 0\.0\]\] has lo >= hi "
     r"on x, y, z: give \[\[x0, y0, z0\], \[x1, y1, z1\]\] \(m\) with x0 < x1"),
    ('broadphase = { kind = "grid", bounds = [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]] }\n' + BALL,
     r"broadphase\.bounds = .* has lo >= hi on z:"),
    ('law = "soft"\n' + BALL, r"law must be one of 'hunt_crossley', 'linear', 'no_tension'"),
    ("[[particles]]\nmass = 1.0\n", r"particles\[0\] is missing required key 'position'"),
    ("gravity = [0, 0, -9.81]\n", r"has no bodies"),
    (BALL + "[fit]\n[fit.targets]\napex_heights = [0.3]\n[fit.weights]\nsettling = 1.0\n",
     r"fit\.weights\.settling weights a target that is not given"),
    ("[[spheres]]\nradius = 0.1\nmass = 1.0\nposition = [0, 0, 1]\n[fit]\n",
     r"fit says nothing to fit: add a \[fit.targets\] table, data = \"record.csv\", or "
     r"params"),
    (BALL + FIT.replace("[fit]", '[fit]\ndata = "r.csv"'), r"fit has both \[fit.targets\] and data"),
    # regression: a body observed twice was kept twice (its residuals counted double)
    (BALL.replace("[[spheres]]", '[[spheres]]\nname = "ball"') + FIT.replace(
        "[fit]", '[fit]\nobserve = ["ball", "ball"]'),
     r"fit\.observe\[1\] names 'ball' a second time \(or another name of the same body\)"),
    # regression: tuning.fit's method name was refused without saying what a file takes
    (BALL + FIT.replace("[fit]", '[fit]\nmethod = "optax"'),
     r"fit\.method 'optax' is tuning\.fit's name .* \"adam\" or \"sgd\""),
    # regression: a typo of a plane's name was told to be an integer
    (BALL.replace("[[planes]]", '[[planes]]\nname = "ground"') + FIT.replace(
        "[fit]", '[fit]\nplane = "grnd"'),
     r"fit\.plane names plane 'grnd', which the scene does not have; named planes: "
     r"\['ground'\]"),
    # regression: linear-space bounds let a fit try a negative stiffness or damping
    (BALL + FIT + '[fit.space]\n"contact.rubber.k" = "linear"\n'
     '[fit.bounds]\n"contact.rubber.k" = [-1e5, 1e5]\n',
     r"fit\.bounds\.contact\.rubber\.k has lo = -100000 < 0, but 'contact\.rubber\.k' "
     r"cannot be negative"),
]


@pytest.mark.parametrize("text, words", [b for b in BAD if b[1] is not None])
def test_bad_scene_files_name_file_key_and_fix(tmp_path, text, words):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    with pytest.raises(SceneFileError, match=words) as exc:
        load_scene_file(str(p))
    assert str(exc.value).startswith(str(p))
    assert isinstance(exc.value, dp.SceneError) and isinstance(exc.value, ValueError)


def test_20000_spheres_need_a_broad_phase(tmp_path):
    p = tmp_path / "crowd.toml"
    p.write_text(_spheres(20000))
    with pytest.raises(SceneFileError, match=r"20,000 colliding spheres and 0 boxes: "
                                             r"199,990,000 contact pairs .* GiB .*broadphase = "
                                             r"\{ kind = \"grid\" \}.*the diffpen commands "
                                             r"keep the limit"):
        load_scene_file(str(p))
    # with a broad phase the same count passes the guard (tested on 200 to stay fast)
    p.write_text('broadphase = { kind = "grid", max_per_cell = 16 }\n' + _spheres(200))
    sf = load_scene_file(str(p), max_dense_pairs=1000)
    assert sf.scene.n_bodies == 200
    assert isinstance(sf.setup.compile_options["broadphase"], dp.broadphase.Grid)
    p.write_text(_spheres(200))
    with pytest.raises(SceneFileError, match="19,900 contact pairs") as e:
        load_scene_file(str(p), max_dense_pairs=1000)
    assert "0.0199 s to list them" in str(e.value)   # was "0 min", a cost of nothing


def test_grid_bounds_are_read(tmp_path):
    p = tmp_path / "grid.toml"
    p.write_text('broadphase = { kind = "grid", bounds = [[-1, -1, 0], [1, 1, 2.5]] }\n' + BALL)
    bp = load_scene_file(str(p)).setup.compile_options["broadphase"]
    assert bp.bounds == ((-1.0, -1.0, 0.0), (1.0, 1.0, 2.5))


def test_builder_node_counts_are_guarded_before_building(tmp_path):
    p = tmp_path / "huge.toml"
    p.write_text("[[cloths]]\nnx = 3000\nny = 3000\nspacing = 0.01\nmass = 1.0\n")
    with pytest.raises(SceneFileError, match=r"describes 9,000,000 bodies \(9,000,000 of them "
                                             r"builder nodes\); the limit is 200,000"):
        load_scene_file(str(p))


def test_binary_and_bom_files(tmp_path):
    p = tmp_path / "bin.toml"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    with pytest.raises(SceneFileError, match=r"bin.toml: is a binary file \(a zero byte at "
                                             r"offset 8\)"):
        load_scene_file(str(p))
    p.write_bytes(b"radius = \xff\xfe\n")
    with pytest.raises(SceneFileError, match=r"line 1: byte 0xff .* not UTF-8"):
        load_scene_file(str(p))
    p.write_bytes(b"\xef\xbb\xbf" + BALL.encode())
    assert load_scene_file(str(p)).scene.n_bodies == 1
    with pytest.raises(SceneFileError, match="is not valid TOML"):
        p.write_text("[[spheres]\n")
        load_scene_file(str(p))
    with pytest.raises(SceneFileError, match="cannot read"):
        load_scene_file(str(tmp_path / "missing.toml"))
    with pytest.raises(SceneFileError, match="is a directory"):
        load_scene_file(str(tmp_path))
    # regression: /dev/zero (size 0, no end) was read until the memory ran out
    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    for special in ("/dev/zero", str(fifo)):
        if os.path.exists(special):
            with pytest.raises(SceneFileError, match="is not a regular file"):
                load_scene_file(special)


def test_fit_data_must_be_a_csv_record_and_is_never_quoted(tmp_path, capsys):
    """[fit] data = "/etc/passwd" used to print the file's first line in the error."""
    secret = tmp_path / "secret.txt"
    secret.write_text("root:x:0:0:SECRET-LINE:/root:/bin/bash\n")
    p = tmp_path / "s.toml"
    p.write_text(BALL + f'[fit]\ndata = "{secret}"\n')
    with pytest.raises(SceneFileError, match=r"fit\.data must name a \.csv record") as exc:
        load_scene_file(str(p))
    assert "SECRET" not in str(exc.value)
    # a .csv that is not a record: the error names the file, never its content
    shutil.copy(secret, tmp_path / "secret.csv")
    p.write_text(BALL + '[fit]\ndata = "secret.csv"\n')
    assert main(["fit", str(p)]) == 2
    err = capsys.readouterr().err
    assert "secret.csv, line 1" in err and "SECRET" not in err and "root:x" not in err


def test_a_ball_record_the_fit_cannot_use_names_the_scene_and_the_record(tmp_path, capsys):
    """Regression: a scene file's t,z record with one flight only ended in "the record holds
    fewer than two flights ...", naming neither the scene file nor the record."""
    (tmp_path / "rec.csv").write_text("t,z\n" + "".join(
        f"{i * 0.005!r},{1.0 - 4.905 * (i * 0.005) ** 2!r}\n" for i in range(60)))
    p = tmp_path / "s.toml"
    p.write_text(BALL + '[fit]\nparams = ["contact.rubber.k", "contact.rubber.c"]\n'
                 'data = ["rec.csv"]\n')
    assert main(["fit", str(p)]) == 2
    err = capsys.readouterr().err
    assert f"{p}: [fit] data {tmp_path / 'rec.csv'}: the record holds fewer than two " \
        "flights" in err, err


def test_ball_TOML_is_a_file_not_the_built_in_ball(tmp_path, capsys):
    assert is_scene_path("ball.TOML") and is_scene_path("x/y.Toml")
    assert not is_scene_path("ball")
    missing = str(tmp_path / "ball.TOML")
    assert main(["simulate", missing]) == 2
    assert f"cannot read {missing}" in capsys.readouterr().err


def test_examples_ball_toml_reads():
    here = os.path.join(os.path.dirname(__file__), "..", "examples", "ball.toml")
    sf = load_scene_file(here)
    assert sf.spec.free == ["contact.rubber.k", "contact.rubber.c"]
    assert sf.spec.targets == {"apex_heights": [0.35], "settling_time": 2.4}
    assert math.isclose(sf.setup.dt * sf.setup.steps, 3.0)


def test_readme_scene_file_example_reads(tmp_path):
    """The README's TOML example is a valid scene file, as written."""
    readme = open(os.path.join(os.path.dirname(__file__), "..", "README.md")).read()
    block = readme.split("```toml\n", 1)[1].split("```", 1)[0]
    for name in ("toss_003.csv", "toss_006.csv"):
        (tmp_path / name).write_text("t,x,y,z\n0,0,0,0.15\n0.01,0,0,0.14\n")
    p = tmp_path / "cube.toml"
    p.write_text(block)
    sf = load_scene_file(str(p))
    assert sf.names["cube"] == 0 and sf.body_index("rope[-1]") == 10
    assert sf.spec.free == ["contact.wood.k", "contact.wood.c", "extra.friction.wood"]
    assert sf.spec.bounds == {"extra.friction.wood": (0.01, 1.0)}
    assert len(sf.spec.data) == 2 and sf.planes == {"board": 0}
    assert isinstance(sf.setup.compile_options["broadphase"], dp.broadphase.Grid)


@pytest.mark.skipif("name" not in __import__("inspect").signature(dp.Scene.add_plane).parameters,
                    reason="planes have no differentiable offset in this build")
def test_named_plane_offset_is_a_linear_space_fit_leaf(tmp_path):
    """A named plane's offset is the params leaf extra.plane_offset.NAME: [fit] accepts it and
    fits it in linear space (it is signed: the cube-toss board sits ~2 mm below z = 0)."""
    p = tmp_path / "g.toml"
    p.write_text(BALL.replace("[[planes]]", "[[planes]]\nname = \"ground\"\noffset = -0.002")
                 + '[fit]\nparams = ["contact.rubber.k", "extra.plane_offset.ground"]\n'
                 'data = "r.csv"\n[fit.bounds]\n"extra.plane_offset.ground" = [-0.01, 0.01]\n')
    (tmp_path / "r.csv").write_text("t,x,y,z\n0,0,0,1\n0.01,0,0,0.99\n")
    spec = load_scene_file(str(p)).spec
    assert spec.space == {"contact.rubber.k": "log", "extra.plane_offset.ground": "linear"}
    assert spec.bounds["extra.plane_offset.ground"] == (-0.01, 0.01)


@pytest.mark.skipif("allow_overlap" not in __import__("inspect").signature(
    dp.Scene.add_sphere).parameters, reason="no initial-overlap check in this build")
def test_allow_overlap_passes_through(tmp_path):
    p = tmp_path / "o.toml"
    deep = BALL.replace("position = [0.0, 0.0, 1.0]", "position = [0.0, 0.0, 0.02]")
    p.write_text(deep)
    with pytest.raises(SceneFileError, match=r"o\.toml: planes\[0\] .*allow_overlap"):
        load_scene_file(str(p))
    p.write_text(deep.replace('material = "rubber"\n[[planes]]',
                              'material = "rubber"\nallow_overlap = true\n[[planes]]'))
    assert load_scene_file(str(p)).scene.n_bodies == 1
    p.write_text("allow_overlap = true\n" + deep)
    assert load_scene_file(str(p)).scene.n_bodies == 1


@pytest.mark.parametrize("extra, words", [
    ('[fit.bounds]\n"contact.rubber.k" = [1e5, 1e3]\n', r"needs lo < hi"),
    ('[fit.bounds]\n"contact.rubber.k" = "wide"\n', r"must be \[lo, hi\], got a string"),
    ('[fit.space]\n"contact.rubber.k" = "exp"\n', r"must be one of 'log', 'linear'"),
    ("[fit.weights]\napex_heights = -1\n", r"fit\.weights\.apex_heights must be >= 0"),
])
def test_fit_table_errors_come_before_any_simulator_is_built(tmp_path, monkeypatch, extra,
                                                             words):
    def boom(*a, **k):
        raise AssertionError("a simulator was built before the [fit] table was checked")
    monkeypatch.setattr(dp, "compile", boom)
    p = tmp_path / "f.toml"
    p.write_text(BALL + FIT + extra)
    with pytest.raises(SceneFileError, match=words):
        load_scene_file(str(p))


def test_ball_record_fit_gets_the_files_law_with_its_exponent(tmp_path, monkeypatch):
    """A ball-record fit of a file with ``law = "hunt_crossley"`` and ``exponent = 1.5``
    simulates Hertz contact (the law record), not the name's default exponent 1."""
    import tuning.scenefile as scenefile
    import tuning.sysid as sysid
    (tmp_path / "rec.csv").write_text("t,z\n0.0,1.0\n0.01,0.99\n")
    path = tmp_path / "hertz.toml"
    path.write_text('law = "hunt_crossley"\nexponent = 1.5\n' + BALL + '[fit]\ndata = "rec.csv"\n')
    seen = {}

    def fake_fit(t, z, **kw):
        seen.update(kw)
        raise RuntimeError("stop before fitting")
    monkeypatch.setattr(sysid, "fit_trajectory", fake_fit)
    monkeypatch.setattr(sysid, "load_csv", lambda p: (np.zeros(2), np.ones(2)))
    with pytest.raises(RuntimeError, match="stop before fitting"):
        scenefile.fit_file(str(path))
    law = dp.laws.get(seen["law"])
    assert (law.name, law.exponent) == ("hunt_crossley", 1.5)


def _two_materials(first_a: bool, top: str = "") -> str:
    a = "[materials.a]\nk = 5e3\nc = 7.0\n"
    b = "[materials.b]\nfriction = 0.3\n"
    return (top + (a + b if first_a else b + a)
            + '[[spheres]]\nradius = 0.1\nmass = 1.0\nposition = [0, 0, 1]\nmaterial = "a"\n'
            + '[[planes]]\nmaterial = "b"\n')


@pytest.mark.parametrize("first_a", [True, False])
def test_material_without_k_c_takes_the_top_level_or_default_not_another_materials(
        tmp_path, first_a):
    """Regression: a material without k / c took the first declared material's, so the
    result depended on the order of [materials.*]; it takes the top-level k / c, else the
    documented defaults k = 1e4 N/m, c = 20 N s/m."""
    p = tmp_path / "m.toml"
    p.write_text(_two_materials(first_a))
    sf = load_scene_file(str(p))
    assert (sf.setup.k, sf.setup.c) == (1e4, 20.0)
    leaves = param_leaves(sf.params(sf.compile()))
    assert (float(leaves["contact.b.k"]), float(leaves["contact.b.c"])) == (1e4, 20.0)
    p.write_text(_two_materials(first_a, top="k = 3e3\nc = 2.0\n"))
    sf = load_scene_file(str(p))
    leaves = param_leaves(sf.params(sf.compile()))
    assert (float(leaves["contact.b.k"]), float(leaves["contact.b.c"])) == (3e3, 2.0)


@pytest.mark.parametrize("law", ['law = "linear"\n', 'law = "no_tension"\n', ""])
def test_exponent_is_refused_outside_hunt_crossley(tmp_path, law):
    """Regression: exponent with another law was silently ignored."""
    p = tmp_path / "e.toml"
    p.write_text(law + "exponent = 2.0\n" + BALL)
    with pytest.raises(SceneFileError, match=r"e\.toml: exponent applies only to law = "
                       r"\"hunt_crossley\", but law = '(linear|no_tension)': remove exponent, "
                       r"or set law = \"hunt_crossley\""):
        load_scene_file(str(p))
    p.write_text('law = "hunt_crossley"\nexponent = 2.0\n' + BALL)
    assert load_scene_file(str(p)).compile_options["exponent"] == 2.0


@pytest.mark.parametrize("timing", ["dt = 1e-3\nduration = 5e-4\n", "dt = 0.01\nduration = 1e-3\n"])
def test_duration_shorter_than_one_step_is_refused(tmp_path, timing):
    """Regression: duration < dt silently ran one step."""
    p = tmp_path / "d.toml"
    p.write_text(timing + BALL)
    with pytest.raises(SceneFileError, match=r"d\.toml: duration = [0-9.e-]+ s is shorter than "
                       r"one step \(dt = [0-9.e-]+ s\).*give duration >= "):
        load_scene_file(str(p))
    p.write_text(timing.split("\n")[0] + "\nduration = 0.01\n" + BALL)
    assert load_scene_file(str(p)).setup.steps >= 1


_ROPE = '[[ropes]]\nn = 5\nstart = [0, 2, 1]\nend = [1, 2, 1]\nmass = 1.0\nk = 100.0\n'
_TWO = ('[[spheres]]\nname = "a"\nradius = 0.1\nmass = 1.0\nposition = [0, 0, 1]\n'
        '[[spheres]]\nname = "b"\nradius = 0.1\nmass = 1.0\nposition = [1, 0, 1]\n')
_SPHERE = '[[spheres]]\nradius = 0.1\nmass = 1.0\nposition = [0, 0, 1]\n'


@pytest.mark.parametrize("text, words, fixed", [
    ('[spring_groups."rope.stretch"]\nk = 1.0\n' + _ROPE,
     r"ropes\[0\] group 'rope\.stretch' already exists in this scene: give this entry another "
     r"name \(e\.g\. name = \"rope2\"; .*or rename the \[spring_groups\.\"rope\.stretch\"\] table",
     '[spring_groups."rope.stretch"]\nk = 1.0\n' + _ROPE + 'name = "rope2"\n'),
    (_SPHERE.replace("[0, 0, 1]", "[0, 0, 0]") + "[[planes]]\n",
     r"planes\[0\] .*overlap .*; or set allow_overlap = true in this entry \(or at the top "
     r"level for the whole file\)",
     _SPHERE.replace("[0, 0, 1]", "[0, 0, 0]") + "[[planes]]\nallow_overlap = true\n"),
    (_TWO + '[[springs]]\na = "a"\nb = "b"\n',
     r"springs\[0\] spring group 'default' is new: give k = \.\.\. \(N/m\) in this entry, or "
     r"declare it in a \[spring_groups\.default\] table with k \(N/m\) and c \(N s/m\)",
     _TWO + '[[springs]]\na = "a"\nb = "b"\nk = 10.0\n'),
    (_SPHERE + "velocity = [1, 0, 0]\npinned = true\n",
     r"spheres\[0\] a pinned body cannot have an initial velocity: drop velocity from this "
     r"entry, or set pinned = false",
     _SPHERE + "velocity = [1, 0, 0]\npinned = false\n"),
    ("[[cloths]]\nnx = 3\nny = 3\nspacing = 0.1\nmass = 1.0\nstructural = false\n",
     r"cloths\[0\] cloth structural springs are required: give structural = k or \[k, c\] "
     r"\(N/m, N s/m\) in this entry, not false",
     "[[cloths]]\nnx = 3\nny = 3\nspacing = 0.1\nmass = 1.0\nstructural = [100.0, 0.1]\n"),
    (_ROPE + "pinned = [[0, 0]]\n",
     r"ropes\[0\]\.pinned\[0\] must be a node index \(a whole number\), got an array \[0, 0\]; "
     r"e\.g\. pinned = \[0, -1\]",
     _ROPE + "pinned = [0, -1]\n"),
], ids=["D3a-group-prefix", "D3b-allow-overlap", "D3c-spring-group", "D3d-pinned-velocity",
        "D3e-structural", "D3f-rope-pinned"])
def test_library_errors_give_the_files_spelling_of_the_fix(tmp_path, text, words, fixed):
    """Regression: the loader passed on the library's Python advice (group= prefix,
    allow_overlap=True, scene.add_spring_group(...), pinned=True, structural=(k, c),
    pinned = 10 for an array); the message now names the file's keys, and following it loads."""
    p = tmp_path / "a.toml"
    p.write_text("dt = 1e-3\nduration = 0.01\n" + text)
    with pytest.raises(SceneFileError, match=words) as exc:
        load_scene_file(str(p))
    msg = str(exc.value)
    for python in ("=True", "group=", "scene.", "=(", "k=", "pinned = 10"):
        assert python not in msg
    p.write_text("dt = 1e-3\nduration = 0.01\n" + fixed)
    assert load_scene_file(str(p)).scene.n_bodies >= 1
