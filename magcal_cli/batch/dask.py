"""Batch jobs on a Dask cluster (`magcal batch --scheduler tcp://HOST:PORT`), through the optional `distributed`
package (`pip install 'magcal-cli[fleet]'`).

Each worker gets one log at a time: a job is sent to a worker only when that worker is free, so a worker's
memory holds one log however many threads it runs. The workers read the logs and write the outputs at the same
absolute paths, so they need the same file system (a shared or network drive) and magcal installed.
"""

from __future__ import annotations

import contextlib
import signal
import time
import uuid
from collections import deque
from dataclasses import replace
from typing import Any

from magcal_cli.batch.plan import Job, LogReport
from magcal_cli.batch.run import STOP_GRACE_S, STOP_POLL_S, Done, Interrupted, died, run_one, stopped
from magcal_cli.errors import MissingDependencyError

INSTALL_HINT = "pip install 'magcal-cli[fleet]'"
#: how long to wait for the scheduler to answer, and for a cluster without workers to get one (s)
CONNECT_TIMEOUT_S = 30.0


def require_distributed() -> Any:
    """The `distributed` module, or MissingDependencyError naming the extra to install."""
    try:
        import distributed
    except ImportError:
        msg = f"--scheduler: Dask's distributed package is not installed. Run: {INSTALL_HINT}"
        raise MissingDependencyError(msg) from None
    return distributed


def _connect(distributed: Any, address: str) -> Any:
    """A client of the scheduler at `address` that has at least one worker, or a one-line MagcalError."""
    from magcal_cli.errors import MagcalError

    try:
        client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        msg = (f"{address}: cannot reach the Dask scheduler ({exc}). Start one with 'dask scheduler' and "
               "workers with 'dask worker ADDRESS', or check --scheduler")
        raise MagcalError(msg) from None
    try:
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError) as exc:
        client.close()
        msg = f"{address}: the Dask scheduler has no workers ({exc}). Start some with 'dask worker {address}'"
        raise MagcalError(msg) from None
    return client


def _workers(client: Any) -> list[str]:
    """The addresses of the cluster's workers now (they may come and go during a batch)."""
    return sorted(client.scheduler_info().get("workers", {}))


def run_dask(jobs: list[Job], address: str, done: Done) -> tuple[list[LogReport], int]:
    """Fit `jobs` on the cluster at `address`, one log per worker at a time; (reports, workers seen). Ctrl-C
    raises Interrupted after `_stop`."""
    distributed = require_distributed()
    client = _connect(distributed, address)
    reports: list[LogReport] = []
    stop = distributed.Event(f"magcal-batch-stop-{uuid.uuid4().hex}", client=client)
    pending = deque(replace(j, stop=stop.name) for j in jobs)
    busy: dict[Any, tuple[Job, str]] = {}
    seen = set(_workers(client))
    free = deque(sorted(seen))

    def submit() -> list[Any]:
        """Give each free worker the next job; pinned loosely, so a job whose worker left runs elsewhere."""
        sent = []
        while pending and free:
            worker, job = free.popleft(), pending.popleft()
            fut = client.submit(run_one, job, workers=[worker], allow_other_workers=True, pure=False,
                                key=f"magcal-batch-{job.name}-{id(job)}")
            busy[fut] = (job, worker)
            sent.append(fut)
        return sent

    try:
        running = distributed.as_completed(submit(), loop=client.loop)   # ours, not a default client
        for fut in running:
            job, worker = busy.pop(fut)
            try:
                report = fut.result()
            except Exception as exc:  # noqa: BLE001 - a worker lost under the task, a task that cannot run
                report = died(job, f"the Dask task failed ({type(exc).__name__}: {exc})")
            reports.append(report)
            done(report)
            now = set(_workers(client))
            free.extend(sorted(now - seen))         # workers that joined during the batch
            seen |= now
            if worker in now:
                free.append(worker)
            for new in submit():
                running.add(new)
    except KeyboardInterrupt:
        reports += _stop(client, stop, busy)
        raise Interrupted(reports) from None
    finally:
        client.close()
    return reports, len(seen)


def _stop(client: Any, stop: Any, busy: dict[Any, tuple[Job, str]]) -> list[LogReport]:
    """Ctrl-C: the queued jobs are never sent; the running fits see `stop` set at their next progress report
    (`run._stopped_by`: no signal reaches a worker's thread) and end without renaming anything into place. Their
    reports are those that came back within STOP_GRACE_S (the others are reported stopped, and their tasks
    released: they end on their own, leaving nothing)."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)   # a second Ctrl-C must not abandon the stop
    try:
        with contextlib.suppress(Exception):   # a scheduler that cannot be told: the fits end unaware, as before
            stop.set()
        deadline = time.monotonic() + STOP_GRACE_S
        while any(not f.done() for f in busy) and time.monotonic() < deadline:
            time.sleep(STOP_POLL_S / 4)
    finally:
        signal.signal(signal.SIGINT, previous)
    finished, late = [f for f in busy if f.done()], [f for f in busy if not f.done()]
    reports = [stopped(busy[f][0]) for f in late]
    for fut in finished:
        try:
            reports.append(fut.result())
        except Exception:  # noqa: BLE001 - the task failed under the stop: nothing of it was renamed into place
            reports.append(stopped(busy[fut][0]))
    with contextlib.suppress(Exception):
        client.cancel(list(late))
    return reports
