"""Write a scene file with fitted parameter values: the input TOML with each fitted leaf put
where the file declares it, checked by reading the result back.

Where a leaf goes (dotted params paths, see :mod:`tuning.scenefile`):

* ``contact.M.k`` / ``contact.M.c`` / ``extra.friction.M``: ``[materials.M]`` k / c /
  friction (the table is added when the material took the top-level k, c);
* ``extra.plane_offset.NAME``: the ``offset`` of the ``[[planes]]`` entry named NAME;
* ``springs.G.k`` / ``.c``: ``[spring_groups.G]`` if declared, else the ``[[springs]]`` /
  ``[[anchored_springs]]`` / ``[[plastic_springs]]`` entries of group G, else the builder
  whose name prefixes G (a rope's or crumple bar's ``k``/``c`` for ``NAME.stretch``, a
  cloth's ``structural = [k, c]``, ...);
* ``extra.drag.G``: the ``c`` of the ``[[drag]]`` entries of group G, or a builder's ``drag``.

Comments of the input are not kept (the file is rewritten from its parsed content). The
result is written atomically (temporary file, then rename).
"""
from __future__ import annotations

import copy
import math
import os
import tempfile
import tomllib

from .fit import FitError

__all__ = ["write_fitted", "dumps_toml"]


# --------------------------------------------------------------------------- TOML out
def _key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else '"' + k.replace(
        '"', '\\"') + '"'


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
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    raise FitError(f"cannot write {v!r} to TOML.")


def _is_table_array(v) -> bool:
    return isinstance(v, list) and v and all(isinstance(x, dict) for x in v)


def dumps_toml(doc: dict) -> str:
    """Serialise a parsed TOML document (tables, arrays of tables, scalars, arrays)."""
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
_BUILDER_KEYS = {"ropes": {"stretch": "kc", "bend": "pair", "drag": "drag"},
                 "crumple_bars": {"stretch": "kc", "drag": "drag"},
                 "cloths": {"structural": "pair", "shear": "pair", "bend": "pair",
                            "drag": "drag"},
                 "jellies": {"edge": "pair", "face": "pair", "body": "pair", "drag": "drag"}}
_DEFAULT_NAMES = {"ropes": "rope", "crumple_bars": "bar", "cloths": "cloth",
                  "jellies": "jelly"}


def _builder(doc, group: str):
    """``(entry, kind, sub)`` of the builder whose group prefix names ``group``."""
    for key, subs in _BUILDER_KEYS.items():
        for e in doc.get(key, []):
            name = e.get("name", _DEFAULT_NAMES[key])
            if group.startswith(name + ".") and group[len(name) + 1:] in subs:
                sub = group[len(name) + 1:]
                return e, subs[sub], sub
    return None, None, None


def _place(doc: dict, path: str, value: float) -> None:
    parts = path.split(".")
    if parts[0] == "contact" and len(parts) == 3:
        mat, field = parts[1], parts[2]
        doc.setdefault("materials", {}).setdefault(mat, {})[field] = value
        return
    if parts[:2] == ["extra", "friction"] and len(parts) == 3:
        doc.setdefault("materials", {}).setdefault(parts[2], {})["friction"] = value
        return
    if parts[:2] == ["extra", "plane_offset"] and len(parts) == 3:
        for e in doc.get("planes", []):
            if e.get("name") == parts[2]:
                e["offset"] = value
                return
        raise FitError(f"{path}: no [[planes]] entry is named {parts[2]!r}.")
    if parts[0] == "springs" and len(parts) >= 3:
        group, field = ".".join(parts[1:-1]), parts[-1]
        if group in doc.get("spring_groups", {}):
            doc["spring_groups"][group][field] = value
            return
        hit = False
        for key in ("springs", "anchored_springs", "plastic_springs"):
            for e in doc.get(key, []):
                if e.get("group", "default" if key != "plastic_springs" else "plastic") == group:
                    if field in e or not hit:
                        e[field] = value
                        hit = True
        if hit:
            return
        e, kind, _ = _builder(doc, group)
        if kind == "kc":
            e[field] = value
            return
        if kind == "pair":
            sub = group.rsplit(".", 1)[1]
            cur = e.get(sub)
            k, c = (cur, 0.0) if isinstance(cur, (int, float)) else (cur or [0.0, 0.0])
            e[sub] = [value, c] if field == "k" else [k, value]
            return
    if parts[:2] == ["extra", "drag"] and len(parts) >= 3:
        group = ".".join(parts[2:])
        hit = False
        for e in doc.get("drag", []):
            if e.get("group", "drag") == group:
                e["c"] = value
                hit = True
        if hit:
            return
        e, kind, _ = _builder(doc, group)
        if kind == "drag":
            e["drag"] = value
            return
    raise FitError(f"cannot place the fitted {path} in the scene file; its value is in the "
                   "JSON output.")


def write_fitted(src: str, values: dict, out: str) -> str:
    """Write ``src`` (a scene file) to ``out`` with the fitted ``values`` (``{dotted leaf
    path: value}``) in place, and check that ``out`` reads back with those values.
    Returns ``out``."""
    from .scenefile import load_scene_file, param_leaves
    with open(src, "rb") as fh:
        doc = tomllib.load(fh)
    doc = copy.deepcopy(doc)
    for path, v in values.items():
        _place(doc, path, float(v))
    fit = doc.get("fit")
    if isinstance(fit, dict) and "data" in fit:      # keep record paths valid from out's folder
        base = os.path.dirname(os.path.abspath(src))
        there = os.path.dirname(os.path.abspath(out))
        items = fit["data"] if isinstance(fit["data"], list) else [fit["data"]]
        items = [os.path.relpath(os.path.join(base, p), there) for p in items]
        fit["data"] = items if isinstance(fit["data"], list) else items[0]
    text = dumps_toml(doc)
    folder = os.path.dirname(os.path.abspath(out))
    fd, tmp = tempfile.mkstemp(prefix=".fitted-", suffix=".toml", dir=folder)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        sf = load_scene_file(tmp)
        sim = sf.compile()
        leaves = param_leaves(sf.params(sim))
        for path, v in values.items():
            got = float(leaves[path])
            if not math.isclose(got, float(v), rel_tol=1e-9, abs_tol=1e-15):
                raise FitError(f"writing {path} = {v} into {out} reads back as {got}.")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out
