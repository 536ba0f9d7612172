"""Independent pieces of the diagnosis (folds, replicates) on the machine's cores.

Threads, not processes: the work is numpy and LAPACK on large arrays, which release the interpreter lock, and
threads share the problem's arrays without copying or pickling them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: worker threads (MAGCAL_JOBS overrides; 1 runs everything in the caller's thread)
JOBS = int(os.environ.get("MAGCAL_JOBS", "0")) or min(2, os.cpu_count() or 1)


def pmap(fn: Callable[[T], R], items: Sequence[T], jobs: int = JOBS) -> list[R]:
    """[fn(x) for x in items], in order, on up to `jobs` threads."""
    if jobs <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(fn, items))
