"""Measured motion records: CSV files of body poses (and optionally velocities) over time.

Format: a header row, then one row per sample (``#`` lines and blank lines are skipped; a UTF-8
byte-order mark is accepted; cells are separated by commas)::

    t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz          (one observed body)
    t,box.x,box.y,box.z,lid.x,lid.y,lid.z,...       (several: "name." before each column)

========================  =========================================================  ======
columns                   meaning                                                    unit
========================  =========================================================  ======
``t``                     sample time, strictly increasing, never missing            s
``x, y, z``               body centre (required for every observed body)             m
``qw, qx, qy, qz``        unit quaternion body -> world (optional)                   -
``vx, vy, vz``            centre velocity, world frame (optional)                    m/s
``wx, wy, wz``            angular velocity, BODY frame (optional)                    rad/s
========================  =========================================================  ======

A missing sample is an empty cell (or ``nan``); a group (position, quaternion, velocity, angular
velocity) is either complete or empty in each row. Every problem raises :class:`RecordError`
naming the file, the line and the column, and saying what to change. Nothing is compiled.

:func:`read_record` reads such a record; :func:`read_height_record` reads the bouncing ball's
``t,z`` record (``diffpen fit --data``) with the same checks.
"""
from __future__ import annotations

import csv
import io
import dataclasses
import math
import os
from typing import Sequence

import numpy as np

from .errors import FitError
from .io import atomic_write
from .record_units import FALL, FALL_FACTOR, MM_LIMIT, MS_SPAN, unit_slip
from .record_units import fall_rate as _fall

__all__ = ["Record", "BodyRecord", "RecordError", "read_record", "load_records",
           "read_height_record", "write_record", "GROUPS", "DEFAULT_MAX_ROWS", "DEFAULT_MAX_BYTES"]

#: column groups of one body: name -> component suffixes (in array order)
GROUPS = {
    "position": ("x", "y", "z"),
    "quaternion": ("qw", "qx", "qy", "qz"),
    "velocity": ("vx", "vy", "vz"),
    "angular_velocity": ("wx", "wy", "wz"),
}
_SUFFIX = {s: (g, i) for g, comps in GROUPS.items() for i, s in enumerate(comps)}

#: size guard: records above these are refused before they are parsed (raise them by argument)
DEFAULT_MAX_ROWS = 500_000
DEFAULT_MAX_BYTES = 256 * 2**20
#: |q| may differ from 1 by this much (trackers write 6 decimals)
QUAT_TOL = 1e-3
#: positions (m), velocities (m/s) and angular velocities (rad/s) of a record must be within
#: this of 0 (a scene file's coordinates: 1e6 m), whatever ``check_units``: a cell of 1e308
#: passed and overflowed the errors to NaN (``diffpen evaluate`` then reported null errors
#: with exit status 0)
MAX_MAGNITUDE = {"position": 1e6, "velocity": 1e6, "angular_velocity": 1e6}
_UNIT = {"position": "m", "velocity": "m/s", "angular_velocity": "rad/s"}


class RecordError(FitError):
    """A record file that cannot be read: the message names the file, line and column, and the
    fix. (A :class:`ValueError`, like every bad-input error of tuning.)"""


@dataclasses.dataclass
class BodyRecord:
    """Samples of one body; rows align with :attr:`Record.t`, NaN where a sample is missing.

    position: (T, 3) m.  quaternion: (T, 4) (w, x, y, z), body -> world, or None.
    velocity: (T, 3) m/s, world frame, or None.  angular_velocity: (T, 3) rad/s, BODY frame,
    or None.
    """
    position: np.ndarray
    quaternion: np.ndarray | None = None
    velocity: np.ndarray | None = None
    angular_velocity: np.ndarray | None = None


@dataclasses.dataclass
class Record:
    """A parsed record: ``path``, sample times ``t`` (T,) s, and ``bodies`` name ->
    :class:`BodyRecord`."""
    path: str
    t: np.ndarray
    bodies: dict

    @property
    def duration(self) -> float:
        """Time from the first to the last sample, s."""
        return float(self.t[-1] - self.t[0])

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __repr__(self) -> str:
        parts = []
        for name, b in self.bodies.items():
            have = [g for g in GROUPS if getattr(b, g) is not None]
            parts.append(f"{name}: {'+'.join(have)}")
        return (f"Record({self.path!r}, {len(self)} samples over {self.duration:g} s, "
                f"{'; '.join(parts)})")


def _q(text: str) -> str:
    """A header cell for a message, cut short (a record's content is never quoted at length)."""
    return repr(text if len(text) <= 40 else text[:37] + "...")


# --------------------------------------------------------------------------- raw reading
def _estimate(path: str, size: int, sample: bytes) -> tuple[int, int]:
    """(estimated rows, estimated columns) of a text file from its first bytes."""
    lines = sample.splitlines()
    if len(sample) < size and lines:
        lines = lines[:-1]          # the last one may be cut
    lines = [ln for ln in lines if ln.strip()]
    if not lines:
        return (1, 1)
    per_line = sum(len(ln) + 1 for ln in lines) / len(lines)
    cols = max(ln.count(b",") + 1 for ln in lines[:50])
    return max(1, int(size / per_line)), cols


def _read_text(path: str, max_rows: int, max_bytes: int) -> str:
    """The decoded text of a record after the size and binary checks."""
    try:
        size = os.path.getsize(path)
        if os.path.isdir(path):
            raise RecordError(f"{path} is a directory; give a CSV record file.")
        if not os.path.isfile(path):    # /dev/zero has size 0 and no end; a FIFO may block
            raise RecordError(f"{path} is not a regular file (a device, pipe or socket); give "
                              "a CSV record file (save a pipe's output to a file first).")
        with open(path, "rb") as fh:
            sample = fh.read(65536)
            if size > max_bytes:
                rows, cols = _estimate(path, size, sample)
                raise RecordError(
                    f"{path} is {size / 2**20:.1f} MiB (about {rows:,} rows of {cols} columns); "
                    f"records above {max_bytes / 2**20:.0f} MiB are refused before reading. "
                    "Downsample it (in Python, read_record(..., max_bytes=, max_rows=) reads it; "
                    "the diffpen commands keep the limit).")
            rows, cols = _estimate(path, size, sample)
            if rows > 1.2 * max_rows + 10:
                mem = rows * cols * 8 / 2**20
                raise RecordError(
                    f"{path} holds about {rows:,} rows of {cols} columns ({mem:.0f} MiB as "
                    f"float64, several times that while parsing); the limit is {max_rows:,} rows. "
                    "Downsample it: a contact fit rarely needs more than a few kHz (in Python, "
                    "read_record(..., max_rows=) reads it; the diffpen commands keep the limit).")
            raw = sample + fh.read()
    except RecordError:
        raise
    except OSError as exc:
        raise RecordError(f"cannot read {path}: {exc.strerror or exc}.") from None
    nul = raw.find(b"\x00", 0, 1 << 16)
    if nul >= 0:
        raise RecordError(f"{path} is a binary file (a zero byte at offset {nul}), not a CSV "
                          "record; export the data as text with a header row such as "
                          "t,x,y,z.")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise RecordError(f"{path}, line {line}: byte 0x{raw[exc.start]:02x} at offset "
                          f"{exc.start} is not UTF-8 text; save the record as UTF-8 (or ASCII) "
                          "CSV.") from None


def _skipped(line: str) -> bool:
    """A blank or comment (``#``) line, which records may hold anywhere."""
    s = line.strip()
    return not s or s[0] == "#"


def header_columns(path: str) -> list[str] | None:
    """The lower-case column names of the record at ``path`` (its first line that is not
    blank or a comment), without reading the rest; None where it cannot be read."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            for line in fh:
                if not _skipped(line):
                    return [c.strip().strip('"').lower() for c in line.split(",")]
    except OSError:
        pass
    return None


def _rows(path: str, text: str) -> tuple[list[str], int, list[tuple[int, list[str]]]]:
    """(header cells, header line number, [(line number, cells)] of the data rows)."""
    lines = text.splitlines()
    quoted = '"' in text               # plain files are split without the csv module (fast)
    header, hline, data = None, 0, []
    for no, line in enumerate(lines, start=1):
        if _skipped(line):
            continue
        if quoted:
            try:
                cells = next(csv.reader([line]))
            except csv.Error as exc:
                raise RecordError(f"{path}, line {no}: cannot split the line into cells "
                                  f"({exc}); write plain comma-separated numbers.") from None
        else:
            cells = line.split(",")
        if header is None:
            header, hline = [c.strip() for c in cells], no
        else:
            data.append((no, cells))
    if header is None:
        raise RecordError(f"{path} is empty: expected a header row (such as t,x,y,z) and rows "
                          "of numbers.")
    return header, hline, data


def _column(path: str, data, j: int, name: str, *, allow_missing: bool) -> np.ndarray:
    """Column ``j`` of the data rows as float64; empty (or nan) cells -> NaN when allowed.
    Converted in one vectorised pass; any problem is located cell by cell."""
    raw = np.array([cells[j] for _, cells in data], dtype=str)
    try:
        if raw.size and (np.char.find(raw, "_") >= 0).any():
            raise ValueError
        vals = np.where(np.char.strip(raw) == "", "nan", raw).astype(np.float64)
    except ValueError:
        return _column_slow(path, data, j, name, allow_missing=allow_missing)
    if np.isinf(vals).any() or (not allow_missing and np.isnan(vals).any()):
        return _column_slow(path, data, j, name, allow_missing=allow_missing)
    return vals


def _column_slow(path: str, data, j: int, name: str, *, allow_missing: bool) -> np.ndarray:
    """:func:`_column` cell by cell, raising at the first bad cell with its line."""
    out = np.empty(len(data))
    for r, (no, cells) in enumerate(data):
        cell = cells[j].strip()
        if cell == "" or cell.lower() in ("nan", "+nan", "-nan"):
            if not allow_missing:
                raise RecordError(f"{path}, line {no}, column {j + 1} ({name}): a value is "
                                  f"required here and must be finite, got {cell!r}.")
            out[r] = math.nan
            continue
        try:
            if "_" in cell:
                raise ValueError
            v = float(cell)
        except ValueError:
            hint = " (or leave the cell empty for a missing sample)" if allow_missing else ""
            raise RecordError(f"{path}, line {no}, column {j + 1} ({name}): {cell[:40]!r} is "
                              f"not a number; write a decimal number{hint}.") from None
        if not math.isfinite(v):
            fix = ("leave the cell empty for a missing sample" if allow_missing else
                   "write a finite decimal number")
            raise RecordError(f"{path}, line {no}, column {j + 1} ({name}): {cell!r} is not "
                              f"finite; {fix}.")
        out[r] = v
    return out


def _check_lengths(path: str, header, data, *, allow_missing: bool = True) -> None:
    for no, cells in data:
        if len(cells) != len(header):
            hint = " (empty for a missing sample)" if allow_missing else ""
            raise RecordError(f"{path}, line {no}: {len(cells)} cells but the header has "
                              f"{len(header)}; every row needs one "
                              f"cell per column{hint}.")


def _check_times(path: str, t: np.ndarray, data, col: int, check_units: bool) -> None:
    bad = np.nonzero(np.diff(t) <= 0.0)[0]
    if bad.size:
        i = int(bad[0])
        raise RecordError(f"{path}, line {data[i + 1][0]}, column {col + 1} (t): times must "
                          f"strictly increase ({t[i]:g} then {t[i + 1]:g}); sort the rows or "
                          "remove duplicates.")
    if check_units and t.size > 2:
        span, step = float(t[-1] - t[0]), float(np.median(np.diff(t)))
        if span > MS_SPAN and step >= 1.0:
            raise RecordError(f"{path}, column {col + 1} (t): times span {span:g} with steps of "
                              f"{step:g}: they look like milliseconds, but t is in seconds. "
                              "Divide t by 1000 (a record whose steps really are seconds is read "
                              "in Python with check_units=False; the diffpen commands refuse "
                              "it).")


# --------------------------------------------------------------------------- records
def _parse_header(path: str, header: list[str], hline: int, body_names, scene_names=None):
    """t column index and {body: {group: [column index per component]}} from the header.
    Column letters are read in any case (``T,X,Y,Z``); body names keep theirs."""
    split = next((h for h in header if h.count("[") != h.count("]")), None)
    if split is not None:
        raise RecordError(f"{path}, line {hline}: header cell {_q(split)} looks like a node name "
                          "split at its comma: node names containing commas must be quoted in "
                          'the CSV header, e.g. "cloth[1, 2].x" in double quotes.')
    header = [f"{h.rpartition('.')[0]}.{h.rpartition('.')[2].lower()}" if "." in h
              else h.lower() for h in header]
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise RecordError(f"{path}, line {hline}: column {_q(dup)} appears twice in the header; "
                          "name each column once.")
    if "t" not in header:
        raise RecordError(f"{path}, line {hline}: the header ({len(header)} column(s)) has no "
                          "time column 't' (s); expected t,x,y,z[,qw,qx,qy,qz][,vx,vy,vz]"
                          "[,wx,wy,wz] or t,NAME.x,NAME.y,NAME.z,... (the file's content is "
                          "not shown: is it the record you meant?)")
    names = None if body_names is None else [str(n) for n in body_names]
    prefixed = [h for h in header if "." in h]
    plain = [h for h in header if "." not in h and h != "t"]
    if prefixed and plain:
        raise RecordError(f"{path}, line {hline}, column {header.index(plain[0]) + 1}: "
                          f"{_q(plain[0])} has no body name while other columns do "
                          f"({_q(prefixed[0])}); write NAME.x etc. for every body column.")
    if plain:
        if names is not None and len(names) > 1:
            raise RecordError(f"{path}, line {hline}: the columns carry no body name but the "
                              f"scene observes {len(names)} bodies "
                              f"({', '.join(names[:10])}); write NAME.x, NAME.y, ... for each, "
                              "or name the one body it observes in the scene file's [fit] "
                              "observe = [\"NAME\"].")
        default = names[0] if names else "body"
    cols: dict = {}
    for j, h in enumerate(header):
        if h == "t":
            continue
        body, _, comp = h.rpartition(".") if "." in h else (default, "", h)
        if comp not in _SUFFIX:
            raise RecordError(f"{path}, line {hline}, column {j + 1}: unknown column {_q(h)}; "
                              "body columns end in one of "
                              f"{', '.join(_SUFFIX)} (t is the time).")
        if not body:
            raise RecordError(f"{path}, line {hline}, column {j + 1}: {_q(h)} has an empty body "
                              "name; write NAME.x etc.")
        # a builder's node (rope[3], cloth[0, 4]) is resolved against the scene by the
        # caller (SceneFile.body_index), named bodies or not
        if names is not None and not plain and body not in names and "[" not in body:
            if scene_names is not None and body in scene_names:
                raise RecordError(f"{path}, line {hline}, column {j + 1}: {_q(h)} names body "
                                  f"{_q(body)}, which is not in [fit] observe "
                                  f"({', '.join(names[:10])}"
                                  f"{', ...' if len(names) > 10 else ''}); add {_q(body)} to "
                                  "observe or drop its columns.")
            fix = "" if names else (" (give the body a name = \"...\" in the scene, or "
                                    "write plain x, y, z for a scene of one free body)")
            raise RecordError(f"{path}, line {hline}, column {j + 1}: {_q(h)} names body "
                              f"{_q(body)}, which the scene does not have; named bodies: "
                              f"{', '.join(names[:10]) or 'none'}"
                              f"{', ...' if len(names) > 10 else ''}{fix}.")
        group, i = _SUFFIX[comp]
        cols.setdefault(body, {}).setdefault(group, [None] * len(GROUPS[group]))[i] = j
    if not cols:
        raise RecordError(f"{path}, line {hline}: the header has only 't'; add the body's "
                          "position columns x,y,z.")
    for body, groups in cols.items():
        label = "" if plain else f"{body}."
        for group, idx in groups.items():
            if None in idx:
                have = [label + c for c, j in zip(GROUPS[group], idx) if j is not None]
                miss = [label + c for c, j in zip(GROUPS[group], idx) if j is None]
                raise RecordError(f"{path}, line {hline}: columns {', '.join(have)} are there "
                                  f"but {', '.join(miss)} is missing; a {group.replace('_', ' ')}"
                                  f" needs all of {', '.join(label + c for c in GROUPS[group])}.")
        if "position" not in groups:
            raise RecordError(f"{path}, line {hline}: body {body!r} has no position columns; "
                              f"add {label}x, {label}y, {label}z.")
    return header.index("t"), cols


def read_record(path, body_names=None, *, scene_names=None, max_rows: int = DEFAULT_MAX_ROWS,
                max_bytes: int = DEFAULT_MAX_BYTES, check_units: bool = True) -> Record:
    """Read a motion record (format in the module docstring).

    body_names: the scene's observed body names (a header without names then belongs to the
    only one; names in the header must be among them, or be a builder's node such as
    ``rope[3]``, which the caller resolves; an empty list: the scene names no body, a plain
    header is body ``"body"``), or None (a plain header is body ``"body"``; any names are
    accepted). scene_names: all the scene's body names when ``body_names`` is a part of them
    (``[fit] observe``): a column of one left out is refused as not observed. max_rows,
    max_bytes: size guard, checked from the file size before anything is parsed.
    check_units: refuse times that look like milliseconds, and heights beyond ``MM_LIMIT``
    (20 m) that look like centimetres or millimetres: unless the body falls there at about
    9.81 m/s^2 (a parabola fitted to the flight around the highest sample, within a factor
    ``FALL_FACTOR`` of ``FALL``), which shows metres.
    Raises :class:`RecordError` (file, line, column and the fix). Nothing is compiled.
    """
    path = os.fspath(path)
    text = _read_text(path, max_rows, max_bytes)
    header, hline, data = _rows(path, text)
    it, cols = _parse_header(path, header, hline, body_names, scene_names)
    _check_lengths(path, header, data)
    if len(data) > max_rows:
        raise RecordError(f"{path} has {len(data):,} rows; the limit is {max_rows:,}. Downsample "
                          "it (in Python, read_record(..., max_rows=) reads it; the diffpen "
                          "commands keep the limit).")
    if len(data) < 2:
        raise RecordError(f"{path} has {len(data)} data row(s); a record needs at least 2.")
    t = _column(path, data, it, "t", allow_missing=False)
    _check_times(path, t, data, it, check_units)
    bodies = {}
    for body, groups in cols.items():
        arrays = {}
        for group, idx in groups.items():
            a = np.stack([_column(path, data, j, header[j], allow_missing=True) for j in idx],
                         axis=1)
            miss = np.isnan(a)
            part = np.nonzero(miss.any(axis=1) & ~miss.all(axis=1))[0]
            if part.size:
                r = int(part[0])
                j = idx[int(np.nonzero(miss[r])[0][0])]
                raise RecordError(f"{path}, line {data[r][0]}, column {j + 1} ({header[j]}): "
                                  f"the {group.replace('_', ' ')} of this row is incomplete; "
                                  "fill every component or leave them all empty (a missing "
                                  "sample; NaN reads as empty).")
            arrays[group] = a
        _check_magnitudes(path, header, data, groups, arrays)
        q = arrays.get("quaternion")
        if q is not None:
            n = np.linalg.norm(q, axis=1)
            bad = np.nonzero(np.abs(n - 1.0) > QUAT_TOL)[0]
            if bad.size:
                r = int(bad[0])
                j = groups["quaternion"][0]
                raise RecordError(f"{path}, line {data[r][0]}, column {j + 1} ({header[j]}): "
                                  f"the quaternion has norm {n[r]:.6g}, not 1; normalise it "
                                  "(qw, qx, qy, qz).")
        p = arrays["position"]
        if np.isnan(p).all():
            raise RecordError(f"{path}: body {_q(body)} has no position sample; a record needs "
                              "at least one.")
        if check_units and np.nanmax(np.abs(p)) > MM_LIMIT:
            # judged at the top of z: a height beyond the limit needs a fall that shows
            # metres; x or y beyond it (a lab frame's far origin) only a fall that shows
            # centimetres or millimetres (z alone let a toss in centimetres through while it
            # stayed below 20 "m" up, x at 22)
            r = int(np.nanargmax(np.abs(p[:, 2])))
            fall = _fall(t, p, r)
            high = np.nanmax(np.abs(p[:, 2])) > MM_LIMIT
            if (fall is None or not FALL / FALL_FACTOR <= fall <= FALL * FALL_FACTOR) \
                    if high else (fall is not None and fall > FALL * FALL_FACTOR):
                rr, k = np.unravel_index(int(np.nanargmax(np.abs(p))), p.shape)
                j = groups["position"][k]
                raise unit_slip(path, data[rr][0], f"{j + 1} ({header[j]})", p[rr, k],
                                "positions", fall, "read_record")
        bodies[body] = BodyRecord(**arrays)
    return Record(path=path, t=t, bodies=bodies)


def _check_magnitudes(path, header, data, groups, arrays) -> None:
    """Refuse a value beyond :data:`MAX_MAGNITUDE` (whatever ``check_units``: no scene
    reaches it), naming file, line and column; before the unit-slip check, which would take
    one absurd height cell of a record in metres for a record in millimetres."""
    for group, a in arrays.items():
        big = np.nonzero(np.abs(np.nan_to_num(a)) > MAX_MAGNITUDE.get(group, np.inf))
        if big[0].size:
            r, k = int(big[0][0]), int(big[1][0])
            j = groups[group][k]
            raise RecordError(f"{path}, line {data[r][0]}, column {j + 1} ({header[j]}): "
                              f"{a[r, k]:g} {_UNIT[group]} is beyond the "
                              f"{MAX_MAGNITUDE[group]:g} {_UNIT[group]} a record's "
                              f"{group.replace('_', ' ')} may reach (a scene's coordinates "
                              "stop there too); check this cell (or leave it empty for a "
                              "missing sample)"
                              + ("; a record in millimetres or centimetres needs its "
                                 "positions in metres" if group == "position" else "") + ".")


def read_height_record(path, *, min_rows: int = 20, max_rows: int = DEFAULT_MAX_ROWS,
                       max_bytes: int = DEFAULT_MAX_BYTES,
                       check_units: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Read the bouncing ball's record: columns ``t`` (s) and ``z`` (m, centre height); other
    columns are ignored, no sample may be missing. Same checks as :func:`read_record`.
    Returns ``(t (N,), z (N,))`` float64 arrays. Raises :class:`RecordError`."""
    path = os.fspath(path)
    text = _read_text(path, max_rows, max_bytes)
    header, hline, data = _rows(path, text)
    low = [h.lower() for h in header]
    dup = next((h for h in ("t", "z") if low.count(h) > 1), None)
    if dup:
        raise RecordError(f"{path}, line {hline}: column {_q(dup)} appears twice in the header; "
                          "name each column once.")
    if "t" not in low or "z" not in low:
        raise RecordError(f"{path}, line {hline}: the first row must be a header with columns "
                          f"'t' and 'z' (time in s, ball centre height in m); it has "
                          f"{len(header)} column(s) and lacks {'t' if 't' not in low else 'z'} "
                          "(the file's content is not shown: is it the record you meant?).")
    _check_lengths(path, header, data, allow_missing=False)
    if len(data) > max_rows:
        raise RecordError(f"{path} has {len(data):,} rows; the limit is {max_rows:,}. Downsample "
                          "it (in Python, read_height_record(..., max_rows=) reads it; the "
                          "diffpen commands keep the limit).")
    it, iz = low.index("t"), low.index("z")
    t = _column(path, data, it, "t", allow_missing=False)
    z = _column(path, data, iz, "z", allow_missing=False)
    if len(t) < min_rows:
        raise RecordError(f"{path} has {len(t)} data rows; a trajectory fit needs at least "
                          f"{min_rows} (several samples per flight).")
    _check_times(path, t, data, it, check_units)
    if check_units and np.abs(z).max() > MM_LIMIT:
        r = int(np.argmax(np.abs(z)))
        fall = _fall(t, z[:, None], r)
        if fall is None or not FALL / FALL_FACTOR <= fall <= FALL * FALL_FACTOR:
            raise unit_slip(path, data[r][0], f"{iz + 1} (z)", z[r], "heights", fall,
                            "read_height_record")
    return t, z


def write_record(path, record: Record) -> None:
    """Write ``record`` in the format :func:`read_record` reads (names prefixed, so that a
    one-body record reads back for a scene of several bodies, except for one body named
    ``"body"`` -- a plain header's -- or by an index; missing samples as empty cells),
    atomically (:func:`tuning.io.atomic_write`)."""
    names = list(record.bodies)
    plain = len(names) == 1 and (names[0] == "body" or not isinstance(names[0], str))
    header, blocks = ["t"], [np.asarray(record.t, dtype=float)[:, None]]
    for name in names:
        b = record.bodies[name]
        for group, comps in GROUPS.items():
            a = getattr(b, group)
            if a is None:
                continue
            header += [c if plain else f"{name}.{c}" for c in comps]
            blocks.append(np.asarray(a, dtype=float))
    table = np.concatenate(blocks, axis=1)
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")        # quotes names such as "cloth[1,2].x"
    w.writerow(header)
    for row in table:
        w.writerow(["" if math.isnan(v) else repr(float(v)) for v in row])
    text = out.getvalue().encode()
    atomic_write(path, lambda fh: fh.write(text))


def _refuse_duplicates(paths: Sequence[str]) -> None:
    """Raise :class:`FitError` when a record file is given twice, or two files hold the same
    bytes: it counted twice, silently (in a fit, its standard errors and evaluate's means)."""
    from .io import file_digest
    seen: dict = {}
    for i, p in enumerate(paths):
        j, first = seen.setdefault(file_digest(p), (i, p))
        if j != i:
            same = os.path.realpath(p) == os.path.realpath(first)
            raise FitError(f"{p} is {'the same file as' if same else 'a copy of'} {first}: a "
                           "record given twice counts twice (its weight in a fit, in the "
                           "standard errors and in the means); give each record once "
                           "(overlapping patterns such as toss_0*.csv toss_00*.csv repeat "
                           "files).")


def load_records(sf, paths: Sequence[str]):
    """Read record files for scene file ``sf`` (:class:`tuning.scenefile.SceneFile`).

    Returns ``(records, bodies)``: the :class:`tuning.records.Record` list and ``{record
    body name: scene body index}``. The observed bodies are ``[fit] observe`` or the scene's
    named bodies, and builder nodes (``rope[3]``, ``rope[-1]``); a record with plain ``x, y,
    z`` columns belongs to the only one (or to the only free body of a scene without names).
    A column naming another body, or two names of one body, is refused.
    Raises :class:`tuning.records.RecordError` / :class:`FitError` before anything compiles.
    """
    if not paths:
        raise FitError("no records: give --data FILE.csv [FILE.csv ...].")
    named = [n for n in sf.names if "[" not in n]
    observe = list(sf.spec.observe) if sf.spec is not None and sf.spec.observe else named
    records = [read_record(p, body_names=observe, scene_names=named) for p in paths]
    _refuse_duplicates(paths)
    bodies, first = {}, {}                  # first: scene body -> (record body, record path)
    for rec in records:
        for name in rec.bodies:
            if name in bodies:
                i = bodies[name]
            elif name in sf.names:
                i = sf.names[name]
            elif observe or "[" in name:
                try:
                    i = sf.body_index(name)
                except Exception as exc:            # SceneFileError: say which record
                    raise FitError(f"{rec.path}: the columns of {name!r}: {exc}") from None
            else:                                   # plain x, y, z; the scene names no body
                free = [i for i, b in enumerate(sf.scene.bodies) if not b.pinned]
                if len(free) != 1:
                    raise FitError(f"{rec.path}: the columns name no body and the scene has "
                                   f"{len(free)} free bodies: name the body in the scene "
                                   "(name = ...) and prefix the columns (NAME.x, ...).")
                i = free[0]
            other, where = first.setdefault(i, (name, rec.path))
            if other != name:
                said = ("" if where == rec.path else f", and {where} names it {other!r}")
                cols = (f"the columns {other}.x, ... and {name}.x, ..." if where == rec.path
                        else f"the columns {name}.x, ...")
                raise FitError(f"{rec.path}: {cols} observe the same scene body {i}{said}: "
                               "name each body once, the same way in every record.")
            bodies[name] = i
    return records, bodies
