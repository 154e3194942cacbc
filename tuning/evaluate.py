"""Open-loop accuracy of a scene against measured records.

Each record is rolled out from its first state (:func:`tuning.trajfit.first_state`) to its
last frame, with no correction on the way, and the simulated pose is sampled at the frame
times. Per record:

* position error: mean over samples of ``|p_sim - p_data| / L`` in % (``L`` the body's
  size, :func:`tuning.trajfit.body_size`: the cube's edge 0.1048 m), over every observed
  body and measured frame (the first frame included, as measured);
* rotation error: mean over samples of the angle of ``q_sim^-1 q_data``, degrees (bodies
  with measured orientations only).

The summary gives the mean and the median over records. All records run in one vmapped
rollout: :func:`evaluator` compiles it once for a batch shape, then each call is one
dispatch.
"""
from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .errors import FitError
from .first_state import FLIGHT_FRAMES
from .io import save_figure_file
from .compiled import ProgramCache
from .record_batch import layout_of, typed_params, with_arrays
from .stable import solver_miss
from .trajfit import Batch, rotation_angle, simulate

__all__ = ["Evaluation", "evaluator", "evaluate_batch", "plot_records"]

#: the file in an ``evaluate --plot`` folder naming the scene, the records and the plots of
#: the run that drew them (the next run into the folder removes those it does not redraw)
PLOT_INDEX = "plots.json"
#: the index's ``written_by``: only an index that carries it names plots this command drew
#: (and may redraw or remove)
PLOT_INDEX_MARK = "diffpen evaluate"


@dataclasses.dataclass
class Evaluation:
    """Accuracy over records.

    position_error_pct, rotation_error_deg: ``{"mean": ..., "median": ...}`` over records
      (rotation None when no record has orientations).
    records: per record ``{"path", "frames", "duration_s", "position_error_pct",
      "rotation_error_deg"}``.
    pos, quat: the simulated poses (R, T, B, 3) / (R, T, B, 4) at the frame times.
    seconds: wall time of the rollouts (after compilation).
    unstable: records whose rollout went past its safe step (``State.aux["unstable"]``):
      their errors are NaN (``records[i]["unstable"]`` True) and left out of the summary.
      ``records[i]["collapsed"]``: a plastic spring of the record's rollout collapsed
      (``State.aux["plastic_collapsed"]``); its errors are kept.
    message: says so when ``unstable`` > 0 or a record collapsed, else "".
    """
    position_error_pct: dict
    rotation_error_deg: dict | None
    records: list
    pos: np.ndarray
    quat: np.ndarray | None
    seconds: float
    unstable: int = 0
    message: str = ""

    def as_dict(self) -> dict:
        return {"position_error_pct": self.position_error_pct,
                "rotation_error_deg": self.rotation_error_deg, "records": self.records,
                "seconds": self.seconds, "unstable": self.unstable, "message": self.message}


def _errors(pos, quat, batch: Batch):
    """Per-record mean position error (%) and rotation error (deg): (R,), (R,) or None."""
    d = jnp.linalg.norm(pos - batch.pos, axis=-1) / jnp.asarray(batch.size)[None, None, :]
    pm = jnp.asarray(batch.pos_mask)
    pe = 100.0 * jnp.sum(d * pm, axis=(1, 2)) / jnp.maximum(jnp.sum(pm, axis=(1, 2)), 1.0)
    if quat is None or not batch.has_rotation:
        return pe, None
    qm = jnp.asarray(batch.quat_mask)
    ang = jnp.degrees(rotation_angle(quat, jnp.asarray(batch.quat)))
    re = jnp.sum(ang * qm, axis=(1, 2)) / jnp.maximum(jnp.sum(qm, axis=(1, 2)), 1.0)
    return pe, re


#: compiled evaluation programs by (simulator, batch layout)
_PROGRAMS = ProgramCache()


class _Bound:
    """An evaluation program with one batch's arrays bound, a function of ``params`` as a
    jitted one is: ``f(params)``, ``f.lower(params).compile()(params)``."""

    def __init__(self, program, arrays, dtype):
        self._program, self._arrays, self._dtype = program, arrays, dtype

    def __call__(self, params):
        return self._program(typed_params(params, self._dtype), self._arrays)

    def lower(self, params):
        return _Lowered(self._program.lower(typed_params(params, self._dtype), self._arrays),
                        self._arrays, self._dtype)


class _Lowered:
    """:meth:`_Bound.lower`'s result: ``compile()`` gives the executable as a function of
    ``params`` (shared with the program's cache: no compile when cached)."""

    def __init__(self, lowered, arrays, dtype):
        self._lowered, self._arrays, self._dtype = lowered, arrays, dtype

    def compile(self):
        exe, arrays, dtype = self._lowered.compile(), self._arrays, self._dtype
        return lambda params: exe(typed_params(params, dtype), arrays)


def evaluator(sim: dp.Simulator, batch: Batch):
    """A compiled ``f(params) -> (pos, quat, pos_err (R,), rot_err (R,) or None)`` for the
    batch (and a fifth, ``collapsed`` (R,) bool, for a scene with plastic springs: a record
    whose rollout collapsed one, :mod:`diffpen.terms.plastic`) (compiled on the first call;
    new parameter values never recompile, and neither does another batch of the same layout
    on the same simulator,
    :func:`tuning.record_batch.layout_of`: the program takes the batch's arrays as
    arguments). ``f.lower(params).compile()`` compiles it ahead of a call."""
    key, layout, arrays = layout_of(batch)

    plastic = bool(sim.scene.plastic_springs)

    def build():
        @jax.jit
        def f(params, arrays):
            b = with_arrays(layout, arrays)
            pos, quat, bad, *crushed = simulate(sim, params, b, with_flag=True,
                                                with_collapse=plastic)
            pe, re = _errors(pos, quat, b)
            nan = jnp.asarray(jnp.nan, pe.dtype)
            pe = jnp.where(bad, nan, pe)            # past the safe step: never a result
            re = None if re is None else jnp.where(bad, nan, re)
            return (pos, quat, pe, re) + tuple(crushed)
        return f
    return _Bound(_PROGRAMS.get((sim, key), build), arrays, sim.dtype)


def _summary(v) -> dict:
    """Mean and median over the records with a result (NaN ones, past the safe step, left
    out; NaN when none has one)."""
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return ({"mean": float(np.mean(v)), "median": float(np.median(v))} if v.size
            else {"mean": math.nan, "median": math.nan})


def evaluate_batch(sim: dp.Simulator, params, batch: Batch, *, fn=None) -> Evaluation:
    """Evaluate ``params`` on every record of ``batch`` (see the module docstring).
    ``fn``: an :func:`evaluator` to reuse (else one is built and compiled)."""
    fn = fn or evaluator(sim, batch)
    if hasattr(fn, "lower"):
        # compiled ahead of the timed run (shared with fn's own cache: no-op when cached),
        # so the records are simulated once, not once to compile and once to time
        run = fn.lower(params).compile()
    else:                                   # a plain function: its first call compiles
        jax.block_until_ready(fn(params))
        run = fn
    t0 = time.perf_counter()
    pos, quat, pe, re, *crushed = jax.block_until_ready(run(params))
    seconds = time.perf_counter() - t0
    crushed = np.asarray(crushed[0]) if crushed else np.zeros(len(batch.paths), bool)
    pe = np.asarray(pe)
    re = None if re is None else np.asarray(re)
    recs = []
    for r, path in enumerate(batch.paths):
        n = int(batch.length[r])
        recs.append({"path": path, "frames": n,
                     "duration_s": float(batch.time[r, n - 1]),
                     "position_error_pct": float(pe[r]),
                     "rotation_error_deg": None if re is None else float(re[r]),
                     "unstable": bool(np.isnan(pe[r])), "collapsed": bool(crushed[r])})
    bad = [rec["path"] for rec in recs if rec["unstable"]]
    message = (f"{len(bad)} of {len(recs)} records ran past the safe step"
               f"{solver_miss(sim)} (State.aux['unstable']): their errors are NaN and left "
               f"out of the summary; lower dt or use softer k / smaller c ({bad[:5]})"
               if bad else "")
    crushed = collapse_message(recs)
    if crushed:
        message += ("; " if message else "") + crushed
    return Evaluation(_summary(pe), None if re is None else _summary(re), recs,
                      np.asarray(pos), None if quat is None else np.asarray(quat), seconds,
                      len(bad), message)


def collapse_message(recs: list) -> str:
    """What to say of the records (``Evaluation.records``) whose rollout collapsed a plastic
    spring (crushed below 5% of its length, :mod:`diffpen.terms.plastic`), or ""."""
    flat = [rec["path"] for rec in recs if rec.get("collapsed")]
    return (f"{len(flat)} of {len(recs)} records crushed a plastic spring below 5% of its "
            "length (State.aux['plastic_collapsed']: no self-contact, past what the model "
            f"describes): their errors are not to be trusted ({flat[:5]})" if flat else "")


def plot_records(path: str, batch: Batch, ev: Evaluation, which=None, *,
                 title: str | None = None) -> str:
    """Draw measured (dots) against simulated (lines) trajectories of a few records: a row
    per record and observed body (the first 3 bodies): its x, y, z (m) and, with
    orientations, its rotation error (deg) against time, each titled with that body's mean
    error. Needs matplotlib (imported here). Returns ``path``."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError("plots need matplotlib: pip install 'diffpen[plot]'") from None
    which = list(range(min(4, len(batch.paths)))) if which is None else list(which)
    bodies = list(range(min(len(batch.names), 3)))           # a row per record and body
    rows = [(r, b) for r in which for b in bodies]
    cols = 2 if batch.has_rotation else 1
    fig, axes = plt.subplots(len(rows), cols, figsize=(5.5 * cols, 2.4 * len(rows)),
                             squeeze=False)
    colors = ("tab:blue", "tab:orange", "tab:green")
    for row, (r, b) in enumerate(rows):
        n = int(batch.length[r])
        t = batch.time[r, :n]
        ax = axes[row, 0]
        ok = batch.pos_mask[r, :n, b] > 0
        for a, c in enumerate(colors):
            ax.plot(t[ok], batch.pos[r, :n, b, a][ok], ".", ms=2.5, color=c,
                    label=f"measured {'xyz'[a]}")
            ax.plot(t, ev.pos[r, :n, b, a], "-", lw=1.2, color=c,
                    label=f"simulated {'xyz'[a]}")
        name = batch.paths[r].rsplit("/", 1)[-1]
        who = f", {batch.names[b]}" if len(batch.names) > 1 else ""
        d = np.linalg.norm(ev.pos[r, :n, b] - batch.pos[r, :n, b], axis=-1)[ok]
        pe = 100.0 * float(np.mean(d)) / float(batch.size[b]) if d.size else math.nan
        ax.set_title(f"{name}{who}: position error {pe:.1f}%", fontsize=9)
        ax.set_ylabel("m")
        if row == 0:
            ax.legend(fontsize=7, ncol=2)
        if batch.has_rotation:
            ax = axes[row, 1]
            okq = batch.quat_mask[r, :n, b] > 0
            ang = np.degrees(np.asarray(rotation_angle(jnp.asarray(ev.quat[r, :n, b]),
                                                       jnp.asarray(batch.quat[r, :n, b]))))
            if okq.any():
                ax.plot(t[okq], ang[okq], "-", color="tab:red")
                ax.set_title(f"rotation error{who} (mean {float(np.mean(ang[okq])):.1f} "
                             "deg)", fontsize=9)
            else:
                ax.set_title(f"no orientations measured{who}", fontsize=9)
            ax.set_ylabel("deg")
        for ax in axes[row]:
            ax.set_xlabel("t (s)") if row == len(rows) - 1 else None
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure_file(fig, path, dpi=110)
    plt.close(fig)
    return path


def evaluate_files(scene_path: str, data, *, estimate: str | None = None,
                   plot: str | None = None, n_plot: int = 4,
                   max_frames: int | None = None) -> dict:
    """``diffpen evaluate SCENE.toml --data FILES...``: open-loop accuracy of the scene file
    (its parameter values as written) on the records. Returns the JSON-ready summary
    (``position_error_pct``, ``rotation_error_deg``, ``records``, ``seconds`` of the
    rollouts after compilation, ``compile_seconds``); with ``plot`` (a folder, checked
    before anything is compiled, and so is every picture's path) also draws the first
    ``n_plot`` records to ``plot/NAME.png`` (for a record ``NAME.csv``; ``NNN_NAME.png``
    when that name is not unique, :func:`_plot_names`) and lists them in
    ``plot/plots.json`` with the scene and the records (:data:`PLOT_INDEX`); the PNGs an
    earlier run's index lists that this run does not redraw are removed (no other file in
    the folder is touched: a record whose ``NAME.png`` another program wrote there is drawn
    to ``NNN_NAME.png``). One run per folder: the run holds
    :class:`tuning.io.OutputLock` on ``plot/plots.json`` from the checks to its end, and a
    second run into the folder is refused at once (:class:`tuning.io.OutputError`).
    ``estimate`` /
    ``max_frames``: the first-state estimate and its frame cap
    (:func:`tuning.first_state.first_state`); None: the scene file's ``[fit] first_state`` /
    ``flight_frames``, else ``"record"`` / ``FLIGHT_FRAMES`` (1000: the whole first flight)."""
    import os

    from .scenefile import load_scene_file
    from .trajfit import load_records
    sf = load_scene_file(scene_path)
    records, bodies = load_records(sf, list(data) if data else list(
        (sf.spec.data if sf.spec is not None else None) or []))
    lock = None
    if plot is not None:            # checked before anything is compiled or rolled out
        if os.path.exists(plot) and not os.path.isdir(plot):
            raise FitError(f"--plot {plot} is a file: --plot names a folder for the "
                           "pictures (one PNG per record); give a folder path.")
        try:
            os.makedirs(plot, exist_ok=True)
        except OSError as exc:
            raise FitError(f"--plot {plot}: cannot create the folder ({exc.strerror}); "
                           "choose another path.") from None
        if not os.access(plot, os.W_OK | os.X_OK):
            raise FitError(f"--plot {plot}: the folder {os.path.abspath(plot)} is not "
                           "writable; choose another path.")
        if os.path.isdir(os.path.join(plot, PLOT_INDEX)):
            raise FitError(f"--plot {plot}: {os.path.join(plot, PLOT_INDEX)} is a folder; "
                           "the plots' index is written there: move it or choose another "
                           "path.")
        from .plots import require_matplotlib
        require_matplotlib()
        from .io import OutputLock, clean_orphans
        # one run per folder: a second run's pictures and index would mix with this one's
        index = os.path.join(plot, PLOT_INDEX)
        lock = OutputLock(index, what="--plot folder's index").acquire()
        clean_orphans(index)            # a killed run's half-written index
    try:
        files = None
        if plot is not None:        # each record's picture: a file name no other one has
            shown = range(min(n_plot, len(records)))
            # files in the folder that no earlier run of this command listed are someone
            # else's: never drawn over (a user's toss_003.png was replaced by the plot)
            ours = {f.lower() for f in _listed_plots(plot)}
            foreign = {f.lower() for f in os.listdir(plot) if f.lower() not in ours}
            files = _plot_names([records[r].path for r in shown], taken=foreign)
            for r, f in zip(shown, files):
                p = os.path.join(plot, f)
                if os.path.isdir(p) or (os.path.exists(p) and not os.access(p, os.W_OK)):
                    raise FitError(
                        f"--plot {plot}: {p} is "
                        + ("a folder" if os.path.isdir(p) else "not writable")
                        + f"; the plot of {records[r].path} is written there: move or "
                        "remove it, or choose another --plot folder.")
        return _evaluate(sf, scene_path, records, bodies, estimate, max_frames, plot, files)
    finally:
        if lock is not None:
            lock.release()


def _plot_names(paths, taken=()) -> list:
    """The file names ``evaluate --plot`` draws the records ``paths`` to, one per record and
    all different (compared without case): ``NAME.png`` for a record ``.../NAME.csv``;
    ``NNN_NAME.png`` (``NNN`` its position) when two records share a name or a name is
    already taken (by an earlier record or among ``taken``, lower-case names of files that
    must not be written over), then ``NNN_NAME_2.png``, ... until free."""
    import os
    names = [os.path.splitext(os.path.basename(str(p)))[0] for p in paths]
    taken, files = {t.lower() for t in taken}, []
    for r, name in enumerate(names):
        stem = name if names.count(name) == 1 else f"{r:03d}_{name}"
        if stem.lower() + ".png" in taken:
            stem = f"{r:03d}_{name}"
        f, k = stem + ".png", 2
        while f.lower() in taken:
            f, k = f"{stem}_{k}.png", k + 1
        taken.add(f.lower())
        files.append(f)
    return files


def _evaluate(sf, scene_path, records, bodies, estimate, max_frames, plot, files) -> dict:
    """The body of :func:`evaluate_files` once its outputs are checked (and the ``--plot``
    folder locked): compile, roll out, summarise, draw ``files`` into ``plot``."""
    import os

    from .trajfit import check_stable, prepare
    spec = sf.spec
    estimate = estimate or (spec.first_state if spec is not None else None) or "record"
    max_frames = max_frames or (spec.flight_frames if spec is not None else None) or \
        FLIGHT_FRAMES
    sim = sf.compile()
    params = sf.params(sim)
    check_stable(sim, params, sf.path)
    batch = prepare(sim, records, bodies=bodies, estimate=estimate, max_frames=max_frames)
    fn = evaluator(sim, batch)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(params))
    compile_s = time.perf_counter() - t0
    ev = evaluate_batch(sim, params, batch, fn=fn)
    out = ev.as_dict()
    out.update({"scene": scene_path, "estimate": estimate, "compile_seconds": compile_s,
                "bodies": bodies})
    if plot is not None:
        shown = range(len(files))
        # an earlier run's plots that this one does not redraw would look current: the
        # index lists every file a run wrote (first with the earlier ones, so that a run
        # stopped half way leaves none unlisted), and those it listed are removed after
        old = [f for f in _listed_plots(plot) if f not in files]
        index = {"scene": os.path.abspath(scene_path),
                 "records": [os.path.abspath(records[r].path) for r in shown]}
        _write_plot_index(plot, dict(index, files=files + old))
        out["plots"] = [plot_records(os.path.join(plot, f), batch, ev, [r])
                        for r, f in zip(shown, files)]
        for f in old:
            if os.path.isfile(os.path.join(plot, f)):
                os.remove(os.path.join(plot, f))
        _write_plot_index(plot, dict(index, files=files))
    return out


def _listed_plots(folder: str) -> list:
    """The plot files the index in ``folder`` lists (plain ``.png`` names in the folder;
    anything else in it is ignored); [] without a readable index written by this command
    (:data:`PLOT_INDEX_MARK`: another program's ``plots.json`` listing its own figures had
    them removed)."""
    import json
    import os
    try:
        with open(os.path.join(folder, PLOT_INDEX)) as fh:
            index = json.load(fh)
        files = index.get("files", [])
    except (OSError, ValueError, AttributeError):
        return []
    if not isinstance(files, list) or index.get("written_by") != PLOT_INDEX_MARK:
        return []
    return [f for f in files if isinstance(f, str) and f.lower().endswith(".png")
            and f == os.path.basename(f)]


def _write_plot_index(folder: str, index: dict) -> None:
    import json
    import os

    from .io import atomic_write
    text = json.dumps(dict(index, written_by=PLOT_INDEX_MARK), indent=1) + "\n"
    atomic_write(os.path.join(folder, PLOT_INDEX), lambda fh: fh.write(text.encode()))
