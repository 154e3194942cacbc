"""Resumable record fits: the checkpoint file of :func:`tuning.trajfit.fit_records`.

A fit given ``checkpoint=PATH`` writes its progress there after every Levenberg-Marquardt
iteration, atomically (:func:`tuning.io.atomic_write`): the key of everything that decides
the fit (:func:`fit_key`: the simulator, the params, the records' arrays, the fitted leaves
and their bounds, the options), the multi-start screen, the runs that ended and the run in
progress (its horizon stage, its point, LM's damping and cost history). A rerun with the
same key resumes where the last write left off and ends with the result an uninterrupted
fit gives, bit for bit: LM's next iteration depends only on its point and damping
(:func:`tuning.lm.levenberg_marquardt`, ``resume=``), and the residuals are a deterministic
function of the point. A checkpoint of another fit is refused, naming what differs, unless
the caller asks for a fresh start.

``diffpen fit SCENE.toml --data ... --out FITTED.toml`` keeps its checkpoint beside the
output (:func:`checkpoint_path`) and removes it once the fitted scene is written.
"""
from __future__ import annotations

import json
import os

import jax
import numpy as np

from .errors import FitError
from .io import (OutputError, atomic_write, check_output, describe_simulator, key_differences,
                 result_key)
from .io import file_digest  # noqa: F401 - its home until tuning.io held it

__all__ = ["FitCheckpoint", "fit_key", "checkpoint_path", "SUFFIX", "file_digest"]

#: appended to an output's name for its fit's checkpoint
SUFFIX = ".fit-progress.json"


def checkpoint_path(out: str) -> str:
    """The checkpoint of a fit that writes ``out``: ``out`` + :data:`SUFFIX`, beside the file
    ``out`` names (a symbolic link is followed to its target)."""
    return os.path.realpath(os.fspath(out)) + SUFFIX


def _leaves(tree) -> dict:
    """``{dotted path: array}`` of a pytree's leaves (the key's view of params and record
    arrays: a refusal names the leaf that differs, e.g. ``params.contact.board.k``)."""
    flat, _ = jax.tree_util.tree_flatten_with_path(tree)
    return {jax.tree_util.keystr(path, simple=True, separator="."): np.asarray(leaf)
            for path, leaf in flat}


def fit_key(sim, params, free, arrays, layouts, **options) -> dict:
    """The key of a record fit (:func:`tuning.io.result_key`): the simulator
    (:func:`tuning.io.describe_simulator`), every params leaf (the start values), the fitted
    leaves with their bounds and fitting space, the batches' layouts and arrays (digests of
    the records as the fit sees them: frames, masks, start states) and ``options`` (loss,
    horizons, iteration limit, multi-start settings...). The fitting-space bounds follow
    from these (with the safe step's caps)."""
    return result_key(
        what="record fit", simulator=describe_simulator(sim), params=_leaves(params),
        fitted={f.name: {"bounds": [float(f.lo), float(f.hi)], "log": bool(f.log)}
                for f in free},
        layouts=repr(layouts), records=[_leaves(a) for a in arrays], **options)


class FitCheckpoint:
    """The checkpoint file at ``path`` for a fit of ``key``.

    ``state`` holds what was read (empty for a new fit): ``"screen"`` (the multi-start
    screen's costs, order and note), ``"runs"`` (the LM runs that ended) and ``"current"``
    (the run in progress). A file with another key raises :class:`FitError` naming the
    differences, unless ``fresh`` (then it is overwritten at the first save); so does an
    unreadable one, and a path that cannot be written (:func:`tuning.io.check_output`), before
    the fit compiles anything. The caller holds the output's lock
    (:class:`tuning.io.OutputLock`)."""

    def __init__(self, path: str, key: dict, *, fresh: bool = False):
        try:
            check_output(path, what="checkpoint", ext=".json")
        except OutputError as exc:
            raise FitError(str(exc)) from None
        self.path = os.fspath(path)
        self.key = key
        self.state: dict = {}
        if fresh or not os.path.exists(self.path):
            return
        try:
            with open(self.path) as fh:
                data = json.load(fh)
            old, state = data["key"], data["state"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise FitError(f"{self.path}: not a readable fit checkpoint ({exc}); remove it, or "
                           "start afresh (diffpen fit --fresh, fit_records(fresh=True)).") from None
        if old != key:
            raise FitError(f"{self.path} holds the progress of another fit, so this one cannot "
                           "resume from it: " + "; ".join(key_differences(old, key))
                           + ". Start afresh (diffpen fit --fresh, fit_records(fresh=True)), "
                           "which overwrites it, or write to another output.")
        self.state = state

    @property
    def resumed_iterations(self) -> int:
        """LM iterations the file held when it was read (0 for a new fit)."""
        n = sum(int(r["iterations"]) for r in self.state.get("runs", []))
        cur = self.state.get("current")
        if cur is not None:
            n += int(cur["it_all"]) - int(cur["it_start"]) + int(cur["lm"]["iterations"])
        return n

    def save(self) -> None:
        """Write the key and ``state`` atomically."""
        text = json.dumps({"key": self.key, "state": self.state})
        atomic_write(self.path, lambda fh: fh.write(text.encode()))

    def remove(self) -> None:
        """Delete the file (the fit's result is written elsewhere)."""
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
