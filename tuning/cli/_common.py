"""Helpers shared by the ``diffpen`` subcommands (argument checks, printing, JAX setup)."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys


class CLIError(argparse.ArgumentTypeError):
    """A bad command line: printed as ``diffpen <cmd>: error: ...`` with exit status 2."""


def setup_jax(x64: bool = True) -> None:
    """float64 for fitting accuracy, and a persistent compilation cache so that a second run
    of the same command skips most of the compile time (``DIFFPEN_CACHE=0`` turns it off)."""
    import jax
    if x64:
        jax.config.update("jax_enable_x64", True)
    if os.environ.get("DIFFPEN_CACHE", "1") != "0":
        path = os.environ.get("DIFFPEN_CACHE_DIR",
                              os.path.join(os.path.expanduser("~"), ".cache", "diffpen", "jax"))
        try:
            os.makedirs(path, exist_ok=True)
            jax.config.update("jax_compilation_cache_dir", path)
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
        except Exception:        # a read-only home must not stop the command
            pass


def positive(name: str):
    """argparse type: a finite number > 0."""
    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise CLIError(f"{name} must be a number, got {text!r}") from None
        if not math.isfinite(v) or v <= 0.0:
            raise CLIError(f"{name} must be a finite number > 0, got {text!r}")
        return v
    conv.__name__ = name
    return conv


def finite(name: str):
    """argparse type: a finite number (``nan`` and ``inf`` are refused)."""
    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise CLIError(f"{name} must be a number, got {text!r}") from None
        if not math.isfinite(v):
            raise CLIError(f"{name} must be a finite number, got {text!r}")
        return v
    conv.__name__ = name
    return conv


def count(name: str, minimum: int | None = 1):
    """argparse type: an integer (digits, or an exact integer in float notation such as
    ``1e9``), >= ``minimum`` unless that is None; ``1.5``, ``nan`` and words are refused."""
    def conv(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            try:
                f = float(text)
            except ValueError:
                f = math.nan
            if not (math.isfinite(f) and f == int(f)):
                raise CLIError(f"{name} must be an integer, got {text!r}") from None
            v = int(f)
        if minimum is not None and v < minimum:
            raise CLIError(f"{name} must be an integer >= {minimum}, got {text!r}")
        return v
    conv.__name__ = name
    return conv


def check_positive(name: str, value) -> None:
    if value is None:
        return
    for v in (value if isinstance(value, (list, tuple)) else [value]):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
            raise CLIError(f"{name} must be a finite number > 0, got {v!r}")


def fail(cmd: str, message: str) -> int:
    sys.stderr.write(f"diffpen {cmd}: error: {message}\n")
    return 2


def dump_json(obj) -> None:
    """One JSON object on stdout (nan/inf become null)."""
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    sys.stdout.write(json.dumps(clean(obj)) + "\n")


def fmt(v, unit: str = "", digits: int = 5) -> str:
    """A number (or list) for printing: ``digits`` significant digits, ``n/a`` for nan."""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(fmt(x, "", digits) for x in v) + "]" + (f" {unit}" if unit else "")
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}g}" + (f" {unit}" if unit else "")
