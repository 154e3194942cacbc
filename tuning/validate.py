"""One validation layer for input files (TOML scene files, CSV records): types checked WITHOUT
coercion (``radius = "0.1"`` and ``mass = true`` are refused, not converted), every message
naming the file and the key (or line and column) and saying what to write instead; and the
size guards that estimate memory and time before anything big is built.

The checkers take a :class:`Where` (file + dotted key) and return the checked value as a
plain Python float/int/str/tuple. They raise :class:`SceneFileError`, which is both a
:class:`diffpen.SceneError` and a :class:`tuning.fit.FitError` (so every ``ValueError``
handler sees it). Nothing here compiles anything.
"""
from __future__ import annotations

import dataclasses
import math
import os

import diffpen as dp

from .errors import FitError

__all__ = ["SceneFileError", "Where", "read_text_file", "table", "tables", "number", "integer",
           "boolean", "string", "choice", "vector", "number_list", "path_list", "check_keys",
           "MAX_FILE_BYTES"]

#: input text files above this size are refused before they are read
MAX_FILE_BYTES = 16 * 2**20


class SceneFileError(FitError, dp.SceneError):
    """A scene file that cannot be read or describes an invalid scene. The message starts with
    the file name and names the key; ``path`` and ``key`` carry them too."""

    def __init__(self, message: str, *, path: str | None = None, key: str | None = None):
        super().__init__(message)
        self.path = path
        self.key = key


@dataclasses.dataclass(frozen=True)
class Where:
    """A place in an input file: ``path`` and a dotted ``key`` such as ``spheres[2].radius``."""
    path: str
    key: str = ""

    def __truediv__(self, sub) -> "Where":
        if isinstance(sub, int):
            return Where(self.path, f"{self.key}[{sub}]")
        return Where(self.path, f"{self.key}.{sub}" if self.key else str(sub))

    def error(self, text: str) -> SceneFileError:
        where = f"{self.path}: {self.key}" if self.key else f"{self.path}:"
        return SceneFileError(f"{where} {text}", path=self.path, key=self.key or None)


def _kind(v) -> str:
    """How a TOML value reads, for messages ("a string", "a boolean", ...)."""
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, int):
        return "an integer"
    if isinstance(v, float):
        return "a number"
    if isinstance(v, dict):
        return "a table"
    if isinstance(v, list):
        return "an array"
    return f"a {type(v).__name__}"


def _show(v, limit: int = 40) -> str:
    text = repr(v)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def read_text_file(path: str, what: str, *, max_bytes: int = MAX_FILE_BYTES) -> str:
    """The UTF-8 text of ``path`` (a BOM is dropped), refusing missing, directory, oversized and
    binary files with a message naming the file and never quoting its content."""
    w = Where(path)
    try:
        if os.path.isdir(path):
            raise w.error(f"is a directory; give a {what} file.")
        if os.path.exists(path) and not os.path.isfile(path):
            # /dev/zero reports size 0 and never ends (read whole, it filled the memory); a
            # FIFO nobody writes blocks
            raise w.error(f"is not a regular file (a device, pipe or socket); give a {what} "
                          "file (save a pipe's output to a file first).")
        size = os.path.getsize(path)
        if size > max_bytes:
            raise w.error(f"is {size / 2**20:.1f} MiB; a {what} file above "
                          f"{max_bytes / 2**20:.0f} MiB is refused before reading (generate "
                          "large scenes with builders instead of listing every body).")
        with open(path, "rb") as fh:
            raw = fh.read()
    except SceneFileError:
        raise
    except OSError as exc:
        raise SceneFileError(f"cannot read {path}: {exc.strerror or exc}.", path=path) from None
    nul = raw.find(b"\x00")
    if nul >= 0:
        raise w.error(f"is a binary file (a zero byte at offset {nul}), not a {what}; give the "
                      f"text {what} file.")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise w.error(f"line {line}: byte 0x{raw[exc.start]:02x} at offset {exc.start} is not "
                      f"UTF-8 text; save the {what} as UTF-8.") from None


# --------------------------------------------------------------------------- checkers
def check_keys(w: Where, tbl: dict, allowed) -> None:
    """Refuse keys of ``tbl`` not in ``allowed``, listing the allowed ones."""
    bad = [k for k in tbl if k not in allowed]
    if bad:
        label = f"[{w.key}]" if w.key else "the top level"
        raise SceneFileError(f"{w.path}: unknown key(s) {bad} in {label}; "
                             f"allowed: {', '.join(sorted(allowed))}.", path=w.path,
                             key=(w / bad[0]).key)


def table(w: Where, v, *, example: str = "") -> dict:
    """A TOML table (``[name]`` or ``{...}``)."""
    if not isinstance(v, dict):
        hint = f" e.g. {example}" if example else ""
        raise w.error(f"must be a table, got {_kind(v)} {_show(v)};{hint}.")
    return v


def tables(w: Where, v, *, header: str) -> list:
    """An array of tables (``[[name]]`` entries)."""
    if isinstance(v, dict):
        raise w.error(f"must be an array of tables: write each entry as [[{header}]] (double "
                      f"brackets), not [{header}].")
    if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
        raise w.error(f"must be an array of tables ([[{header}]] entries), got {_kind(v)} "
                      f"{_show(v)}.")
    return v


def number(w: Where, v, *, low: float | None = None, high: float | None = None,
           low_open: bool = False, high_open: bool = False, unit: str = "") -> float:
    """A finite number (TOML integer or float, never a string or boolean) in the range."""
    u = f" ({unit})" if unit else ""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        name = _leaf(w)
        item = w.key.endswith("]")          # an array's element: quote the element alone
        fix = ((f"; write it without quotes: {v}" if item else
                f"; write it without quotes, e.g. {name} = {v}")
               if isinstance(v, str) and _numeric(v) else
               ("; write a number without quotes, e.g. 1.0" if item else
                f"; write a number without quotes, e.g. {name} = 1.0"))
        raise w.error(f"must be a number{u}, got {_kind(v)} {_show(v)}{fix}.")
    x = float(v)
    if not math.isfinite(x):
        raise w.error(f"must be finite, got {v!r}.")
    if low is not None and (x < low or (low_open and x == low)):
        raise w.error(f"must be {'>' if low_open else '>='} {low:g}{u}, got {v!r}.")
    if high is not None and (x > high or (high_open and x == high)):
        raise w.error(f"must be {'<' if high_open else '<='} {high:g}{u}, got {v!r}.")
    return x


def _leaf(w: Where) -> str:
    """The last key of ``w`` ("radius" of "spheres[0].radius"; "x" for an array item)."""
    last = w.key.rsplit(".", 1)[-1]
    return last.split("[", 1)[0] or "x"


def _numeric(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def integer(w: Where, v, *, low: int | None = None, high: int | None = None) -> int:
    """An integer (a TOML integer; ``2.0``, ``"2"`` and ``true`` are refused)."""
    if isinstance(v, bool) or not isinstance(v, int):
        fix = (f"; write {int(v)} instead of {v!r}" if isinstance(v, float) and v.is_integer()
               else f"; write a whole number without quotes, e.g. {_leaf(w)} = 10")
        raise w.error(f"must be an integer, got {_kind(v)} {_show(v)}{fix}.")
    if low is not None and v < low:
        raise w.error(f"must be an integer >= {low}, got {v}.")
    if high is not None and v > high:
        raise w.error(f"must be an integer <= {high}, got {v}.")
    return v


def boolean(w: Where, v) -> bool:
    if not isinstance(v, bool):
        raise w.error(f"must be true or false (without quotes), got {_kind(v)} {_show(v)}.")
    return v


def string(w: Where, v) -> str:
    if not isinstance(v, str) or not v:
        raise w.error(f"must be a non-empty string (in quotes), got {_kind(v)} {_show(v)}.")
    return v


def choice(w: Where, v, options) -> str:
    string(w, v)
    if v not in options:
        raise w.error(f"must be one of {', '.join(map(repr, options))}, got {_show(v)}.")
    return v


def vector(w: Where, v, n: int = 3, *, what: str = "x, y, z", unit: str = "",
           limit: float | None = None, beyond: str | None = None) -> tuple:
    """``n`` finite numbers (each of magnitude <= ``limit`` when given; ``beyond``: what the
    error says past it, else that it is a position too far from the origin)."""
    if not isinstance(v, list) or len(v) != n:
        raise w.error(f"must be {n} numbers [{what}]{' in ' + unit if unit else ''}, got "
                      f"{_kind(v)} {_show(v)}.")
    out = tuple(number(w / i, x) for i, x in enumerate(v))
    if limit is not None and beyond is not None and max(abs(x) for x in out) > limit:
        raise w.error(f"= {_show(v)} has a component beyond {limit:g} {unit}: {beyond}")
    if limit is not None and max(abs(x) for x in out) > limit:
        raise w.error(f"= {_show(v)} is farther than {limit:g} {unit or 'units'} from the "
                      f"origin: at that distance float32 positions resolve only "
                      f"{limit * 2**-24:.2g} {unit}; move the scene near the origin.")
    return out


def number_list(w: Where, v, *, low: float | None = None, low_open: bool = False,
                high: float | None = None, unit: str = "", scalar_ok: bool = True) -> list:
    """A non-empty array of numbers (a single number too, when ``scalar_ok``)."""
    if scalar_ok and not isinstance(v, list):
        v = [v] if isinstance(v, (int, float)) and not isinstance(v, bool) else v
    if not isinstance(v, list) or not v:
        raise w.error(f"must be a non-empty array of numbers{' in ' + unit if unit else ''}, "
                      f"got {_kind(v)} {_show(v)}.")
    return [number(w / i, x, low=low, low_open=low_open, high=high, unit=unit)
            for i, x in enumerate(v)]


def path_list(w: Where, v, *, suffix: str) -> list:
    """One file name or an array of them, each ending in ``suffix`` (case-insensitive),
    resolved relative to the folder of ``w.path``. Existence is checked; content is not read
    (and never quoted)."""
    items = [v] if isinstance(v, str) else v
    if not isinstance(items, list) or not items:
        raise w.error(f"must be a file name or an array of file names ({suffix}), got "
                      f"{_kind(v)} {_show(v)}; e.g. {_leaf(w)} = \"record{suffix}\".")
    base = os.path.dirname(os.path.abspath(w.path))
    out = []
    for i, name in enumerate(items):
        wi = w / i if isinstance(v, list) else w
        string(wi, name)
        if not name.lower().endswith(suffix):
            raise wi.error(f"must name a {suffix} record, got {_show(name)}; records are CSV "
                           f"files ending in {suffix}.")
        full = os.path.join(base, os.path.expanduser(name))
        if not os.path.isfile(full):
            raise wi.error(f"names {_show(name)}, which is not a file (looked for {full}).")
        out.append(full)
    return out
