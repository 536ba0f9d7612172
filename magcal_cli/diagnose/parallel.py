"""Independent pieces of the diagnosis (folds, replicates) on the machine's cores.

Threads, not processes: the work is numpy and LAPACK on large arrays, which release the interpreter lock, and
threads share the problem's arrays without copying or pickling them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from magcal_cli.models.normal import one_blas_thread
from magcal_cli.progress import Shares

T = TypeVar("T")
R = TypeVar("R")

#: worker threads (MAGCAL_JOBS overrides; 1 runs everything in the caller's thread)
JOBS = int(os.environ.get("MAGCAL_JOBS", "0")) or min(2, os.cpu_count() or 1)


def pmap(fn: Callable[[T], R], items: Sequence[T], jobs: int | None = None,
         done: Callable[[float, int], None] | None = None) -> list[R]:
    """[fn(x) for x in items], in order, on up to `jobs` threads; `done(d, n)` as they progress: d counts the items
    ended and the running items' share of their own progress reports (progress.Shares: a stage of few long items
    moves while they run), called from the items' threads in the caller's context (its progress hook)."""
    jobs = JOBS if jobs is None else jobs              # read on each call: tests compare job counts
    if done is not None:
        shares = Shares(len(items), done)
        return pmap(lambda ix: shares.run(ix[0], fn, ix[1]), list(enumerate(items)), jobs)
    # one BLAS thread for the whole section, whatever `jobs` is: the limit is process-wide, so a section that set
    # it only around its solves ran the rest with one or two BLAS threads depending on the other thread's timing,
    # and its results differed in their last digits from run to run and from MAGCAL_JOBS=1
    with one_blas_thread():
        if jobs <= 1 or len(items) <= 1:
            return [fn(x) for x in items]
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            return list(pool.map(fn, items))
