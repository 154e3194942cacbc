"""Progress on long work, on stderr.

On a terminal a one-line bar is redrawn in place; otherwise (a log file, a pipe, a batch
job) a plain line is written every ``every`` seconds (default 5 s), so a long run always
shows that it is alive and how far it is, and a short one prints nothing.
"""
from __future__ import annotations

import contextlib
import sys
import time

__all__ = ["Progress", "interrupt", "raise_pending", "clear_pending", "pending",
           "uninterrupted", "held"]

#: interrupts raised by a command's signal handler (:func:`interrupt`) and not yet ended
_PENDING: list = []
#: depth of :func:`uninterrupted` blocks now running (an interrupt then waits for their end)
_HELD = [0]


def interrupt(exc_type=KeyboardInterrupt):
    """Raise ``exc_type`` for a signal and remember it until :func:`clear_pending`: a
    handler raises where the interpreter happens to be, and Python drops an exception raised
    inside a garbage-collection callback (JAX registers one, which runs often while a
    command starts), so a Ctrl-C there was lost and the run went on. :meth:`Progress.update`
    raises it again (:func:`raise_pending`). Inside :func:`uninterrupted` it is only
    remembered, and raised where the block ends."""
    _PENDING.append(exc_type)
    if not _HELD[0]:
        raise exc_type


def held() -> bool:
    """Whether an :func:`uninterrupted` block is running (in any thread)."""
    return bool(_HELD[0])


@contextlib.contextmanager
def uninterrupted():
    """A block that a command's Ctrl-C or SIGTERM does not cut short (writing a set of files
    that must agree, e.g. a sweep's .npz and its .csv): the interrupt is raised where the
    block ends (only one that arrived inside it: an interrupt already on its way out, with
    the block in a ``finally``, is not raised twice). Library use, without the command's
    handlers, is not affected."""
    before = len(_PENDING)
    _HELD[0] += 1
    try:
        yield
    finally:
        _HELD[0] -= 1
    if not _HELD[0] and len(_PENDING) > before:
        raise _PENDING[-1]


def raise_pending() -> None:
    """Raise an interrupt :func:`interrupt` raised that has not ended the run (see there);
    nothing in library use, where no handler records one."""
    if _PENDING:
        raise _PENDING[-1]


def pending() -> bool:
    """Whether an interrupt :func:`interrupt` raised has not ended the run yet."""
    return bool(_PENDING)


def clear_pending() -> None:
    """The run ended (interrupted, or finished before a lost interrupt could be raised)."""
    _PENDING.clear()


class Progress:
    """Progress of ``total`` units of work labelled ``label``.

    Args:
      total: number of units (iterations, chunks).
      label: what is running, e.g. ``"diffpen fit"``.
      enabled: None (default): a bar on a terminal, a line every ``every`` s otherwise;
        True: as None; False: silent.
      value: name of the number passed to :meth:`update` (``"loss"``; ``"done"`` prints it as
        a percentage of the work done).
      every: seconds between lines when stderr is not a terminal.
      stream: where to write (default ``sys.stderr``, looked up at each write).
    """

    def __init__(self, total: int, label: str = "fit", enabled: bool | None = None, *,
                 value: str = "loss", every: float = 5.0, stream=None):
        raise_pending()                 # a lost interrupt ends the run before its long loop
        self.total = total
        self.label = label
        self.value = value
        self.every = float(every)
        self._stream = stream
        self.enabled = enabled is not False
        out = self.stream
        self.tty = bool(getattr(out, "isatty", lambda: False)())
        self._t0 = time.perf_counter()
        self._last = self._t0 if not self.tty else 0.0
        self._drawn = False
        self._pending = None            # the last update not drawn (throttled)

    @property
    def stream(self):
        return self._stream if self._stream is not None else sys.stderr

    def _text(self, i: int, value):
        """``(count, frac)``: ``"i/total"`` plus the value, and the fraction done."""
        frac = min(i, self.total) / max(self.total, 1)
        if value is None:
            tail = ""
        elif self.value == "done":
            tail = f" {100.0 * float(value):.1f}% done"
        else:
            tail = f" {self.value} {float(value):.3e}"
        return f"{i}/{self.total}{tail}", frac

    def update(self, i: int, value=None, force: bool = False) -> None:
        """Report that ``i`` of ``total`` units are done (``value``: the current loss, or
        the fraction done for ``value="done"``). Raises a command's interrupt that an
        earlier raise lost (:func:`interrupt`): every long loop reports here."""
        raise_pending()
        if not self.enabled:
            return
        self._pending = (i, value)
        now = time.perf_counter()
        count, frac = self._text(i, value)
        if self.tty:
            if not force and now - self._last < 0.05:
                return
            self._last = now
            width = 24
            done = int(width * frac)
            bar = "#" * done + "." * (width - done)
            self.stream.write(f"\r{self.label} [{bar}] {count}")
            self._drawn = True
            self._pending = None
        else:
            if not force and now - self._last < self.every:
                return
            self._last = now
            self.stream.write(f"{self.label} {count} ({now - self._t0:.0f} s)\n")
            self._pending = None
        self.stream.flush()

    def close(self) -> None:
        """End the bar: on a terminal, draw the last update if it was skipped (updates
        closer than 50 ms apart are), then end the line."""
        if self.enabled and self.tty:
            pending = self._pending
            if pending is not None:
                self.update(*pending, force=True)
            if self._drawn:
                self.stream.write("\n")
                self.stream.flush()
