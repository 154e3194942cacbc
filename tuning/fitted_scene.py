"""Write a scene file with fitted parameter values: the input TOML with each fitted leaf put
where the file declares it, checked by reading the result back.

Where a leaf goes (dotted params paths, see :mod:`tuning.scenefile`):

* ``contact.M.k`` / ``contact.M.c`` / ``extra.friction.M``: ``[materials.M]`` k / c /
  friction (the table is added when the material took the top-level k, c; slip speed is a
  compile-time constant, not a leaf). When the file has no top-level ``k`` / ``c``, the
  loader uses the defaults k = 1e4 N/m and c = 20 N s/m; they are then written explicitly
  with those values, so that the written file reads back the same whatever those defaults
  become;
* ``extra.plane_offset.NAME``: the ``offset`` of the ``[[planes]]`` entry named NAME;
* ``springs.G.k`` / ``.c``: wherever spring group G is declared, in the loader's order: a
  ``[spring_groups.G]`` table, else the builder that makes it (a rope's ``k`` / ``c`` for
  ``NAME.stretch``, a crumple bar's ``k`` / ``c`` for its group ``NAME``, a builder group
  ``structural = [k, c]``, ``bend``, ``edge``, ...: written as a pair that keeps the other
  member's value, library defaults included), else the first ``[[springs]]`` /
  ``[[anchored_springs]]`` / ``[[plastic_springs]]`` entry of group G; every other entry of G
  that states the value gets it too (they must agree);
* ``extra.drag.G``: a builder's ``drag`` for ``NAME.drag``, else the first ``[[drag]]`` entry
  of group G; every ``[[drag]]`` entry of G that states ``c`` gets it too;
* ``extra.plastic.G`` (yield strain): a crumple bar's ``yield_strain`` for its group ``NAME``,
  else the first ``[[plastic_springs]]`` entry of group G; every entry of G that states
  ``yield_strain`` gets it too.

Only leaves of the scene's params are placed (others are refused with the list of leaves).
The result is read back before it replaces ``out``: every fitted leaf must have its value and
every other leaf the value it had in the input (a file that reads back otherwise is not
written). Comments of the input are not kept (the file is rewritten from its parsed content).
The result is written atomically (temporary file, then rename; a symbolic link is followed to
the file it names), as UTF-8.
"""
from __future__ import annotations

import copy
import datetime
import math
import os
import re
import tomllib

import numpy as np

from .errors import FitError
from .io import atomic_write

__all__ = ["write_fitted", "dumps_toml", "is_fitted_scene", "FITTED_MARK"]


# --------------------------------------------------------------------------- TOML out
_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")
_ESCAPES = {"\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r", '"': '\\"',
            "\\": "\\\\"}


def _string(s: str) -> str:
    """``s`` as a TOML basic string: quote, backslash and control characters escaped (the
    spec's short escapes, else ``\\uXXXX``); other characters, unicode included, as they are."""
    out = []
    for ch in s:
        o = ord(ch)
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif o < 0x20 or o == 0x7F:
            out.append(f"\\u{o:04X}")
        elif 0xD800 <= o <= 0xDFFF:
            raise FitError(f"cannot write {s!r} to TOML: it holds a lone surrogate "
                           f"(U+{o:04X}), which is not a Unicode character.")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _key(k: str) -> str:
    """A TOML key: bare when it is only ASCII letters, digits, ``_`` and ``-``, else quoted."""
    return k if _BARE_KEY.match(k) else _string(k)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (datetime.datetime, datetime.date, datetime.time)):
        return v.isoformat()
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    raise FitError(f"cannot write {v!r} to TOML.")


def _is_table_array(v) -> bool:
    return isinstance(v, list) and v and all(isinstance(x, dict) for x in v)


def dumps_toml(doc: dict) -> str:
    """Serialise a parsed TOML document (tables, arrays of tables, scalars, arrays, strings
    escaped per the TOML spec); ``tomllib.loads`` of the result gives ``doc`` back."""
    lines: list[str] = []

    def emit(prefix: str, table: dict):
        scalars = [(k, v) for k, v in table.items()
                   if not isinstance(v, dict) and not _is_table_array(v)]
        for k, v in scalars:
            lines.append(f"{_key(k)} = {_value(v)}")
        for k, v in table.items():
            name = f"{prefix}.{_key(k)}" if prefix else _key(k)
            if isinstance(v, dict):
                if not v or any(not isinstance(x, dict) and not _is_table_array(x)
                                for x in v.values()):
                    lines.append("")
                    lines.append(f"[{name}]")
                emit(name, v)
            elif _is_table_array(v):
                for item in v:
                    lines.append("")
                    lines.append(f"[[{name}]]")
                    emit(name, item)
    emit("", doc)
    return "\n".join(lines).lstrip("\n") + "\n"


# --------------------------------------------------------------------------- placing leaves
#: builder table -> {group suffix: how the builder states it}; "" is the builder's own name
#: (a crumple bar's springs and plastic group)
_BUILDER_KEYS = {"ropes": {"stretch": "kc", "bend": "pair", "drag": "drag"},
                 "crumple_bars": {"": "kc", "drag": "drag"},
                 "cloths": {"structural": "pair", "shear": "pair", "bend": "pair",
                            "drag": "drag"},
                 "jellies": {"edge": "pair", "face": "pair", "body": "pair", "drag": "drag"}}
_DEFAULT_NAMES = {"ropes": "rope", "crumple_bars": "bar", "cloths": "cloth",
                  "jellies": "jelly"}
_DEFAULT_GROUP = {"springs": "default", "anchored_springs": "default",
                  "plastic_springs": "plastic", "drag": "drag"}


def _entries(doc: dict, key: str) -> list:
    v = doc.get(key, [])
    return [e for e in v if isinstance(e, dict)] if isinstance(v, list) else []


def _builder(doc, group: str):
    """``(entry, table, kind, sub)`` of the builder that makes ``group`` (``NAME.SUB``, or a
    crumple bar's ``NAME``), or four Nones."""
    for key, subs in _BUILDER_KEYS.items():
        for e in _entries(doc, key):
            name = e.get("name", _DEFAULT_NAMES[key])
            if not isinstance(name, str):
                continue
            if group == name and "" in subs:
                return e, key, subs[""], ""
            if group.startswith(name + ".") and group[len(name) + 1:] in subs:
                sub = group[len(name) + 1:]
                if sub:
                    return e, key, subs[sub], sub
    return None, None, None, None


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _set_sites(path: str, sites: list, value: float) -> None:
    """Put ``value`` in every site ``(table, key, states)`` that states it, and in the first
    (the declaration the loader reads the group's value from)."""
    if not sites:
        raise FitError(f"cannot place the fitted {path} in the scene file: no table declares "
                       "it; its value is in the JSON output.")
    for i, (table, key, states) in enumerate(sites):
        if i == 0 or states:
            table[key] = value


def _place_spring(doc: dict, path: str, group: str, field: str, value: float, scene) -> None:
    """``springs.GROUP.k`` / ``.c`` (see the module docstring)."""
    sites = []
    declared = doc.get("spring_groups", {})
    if isinstance(declared, dict) and isinstance(declared.get(group), dict):
        sites.append((declared[group], field, True))
    e, _, kind, sub = _builder(doc, group)
    declared_by_pair = False
    if kind == "kc":
        sites.append((e, field, True))
    elif kind == "pair" and e.get(sub) is not False and not sites:
        # written as [k, c]: the other member keeps the value the scene compiled with (a bare
        # k's c = 0, the library's default pair when the key is left out)
        cur = e.get(sub)
        if isinstance(cur, list) and len(cur) == 2:
            k, c = cur
        elif group in scene.spring_groups:
            k, c = scene.spring_groups[group].k, scene.spring_groups[group].c
        else:
            raise FitError(f"cannot place the fitted {path}: the scene has no spring group "
                           f"{group!r}.")
        e[sub] = [value, c] if field == "k" else [k, value]
        declared_by_pair = True
    for key in ("springs", "anchored_springs", "plastic_springs"):
        for s in _entries(doc, key):
            if s.get("group", _DEFAULT_GROUP[key]) == group:
                sites.append((s, field, field in s))
    if declared_by_pair:                    # entries that state it too must agree
        for table, key, states in sites:
            if states:
                table[key] = value
        return
    _set_sites(path, sites, value)


def _place_drag(doc: dict, path: str, group: str, value: float) -> None:
    """``extra.drag.GROUP``: a builder's ``drag``, ``[[drag]]`` entries' ``c``."""
    sites = []
    e, _, kind, _ = _builder(doc, group)
    if kind == "drag" and _is_number(e.get("drag")):
        sites.append((e, "drag", True))
    for d in _entries(doc, "drag"):
        if d.get("group", _DEFAULT_GROUP["drag"]) == group:
            sites.append((d, "c", "c" in d))
    _set_sites(path, sites, value)


def _place_plastic(doc: dict, path: str, group: str, value: float) -> None:
    """``extra.plastic.GROUP`` (yield strain): a crumple bar's or plastic springs'
    ``yield_strain``."""
    sites = []
    e, table, _, sub = _builder(doc, group)
    if table == "crumple_bars" and sub == "":
        sites.append((e, "yield_strain", True))
    for s in _entries(doc, "plastic_springs"):
        if s.get("group", _DEFAULT_GROUP["plastic_springs"]) == group:
            sites.append((s, "yield_strain", "yield_strain" in s))
    _set_sites(path, sites, value)


def _material(doc: dict, path: str, name: str) -> dict:
    mats = doc.setdefault("materials", {})
    if not isinstance(mats, dict) or not isinstance(mats.setdefault(name, {}), dict):
        raise FitError(f"cannot place the fitted {path}: [materials] of the scene file is not "
                       "a table of tables.")
    return mats[name]


def _place(doc: dict, path: str, value: float, sf) -> None:
    """Put the fitted leaf ``path`` = ``value`` into ``doc`` (the parsed input of the scene
    file ``sf`` was loaded from)."""
    parts = path.split(".")
    if parts[0] == "contact" and len(parts) >= 3 and parts[-1] in ("k", "c"):
        field = parts[-1]
        for top, old in (("k", sf.setup.k), ("c", sf.setup.c)):
            if top not in doc:      # the loader's defaults, written explicitly
                doc[top] = float(old)
        _material(doc, path, ".".join(parts[1:-1]))[field] = value
        return
    if parts[0] == "extra" and len(parts) >= 3:
        kind, name = parts[1], ".".join(parts[2:])
        if kind == "friction":
            _material(doc, path, name)[kind] = value
            return
        if kind == "plane_offset":
            for e in _entries(doc, "planes"):
                if e.get("name") == name:
                    e["offset"] = value
                    return
            raise FitError(f"{path}: no [[planes]] entry is named {name!r}.")
        if kind == "drag":
            return _place_drag(doc, path, name, value)
        if kind == "plastic":
            return _place_plastic(doc, path, name, value)
    if parts[0] == "springs" and len(parts) >= 3 and parts[-1] in ("k", "c"):
        return _place_spring(doc, path, ".".join(parts[1:-1]), parts[-1], value, sf.scene)
    raise FitError(f"cannot place the fitted {path} in the scene file; its value is in the "
                   "JSON output.")


# --------------------------------------------------------------------------- writing
def _leaf_values(sf) -> dict:
    from .scenefile import param_leaves
    return {k: np.asarray(v) for k, v in param_leaves(sf.params(sf.compile())).items()}


def _differences(before: dict, after: dict, values: dict) -> list[str]:
    """Leaves of ``after`` that are not ``values`` (fitted, at the leaf's precision) or, for
    the others, exactly their value in ``before``."""
    out = []
    for path in sorted(set(before) | set(after)):
        if path not in after:
            out.append(f"{path} is missing")
            continue
        got = after[path]
        if path in values:
            want = np.asarray(values[path], dtype=got.dtype)
        elif path in before:
            want = before[path]
        else:
            out.append(f"{path} is new")
            continue
        if not np.array_equal(got, want):
            out.append(f"{path} = {got.tolist()} instead of {want.tolist()}")
    return out


#: the first line of a fitted scene file (:func:`write_fitted`), by which ``diffpen fit --out``
#: knows a file it may replace (:func:`is_fitted_scene`)
FITTED_MARK = "# written by diffpen fit: the fitted values of"


def is_fitted_scene(path: str) -> bool:
    """Whether ``path`` starts with :data:`FITTED_MARK` (a scene :func:`write_fitted` wrote)."""
    try:
        with open(path, "rb") as fh:
            return fh.readline(256).decode("utf-8", "replace").startswith(FITTED_MARK)
    except OSError:
        return False


def write_fitted(src: str, values: dict, out: str, fit: dict | None = None) -> str:
    """Write ``src`` (a scene file) to ``out`` with the fitted ``values`` (``{dotted leaf
    path: value}``) in place, and check that ``out`` reads back with those values and every
    other leaf unchanged. ``fit``: ``[fit]`` keys set in ``out`` (the fit's start-state
    settings where the command line overrode the scene file's, e.g. ``{"first_state":
    "record"}``), so that ``diffpen evaluate`` of ``out`` measures what the fit reported.
    Returns ``out``.

    Raises :class:`FitError` (``SceneFileError`` for an unreadable ``src``) naming the leaf
    when a path is not a leaf of the scene's params, a value cannot be placed, or the
    written file would not read back as fitted; ``out`` is then left as it was."""
    from . import validate as V
    from .scenefile import load_scene_file
    src, out = os.fspath(src), os.fspath(out)
    sf = load_scene_file(src)
    before = _leaf_values(sf)
    unknown = [p for p in values if p not in before]
    if unknown:
        verb = "is not a parameter leaf" if len(unknown) == 1 else "are not parameter leaves"
        raise FitError(f"{src}: {', '.join(map(repr, unknown))} {verb} of this scene; its "
                       f"leaves: {', '.join(before)}.")
    fitted = {}
    for path, v in values.items():
        try:
            fitted[path] = float(v)
        except (TypeError, ValueError):
            raise FitError(f"the fitted {path} = {v!r} is not a number.") from None
    doc = copy.deepcopy(tomllib.loads(V.read_text_file(src, "TOML scene")))
    for path, v in fitted.items():
        _place(doc, path, v, sf)
    if fit:
        doc.setdefault("fit", {}).update(fit)
    fit = doc.get("fit")
    if isinstance(fit, dict) and "data" in fit:      # keep record paths valid from out's folder
        base = os.path.dirname(os.path.abspath(src))
        there = os.path.dirname(os.path.abspath(out))
        items = fit["data"] if isinstance(fit["data"], list) else [fit["data"]]
        items = [p if os.path.isabs(p) else os.path.relpath(os.path.join(base, p), there)
                 for p in items]
        fit["data"] = items if isinstance(fit["data"], list) else items[0]
    text = f"{FITTED_MARK} {os.path.basename(src)}\n" + dumps_toml(doc)

    def check(tmp):                  # the written file reads back as fitted
        try:
            after = _leaf_values(load_scene_file(tmp))
        except FitError as exc:
            raise FitError("the fitted values do not make a valid scene file: "
                           + str(exc).replace(tmp, out)) from None
        bad = _differences(before, after, fitted)
        if bad:
            raise FitError(f"writing the fitted values into {out} reads back with "
                           f"{'; '.join(bad)}; {out} is not written.")
    # a symbolic link is followed: its target is replaced and the link kept (tuning.io)
    atomic_write(out, lambda fh: fh.write(text.encode("utf-8")), check=check)
    return out
