"""Independent pieces of the diagnosis (folds, replicates) on the machine's cores.

Threads, not processes: the work is numpy and LAPACK on large arrays, which release the interpreter lock, and
threads share the problem's arrays without copying or pickling them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: worker threads (MAGCAL_JOBS overrides; 1 runs everything in the caller's thread)
JOBS = int(os.environ.get("MAGCAL_JOBS", "0")) or min(2, os.cpu_count() or 1)


def pmap(fn: Callable[[T], R], items: Sequence[T], jobs: int = JOBS,
         done: Callable[[int, int], None] | None = None) -> list[R]:
    """[fn(x) for x in items], in order, on up to `jobs` threads; `done(i, n)` after each of the first i results,
    called in the caller's thread (where the progress hook lives)."""
    if jobs <= 1 or len(items) <= 1:
        return _collect((fn(x) for x in items), len(items), done)
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        return _collect(pool.map(fn, items), len(items), done)


def _collect(results: Iterator[R], n: int, done: Callable[[int, int], None] | None) -> list[R]:
    """The results as a list, reporting each arrival."""
    out: list[R] = []
    for r in results:
        out.append(r)
        if done is not None:
            done(len(out), n)
    return out
