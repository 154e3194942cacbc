"""Fuzzed input files: hundreds of generated bad TOML scene files and CSV records (fixed seed,
parsing only, nothing compiled) each end in a clear diffpen error naming the file -- never a
raw exception from tomllib, numpy or JAX, and never a hang."""
import random
import time

import numpy as np
import pytest

from tuning.records import RecordError, read_height_record, read_record
from tuning.scenefile import SceneFileError, load_scene_file

BASES = [
    """
dt = 1e-3
duration = 1.0
[materials.rubber]
k = 1e4
c = 10.0
friction = 0.2
slip_speed = 0.01
[[spheres]]
name = "ball"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 1.0]
material = "rubber"
[[planes]]
name = "ground"
offset = 0.0
material = "rubber"
[fit]
params = ["contact.rubber.k", "contact.rubber.c"]
settle_tol = 1e-3
maxiter = 10
[fit.targets]
apex_heights = [0.3]
settling_time = 2.0
""",
    """
gravity = [0.0, 0.0, -9.81]
integrator = "semi_implicit_euler"
[materials.steel]
k = 2e4
c = 20.0
friction = 0.3
[[boxes]]
name = "cube"
half_extents = [0.05, 0.05, 0.05]
mass = 0.37
position = [0.0, 0.0, 0.3]
orientation = [1.0, 0.0, 0.0, 0.0]
body_angular_velocity = [0.0, 1.0, 0.0]
inertia = [8e-4, 8e-4, 8e-4]
material = "steel"
[[rigid_spheres]]
radius = 0.05
mass = 0.2
position = [1.0, 0.0, 0.3]
[[planes]]
material = "steel"
[[anchored_springs]]
a = "cube"
anchor_a = [0.05, 0.05, 0.05]
anchor_b = [0.0, 0.0, 1.0]
k = 50.0
c = 0.5
group = "hang"
[[drag]]
bodies = ["cube"]
c = 0.01
""",
    """
broadphase = { kind = "aabb", max_pairs = 64 }
[spring_groups.tie]
k = 10.0
c = 0.1
[[ropes]]
n = 4
start = [0.0, 0.0, 1.0]
end = [0.3, 0.0, 1.0]
mass = 0.1
k = 100.0
c = 0.1
bend = [10.0, 0.01]
pinned = [0]
drag = 0.01
[[cloths]]
nx = 3
ny = 3
spacing = 0.1
mass = 0.1
origin = [0.0, 1.0, 1.0]
shear = false
pinned = [[0, 0]]
[[jellies]]
nx = 2
ny = 2
nz = 2
spacing = 0.05
mass = 0.1
origin = [0.0, 2.0, 1.0]
[[crumple_bars]]
n = 3
start = [0.0, 3.0, 1.0]
end = [0.2, 3.0, 1.0]
mass = 0.1
k = 500.0
yield_strain = 0.05
[[springs]]
a = "rope[1]"
b = "cloth[1,1]"
group = "tie"
[[plastic_springs]]
a = "jelly[0,0,0]"
b = "bar[2]"
k = 5.0
yield_strain = 0.2
group = "crush"
[[fixed_spheres]]
center = [5.0, 5.0, 0.0]
radius = 0.5
""",
]

JUNK = ['"0.1"', "true", "false", "-1", "0", "-1e300", "1e300", "nan", "inf", "-inf", "[]",
        "[1, 2]", '["a", "b", "c"]', "{}", '{ x = 1 }', '"zero"', '"../../etc/passwd"',
        "2.5", "9223372036854775807", "-9223372036854775808", "[[1, 2, 3]]", '""',
        "[1.0, 2.0, 3.0, 4.0]", "1979-05-27", '"rope[99]"', '"cloth[0,0,0]"', "[0, 0, 0]",
        "1e-320", "[nan, 0, 0]", '"lots"']
KEYS = ["dt", "duration", "k", "c", "radius", "mass", "position", "velocity", "material",
        "friction", "slip_speed", "targets", "data", "weights", "maxiter", "body", "plane",
        "params", "n", "nx", "spacing", "pinned", "bend", "drag", "yield_strain", "a", "b",
        "group", "bodies", "orientation", "inertia", "broadphase", "law", "settle_tol",
        "half_extents", "anchor_a", "width", "axes", "observe", "method", "name", "offset"]


def _mutate(rng: random.Random, text: str) -> bytes:
    lines = text.strip("\n").split("\n")
    op = rng.randrange(10)
    if op <= 3:                                   # a value replaced by junk
        idx = [i for i, ln in enumerate(lines) if " = " in ln] or [0]
        i = rng.choice(idx)
        key = lines[i].split(" = ")[0]
        lines[i] = f"{key} = {rng.choice(JUNK)}"
    elif op == 4 and len(lines) > 1:              # a line dropped
        del lines[rng.randrange(len(lines))]
    elif op == 5:                                 # a line duplicated or moved
        i = rng.randrange(len(lines))
        lines.insert(rng.randrange(len(lines)), lines[i])
    elif op == 6:                                 # a key added with junk
        i = rng.randrange(len(lines))
        lines.insert(i + 1, f"{rng.choice(KEYS)} = {rng.choice(JUNK)}")
    elif op == 7:                                 # a table header renamed or re-bracketed
        idx = [i for i, ln in enumerate(lines) if ln.startswith("[")] or [0]
        i = rng.choice(idx)
        name = lines[i].strip("[]")
        lines[i] = rng.choice([f"[{name}]", f"[[{name}]]", f"[{name}s]", f"[[{rng.choice(KEYS)}]]",
                               f"[fit.{name}]"])
    data = ("\n".join(lines) + "\n").encode()
    if op == 8:                                   # truncated
        data = data[:rng.randrange(len(data))]
    elif op == 9:                                 # bytes spliced in
        i = rng.randrange(len(data) + 1)
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 6)))
        data = data[:i] + junk + data[i:]
    return data


def _check(fn, path, errors):
    t0 = time.perf_counter()
    try:
        fn(path)
        ok = True
    except errors as exc:
        msg = str(exc)
        assert msg.startswith(path) or msg.startswith(f"cannot read {path}"), msg
        assert "Traceback" not in msg and len(msg) < 2000, msg
        ok = False
    # anything else (TypeError, KeyError, numpy or tomllib errors, ...) fails the test as is
    assert time.perf_counter() - t0 < 5.0, f"{path} took too long"
    return ok


@pytest.mark.filterwarnings("error")
def test_fuzzed_scene_files_end_in_scene_file_errors(tmp_path):
    rng = random.Random(20261201)
    n, loaded = 300, 0
    t0 = time.perf_counter()
    for i in range(n):
        base = BASES[i % len(BASES)]
        data = _mutate(rng, base)
        if rng.random() < 0.3:                    # two mutations at once
            data = _mutate(rng, data.decode("utf-8", "replace"))
        path = str(tmp_path / f"f{i}.toml")
        with open(path, "wb") as fh:
            fh.write(data)
        loaded += _check(load_scene_file, path, SceneFileError)
    # most mutations are errors; the ones that still describe a valid scene load
    assert loaded < n * 0.6
    assert time.perf_counter() - t0 < 30.0


CSV_JUNK = ["abc", "", "nan", "1e999", "--1", "0x10", " ", "1_0", "inf", "-", "1e-400",
            "1,2", '"', "\x00", "é", "1.0.0", "+", "NaN", "1e5", "-0", "12345678901234567890"]


def _record(rng: random.Random) -> str:
    t = np.arange(12) / 148.0
    q = np.tile([1.0, 0.0, 0.0, 0.0], (12, 1))
    if rng.random() < 0.5:
        cols = "t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz".split(",")
        rows = [[ti, 0.1, 0.2, 0.1 + ti, *qi, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
                for ti, qi in zip(t, q)]
    else:
        cols = ["t", "a.x", "a.y", "a.z", "b.x", "b.y", "b.z", "b.qw", "b.qx", "b.qy", "b.qz"]
        rows = [[ti, 0.0, 0.0, 1.0 - ti, 1.0, 0.0, 0.5, *qi] for ti, qi in zip(t, q)]
    cells = [cols] + [[f"{v:.6g}" for v in r] for r in rows]
    for _ in range(rng.randrange(1, 4)):
        op = rng.randrange(9)
        r = rng.randrange(len(cells))
        if not cells[r]:
            continue
        c = rng.randrange(len(cells[r]))
        if op <= 2:
            cells[r][c] = rng.choice(CSV_JUNK)
        elif op == 3:
            del cells[r][c]
        elif op == 4:
            cells[r].append(rng.choice(CSV_JUNK))
        elif op == 5 and r > 1:
            cells[r], cells[r - 1] = cells[r - 1], cells[r]
        elif op == 6 and c < len(cells[0]):
            cells[0][c] = rng.choice(["t", "x", "qw", "a.q", "b.", ".x", "T", "a.x", "zz"])
        elif op == 7:
            cells.insert(r, list(cells[r]))
        else:
            cells[r] = []
    return "\n".join(",".join(row) for row in cells) + "\n"


@pytest.mark.filterwarnings("error")
def test_fuzzed_records_end_in_record_errors(tmp_path):
    rng = random.Random(13)
    n, loaded = 300, 0
    t0 = time.perf_counter()
    for i in range(n):
        data = _record(rng).encode("utf-8", "surrogatepass")
        if rng.random() < 0.15:
            i0 = rng.randrange(len(data))
            data = data[:i0] + bytes(rng.randrange(256) for _ in range(3)) + data[i0:]
        if rng.random() < 0.1:
            data = data[:rng.randrange(len(data))]
        if rng.random() < 0.1:
            data = b"\xef\xbb\xbf" + data
        path = str(tmp_path / f"r{i}.csv")
        with open(path, "wb") as fh:
            fh.write(data)
        names = rng.choice([None, ["a", "b"], ["body"], ["cube"]])
        loaded += _check(lambda p: read_record(p, body_names=names), path, RecordError)
        _check(lambda p: read_height_record(p, min_rows=2), path, RecordError)
    assert loaded < n * 0.8
    assert time.perf_counter() - t0 < 30.0


@pytest.mark.parametrize("text", ["t,x,y,z\n" + "0," * 10**5 + "\n", "t" + ",x" * 10**5 + "\n",
                                  "\n" * 10**5, "#" * 10**6])
def test_degenerate_records_do_not_hang(tmp_path, text):
    path = str(tmp_path / "deg.csv")
    with open(path, "w") as fh:
        fh.write(text)
    t0 = time.perf_counter()
    with pytest.raises(RecordError):
        read_record(path)
    assert time.perf_counter() - t0 < 5.0
