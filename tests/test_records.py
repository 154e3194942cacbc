"""Motion records (tuning.records): the real cube tosses read as they are, every malformed
record is refused with its file, line and column, write/read round-trips, and a record's
columns matched to a scene's bodies (named bodies, builder nodes, pinned bodies)."""
import glob
import os
import re

import numpy as np
import pytest

from tuning import trajfit as tf
from tuning.records import (BodyRecord, Record, RecordError, read_height_record, read_record,
                            write_record)
from tuning.scenefile import load_scene_file
from tuning.sysid import load_csv

from record_scenes import ROPE, record_file

#: the 100 real tosses shipped with the examples (examples/data/cube-toss, with its README
#: and licence)
CUBE = sorted(glob.glob(os.path.join(os.path.dirname(__file__), "..", "examples", "data",
                                     "cube-toss", "toss_*.csv")))


def _write(tmp_path, text, name="rec.csv", mode="w"):
    p = tmp_path / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text)
    return str(p)


def _rows(n=5, cols="x,y,z", fmt=None):
    k = len(cols.split(","))
    lines = [f"t,{cols}"]
    for i in range(n):
        vals = fmt(i) if fmt else [0.1 * (j + 1) + 0.01 * i for j in range(k)]
        lines.append(",".join([f"{0.01 * i:.4f}"] + [f"{v:.6g}" for v in vals]))
    return "\n".join(lines) + "\n"


def test_cube_tosses_read_as_they_are():
    assert len(CUBE) == 100                      # shipped: never skipped for want of data
    for path in CUBE:
        rec = read_record(path, body_names=["cube"])
        b = rec.bodies["cube"]
        T = len(rec)
        assert set(rec.bodies) == {"cube"} and 80 <= T <= 375
        assert b.position.shape == (T, 3) and b.quaternion.shape == (T, 4)
        assert b.velocity.shape == (T, 3) and b.angular_velocity.shape == (T, 3)
        assert np.all(np.diff(rec.t) > 0) and rec.t[0] == 0.0
        np.testing.assert_allclose(np.linalg.norm(b.quaternion, axis=1), 1.0, atol=1e-5)
    # the values are the file's own (first data row of the first toss, by hand)
    raw = np.loadtxt(CUBE[0], delimiter=",", skiprows=1)
    rec = read_record(CUBE[0])
    assert list(rec.bodies) == ["body"]
    np.testing.assert_array_equal(rec.bodies["body"].position, raw[:, 1:4])
    np.testing.assert_array_equal(rec.bodies["body"].angular_velocity, raw[:, 11:14])


def test_named_bodies_missing_samples_and_round_trip(tmp_path):
    t = np.linspace(0.0, 0.1, 6)
    pa = np.stack([t, 2 * t, 0.5 + t], 1)
    pb = pa + 1.0
    pb[2] = np.nan                                   # a missing sample
    q = np.tile([1.0, 0.0, 0.0, 0.0], (6, 1))
    rec = Record(path="x", t=t, bodies={"box": BodyRecord(position=pa, quaternion=q),
                                        "lid": BodyRecord(position=pb,
                                                          velocity=np.ones((6, 3)))})
    path = str(tmp_path / "two.csv")
    write_record(path, rec)
    assert open(path).readline().strip() == ("t,box.x,box.y,box.z,box.qw,box.qx,box.qy,box.qz,"
                                             "lid.x,lid.y,lid.z,lid.vx,lid.vy,lid.vz")
    back = read_record(path, body_names=["box", "lid", "other"])
    np.testing.assert_array_equal(back.t, t)
    np.testing.assert_array_equal(back.bodies["box"].position, pa)
    np.testing.assert_array_equal(back.bodies["lid"].position, pb)   # NaN row kept
    assert back.bodies["box"].velocity is None and back.bodies["lid"].quaternion is None
    with pytest.raises(RecordError, match=r"two.csv, line 1, column 9: 'lid.x' names body "
                                          r"'lid', which the scene does not have"):
        read_record(path, body_names=["box"])


def test_bom_comments_and_one_named_body(tmp_path):
    path = _write(tmp_path, b"\xef\xbb\xbf# recorded 2026\nT,X,Y,Z\n0,0,0,1\n\n0.1,0,0,0.9\n")
    rec = read_record(path, body_names=["ball"])
    assert list(rec.bodies) == ["ball"] and len(rec) == 2
    with pytest.raises(RecordError, match="carry no body name but the scene observes 2"):
        read_record(path, body_names=["a", "b"])


GOOD = _rows()


@pytest.mark.parametrize("text, words", [
    ("", "is empty"),
    ("x,y,z\n1,2,3\n", r"line 1: the header \(3 column\(s\)\) has no time column 't'"),
    ("t,x,y\n0,1,2\n0.1,1,2\n", r"line 1: columns x, y are there but z is missing"),
    ("t,x,y,z,qw,qx,qy\n0,1,2,3,1,0,0\n", "but qz is missing"),
    ("t,x,y,z,foo\n0,1,2,3,4\n0.1,1,2,3,4\n", r"line 1, column 5: unknown column 'foo'"),
    ("t,x,x,y,z\n", "appears twice"),
    ("t,a.x,a.y,a.z,z\n", r"column 5: 'z' has no body name"),
    ("t,qw,qx,qy,qz\n0,1,0,0,0\n0.1,1,0,0,0\n", "has no position columns"),
    (GOOD.replace("0.0200,0.12", "0.0200,abc"), r"line 4, column 2 \(x\): 'abc' is not a number"),
    (GOOD.replace("0.0200,0.12", "0.0200,inf"), r"line 4, column 2 \(x\): 'inf' is not finite"),
    # regression: a finite cell too large for the errors' squares (diffpen evaluate reported
    # null errors with exit status 0, diffpen fit advised a smaller dt)
    (GOOD.replace("0.0200,0.12", "0.0200,1e308"), r"line 4, column 2 \(x\): 1e\+308 m is "
                                                  r"beyond the 1e\+06 m"),
    ("t,x,y,z,vx,vy,vz\n0,0,0,1,0,0,0\n0.1,0,0,1,0,-2e7,0\n",
     r"line 3, column 6 \(vy\): -2e\+07 m/s is beyond"),
    # one absurd height cell of a record in metres: the cell, not "centimetres" (the
    # unit-slip check ran first)
    ("t,x,y,z\n" + "".join(f"{i * 0.01:.2f},0,0,{1e308 if i == 4 else 1.0}\n"
                           for i in range(8)),
     r"line 6, column 4 \(z\): 1e\+308 m is beyond the 1e\+06 m"),
    (GOOD.replace("0.0200,", ","), r"line 4, column 1 \(t\): a value is required"),
    (GOOD.replace("0.0200,", "0.0100,"), r"line 4, column 1 \(t\): times must strictly increase"),
    (GOOD.replace("0.0200,0.12", "0.0200,"), r"line 4, column 2 \(x\): the position of this "
                                             "row is incomplete"),
    (GOOD.replace("0.0300,0.13,0.23,0.33", "0.0300,0.13,0.23"), r"line 5: 3 cells but the "
                                                                  "header has 4"),
    (_rows(3, "x,y,z,qw,qx,qy,qz", lambda i: [0, 0, 1, 1, 0, 0, 0.5 * i]),
     r"line 3, column 5 \(qw\): the quaternion has norm 1.11803, not 1"),
    ("t,x,y,z\n" + "".join(f"{i * 10},0,0,1\n" for i in range(10)), "look like milliseconds"),
    ("t,x,y,z\n0,0,0,1\n0.1,0,0,145\n", r"line 3, column 4 \(z\): 145 m .* look like "
                                        "centimetres or millimetres"),
    ("t,x,y,z\n0,1,2,3\n", "1 data row"),
    ('t,x,y,z\n0,"1,2,3\n', "cells"),
    ("t,x,y,z\n0,1_0,2,3\n0.1,1,2,3\n", "'1_0' is not a number"),
    (b"t,x,y,z\n0,1,2\x00\x01,3\n", r"binary file \(a zero byte at offset 13\)"),
    (b"t,x,y,z\n0,1,2,3\n0.1,\xff\xfe,2,3\n", r"line 3: byte 0xff at offset 20 is not UTF-8"),
])
def test_bad_records_name_file_line_and_column(tmp_path, text, words):
    path = _write(tmp_path, text)
    with pytest.raises(RecordError, match=words) as exc:
        read_record(path)
    assert str(exc.value).startswith(path)


def test_unit_hints_can_be_turned_off(tmp_path):
    path = _write(tmp_path, "t,x,y,z\n" + "".join(f"{i * 10},0,0,{i * 100}\n" for i in range(10)))
    rec = read_record(path, check_units=False)
    assert rec.t[-1] == 90.0 and rec.bodies["body"].position[-1, 2] == 900.0


def test_size_guard_refuses_before_parsing(tmp_path):
    body = "".join(f"{i * 1e-3:.6f},0.1,0.2,0.3\n" for i in range(20000))
    path = _write(tmp_path, "t,x,y,z\n" + body)
    with pytest.raises(RecordError, match=r"about 2\d,\d{3} rows of 4 columns .* limit is "
                                          r"1,000 rows.*max_rows="):
        read_record(path, max_rows=1000)
    with pytest.raises(RecordError, match=r"MiB.*max_bytes=") as e:
        read_record(path, max_bytes=10_000)
    # regression: "pass max_rows= to read it anyway" was offered to command-line users, whose
    # commands have no such option
    assert "the diffpen commands keep the limit" in str(e.value)
    assert len(read_record(path, max_rows=30_000)) == 20000
    with pytest.raises(RecordError, match="is a directory"):
        read_record(str(tmp_path))
    # regression: /dev/zero reports size 0 and never ends: it was read until the memory ran
    # out (23.7 GB, killed); a FIFO nobody writes blocked forever
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    for special in ("/dev/zero", str(fifo)):
        if os.path.exists(special):
            with pytest.raises(RecordError, match=r"is not a regular file \(a device, pipe "
                                                  r"or socket\); give a CSV record file"):
                read_record(special)
    with pytest.raises(RecordError, match="cannot read"):
        read_record(str(tmp_path / "nope.csv"))


def test_ball_height_record_reads_through_the_same_module(tmp_path):
    """The ball's t,z record (diffpen fit --data) goes through tuning.records: the same unit
    hints and binary checks apply (a t,z record in milliseconds used to be fitted to nonsense)."""
    ms = _write(tmp_path, "t,z\n" + "".join(f"{i * 5},{1.0 - 1e-6 * i * i}\n" for i in range(40)))
    with pytest.raises(RecordError, match=r"look like milliseconds.*a record whose steps "
                                          r"really are seconds is read in Python with "
                                          r"check_units=False; the diffpen commands refuse"):
        load_csv(ms)
    mm = _write(tmp_path, "t,z\n" + "".join(f"{i * 0.005},{1000 - i}\n" for i in range(40)),
                name="mm.csv")
    with pytest.raises(RecordError, match="look like centimetres or millimetres"):
        load_csv(mm)
    ok = _write(tmp_path, "\ufefft,z,extra\n" + "".join(f"{i * 0.005},{1 - i * 1e-3},x\n"
                                                         for i in range(40)), name="ok.csv")
    t, z = read_height_record(ok)
    assert t.shape == z.shape == (40,) and z[1] == 0.999


def _fall(z, up=0.0, duration=2.0, noise=1e-3, scale=1.0, cols="z"):
    """A record of a body leaving height z (m) at ``up`` m/s, at 200 Hz: free fall at
    9.81 m/s^2 with ``noise`` (m), written times ``scale`` (100: cm). Returns (text, heights)."""
    t = np.arange(0.0, duration, 0.005)
    h = z + up * t - 4.905 * t * t + noise * np.random.default_rng(0).standard_normal(t.shape)
    pad = "0,0," if cols != "z" else ""
    return (f"t,{cols}\n" + "".join(f"{a:.4f},{pad}{b * scale:.9g}\n" for a, b in zip(t, h)),
            h)


def test_heights_beyond_20_m_that_fall_at_g_are_metres(tmp_path):
    """A ball dropped from 20 m or 25 m, or thrown up to 25.7 m, in metres: refused as
    "centimetres or millimetres" (beyond 20 m) with advice the commands could not follow;
    it falls at 9.81 m/s^2, so it is read. A 1 m drop written in cm or mm falls at 981 or
    9810 per s^2 and is still refused, for both the t,z and the scene records."""
    for z, up, cols in ((20.0001, 0.0, "z"), (25.0, 0.0, "z"), (1.0, 22.0, "x,y,z")):
        text, h = _fall(z, up, duration=4.0 if up else 2.0, cols=cols)
        path = _write(tmp_path, text)
        got = (read_height_record(path)[1] if cols == "z"
               else read_record(path).bodies["body"].position[:, 2])
        np.testing.assert_allclose(got, h, atol=1e-6)
    for scale, accel in ((100.0, r"9\d\d per s\^2 \(\d+ g"),
                         (1000.0, r"9\d{3} per s\^2 \(\d+ g")):
        for cols, read in (("z", read_height_record), ("x,y,z", read_record)):
            text, _ = _fall(1.0, duration=0.4, noise=1e-3 / scale, scale=scale, cols=cols)
            path = _write(tmp_path, text)
            with pytest.raises(RecordError, match=r"line 2, column \d \(z\): \d+ m is beyond "
                                                  rf"20 m and the record falls there at about "
                                                  rf"{accel}.*look like centimetres or "
                                                  r"millimetres.*Divide them by 100 or 1000\.$"):
                read(path)


def test_heights_beyond_20_m_without_a_fall_say_how_to_read_metres(tmp_path):
    """A record beyond 20 m that shows no free fall (at rest, or a straight line) cannot be
    told from centimetres: it is refused, and the advice for a record that really is in metres
    names the Python reader and its check_units=False (the commands have no such option)."""
    rest = "".join(f"{i * 0.01:.2f},{25.0 + 1e-3 * (-1) ** i}\n" for i in range(40))
    for head, read in (("t,z", "read_height_record"), ("t,x,y,z", "read_record")):
        text = head + "\n" + (rest if head == "t,z" else rest.replace(",", ",0,0,"))
        path = _write(tmp_path, text)
        with pytest.raises(RecordError, match=r"25.001 m is beyond 20 m and the record shows "
                                              r"no free fall .*look like centimetres or "
                                              rf"millimetres.*tuning\.records\.{read}\(path, "
                                              r"check_units=False\) \(the diffpen commands "
                                              r"refuse it\)"):
            (read_height_record if head == "t,z" else read_record)(path)
        if head == "t,z":
            assert read_height_record(path, check_units=False)[1][1] == 24.999


def test_builder_node_names_round_trip(tmp_path):
    """Builder nodes are named like "cloth[1,2]": the header cell is quoted and read back."""
    t = np.array([0.0, 0.01, 0.02])
    p = np.arange(9.0).reshape(3, 3) * 0.1
    rec = Record(path="x", t=t, bodies={"cloth[1,2]": BodyRecord(position=p),
                                        "rope[3]": BodyRecord(position=p + 1)})
    path = str(tmp_path / "nodes.csv")
    write_record(path, rec)
    back = read_record(path, body_names=["cloth[1,2]", "rope[3]"])
    np.testing.assert_array_equal(back.bodies["cloth[1,2]"].position, p)
    np.testing.assert_array_equal(back.bodies["rope[3]"].position, p + 1)


@pytest.mark.parametrize("cols", ["cloth[1,2].x,cloth[1,2].y,cloth[1,2].z",
                                  "cloth[1, 2].x,cloth[1, 2].y,cloth[1, 2].z",
                                  "cloth[1,2].x"])
def test_unquoted_node_name_with_a_comma_says_to_quote_it(tmp_path, cols):
    """Regression: an unquoted "cloth[1,2].x" is split at its comma by the CSV reader and was
    refused as "column 'cloth[1' appears twice"; the message now says to quote it."""
    path = _write(tmp_path, _rows(3, cols))
    with pytest.raises(RecordError, match=r"line 1: header cell 'cloth\[1' looks like a node "
                       r"name split at its comma: node names containing commas must be quoted "
                       r'in the CSV header, e\.g\. "cloth\[1, 2\]\.x" in double quotes') as exc:
        read_record(path)
    assert "appears twice" not in str(exc.value)


def test_one_named_body_keeps_its_name(tmp_path):
    """Regression: a one-body record was written t,x,y,z, dropping the body's name: read back
    it was body "body" and a scene observing two bodies refused it. A plain one-body file
    (and a record of body "body") still reads as before."""
    t = np.array([0.0, 0.01, 0.02])
    p = np.zeros((3, 3)) + [0.0, 0.0, 0.1]
    path = str(tmp_path / "cube.csv")
    write_record(path, Record("x", t, {"cube": BodyRecord(position=p)}))
    assert open(path).readline().strip() == "t,cube.x,cube.y,cube.z"
    back = read_record(path, body_names=["ball", "cube"])
    assert list(back.bodies) == ["cube"]
    np.testing.assert_array_equal(back.bodies["cube"].position, p)
    write_record(path, Record("x", t, {"body": BodyRecord(position=p)}))
    assert open(path).readline().strip() == "t,x,y,z"
    assert list(read_record(path, body_names=["cube"]).bodies) == ["cube"]
    assert list(read_record(path).bodies) == ["body"]


@pytest.mark.parametrize("header", ["t,z,z", "t,T,z", "T,Z,t,z"])
def test_ball_height_record_refuses_a_column_twice(tmp_path, header):
    """Regression: read_height_record used the first of two z (or t) columns; read_record
    refuses duplicates, and so does it now."""
    n = len(header.split(","))
    path = _write(tmp_path, header + "\n" + "".join(
        ",".join([f"{i * 0.005}"] * n) + "\n" for i in range(40)))
    with pytest.raises(RecordError, match=r"line 1: column '[tz]' appears twice in the header"):
        read_height_record(path)


def test_a_scene_body_left_out_of_observe_is_named_as_such(tmp_path):
    """Regression: with [fit] observe = ["cube"], columns of the scene's body 'ball' were
    refused as a body the scene does not have; the message now says it is not observed."""
    path = _write(tmp_path, _rows(3, "cube.x,cube.y,cube.z,ball.x,ball.y,ball.z"))
    with pytest.raises(RecordError, match=r"rec.csv, line 1, column 5: 'ball.x' names body "
                                          r"'ball', which is not in \[fit\] observe \(cube\); "
                                          r"add 'ball' to observe or drop its columns"):
        read_record(path, body_names=["cube"], scene_names=["ball", "cube"])
    with pytest.raises(RecordError, match="which the scene does not have; named bodies: cube"):
        read_record(path, body_names=["cube"], scene_names=["cube"])
    with pytest.raises(RecordError, match=r"column 2: 'cube.x' names body 'cube', which the "
                                          r"scene does not have; named bodies: none \(give"):
        read_record(path, body_names=[])


def test_empty_cell_hint_only_where_a_sample_may_be_missing(tmp_path):
    """Regression: a bad cell of the t,z record (or of a record's t column) said "write a
    decimal number (or leave the cell empty for a missing sample)", and an empty cell there
    was then refused ("a value is required here"). The hint is now given only in the
    columns that allow a missing sample (a body's x, y, z, ...)."""
    rows = [f"{i * 0.01!r},{1.0 - 0.5 * 9.81 * (i * 0.01) ** 2!r}" for i in range(30)]
    for cell, words in (("1..2", "'1..2' is not a number; write a decimal number."),
                        ("inf", "'inf' is not finite; write a finite decimal number."),
                        ("", "a value is required here")):
        path = _write(tmp_path, "t,z\n" + "\n".join(rows[:10] + [f"0.1,{cell}"] + rows[11:]))
        with pytest.raises(RecordError, match=r"line 12, column 2 \(z\): " + re.escape(words)) \
                as exc:
            read_height_record(path)
        assert "missing sample" not in str(exc.value)
    short = _write(tmp_path, "t,z\n" + "\n".join(rows[:10] + ["0.1"] + rows[11:]))
    with pytest.raises(RecordError, match="line 12: 1 cells but the header has 2") as exc:
        read_height_record(short)
    assert "missing sample" not in str(exc.value)
    for t_cell in ("abc", "inf"):
        with pytest.raises(RecordError, match=r"line 4, column 1 \(t\)") as exc:
            read_record(_write(tmp_path, GOOD.replace("0.0200,", f"{t_cell},")))
        assert "missing sample" not in str(exc.value)
    # a body column allows one: there the hint stays
    with pytest.raises(RecordError, match=r"write a decimal number \(or leave the cell empty "
                                          r"for a missing sample\)"):
        read_record(_write(tmp_path, GOOD.replace("0.0200,0.12", "0.0200,abc")))


def test_write_record_follows_a_symbolic_link(tmp_path):
    """write_record wrote through its own temporary file and os.replace: a symbolic link was
    replaced by a plain file, its target left as it was. It writes through tuning.io's
    atomic_write now: the target gets the record, the link stays, no temporary file is left."""
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "rec.csv"
    target.write_text("old\n")
    link = tmp_path / "rec.csv"
    link.symlink_to(target)
    t = np.arange(4) * 0.01
    pos = np.column_stack([t, 2 * t, 1.0 - t])
    write_record(str(link), Record(str(link), t, {"body": BodyRecord(pos)}))
    assert link.is_symlink()
    np.testing.assert_array_equal(read_record(str(target)).bodies["body"].position, pos)
    assert sorted(os.listdir(tmp_path / "real")) == ["rec.csv"]


def test_a_rigid_body_without_orientation_columns_is_warned_about(tmp_path, cube):
    """A record with positions only of a box started it silently from the scene file's
    orientation with no spin (31.9% position error against 1.40% with quaternions)."""
    from tuning.records import BodyRecord, Record
    t = np.arange(12) * 5e-3
    pos = np.stack([np.zeros(12), np.zeros(12), 0.3 - 4.9 * t ** 2], axis=1)
    rec = Record(path=str(tmp_path / "posonly.csv"), t=t, bodies={"0": BodyRecord(pos)})
    with pytest.warns(UserWarning, match="no orientation columns .* posonly.csv"):
        tf.prepare(cube, [rec])


def test_a_record_of_a_pinned_body_prepares(tmp_path):
    """A record that also tracks a rope's pinned end failed ("body 0 is pinned ... takes
    no velocity"): its estimated velocity went to state_from. A pinned body keeps zero
    velocity; a zero velocity is accepted."""
    text = ROPE.format(k=200.0, c=0.3)
    scene, rec = record_file(tmp_path, text, {}, ["rope[0]", "rope[2]"], "rope",
                              integrator="rk4", dt=2.5e-4, every=5e-3, duration=0.1,
                              noise=1e-4, seed=1)
    sf = load_scene_file(scene)
    sim = sf.compile()
    records, bodies = tf.load_records(sf, [rec])
    for est in ("record", "fit"):
        batch = tf.prepare(sim, records, bodies=bodies, estimate=est)
        assert np.all(np.asarray(batch.start.velocity)[0, sf.names["rope[0]"]] == 0.0)
    sim.state_from(body=sf.names["rope[0]"], velocity=(0.0, 0.0, 0.0))


def test_records_may_observe_builder_nodes_beside_named_bodies(tmp_path):
    """Regression: with a named body in the scene, a record column of a builder's node
    (rope[3].x, the README's multi-body form) was refused as 'names body rope[3], which the
    scene does not have'; now it resolves to the node (a node outside the builder is still
    refused, naming the record)."""
    scene = tmp_path / "mixed.toml"
    scene.write_text('dt = 1e-3\nduration = 0.2\n[[boxes]]\nname = "cube"\n'
                     'half_extents = [0.05, 0.05, 0.05]\nmass = 0.4\n'
                     'position = [0.0, 0.0, 0.5]\n[[ropes]]\nn = 4\nstart = [0.0, 0.5, 1.0]\n'
                     'end = [0.3, 0.5, 1.0]\nmass = 0.1\nk = 200.0\nc = 0.2\n'
                     '[fit]\nparams = ["springs.rope.stretch.k"]\n')
    sf = load_scene_file(str(scene))
    good, bad = tmp_path / "good.csv", tmp_path / "bad.csv"
    for path, node in ((good, "rope[3]"), (bad, "rope[9]")):
        path.write_text(f"t,cube.x,cube.y,cube.z,{node}.x,{node}.y,{node}.z\n"
                        "0.0,0.0,0.0,0.5,0.3,0.5,1.0\n0.01,0.0,0.0,0.4995,0.3,0.5,0.9995\n")
    _, bodies = tf.load_records(sf, [str(good)])
    assert bodies == {"cube": sf.names["cube"], "rope[3]": sf.body_index("rope[3]")}
    with pytest.raises(tf.FitError, match="bad.csv: the columns of 'rope\\[9\\]'"):
        tf.load_records(sf, [str(bad)])


SPHERE = ('dt = 1e-3\nduration = 0.1\n[[spheres]]\n{name}radius = 0.05\nmass = 0.2\n'
          'position = [0.0, 0.0, 0.5]\n')


ROPE_ONLY = ('dt = 1e-3\nduration = 0.1\n{pinned}[[ropes]]\nn = 4\nstart = [0.0, 0.0, 1.0]\n'
             'end = [0.3, 0.0, 1.0]\nmass = 0.4\nk = 300.0\n')


PINNED = ('[[spheres]]\nname = "s"\nradius = 0.05\nmass = 0.1\nposition = [5.0, 0.0, 1.0]\n'
          'pinned = true\n')


def _scene_and_records(tmp_path, text, *headers):
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    paths = []
    for k, header in enumerate(headers):
        n = header.count(".x") or 1
        path = tmp_path / f"rec{k}.csv"
        path.write_text(f"t,{header}\n" + "".join(
            f"{0.01 * i}" + ",0.3,0.0,1.0" * n + "\n" for i in range(3)))
        paths.append(str(path))
    return load_scene_file(str(scene)), paths


def test_record_columns_of_bodies_the_scene_lacks_are_refused(tmp_path):
    """Regression: in a scene without named bodies, columns a.x, b.x (bodies it does not
    have) were both mapped onto its only free body. They are refused with the file, line
    and column; plain x, y, z columns still belong to that body."""
    sf, (plain, ab) = _scene_and_records(tmp_path, SPHERE.format(name=""), "x,y,z",
                                         "a.x,a.y,a.z,b.x,b.y,b.z")
    assert tf.load_records(sf, [plain])[1] == {"body": 0}
    with pytest.raises(tf.FitError, match=r"rec1.csv, line 1, column 2: 'a.x' names body "
                                          r"'a', which the scene does not have; named "
                                          r"bodies: none"):
        tf.load_records(sf, [ab])


@pytest.mark.parametrize("pinned", ["", PINNED])
def test_node_columns_resolve_with_or_without_named_bodies(tmp_path, pinned):
    """Regression: rope[-1].x and rope[ 3 ].x (the README's node forms) were refused when the
    scene had no named body ("the columns name no body and the scene has 3 free bodies")."""
    sf, paths = _scene_and_records(tmp_path, ROPE_ONLY.format(pinned=pinned),
                                   *(f"{n}.x,{n}.y,{n}.z" for n in
                                     ("rope[3]", "rope[-1]", "rope[ 3 ]")))
    node = sf.body_index("rope[3]")
    for path, name in zip(paths, ("rope[3]", "rope[-1]", "rope[ 3 ]")):
        assert tf.load_records(sf, [path])[1] == {name: node}


def test_one_body_under_two_names_is_refused(tmp_path):
    """Regression: rope[3] and rope[-1] (the same node) with different data were accepted,
    the start state taken from the last. Two names of one body are refused, naming both,
    within a record and across records; prepare's own body map refuses it too."""
    sf, (both, three, last) = _scene_and_records(
        tmp_path, ROPE_ONLY.format(pinned=PINNED),
        "rope[3].x,rope[3].y,rope[3].z,rope[-1].x,rope[-1].y,rope[-1].z",
        "rope[3].x,rope[3].y,rope[3].z", "rope[-1].x,rope[-1].y,rope[-1].z")
    node = sf.body_index("rope[3]")
    with pytest.raises(tf.FitError, match=r"rec0.csv: the columns rope\[3\].x, ... and "
                                          rf"rope\[-1\].x, ... observe the same scene body "
                                          rf"{node}: name each body once"):
        tf.load_records(sf, [both])
    with pytest.raises(tf.FitError, match=r"rec2.csv: the columns rope\[-1\].x, ... observe "
                                          rf"the same scene body {node}, and .*rec1.csv names "
                                          r"it 'rope\[3\]'"):
        tf.load_records(sf, [three, last])
    from tuning.records import read_record
    rec = read_record(both)
    with pytest.raises(tf.FitError, match=r"record bodies 'rope\[3\]' and 'rope\[-1\]' both "
                                          rf"map to body {node}"):
        tf.prepare(sf.compile(), [rec], bodies={"rope[3]": node, "rope[-1]": node})


def test_columns_of_a_body_left_out_of_observe_say_so(tmp_path):
    """Regression: with [fit] observe = ["cube"], columns of the scene's body 'ball' were
    refused as a body 'the scene does not have'."""
    text = (SPHERE.format(name='name = "ball"\n') + SPHERE.format(name='name = "cube"\n')
            .replace("0.0, 0.0, 0.5", "1.0, 0.0, 0.5").split("duration = 0.1\n")[1]
            + '[fit]\nobserve = ["cube"]\nparams = ["contact.default.k"]\n')
    sf, (path,) = _scene_and_records(tmp_path, text, "cube.x,cube.y,cube.z,ball.x,ball.y,ball.z")
    with pytest.raises(tf.FitError, match=r"rec0.csv, line 1, column 5: 'ball.x' names body "
                                          r"'ball', which is not in \[fit\] observe \(cube\); "
                                          r"add 'ball' to observe or drop its columns"):
        tf.load_records(sf, [path])


def test_a_record_given_twice_is_refused(tmp_path):
    """Regression: the same record given twice (or a copy of it; overlapping shell patterns
    repeat files) was fitted twice without a word: k moved from 1.09e4 to 5882 on two cube
    tosses, and the standard errors counted the copies as independent records."""
    sf = load_scene_file(os.path.join(os.path.dirname(__file__), "..", "examples",
                                      "cube_toss.toml"))
    a, b = CUBE[0], CUBE[1]
    copy = tmp_path / "copy.csv"
    copy.write_bytes(open(a, "rb").read())
    spelled = os.path.join(os.path.dirname(a), ".", os.path.basename(a))
    for paths, words in (([a, b, a], "is the same file as"), ([a, spelled], "is the same file"),
                         ([a, str(copy)], f"copy.csv is a copy of {a}")):
        with pytest.raises(tf.FitError, match="give each record once") as exc:
            tf.load_records(sf, paths)
        assert words in str(exc.value)
    records, bodies = tf.load_records(sf, [a, b])
    assert len(records) == 2


def test_a_toss_in_centimetres_below_twenty_up_is_refused(tmp_path):
    """Regression: only z was held against the 20 m limit, so a cube toss in centimetres that
    stayed below 20 "m" up (z ~ 14.5, x ~ 22) was read as metres and evaluated at 823%."""
    lines = open(CUBE[0]).read().splitlines()
    header = lines[0].split(",")
    cols = [header.index(c) for c in ("x", "y", "z")]
    rows = []
    for line in lines[1:30]:
        cells = line.split(",")
        for c in cols:
            cells[c] = repr(float(cells[c]) * 100.0)
        rows.append(",".join(cells))
    path = _write(tmp_path, "\n".join([lines[0], *rows]) + "\n", name="cm.csv")
    as_read = read_record(path, check_units=False).bodies["body"].position
    assert np.nanmax(np.abs(as_read[:, 2])) < 20 < np.nanmax(np.abs(as_read))
    with pytest.raises(RecordError, match=r"column \d+ \(x\): .* m is beyond 20 m .* look like "
                                          r"centimetres or millimetres"):
        read_record(path)


def test_a_record_far_from_the_origin_in_metres_is_read(tmp_path):
    """Regression of the check above: x or y beyond 20 m with no fall to judge by (a cube at
    rest 25 m from a lab frame's origin) was refused as centimetres; only a fall that shows
    centimetres refuses x or y now (a height beyond 20 m still needs a fall that shows
    metres)."""
    rows = "".join(f"{i / 148!r},25.0,0.0,0.0514,1,0,0,0\n" for i in range(40))
    path = _write(tmp_path, "t,x,y,z,qw,qx,qy,qz\n" + rows, name="far.csv")
    assert read_record(path).bodies["body"].position[0, 0] == 25.0
    high = _write(tmp_path, "t,x,y,z\n" + "".join(f"{i / 148!r},0,0,25.0\n" for i in range(40)),
                  name="high.csv")
    with pytest.raises(RecordError, match="beyond 20 m and the record shows no free fall"):
        read_record(high)
