"""TOML scene files (tuning.scenefile): every element kind builds the same scene as the Python
API, [fit] names any params leaf by its key path, and every bad file is refused with the file,
the key and the fix before anything is compiled (test_scenefile_errors.py)."""
import numpy as np
import pytest

import diffpen as dp
from diffpen import builders
from tuning.scenefile import SceneFileError, leaf_space, load_scene_file, param_leaves

ALL = """
description = "every element"
gravity = [0.0, 0.0, -9.81]
dt = 5e-4
duration = 0.05
integrator = "semi_implicit_euler"
smoothing = 1e-4

[materials.rubber]
k = 2e4
c = 15.0
friction = 0.3
slip_speed = 0.02

[spring_groups.tether]
k = 300.0
c = 0.5

[[spheres]]
name = "ball"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 1.0]
velocity = [0.5, 0.0, 0.0]
material = "rubber"

[[particles]]
name = "dot"
mass = 0.1
position = [1.0, 0.0, 1.0]

[[boxes]]
name = "cube"
half_extents = [0.05, 0.04, 0.03]
mass = 0.37
position = [2.0, 0.0, 0.5]
orientation = [0.9, 0.1, 0.3, 0.2]
body_angular_velocity = [0.5, -1.0, 2.0]
inertia = [8.1e-4, 7e-4, 6e-4]
material = "rubber"

[[rigid_spheres]]
name = "wheel"
radius = 0.05
mass = 0.5
position = [3.0, 0.0, 0.5]
angular_velocity = [0.0, 2.0, 0.0]

[[planes]]
offset = -0.002
material = "rubber"

[[planes]]
normal = [-1.0, 0.0, 0.0]
offset = -10.0

[[fixed_spheres]]
center = [5.0, 0.0, 0.0]
radius = 0.5

[[springs]]
a = "ball"
b = "dot"
k = 100.0
group = "link"

[[springs]]
a = 1
b = [1.0, 0.0, 2.0]
group = "tether"
rest_length = 0.9

[[anchored_springs]]
a = "cube"
anchor_a = [0.05, 0.04, 0.03]
anchor_b = [2.0, 0.0, 1.0]
k = 50.0
c = 0.2
group = "hang"

[[anchored_springs]]
a = "cube"
b = "wheel"
anchor_a = [-0.05, 0.0, 0.0]
anchor_b = [0.0, 0.0, 0.05]
group = "hang"

[[ropes]]
n = 5
start = [0.0, 1.0, 1.0]
end = [0.5, 1.0, 1.0]
mass = 0.1
k = 200.0
c = 0.1
bend = [20.0, 0.01]
drag = 0.01
pinned = [0, -1]

[[cloths]]
name = "sheet"
nx = 3
ny = 4
spacing = 0.1
mass = 0.2
origin = [0.0, 2.0, 1.0]
axes = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
structural = 150.0
shear = false
bend = [5.0, 0.02]
pinned = [[0, 0], [0, -1]]

[[jellies]]
nx = 2
ny = 2
nz = 3
spacing = 0.05
mass = 0.1
origin = [0.0, 3.0, 0.5]
edge = [400.0, 0.4]
body = false

[[crumple_bars]]
n = 4
start = [0.0, 4.0, 0.5]
end = [0.3, 4.0, 0.5]
mass = 0.1
k = 1000.0
c = 1.0
yield_strain = 0.05
width = 0.05
pinned = [0]

[[plastic_springs]]
a = "rope[-2]"
b = "sheet[2,3]"
k = 10.0
yield_strain = 0.1
group = "crush"

[[drag]]
bodies = ["ball", "cube"]
c = 0.05
group = "air"
"""


def _quat_matrix(q):
    # normalised as the scene does (diffpen.elements.unit_vector), to the last bit
    from diffpen.elements import unit_vector
    w, x, y, z = unit_vector(np.asarray(q, float))[0]
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _api_scene():
    """The scene of ALL, built with the Python API."""
    s = dp.Scene(gravity=(0.0, 0.0, -9.81))
    s.add_material("rubber", k=2e4, c=15.0, friction=0.3, slip_speed=0.02)
    s.add_spring_group("tether", 300.0, 0.5)
    ball = s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0), (0.5, 0.0, 0.0), material="rubber")
    dot = s.add_particle(0.1, (1.0, 0.0, 1.0))
    q = (0.9, 0.1, 0.3, 0.2)
    cube = s.add_box((0.05, 0.04, 0.03), 0.37, (2.0, 0.0, 0.5), orientation=q,
                     angular_velocity=tuple(_quat_matrix(q) @ np.array([0.5, -1.0, 2.0])),
                     inertia=(8.1e-4, 7e-4, 6e-4), material="rubber")
    wheel = s.add_rigid_sphere(0.05, 0.5, (3.0, 0.0, 0.5), angular_velocity=(0.0, 2.0, 0.0))
    rope = builders.add_rope(s, 5, (0.0, 1.0, 1.0), (0.5, 1.0, 1.0), 0.1, 200.0, 0.1,
                             bend=(20.0, 0.01), drag=0.01, pinned=(0, -1))
    sheet = builders.add_cloth(s, 3, 4, 0.1, 0.2, origin=(0.0, 2.0, 1.0),
                               axes=((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)), structural=150.0,
                               shear=None, bend=(5.0, 0.02), pinned=[(0, 0), (0, -1)],
                               group="sheet")
    builders.add_jelly(s, 2, 2, 3, 0.05, 0.1, origin=(0.0, 3.0, 0.5), edge=(400.0, 0.4),
                       body=None)
    builders.add_crumple_bar(s, 4, (0.0, 4.0, 0.5), (0.3, 4.0, 0.5), 0.1, 1000.0, 1.0,
                             yield_strain=0.05, width=0.05, pinned=[0])
    s.add_plane(offset=-0.002, material="rubber")
    s.add_plane(normal=(-1.0, 0.0, 0.0), offset=-10.0)
    s.add_fixed_sphere((5.0, 0.0, 0.0), 0.5)
    s.add_spring(ball, dot, k=100.0, group="link")
    s.add_spring(dot, (1.0, 0.0, 2.0), group="tether", rest_length=0.9)
    s.add_anchored_spring(cube, None, (0.05, 0.04, 0.03), (2.0, 0.0, 1.0), k=50.0, c=0.2,
                          group="hang")
    s.add_anchored_spring(cube, wheel, (-0.05, 0.0, 0.0), (0.0, 0.0, 0.05), group="hang")
    s.add_plastic_spring(int(rope[-2]), int(sheet[2, 3]), k=10.0, yield_strain=0.1,
                         group="crush")
    s.add_drag([ball, cube], c=0.05, group="air")
    return s


RECORDS = ("bodies", "springs", "anchored_springs", "planes", "fixed_spheres", "materials",
           "spring_groups", "drags", "drag_groups", "plastic_springs", "plastic_groups",
           "gravity", "plastic_smoothing")


@pytest.fixture(scope="module")
def all_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("scenes") / "all.toml"
    p.write_text(ALL)
    return str(p)


def test_every_element_kind_builds_the_python_api_scene(all_file):
    sf = load_scene_file(all_file)
    api = _api_scene()
    for rec in RECORDS:
        got, want = getattr(sf.scene, rec), getattr(api, rec)
        assert got == want, rec
    # the body-frame angular velocity was turned into the world frame the API takes
    cube = sf.scene.bodies[sf.names["cube"]]
    assert not np.allclose(cube.angular_velocity, (0.5, -1.0, 2.0))
    # names: user names and builder nodes, negative node indices resolved
    assert sf.names["ball"] == 0 and sf.names["dot"] == 1 and sf.names["wheel"] == 3
    assert sf.body_index("rope[-1]") == sf.names["rope[4]"] == 8
    assert sf.body_index("sheet[1, 2]") == sf.names["sheet[1,2]"]
    assert sf.nodes["sheet"].shape == (3, 4) and sf.nodes["bar"].shape == (4, 2)
    assert sf.setup.steps == 100 and sf.setup.dt == 5e-4
    sim = sf.compile()
    assert sim.integrator == "semi_implicit_euler" and sim.smoothing == 1e-4
    # and the compiled parameters equal the API scene's (a material without k and c takes
    # the top-level ones; this file gives none, so the documented 1e4 N/m and 20 N s/m)
    sim_api = dp.compile(api, 5e-4, smoothing=1e-4)
    pa = param_leaves(sf.params(sim))
    pb = param_leaves(sim_api.params(contact={"default": (1e4, 20.0)}))
    assert pa.keys() == pb.keys()
    for key in pa:
        assert float(pa[key]) == float(pb[key]), key


def test_fit_params_are_key_paths_of_the_params_pytree(tmp_path):
    body = ALL + """
[fit]
params = ["contact.rubber.k", ".contact['rubber'].c", "extra.friction.rubber",
          "springs.rope.stretch.k", "springs.sheet.structural.c", "extra.drag.air",
          "extra.plastic.crush", "extra.drag.rope.drag"]
data = ["rec.csv"]
observe = ["cube", "rope[2]"]
method = "adam"
maxiter = 30
[fit.bounds]
"contact.rubber.k" = [1e3, 1e6]
[fit.space]
"extra.drag.air" = "linear"
"""
    (tmp_path / "rec.csv").write_text("t,cube.x,cube.y,cube.z\n0,2,0,0.5\n0.01,2,0,0.49\n")
    p = tmp_path / "fit.toml"
    p.write_text(body)
    sf = load_scene_file(str(p))
    spec = sf.spec
    # the simulator built to check the paths is the one sf.compile() gives (built once)
    assert sf.compile() is sf.compile() and sf.compile().dt == 5e-4
    assert sf.compile(dt=1e-4).dt == 1e-4
    assert spec.free == ["contact.rubber.k", "contact.rubber.c", "extra.friction.rubber",
                         "springs.rope.stretch.k", "springs.sheet.structural.c",
                         "extra.drag.air", "extra.plastic.crush", "extra.drag.rope.drag"]
    assert spec.bounds == {"contact.rubber.k": (1e3, 1e6)}
    assert spec.space["extra.drag.air"] == "linear" and spec.space["contact.rubber.c"] == "log"
    assert spec.data == [str(tmp_path / "rec.csv")] and spec.observe == ["cube", "rope[2]"]
    assert spec.method == "adam" and spec.maxiter == 30
    # a leaf that is not in the pytree lists the ones that are
    p.write_text(body.replace('"extra.plastic.crush"', '"extra.slip_speed.rubber"'))
    with pytest.raises(SceneFileError, match=r"fit\.params\[6\] 'extra.slip_speed.rubber' is "
                                             r"not a parameter of this scene; its parameters "
                                             r"are: contact.default.k"):
        load_scene_file(str(p))


def test_drag_on_every_node_of_a_builder(tmp_path):
    p = tmp_path / "d.toml"
    p.write_text("[[ropes]]\nn = 4\nstart = [0, 0, 1]\nend = [0.3, 0, 1]\nmass = 0.1\n"
                 "k = 100.0\n[[drag]]\nbodies = \"rope\"\nc = 0.02\ngroup = \"air\"\n")
    sf = load_scene_file(str(p))
    assert [d.body for d in sf.scene.drags if d.group == "air"] == [0, 1, 2, 3]
    assert sf.scene.drag_groups == {"air": 0.02}


def test_leaf_space_signed_offsets_linear_positive_log():
    assert leaf_space("extra.plane_offset.ground", -0.002) == "linear"
    assert leaf_space("extra.plane_offset.ground", 0.01) == "linear"
    assert leaf_space("contact.offset_rubber.k", 1e4) == "log"       # a material's name
    assert leaf_space("extra.slip_speed.rubber", 0.01) == "log"
    assert leaf_space("extra.plastic.bar", 0.05) == "log"


def test_named_plane_and_body_references(tmp_path):
    p = tmp_path / "b.toml"
    p.write_text("""
[[boxes]]
name = "cube"
half_extents = [0.05, 0.05, 0.05]
mass = 0.37
position = [0.0, 0.0, 0.2]
[[spheres]]
name = "ball"
radius = 0.1
mass = 1.0
position = [1.0, 0.0, 1.0]
[[planes]]
name = "wall"
normal = [-1.0, 0.0, 0.0]
offset = -3.0
[[planes]]
name = "ground"
[fit]
body = "ball"
plane = "ground"
[fit.targets]
apex_heights = [0.3]
""")
    sf = load_scene_file(str(p))
    assert sf.names == {"ball": 0, "cube": 1}         # spheres are numbered before boxes
    assert sf.planes == {"wall": 0, "ground": 1}
    assert sf.spec.body == 0 and sf.spec.plane == 1 and sf.spec.observe == ["ball", "cube"]
    assert sf.setup.metrics is not None                # the ball bounces: bounce metrics


def test_a_scene_file_ball_without_k_or_c_is_the_built_in_ball(tmp_path):
    """Regression: a material giving neither k nor c took c = 10 N s/m from a scene file and
    20 from the built-in ball (tuning.scenes.ball): the same ball bounced to 0.65 m against
    0.47 m and did not settle."""
    import inspect

    from tuning.scenes import ball
    defaults = inspect.signature(ball).parameters
    path = tmp_path / "ball.toml"
    path.write_text('dt = 1e-3\n[[spheres]]\nradius = 0.1\nmass = 1.0\n'
                    'position = [0.0, 0.0, 1.0]\n[[planes]]\n', encoding="utf-8")
    sf = load_scene_file(str(path))
    p = sf.params(sf.compile())
    assert float(p.contact["default"].k) == defaults["k"].default
    assert float(p.contact["default"].c) == defaults["c"].default
