"""What the scripts in examples/ share: their command-line flags and writing their pictures.

The library (:mod:`tuning.plots`) draws and returns the paths it wrote; the scripts parse their
arguments and print, here. Imported as ``from _common import ...``: a script run as
``python examples/NAME.py`` has examples/ on its path.
"""
from __future__ import annotations

import argparse
import pathlib

from tuning import plots

#: this folder (examples/): the README's pictures are in its images/
HERE = pathlib.Path(__file__).resolve().parent

__all__ = ["example_parser", "example_pyplot", "save_figure", "save_strip", "save_gif",
           "picture_path", "positive_int"]


def picture_path(text: str) -> str:
    """argparse type of ``--out``: a figure name matplotlib can write (:func:`tuning.io.
    check_plot`), checked before the example computes anything."""
    from tuning.io import OutputError, check_plot
    try:
        check_plot(text, what="--out")
    except OutputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return v


def example_parser(description: str, default_out: str, *,
                   quick_help: str = "shorter run (seconds)",
                   gif_help: str = "also write an animated GIF") -> argparse.ArgumentParser:
    """An ``argparse.ArgumentParser`` with the flags every example takes: ``--quick``,
    ``--out`` (the PNG, default ``default_out``; the GIF goes next to it) and ``--gif``.
    A default under ``examples/`` names the README's pictures in this folder, wherever the
    script runs from (as the other examples' defaults do), not a folder of that name under
    the current one. Add the example's own flags to the returned parser."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--quick", action="store_true", help=quick_help)
    if default_out.startswith("examples/"):
        default_out = str(HERE / default_out[len("examples/"):])
    ap.add_argument("--out", default=default_out, type=picture_path,
                    help="the picture (default: %(default)s)")
    ap.add_argument("--gif", action="store_true", help=gif_help)
    return ap


def example_pyplot(out):
    """``matplotlib.pyplot`` (Agg backend) with the parent folder of ``out`` created, or None
    after printing that matplotlib is missing (the example then writes no picture)."""
    try:
        plt = plots.require_matplotlib()
    except ImportError:
        print("matplotlib is not installed (pip install 'diffpen[plot]'): no picture.")
        return None
    pathlib.Path(out).parent.mkdir(parents=True, exist_ok=True)
    return plt


def save_figure(fig, out, **kw) -> None:
    """:func:`tuning.plots.save_figure`, then print ``wrote <path>``."""
    print(f"wrote {plots.save_figure(fig, out, **kw)}")


def save_strip(draw_frame, frames, out, **kw) -> None:
    """:func:`tuning.plots.save_strip`, then print ``wrote <path>``."""
    print(f"wrote {plots.save_strip(draw_frame, frames, out, **kw)}")


def save_gif(draw_frame, frames, out, **kw) -> None:
    """:func:`tuning.plots.save_gif`, then print ``wrote <path>``."""
    print(f"wrote {plots.save_gif(draw_frame, frames, out, **kw)}")
