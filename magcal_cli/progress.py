"""Progress on stderr: the stage, its fraction and the time left on one updating terminal line.

The pipeline and the estimators report through a `Hook`: `hook("reading x.bin")` announces a stage (a log
line), `hook("MAG[0] ekf-ml pass 2", done, total)` reports a fraction of one. `Progress` renders them: messages
as lines, fractions on one line rewritten with a carriage return, at most `RATE_HZ` times a second, and only
when the stream is a terminal (a pipe or a file gets the messages alone). Code that cannot take the hook as an
argument (a caller that is not ours to change) finds it with `current()`, set by `active()`.

A stage names the whole it belongs to: `Parts` prefixes the stages of each part ("magnetometer 2 of 3: ...") and,
once a part has ended, estimates the whole's time left from the parts' durations; `Shares` turns the reports of
items running side by side (threads or forked processes) into one rising fraction (the diagnosis' held-out folds move while they run); `steps`
moves a stage inside one part's share when that part's own steps are not known ahead (a report section's figures).
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar, Token, copy_context
from typing import Protocol, TextIO, TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: redraws per second at most: a hot loop may call the hook far more often
RATE_HZ = 5.0
#: a new stage is drawn sooner (a stage without fractions would otherwise show the previous one), but not faster
STAGE_HZ = 20.0
#: a time left is shown once the stage has run this long (the first steps' rate is noise)
ETA_AFTER_S = 1.0
#: erase from the cursor to the end of the line (ANSI EL)
CLEAR = "\033[K"
#: the reports a threaded item is assumed to make before one has ended and shown how many it makes (Shares)
GUESS_STEPS = 4
#: the most of an item's share its own reports can fill before it has ended (Shares)
ITEM_CAP = 0.9


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


def steps(hook: Hook, stage: str, lo: float, hi: float) -> Hook:
    """A hook for the share lo..hi (fractions of one) of `stage`, for work whose own steps are not known ahead (a
    report section's figures): it reports `lo` at once, and every report made from inside (a figure drawn) moves
    `stage` up within the share, to 1/2, 2/3, 3/4 of it, never to its end."""
    made, name, lock = 0, stage, threading.Lock()

    def step(stage: str, done: float | None = None, total: float | None = None) -> None:
        nonlocal made
        with lock:
            made += 1
            hook(name, lo + (hi - lo) * made / (made + 1), 1.0)
    hook(name, lo, 1.0)
    return step


class WithWhole(str):
    """A stage's text that already names the whole it is part of and the whole's time left ("magnetometer 2 of 3,
    about 20 s left: ..."): the renderer adds no time left of the stage's own (one estimate per line)."""

    __slots__ = ()


class Parts:
    """A whole made of `count` like parts, each run inside `part(i)` (the magnetometers of a fit).

    Inside a part every stage reported through `current()` is named "magnetometer 2 of 3: <stage>", and once a
    part has ended the whole's time left is estimated from the mean duration of the parts that ended and added:
    "magnetometer 2 of 3, about 20 s left: <stage>".
    """

    def __init__(self, hook: Hook, noun: str, count: int, clock: Callable[[], float] = time.monotonic) -> None:
        """`hook` receives the named stages; `clock` is injectable for tests."""
        self.hook, self.noun, self.count, self.clock = hook, noun, count, clock
        self.durations: list[float] = []

    def left(self, index: int, started: float) -> float | None:
        """The whole's time left while part `index` (from 0) runs since `started`: this part's mean duration less
        its time so far, and the mean for each part after it. None before a part has ended, and below a second
        (the last part running longer than the others: its end is not known)."""
        if not self.durations:
            return None
        mean = sum(self.durations) / len(self.durations)
        left = max(mean - (self.clock() - started), 0.0) + mean * (self.count - index - 1)
        return left if left >= 1.0 else None

    def named(self, index: int, started: float) -> Hook:
        """The hook of part `index`: the stage named after the part, with the whole's time left when known (a
        whole of one part passes its stages unchanged)."""
        if self.count <= 1:
            return self.hook

        def report(stage: str, done: float | None = None, total: float | None = None) -> None:
            left = self.left(index, started)
            head = f"{self.noun} {index + 1} of {self.count}"
            if left is None:
                self.hook(f"{head}: {stage}", done, total)
            else:
                self.hook(WithWhole(f"{head}, about {duration(left)} left: {stage}"), done, total)
        return report

    @contextmanager
    def part(self, index: int) -> Iterator[Hook]:
        """Run part `index` (from 0) with its named hook as `current()`; its duration counts once it ends."""
        started = self.clock()
        with active(self.named(index, started)) as hook:
            yield hook
        self.durations.append(self.clock() - started)

    def each(self, items: Sequence[T]) -> Iterator[T]:
        """The items in turn, the loop's body over each running as the next part."""
        for index, item in enumerate(items):
            with self.part(index):
                yield item


class Shares:
    """The progress of `count` items run side by side (the diagnosis' magnetometers, folds and replicates), as one
    rising number.

    `run(i, fn, x)` runs item i with `current()` counting its own reports (the stages of its fits) as its steps;
    `report(done, count)` then gets the items ended plus, for each running item, its steps over the steps an
    ended item made (at most ITEM_CAP of it; `guess` or GUESS_STEPS before any ended). The number never goes back.
    It is reported from the items' threads (or the threads relaying forked workers' reports), one at a time, in the
    context `Shares` was made in (its `current()` is the caller's hook, not an item's).
    """

    def __init__(self, count: int, report: Callable[[float, int], None], guess: int | None = None) -> None:
        """`report(done, count)`: e.g. a stage's hook, `lambda d, n: hook("folds", d, n)`; `guess`: the reports an
        item makes, before one has ended (GUESS_STEPS if not known)."""
        self.count, self.report, self.guess = count, report, guess or GUESS_STEPS
        self._steps = [0] * count
        self._ended = [False] * count
        self._shown = 0.0
        self._lock = threading.Lock()
        self._context = copy_context()      # entered under the lock only: never by two threads at once

    def _done(self) -> float:
        """Items ended, plus the running ones' share of their own steps."""
        made = [s for s, e in zip(self._steps, self._ended, strict=True) if e]
        per_item = max(sum(made) / len(made), 1.0) if made else float(self.guess)
        return sum(1.0 if e else min(s / per_item, ITEM_CAP) for s, e in zip(self._steps, self._ended, strict=True))

    def _update(self, index: int, ended: bool) -> None:
        """Count a step of item `index` (or its end) and report the new number when it rose."""
        with self._lock:
            if ended:
                self._ended[index] = True
            else:
                self._steps[index] += 1
            done = self._done()
            if done > self._shown or ended:
                self._shown = max(done, self._shown)
                self._context.run(self.report, self._shown, self.count)

    def hook(self, index: int) -> Hook:
        """The hook of item `index`: each report counts as one of its steps."""
        def step(stage: str, done: float | None = None, total: float | None = None) -> None:
            self._update(index, ended=False)
        return step

    def ended(self, index: int) -> None:
        """Item `index` has ended."""
        self._update(index, ended=True)

    def run(self, index: int, fn: Callable[[T], R], item: T) -> R:
        """fn(item), its reports through `current()` counted as steps of item `index`; its end reported."""
        with active(self.hook(index)):
            out = fn(item)
        self.ended(index)
        return out


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
            if elapsed >= ETA_AFTER_S and moved > 0 and not isinstance(stage, WithWhole):
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
