"""Figures for fits and sweeps. matplotlib is an optional extra (``pip install diffpen[plot]``)
and is imported only when a figure is drawn."""
from __future__ import annotations

import pathlib

import numpy as np

from .io import save_figure_file

__all__ = ["require_matplotlib", "fit_figure", "trajectory_fit_figure", "heatmap",
           "save_figure", "save_strip", "save_gif"]


def require_matplotlib():
    """Import matplotlib with the Agg backend, or raise ImportError saying how to install it."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError("plots need matplotlib: pip install 'matplotlib>=3.7' (or, in a "
                          "diffpen checkout, pip install -e '.[plot]').") from None
    return plt


def fit_figure(path, t, z, *, targets: dict, achieved: dict, loss_history, radius: float,
               settle_tol: float | None = None, rest: float | None = None,
               title: str = "", evaluations: bool = False) -> pathlib.Path:
    """Two panels: the fitted trajectory (lowest point above the surface, m, against s) with
    the apex targets and the settling band, and the loss against the iteration.

    Args:
      t: (S,) s.  z: (S,) centre height, m.  targets, achieved: as in ``FitResult``.
      loss_history: (I,) loss per iteration (or per evaluation with ``evaluations=True``).
      radius: m.  rest: resting centre height, m.
    """
    plt = require_matplotlib()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [2, 1]})
    t, z = np.asarray(t), np.asarray(z)
    a1.plot(t, z - radius, lw=1.0, label="fitted trajectory (lowest point)")
    for i, h in enumerate(np.atleast_1d(targets.get("apex_heights", []))):
        a1.axhline(h, color="C1", ls="--", lw=0.8, label="apex target" if i == 0 else None)
    ts = targets.get("settling_time")
    if ts is not None:
        a1.axvline(ts, color="C2", ls="--", lw=0.8, label=f"settling target {ts:.3g} s")
        got = achieved.get("settling_time")
        if got is not None and np.isfinite(got):
            a1.axvline(got, color="C2", lw=0.8, label=f"settling achieved {got:.4g} s")
    if rest is not None and settle_tol is not None:
        a1.axhspan(rest - radius - settle_tol, rest - radius + settle_tol, color="C2",
                   alpha=0.2, label=f"band +-{settle_tol * 1e3:.3g} mm")
    a1.set_xlabel("time (s)")
    a1.set_ylabel("height of lowest point (m)")
    a1.legend(fontsize=8)
    a1.set_title(title or "fitted trajectory")
    hist = np.maximum(np.asarray(loss_history, float), 1e-300)
    a2.semilogy(np.arange(len(hist)), hist, ".-")
    a2.set_xlabel("evaluation" if evaluations else "iteration")
    a2.set_ylabel("loss (sum of squared relative errors)")
    a2.set_title("loss per simulation (search, then LM)" if evaluations
                 else "loss")
    return save_figure(fig, path, dpi=120)


def trajectory_fit_figure(path, t, z, z_fit, history, *, title: str = "") -> pathlib.Path:
    """Measured record and fitted model (m against s), residuals, and the LM cost."""
    plt = require_matplotlib()
    fig, (a1, a2, a3) = plt.subplots(3, 1, figsize=(9, 8), sharex=False)
    a1.plot(t, z, ".", ms=2, label="record")
    a1.plot(t, z_fit, lw=1.0, label="fit")
    a1.set_ylabel("centre height (m)")
    a1.legend(fontsize=8)
    a1.set_title(title or "trajectory fit")
    a2.plot(t, (np.asarray(z_fit) - np.asarray(z)) * 1e3, lw=0.6)
    a2.set_ylabel("residual (mm)")
    a2.set_xlabel("time (s)")
    a3.semilogy(np.maximum(np.asarray(history), 1e-300))
    a3.set_xlabel("LM step (all horizons)")
    a3.set_ylabel("cost (m^2)")
    return save_figure(fig, path, dpi=120)


def cell_edges(x, log: bool) -> np.ndarray:
    """(n + 1,) edges of the cells around the (n,) increasing grid points ``x``: midway
    between neighbours (in log x when ``log``), the ends as far out as the first and last
    halves; one point gets a cell of a factor 2 (log) or +-0.5 around it."""
    x = np.asarray(x, float)
    y = np.log(x) if log else x
    if y.size == 1:
        half = np.log(2.0) / 2 if log else 0.5
        e = np.array([y[0] - half, y[0] + half])
    else:
        mid = 0.5 * (y[1:] + y[:-1])
        e = np.concatenate([[2 * y[0] - mid[0]], mid, [2 * y[-1] - mid[-1]]])
    return np.exp(e) if log else e


def heatmap(path, k, c, values, *, metric: str, target: float | None = None,
            point: tuple | None = None, title: str = "",
            labels: tuple = ("k (N/m)", "c (N s/m)"), log: tuple = (True, True)) -> pathlib.Path:
    """A metric over a (k, c) grid on log axes, with the ``target`` contour.

    Args:
      k: (nk,) N/m.  c: (nc,) N s/m.  values: (nk, nc) metric values (nan where undefined).
      point: optional (k, c) to mark (e.g. a fitted point).
      labels, log: the axes' labels and whether each is logarithmic (any two parameters).
    """
    plt = require_matplotlib()
    fig, ax = plt.subplots(figsize=(6.5, 5))
    v = np.ma.masked_invalid(np.asarray(values, float).T)
    # cell edges midway between the points on each axis's own scale (geometric midpoints on a
    # log axis): matplotlib's "nearest" shading takes arithmetic midpoints, which on log axes
    # gave the cells unequal widths and the first a negative edge
    mesh = ax.pcolormesh(cell_edges(k, log[0]), cell_edges(c, log[1]), v, shading="flat",
                         cmap="viridis")
    fig.colorbar(mesh, ax=ax, label=metric)
    finite = np.isfinite(np.asarray(values, float))
    if target is not None and finite.any() \
            and np.nanmin(values) < target < np.nanmax(values):
        cs = ax.contour(k, c, v, levels=[target], colors="w", linewidths=1.5)
        ax.clabel(cs, fmt={target: f"target {target:.3g}"}, fontsize=8)
    if point is not None:
        ax.plot(*point, "r*", ms=12)
    ax.set_xscale("log" if log[0] else "linear")
    ax.set_yscale("log" if log[1] else "linear")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_title(title or metric)
    return save_figure(fig, path, dpi=120)


# --- figure files (the examples' strips and animations) ---------------------------------------

def save_figure(fig, out, *, dpi: int = 110) -> pathlib.Path:
    """Lay out ``fig``, save it to ``out`` (its folder must exist), close it; returns the path
    written."""
    plt = require_matplotlib()
    fig.tight_layout()
    save_figure_file(fig, out, dpi=dpi)
    plt.close(fig)
    return pathlib.Path(out)


def save_strip(draw_frame, frames, out, *, title: str, figsize_per_frame=(2.2, 2.6),
               figsize=None, sharey: bool = True, dpi: int = 110, projection: str | None = None,
               extra=None, extra_width: float = 1.6) -> pathlib.Path:
    """A row of snapshots saved as a PNG: one panel per entry of ``frames``. Returns the path
    written.

    Args:
      draw_frame: ``draw_frame(ax, i)`` draws saved frame ``i`` into ``ax``.
      frames: the frame indices, left to right.
      out: PNG path (its folder must exist).
      title: the figure's title.  figsize_per_frame: (width, height) in inches per panel;
        ``figsize`` overrides the whole figure's size.  sharey: share the panels' y axis.
      projection: e.g. ``"3d"`` for 3D panels.
      extra: optional ``extra(ax)`` that draws one more, wider panel (``extra_width`` times a
        snapshot's width) at the right end, e.g. a quantity over time.
    """
    plt = require_matplotlib()
    frames = list(frames)
    n = len(frames) + (extra is not None)
    kw = {}
    if projection is not None:
        kw["subplot_kw"] = {"projection": projection}
    if extra is not None:
        kw["gridspec_kw"] = {"width_ratios": [1] * len(frames) + [extra_width]}
    else:
        kw["sharey"] = sharey
    if figsize is None:
        figsize = (figsize_per_frame[0] * n, figsize_per_frame[1])
    fig, axes = plt.subplots(1, n, figsize=figsize, squeeze=False, **kw)
    axes = axes[0]
    for ax, f in zip(axes, frames):
        draw_frame(ax, f)
    if extra is not None:
        extra(axes[-1])
    fig.suptitle(title)
    return save_figure(fig, out, dpi=dpi)


def save_gif(draw_frame, frames, out, *, figsize=(3.5, 3.5), fps: int = 20,
             projection: str | None = None, nrows: int = 1) -> pathlib.Path:
    """An animation saved next to ``out`` with the suffix ``.gif`` (matplotlib's PillowWriter).
    Returns the path written.

    Args:
      draw_frame: ``draw_frame(ax, i)`` draws saved frame ``i``; the axes are cleared before
        each frame. With ``nrows > 1`` it gets the array of ``nrows`` stacked axes instead.
      frames: the frame indices to animate, in order (e.g. ``range(0, len(t), step)``).
      figsize: inches.  fps: frames per second.  projection: e.g. ``"3d"``.
    """
    plt = require_matplotlib()
    from matplotlib.animation import FuncAnimation, PillowWriter
    fig, axes = plt.subplots(nrows, 1, figsize=figsize, squeeze=False,
                             subplot_kw={"projection": projection} if projection else None)
    axes = axes[:, 0]

    def update(f):
        for ax in axes:
            ax.clear()
        draw_frame(axes[0] if nrows == 1 else axes, f)
    anim = FuncAnimation(fig, update, frames=frames)
    path = pathlib.Path(out).with_suffix(".gif")
    anim.save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path
