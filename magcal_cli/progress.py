"""Progress on stderr: the stage, its fraction and the time left on one updating terminal line.

The pipeline and the estimators report through a `Hook`: `hook("reading x.bin")` announces a stage (a log
line), `hook("MAG[0] ekf-ml pass 2", done, total)` reports a fraction of one. `Progress` renders them: messages
as lines, fractions on one line rewritten with a carriage return, at most `RATE_HZ` times a second, and only
when the stream is a terminal (a pipe or a file gets the messages alone). Code that cannot take the hook as an
argument (a caller that is not ours to change) finds it with `current()`, set by `active()`.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar, Token
from typing import Protocol, TextIO

#: redraws per second at most: a hot loop may call the hook far more often
RATE_HZ = 5.0
#: a new stage is drawn sooner (a stage without fractions would otherwise show the previous one), but not faster
STAGE_HZ = 20.0
#: a time left is shown once the stage has run this long (the first steps' rate is noise)
ETA_AFTER_S = 1.0
#: erase from the cursor to the end of the line (ANSI EL)
CLEAR = "\033[K"


class Hook(Protocol):
    """Where stages and their fractions are reported."""

    def __call__(self, stage: str, done: float | None = None, total: float | None = None) -> None:
        """A stage message (no `done`), `done` of `total` steps of a stage, or a stage of unknown size (no
        `total`)."""


def noop(stage: str, done: float | None = None, total: float | None = None) -> None:
    """The hook that reports nothing."""


_CURRENT: ContextVar[Hook] = ContextVar("magcal_progress", default=noop)


def current() -> Hook:
    """The hook set by the innermost `active()`, else `noop`."""
    return _CURRENT.get()


@contextmanager
def active(hook: Hook) -> Iterator[Hook]:
    """Make `hook` the one `current()` returns inside the block (this thread and context only)."""
    token = _CURRENT.set(hook)
    try:
        yield hook
    finally:
        _CURRENT.reset(token)


def every(hook: Hook, stage: str, total: int, step: int) -> Callable[[int], None]:
    """A per-index reporter that calls `hook` only on every `step`-th index (hot loops stay hot)."""
    step = max(1, step)

    def report(i: int) -> None:
        if i % step == 0:
            hook(stage, i, total)
    return report


def within(hook: Hook, lo: float, hi: float) -> Hook:
    """`hook` with each fraction mapped into lo..hi of one: the steps of one stage (parse the bytes, then build
    the streams) rise as one fraction from 0 to 1. Messages and reports without a total pass unchanged."""

    def part(stage: str, done: float | None = None, total: float | None = None) -> None:
        if done is None or not total:
            hook(stage, done, total)
        else:
            hook(stage, lo + (hi - lo) * min(done / total, 1.0), 1.0)
    return part


def duration(seconds: float) -> str:
    """'8 s', '2 min 05 s', '1 h 03 min'."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class Progress:
    """Renders a Hook's reports on `stream`: message lines when `lines`, the live fraction line when `live`."""

    def __init__(self, stream: TextIO, *, live: bool, lines: bool = True, prefix: str = "magcal: ",
                 clock: Callable[[], float] = time.monotonic, width: Callable[[], int] | None = None) -> None:
        """`clock` and `width` are injectable for tests (a fake clock, a fixed terminal width)."""
        self.stream, self.live, self.lines, self.prefix, self.clock = stream, live, lines, prefix, clock
        self.width = width or (lambda: shutil.get_terminal_size((100, 24)).columns)
        self._stage: str | None = None
        self._t0 = 0.0
        self._done0 = 0.0
        self._last = -float("inf")
        self._shown = False
        self._token: Token[Hook] | None = None
        self._lock = threading.Lock()      # the diagnosis may report from worker threads

    @classmethod
    def for_stderr(cls, quiet: bool) -> Progress:
        """stderr's renderer: nothing with -q, the live line only on a terminal."""
        stream = sys.stderr
        return cls(stream, live=not quiet and stream.isatty(), lines=not quiet)

    def __call__(self, stage: str, done: float | None = None, total: float | None = None) -> None:
        """Print a message, or redraw the live line (rate-limited) with the fraction and the time left."""
        with self._lock:
            if done is None:
                self._message(stage)
            elif self.live:
                self._fraction(stage, done, total)

    def _message(self, text: str) -> None:
        """A permanent line (the live line, if any, is erased first and comes back on the next update)."""
        self._stage = None
        if not self.lines:
            return
        self._erase()
        self.stream.write(f"{self.prefix}{text}\n")
        self.stream.flush()

    def _fraction(self, stage: str, done: float, total: float | None) -> None:
        """Redraw the live line unless it was drawn less than 1/RATE_HZ s ago."""
        now = self.clock()
        changed = stage != self._stage
        if changed:
            self._stage, self._t0, self._done0 = stage, now, done
        if now - self._last < 1.0 / (STAGE_HZ if changed else RATE_HZ):
            return
        self._last = now
        text = f"{self.prefix}{stage}"
        if total:
            text += f": {100.0 * min(done / total, 1.0):3.0f} %"
            elapsed, moved = now - self._t0, done - self._done0
            if elapsed >= ETA_AFTER_S and moved > 0:
                text += f", {duration(elapsed / moved * max(total - done, 0.0))} left"
        cols = max(self.width() - 1, 10)    # a line that wraps cannot be rewritten with a carriage return
        self.stream.write("\r" + text[:cols] + CLEAR)
        self.stream.flush()
        self._shown = True

    def _erase(self) -> None:
        """Erase the live line so that the next output starts on a clean line."""
        if self._shown:
            self.stream.write("\r" + CLEAR)
            self.stream.flush()
            self._shown = False

    def close(self) -> None:
        """Erase the live line (before results or warnings are printed)."""
        with self._lock:
            self._erase()
            self._stage = None

    def __enter__(self) -> Progress:
        """Make this the current hook."""
        self._token = _CURRENT.set(self)
        return self

    def __exit__(self, *_: object) -> None:
        """Restore the previous hook and erase the live line."""
        if self._token is not None:
            _CURRENT.reset(self._token)
            self._token = None
        self.close()
