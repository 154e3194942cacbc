"""Scene-file texts shared by the record-fit tests (tests/test_trajfit.py,
tests/test_first_state.py, tests/test_fit_resume.py): a box hung on two anchored springs
(group "hang", ``{k}`` N/m and ``{c}`` N s/m to fill in), and a particle thrown through air
with drag (group "air", fitted from 0.05)."""

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
