"""The fix in a library :class:`diffpen.SceneError` written for a TOML scene file.

The library's messages give Python advice (``allow_overlap=True``, ``group=``,
``scene.add_spring_group(...)``, ``structural=(k, c)``); a scene file spells the same fix
differently. :func:`file_advice` rewrites each known Python phrase into the file's keys; a
message without one is returned unchanged."""
from __future__ import annotations

import re

from .schema import BUILDER_TABLES

_BARE = re.compile(r"^[A-Za-z0-9_\-]+$")


def _toml_key(name: str) -> str:
    """``name`` as a TOML table key: bare where allowed, else double-quoted."""
    return name if _BARE.match(name) else '"' + name.replace('"', '\\"') + '"'


def _builder_group(m: re.Match, table: str, doc: dict) -> str:
    group = m.group(1)
    prefix = group.rpartition(".")[0] or group
    declared = isinstance(doc.get("spring_groups"), dict) and group in doc["spring_groups"]
    also = (f", or rename the [spring_groups.{_toml_key(group)}] table" if declared else "")
    return (f"group {group!r} already exists in this scene: give this entry another name "
            f"(e.g. name = \"{prefix}2\"; a builder's name is the prefix of its groups){also}.")


def _new_spring_group(m: re.Match, table: str, doc: dict) -> str:
    group = m.group(1)
    return (f"spring group {group!r} is new: give k = ... (N/m) in this entry, or declare it "
            f"in a [spring_groups.{_toml_key(group)}] table with k (N/m) and c (N s/m).")


def _overlap(m: re.Match, table: str, doc: dict) -> str:
    where = ("at the top level of the file" if table in BUILDER_TABLES else
             "in this entry (or at the top level for the whole file)")
    return f"; or set allow_overlap = true {where} to start it compressed on purpose."


#: (library phrase, its scene-file spelling): a replacement string or a function of the match,
#: the entry's table name ("spheres", "ropes", ...) and the parsed file
_REWRITES = (
    (re.compile(r"group '([^']*)' already exists in this scene: pass another group= prefix "
                r"to the builder\."), _builder_group),
    (re.compile(r"; or pass allow_overlap=True to start it compressed on purpose\."), _overlap),
    (re.compile(r"spring group '([^']*)' is new: give k= \(N/m\), or declare it with "
                r"scene\.add_spring_group\('[^']*', k=\.\.\., c=\.\.\.\)\."), _new_spring_group),
    (re.compile(r"drop velocity= or pinned=True\."),
     "drop velocity from this entry, or set pinned = false."),
    (re.compile(r"give structural=\(k, c\)\."),
     "give structural = k or [k, c] (N/m, N s/m) in this entry, not false."),
)


def file_advice(message: str, table: str, doc: dict) -> str:
    """``message`` (a library SceneError's text) with its Python advice in scene-file keys.
    ``table``: the top-level table of the entry being added ("spheres", "ropes", ...)."""
    for pattern, repl in _REWRITES:
        if callable(repl):
            message = pattern.sub(lambda m, f=repl: f(m, table, doc), message)
        else:
            message = pattern.sub(lambda m, r=repl: r, message)
    return message
