"""tuning.fitted_scene.write_fitted: a fitted scene file moves the fitted leaves and nothing
else. Each case writes a fitted copy of a small scene, reads it back with load_scene_file,
compiles it and compares every parameter leaf with the input's: fitted leaves at their
fitted values, all others unchanged, exactly."""
import pathlib
import re
import tomllib

import pytest

from tuning import trajfit as tf
from tuning.errors import FitError
from tuning.fitted_scene import dumps_toml, write_fitted
from tuning.scenefile import load_scene_file, param_leaves

RUN = "dt = 1e-3\nduration = 0.5\n"
PLANE = "[[planes]]\noffset = -0.5\n"
CLOTH = """[[cloths]]
nx = 3
ny = 3
spacing = 0.1
mass = 0.2
origin = [0.0, 0.0, 1.0]
"""
JELLY = """[[jellies]]
nx = 2
ny = 2
nz = 2
spacing = 0.1
mass = 0.2
origin = [0.0, 0.0, 1.0]
"""
BAR = """[[crumple_bars]]
n = 4
start = [0.0, 0.0, 1.0]
end = [0.4, 0.0, 1.0]
mass = 0.2
k = 1000.0
c = 0.5
"""
ROPE = """[[ropes]]
n = 5
start = [0.0, 0.0, 1.0]
end = [1.0, 0.0, 1.0]
mass = 0.2
k = 500.0
c = 0.5
"""
BALLS = """[[spheres]]
name = "ball"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 1.0]
material = "rubber"
[[spheres]]
name = "other"
radius = 0.1
mass = 1.0
position = [1.0, 0.0, 1.0]
"""


def _leaves(path) -> dict:
    sf = load_scene_file(str(path))
    return {k: float(v) for k, v in param_leaves(sf.params(sf.compile())).items()}


def _roundtrip(tmp_path, text: str, values: dict, name: str = "scene") -> tuple:
    """Write ``text``, write_fitted it with ``values``, and check every leaf of the result:
    the fitted ones equal ``values``, the others their input value (exactly). Returns the
    input's leaves and the written file's parsed TOML."""
    src = tmp_path / f"{name}.toml"
    src.write_text(text, encoding="utf-8")
    before = _leaves(src)
    for path, v in values.items():      # each fitted value really moves its leaf
        assert path in before and before[path] != v, path
    out = tmp_path / f"{name}_fitted.toml"
    assert write_fitted(str(src), values, str(out)) == str(out)
    expect = dict(before)
    expect.update(values)
    assert _leaves(out) == expect
    return before, tomllib.loads(out.read_text(encoding="utf-8"))


# --------------------------------------------------------------------------- 1: builder pairs
@pytest.mark.parametrize("extra, values", [
    ("", {"springs.cloth.structural.k": 57.79}),                 # default (100, 0.1)
    ("", {"springs.cloth.shear.c": 0.07}),                       # default (50, 0.05)
    ("", {"springs.cloth.bend.k": 12.0, "springs.cloth.bend.c": 0.02}),
    ("shear = 50.0\n", {"springs.cloth.shear.c": 0.5}),          # a bare k: c was 0
    ("structural = [80.0, 0.3]\n", {"springs.cloth.structural.k": 90.0}),
])
def test_cloth_group_keeps_the_unfitted_member(tmp_path, extra, values):
    """Fitting one of a cloth group's k / c keeps the other at the value the scene compiled
    with (the library default when the file gives none; it was written as 0.0)."""
    _roundtrip(tmp_path, RUN + CLOTH + extra + PLANE, values)


@pytest.mark.parametrize("values", [{"springs.jelly.edge.c": 0.7},
                                    {"springs.jelly.face.k": 333.0},
                                    {"springs.jelly.body.c": 0.25}])
def test_jelly_group_keeps_the_unfitted_member(tmp_path, values):
    _roundtrip(tmp_path, RUN + JELLY + PLANE, values)


def test_the_written_scene_gets_plain_file_permissions(tmp_path):
    """Regression: the fitted scene was written through mkstemp and kept its owner-only mode
    (-rw-------) while every other output gets 0o666 less the umask."""
    import os
    _roundtrip(tmp_path, RUN + ROPE + PLANE, {"springs.rope.stretch.k": 432.0})
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(tmp_path / "scene_fitted.toml").st_mode & 0o777 == 0o666 & ~umask


def test_rope_groups(tmp_path):
    """A rope's stretch (k, c), bend pair (bare k) and drag."""
    _roundtrip(tmp_path, RUN + ROPE + "bend = 20.0\ndrag = 0.01\n" + PLANE,
               {"springs.rope.stretch.k": 432.0, "springs.rope.bend.c": 0.04,
                "extra.drag.rope.drag": 0.02})


# --------------------------------------------------------------------------- 2: plastic
@pytest.mark.parametrize("extra", ["", "yield_strain = 0.05\n", "width = 0.05\n"])
def test_crumple_bar_springs_and_yield_strain(tmp_path, extra):
    """A crumple bar's group is its name: springs.bar.k / .c and extra.plastic.bar go to the
    bar's k, c and yield_strain (they could not be placed)."""
    _roundtrip(tmp_path, RUN + BAR + extra + PLANE,
               {"springs.bar.k": 1234.0, "springs.bar.c": 0.75, "extra.plastic.bar": 0.07})


def test_named_crumple_bar_joined_by_plastic_springs(tmp_path):
    """[[plastic_springs]] that join a crumple bar's group and state its k get the fitted k
    too (else the file contradicts itself)."""
    text = (RUN + BAR + 'name = "strut"\nyield_strain = 0.1\n' + PLANE
            + '[[plastic_springs]]\na = "strut[0]"\nb = "strut[2]"\nk = 1000.0\n'
              'yield_strain = 0.1\ngroup = "strut"\n')
    _, doc = _roundtrip(tmp_path, text, {"springs.strut.k": 800.0,
                                         "extra.plastic.strut": 0.2})
    assert doc["plastic_springs"][0]["k"] == 800.0
    assert doc["plastic_springs"][0]["yield_strain"] == 0.2


@pytest.mark.parametrize("group, values", [
    ("", {"extra.plastic.plastic": 0.2, "springs.plastic.c": 0.3}),
    ('group = "crush"\n', {"extra.plastic.crush": 0.3, "springs.crush.k": 150.0}),
])
def test_plastic_springs_yield_strain(tmp_path, group, values):
    """[[plastic_springs]]: the yield strain goes to the entries of the group (the first
    declares it; later entries that state it must agree)."""
    springs = "".join(f"[[plastic_springs]]\na = {a}\nb = {b}\nk = 100.0\nyield_strain = 0.1\n"
                      + group for a, b in ((0, 3), (1, 4)))
    _roundtrip(tmp_path, RUN + ROPE + springs + PLANE, values)


# --------------------------------------------------------------------------- 3: default k, c
def test_default_material_keeps_the_defaults(tmp_path):
    """Without top-level k / c the default material takes the defaults (1e4 N/m, 20 N s/m),
    not the first material's: fitting that material's k and c must not move contact.default,
    and the written file states the defaults."""
    text = (RUN + "[materials.rubber]\nk = 2e3\nc = 20.0\n" + BALLS
            + '[[fixed_spheres]]\ncenter = [3.0, 0.0, 0.5]\nradius = 0.2\n'
              'material = "rubber"\n[[planes]]\n')
    before, doc = _roundtrip(tmp_path, text, {"contact.rubber.k": 2e4, "contact.rubber.c": 5.0})
    assert before["contact.default.k"] == 1e4 and before["contact.default.c"] == 20.0
    assert (doc["k"], doc["c"]) == (1e4, 20.0)


def test_materials_without_their_own_k_keep_it(tmp_path):
    """A material that gives only c uses the top-level fallback (here the default 1e4 N/m);
    fitting another material's c, or the default material's k, leaves it where it was."""
    text = (RUN + "[materials.rubber]\nc = 20.0\n[materials.board]\nk = 3e3\nfriction = 0.2\n"
            + BALLS + '[[boxes]]\nhalf_extents = [0.05, 0.05, 0.05]\nmass = 0.37\n'
              'position = [3.0, 0.0, 0.3]\nmaterial = "board"\n'
              '[[fixed_spheres]]\ncenter = [5.0, 0.0, 0.5]\nradius = 0.2\nmaterial = "rubber"\n'
              '[[planes]]\nname = "ground"\nmaterial = "board"\n')
    before, _ = _roundtrip(tmp_path, text, {"contact.board.c": 7.0, "contact.default.k": 5e3,
                                "extra.friction.board": 0.3,
                                "extra.plane_offset.ground": -0.002})
    assert before["contact.rubber.k"] == 1e4        # the fallback: the default k


def test_readme_example_scene(tmp_path):
    """The README's scene-file example (its [fit] records left out): fitting the wood's k,
    c and friction moves nothing else (contact.default followed the wood)."""
    text = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"\*\*Scene files\.\*\*.*?```toml\n(.*?)```", text, re.S).group(1)
    block = block[:block.index("[fit]")]
    _roundtrip(tmp_path, block, {"contact.wood.k": 1742.0, "contact.wood.c": 3.5,
                                 "extra.friction.wood": 0.17,
                                 "springs.tie.k": 80.0, "springs.rope.stretch.c": 0.25})


# --------------------------------------------------------------------------- 4: strings
SPECIAL = ['two\nlines', 'a "quoted" word', "back\\slash C:\\path\\", "tab\there",
           "cr\r\nlf", "bell\x07 del\x7f nul\x00", "unicode: é ü 中文 ∑ 🙂", "'single'",
           '"""', "trailing backslash \\"]


@pytest.mark.parametrize("desc", SPECIAL)
def test_special_strings_are_written_as_valid_toml(tmp_path, desc):
    """Strings are escaped per the TOML spec (they were written raw: a newline made the file
    invalid); the description and the group names read back unchanged."""
    doc = {"description": desc, "dt": 1e-3, "duration": 0.5,
           "spring_groups": {desc: {"k": 100.0}},
           "spheres": [{"radius": 0.1, "mass": 1.0, "position": [0.0, 0.0, 1.0]},
                       {"radius": 0.1, "mass": 1.0, "position": [1.0, 0.0, 1.0]}],
           "springs": [{"a": 0, "b": 1, "group": desc}], "planes": [{}]}
    assert tomllib.loads(dumps_toml(doc)) == doc
    _, out = _roundtrip(tmp_path, dumps_toml(doc), {f"springs.{desc}.k": 120.0,
                                                    "contact.default.c": 3.0})
    assert out["description"] == desc


def test_dumps_toml_round_trips_keys_and_values():
    """Keys that are not bare ASCII (unicode letters included) are quoted and escaped; dates,
    special floats and nested tables survive."""
    doc = tomllib.loads('x = 1979-05-27T07:32:00Z\nd = 1979-05-27\nt = 07:32:00\n'
                        'f = [inf, -inf, -0.0, 1e-300, 1.5e300]\n'
                        '[a."b.c"."é"]\n"x y" = "z"\n"tab\\tkey" = 1\n"" = 2\n'
                        '[[arr]]\nv = { w = "\\n" }\n[[arr.sub]]\nq = true\n')
    assert tomllib.loads(dumps_toml(doc)) == doc
    assert dumps_toml({"é": 1}).startswith('"é" = 1')


# --------------------------------------------------------------------------- other leaves
def test_spring_groups_drag_and_anchored_springs(tmp_path):
    """A [spring_groups] table and the [[springs]] entries that state its k; an anchored
    spring group; [[drag]] groups (the first entry declares c, later ones that state it must
    agree); a builder's drag joined by a [[drag]] entry; a named plane's offset."""
    text = (RUN + "[materials.rubber]\nk = 1e4\nc = 20.0\n" + BALLS + ROPE + "drag = 0.01\n"
            + '[[planes]]\nname = "ground"\noffset = -0.5\n'
            + "[spring_groups.tether]\nk = 50.0\n"
            + '[[springs]]\na = "ball"\nb = "other"\ngroup = "tether"\nk = 50.0\n'
            + '[[springs]]\na = "ball"\nb = [0.0, 0.0, 2.0]\nk = 10.0\nc = 0.1\n'
            + '[[springs]]\na = "other"\nb = [1.0, 0.0, 2.0]\nk = 10.0\n'
            + '[[anchored_springs]]\na = "ball"\nb = "rope[-1]"\nk = 100.0\ngroup = "tie"\n'
            + '[[drag]]\nbodies = "ball"\nc = 0.3\n[[drag]]\nbodies = ["other"]\nc = 0.3\n'
            + '[[drag]]\nbodies = "other"\nc = 0.01\ngroup = "rope.drag"\n')
    _, doc = _roundtrip(tmp_path, text, {
        "springs.tether.k": 60.0, "springs.tether.c": 0.2, "springs.default.k": 11.0,
        "springs.tie.c": 0.4, "extra.drag.drag": 0.35, "extra.drag.rope.drag": 0.02,
        "extra.plane_offset.ground": -0.25})
    assert doc["springs"][0]["k"] == 60.0 and doc["springs"][2]["k"] == 11.0
    assert doc["drag"][2]["c"] == 0.02


def test_rope_group_joined_by_springs(tmp_path):
    """[[springs]] entries may join a rope's stretch group and state its k: both move."""
    text = (RUN + ROPE + PLANE
            + '[[springs]]\na = "rope[0]"\nb = "rope[2]"\nk = 500.0\ngroup = "rope.stretch"\n')
    _roundtrip(tmp_path, text, {"springs.rope.stretch.k": 450.0})


def test_unknown_leaf_is_refused_and_nothing_written(tmp_path):
    """A path that is not a leaf is refused with the leaves; a value the loader refuses is
    reported against out (not the temporary file); out is not written in either case."""
    src = tmp_path / "s.toml"
    src.write_text(RUN + BAR + PLANE)
    out = tmp_path / "out.toml"
    with pytest.raises(FitError, match=r"extra\.slip_speed\.default.*not a parameter leaf.*"
                                       r"springs\.bar\.k"):
        write_fitted(str(src), {"extra.slip_speed.default": 0.02}, str(out))
    with pytest.raises(FitError, match=r"do not make a valid scene file: .*out\.toml: "
                                       r"crumple_bars\[0\]\.yield_strain"):   # must be < 1
        write_fitted(str(src), {"extra.plastic.bar": 1.5}, str(out))
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["s.toml"]


def test_write_fitted_places_every_kind_of_leaf(tmp_path):
    """Materials (k, c, friction), a named plane's offset, a cloth's spring groups and drag
    are written where the file declares them and read back equal."""
    from tuning.fitted_scene import write_fitted
    src = tmp_path / "s.toml"
    src.write_text("""
[materials.board]
k = 1e4
c = 100.0
friction = 0.2
[[boxes]]
name = "cube"
half_extents = [0.05, 0.05, 0.05]
mass = 0.37
position = [0.0, 0.0, 0.5]
material = "board"
[[planes]]
name = "ground"
material = "board"
[[cloths]]
nx = 3
ny = 3
spacing = 0.1
mass = 0.1
origin = [1.0, 0.0, 1.0]
structural = [100.0, 0.1]
shear = 50.0
drag = 0.01
""")
    values = {"contact.board.k": 2024.5, "contact.board.c": 25.25,
              "extra.friction.board": 0.175, "extra.plane_offset.ground": -0.001,
              "springs.cloth.structural.k": 123.0, "springs.cloth.shear.c": 0.5,
              "extra.drag.cloth.drag": 0.02}
    out = tmp_path / "out.toml"
    write_fitted(str(src), values, str(out))
    sf = load_scene_file(str(out))
    params = sf.params(sf.compile())
    for name, v in values.items():
        assert float(tf.get_leaf(params, name)) == v
    assert float(tf.get_leaf(params, "springs.cloth.structural.c")) == 0.1
