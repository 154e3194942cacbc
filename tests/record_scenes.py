"""Scene-file texts and a record maker shared by the record-fit tests (test_trajfit,
test_records, test_record_batch, test_fit_command, test_first_state, test_fit_resume): a box
hung on two anchored springs (group "hang", ``{k}`` N/m and ``{c}`` N s/m to fill in), a
particle thrown through air with drag (group "air", fitted from 0.05), a four-node rope, a
crumple bar hitting a wall, and
:func:`record_file`, which writes a scene file and a record of it at given values."""
from tuning import trajfit as tf
from tuning.records import write_record
from tuning.scenefile import load_scene_file


BOX = """
dt = 1e-3
[[boxes]]
name = "box"
half_extents = [0.1, 0.05, 0.03]
mass = 1.0
position = [0.0, 0.0, 0.0]
orientation = [0.98, 0.1, 0.15, 0.0]
collide = false
[[anchored_springs]]
a = "box"
anchor_a = [0.1, 0.05, 0.03]
anchor_b = [0.05, 0.02, 0.3]
k = {k}
c = {c}
rest_length = 0.2
group = "hang"
[[anchored_springs]]
a = "box"
anchor_a = [-0.1, -0.05, 0.03]
anchor_b = [-0.12, 0.0, 0.3]
group = "hang"
rest_length = 0.2
[fit]
params = ["springs.hang.k", "springs.hang.c"]
"""


DRAG = """
dt = 1e-3
[[particles]]
name = "p"
mass = 0.1
position = [0.0, 0.0, 5.0]
velocity = [1.0, 0.0, 2.0]
[[drag]]
bodies = "p"
c = 0.05
group = "air"
[fit]
params = ["extra.drag.air"]
"""


#: a rope of four nodes (node 0 pinned), spring group "rope.stretch" at ``{k}`` N/m and
#: ``{c}`` N s/m to fill in, both fitted
ROPE = """
dt = 1e-3
[[ropes]]
n = 4
start = [0.0, 0.0, 1.0]
end = [0.3, 0.0, 1.0]
mass = 0.3
k = {k}
c = {c}
pinned = [0]
[fit]
params = ["springs.rope.stretch.k", "springs.rope.stretch.c"]
"""


#: a 1 kg ball of radius 0.1 m dropped from 1 m onto a rubber plane, its contact k and c
#: fitted (from 7000, 15); add its records with data = [...]
BALL_FIT = """
dt = 1e-3
[materials.rubber]
k = 7000.0
c = 15.0
[[spheres]]
name = "ball"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 1.0]
material = "rubber"
[[planes]]
material = "rubber"
[fit]
params = ["contact.rubber.k", "contact.rubber.c"]
"""


def record_file(tmp_path, text, truth, bodies, name, *, integrator, dt, every, duration,
                 noise, seed, velocities=True):
    """Write the scene (start values) and a record of the truth made by ``integrator`` at
    ``dt`` (``velocities``: with velocity columns); returns (scene path, record path)."""
    scene = tmp_path / f"{name}.toml"
    scene.write_text(text)
    sf = load_scene_file(str(scene))
    sim = sf.compile(integrator=integrator, dt=dt)
    params = tf.with_leaves(sf.params(sim), truth)
    ids = {b: sf.names[b] for b in bodies}
    rec = tf.synthetic_record(sim, params, duration, every, ids, noise=noise, seed=seed,
                              velocities=velocities)
    path = tmp_path / f"{name}.csv"
    write_record(str(path), rec)
    return str(scene), str(path)


#: a six-node crumple bar (group "bar", k fitted) moving at 1 m/s into a wall plane, no
#: gravity: at k 200 N/m its members collapse (diffpen.terms.plastic), at 2000 they do not
CRUMPLE = """
dt = 1e-4
gravity = [0.0, 0.0, 0.0]
[materials.wall]
k = 1e5
c = 10.0
[[crumple_bars]]
n = 6
start = [0.1, 0.0, 0.5]
end = [0.6, 0.0, 0.5]
mass = 1.0
k = 2000.0
c = 1.0
yield_strain = 0.05
velocity = [-1.0, 0.0, 0.0]
[[planes]]
normal = [1.0, 0.0, 0.0]
offset = 0.0
material = "wall"
[fit]
params = ["springs.bar.k"]
"""
