"""Independent pieces of the diagnosis (folds, replicates, magnetometers) on the machine's cores.

On Linux they run in forked processes (`forked.py`: 1.75x on two cores, where threads gave 1.2x: a fit's many
small numpy calls hold the interpreter lock); elsewhere, or where forking is not safe, on threads, which share
the problem's arrays without copying or pickling them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Generic, TypeVar

from magcal_cli.diagnose import forked
from magcal_cli.models.normal import one_blas_thread
from magcal_cli.progress import Hook, Shares, noop

T = TypeVar("T")
R = TypeVar("R")

#: processes (or threads) at once (MAGCAL_JOBS overrides; 1 runs everything in the caller, in turn)
JOBS = int(os.environ.get("MAGCAL_JOBS", "0")) or min(2, len(os.sched_getaffinity(0)) if hasattr(
    os, "sched_getaffinity") else (os.cpu_count() or 1))


@dataclass(frozen=True, eq=False)
class Outcome(Generic[R]):
    """What a piece of work run ahead gave: its value, or the error it raised (raised again by `get`)."""

    value: R | None
    error: Exception | None = None

    def get(self) -> R:
        """The value, or the error raised."""
        if self.error is not None:
            raise self.error
        return self.value  # type: ignore[return-value]


def captured(fn: Callable[[], R]) -> Outcome[R]:
    """fn()'s outcome: work run ahead of the need for it raises only where it is used."""
    try:
        return Outcome(fn())
    except Exception as exc:      # noqa: BLE001 - kept for `Outcome.get`
        return Outcome(None, exc)


def side_by_side(count: int) -> bool:
    """Whether `count` items given to `pmap` now would run in separate processes."""
    return JOBS > 1 and forked.available(count)


def pmap(fn: Callable[[T], R], items: Sequence[T], jobs: int | None = None,
         done: Callable[[float, int], None] | None = None, guess: int | None = None) -> list[R]:
    """[fn(x) for x in items], in order, on up to `jobs` processes or threads; `done(d, n)` as they progress: d
    counts the items ended and the running items' share of their own progress reports (progress.Shares, with
    `guess` reports per item before one has ended: a stage of few long items moves while they run), called in the
    caller's context (its progress hook)."""
    jobs = JOBS if jobs is None else jobs              # read on each call: tests compare job counts
    # without `done`, the items report to the caller's hook in turn and nowhere side by side
    shares = Shares(len(items), done or (lambda d, n: None), guess)

    def serial(i: int, x: T) -> R:
        return fn(x) if done is None else shares.run(i, fn, x)

    def hook_for(i: int) -> Hook:
        return noop if done is None else shares.hook(i)
    # one BLAS thread for the whole section, whatever `jobs` is: the limit is process-wide, so a section that set
    # it only around its solves ran the rest with one or two BLAS threads depending on the other thread's timing,
    # and its results differed in their last digits from run to run and from MAGCAL_JOBS=1
    with one_blas_thread():
        if jobs <= 1 or len(items) <= 1:
            return [serial(i, x) for i, x in enumerate(items)]
        if forked.available(len(items)):              # on the cores free now (none: here, in turn)
            return forked.run(fn, items, jobs, hook_for, shares.ended)
        with ThreadPoolExecutor(max_workers=jobs) as pool:       # threads start with no hook: `noop` reports
            return list(pool.map(lambda ix: serial(*ix), enumerate(items)))
