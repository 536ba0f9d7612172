"""Running batch jobs: one log's fit as `magcal fit` would run it (`run_one`, also the Dask task), and a pool of
local worker processes that fit one log at a time each and are replaced after every log, so a huge log's
memory goes back to the system."""

from __future__ import annotations

import contextlib
import importlib
import multiprocessing
import os
import shutil
import signal
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from types import FrameType
from typing import Any

from magcal_cli.batch.plan import AUTO_EFFECTS, Job, LogReport, write_status
from magcal_cli.errors import MagcalError
from magcal_cli.progress import Hook, active, noop
from magcal_cli.writers.fitrun import USER_ERRNOS

#: logs a local worker fits before it is replaced (its memory returned); forked from a preloaded server, a new
#: worker costs milliseconds, not the seconds of importing numpy and scipy again
TASKS_PER_WORKER = 1
#: imported once in the fork server, so that every worker starts with them: with a fresh worker per log, a
#: module a fit imports lazily would otherwise be imported again for every log (1-2 s of a 3 s log)
PRELOAD = ["magcal_cli.batch.run", "magcal_cli.pipeline", "magcal_cli.history.entry", "magcal_cli.writers.fitrun", "magcal_cli.firmware.gates", "pygeomag",
           "scipy.ndimage", "scipy.optimize"]
#: the subpackages whose every module a fit may import (readers, estimators, effects, outputs)
PRELOAD_PACKAGES = ("readers", "models", "effects", "diagnose", "firmware", "writers")
WORKER_DIED = ("the worker process fitting this log died (killed, e.g. out of memory, or crashed). Fit it alone "
               "with magcal fit to see why")
#: how often a Ctrl-C'd batch interrupts its workers again until they have stopped (s)
STOP_POLL_S = 0.2
#: how long a Ctrl-C'd batch waits for its running fits to stop and clean up before it kills their workers (s): a
#: fit deep in a long computation, or waiting for its threads, answers only when that ends (once 14 s)
STOP_GRACE_S = 0.3
#: how long a Ctrl-C during the forkserver's preload waits for the start it cut to send its child's data (s): the
#: microseconds of a few system calls, on a loaded machine
START_GRACE_S = 0.05
Done = Callable[[LogReport], None]


class Interrupted(KeyboardInterrupt):
    """Ctrl-C stopped the batch: `reports` holds the logs that ended, complete or stopped ("interrupted")."""

    def __init__(self, reports: list[LogReport]) -> None:
        """The reports gathered up to the stop."""
        super().__init__()
        self.reports = reports


def _interrupt_once(_: int, __: FrameType | None) -> None:
    """SIGINT in a worker: one KeyboardInterrupt; a second Ctrl-C must not break the clean-up it started."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise KeyboardInterrupt


@contextlib.contextmanager
def _interruptible() -> Iterator[None]:
    """Ctrl-C interrupts the fit inside the block; an idle worker ignores it (the main process decides)."""
    main = threading.current_thread() is threading.main_thread()      # Dask runs tasks in threads
    previous = signal.signal(signal.SIGINT, _interrupt_once) if main else None
    try:
        yield
    finally:
        if main:
            signal.signal(signal.SIGINT, previous)    # a pool worker's: ignored; a caller's own: as it was


@contextlib.contextmanager
def _starting_processes() -> Iterator[None]:
    """A Ctrl-C while the block starts processes is raised after it: interrupted between asking the forkserver for
    a child and sending it its start-up data, the child would read nothing and print its EOFError traceback."""
    got: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda sig, _: got.append(sig))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if got:                             # also when the block raised: a Ctrl-C is never lost
            signal.raise_signal(signal.SIGINT)      # to the handler that was there: KeyboardInterrupt, or ignored


def _worker_init(jobs: int = 1) -> None:
    """A local worker: Ctrl-C only while fitting (an idle worker would die printing a traceback); numpy's
    RuntimeWarnings on degenerate data kept off stderr, as `magcal fit` keeps them; `jobs` processes for its fit's
    diagnosis (the cores left to each worker: the workers themselves already keep the others busy)."""
    from magcal_cli.diagnose import parallel

    parallel.JOBS = jobs
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):          # should a platform's exec keep the mask _context blocked
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    warnings.filterwarnings("ignore", category=RuntimeWarning)


def _mag_numbers(result: Any) -> list[dict[str, Any]]:
    """The key numbers of each magnetometer for the summary."""
    import numpy as np

    from magcal_cli import so3
    from magcal_cli.firmware.metrics import heading_std_deg

    out = []
    for m in result.calibration.magnetometers:
        q = m.quality
        out.append({"id": m.id, "status": "calibrated", "method": m.method, "dip_deg": float(m.dip_deg),
                    "field_norm_rms_pct": None if q is None else float(q.field_norm_rms_pct),
                    "coverage_pct": None if q is None else float(q.coverage_pct),
                    "misalignment_deg": float(np.rad2deg(so3.angle(m.misalignment))),
                    "heading_std_deg": heading_std_deg(m)})
    # every compass of the log has a row: a refused one with its reason and no numbers (issue 38)
    out += [{"id": r["id"], "status": "refused", "reason": r["reason"], "dip_deg": None, "field_norm_rms_pct": None,
             "coverage_pct": None, "misalignment_deg": None, "heading_std_deg": None}
            for r in result.calibration.refused]
    return out


def _fit(job: Job, report: LogReport, start: float) -> None:
    """Fit the log and write its outputs as `magcal fit` does, filling `report`; errors propagate."""
    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate
    from magcal_cli.writers import FIRMWARE_OUTPUTS
    from magcal_cli.writers.fitrun import gate_failures, write_fit_outputs

    o = job.options
    auto = o.effects == AUTO_EFFECTS
    cfg = Config(method=o.method, mag=",".join(o.mags) or "all", allow_truncated=not o.strict,
                 effects=() if auto else o.effects, diagnose=auto, imu_timing=o.imu_timing,
                 mag_timing=o.mag_timing, start_s=o.start_s, end_s=o.end_s)
    result = calibrate(job.log, cfg)
    report.format, report.method = result.recording.format, result.calibration.method
    names = list(job.names)
    if job.auto and FIRMWARE_OUTPUTS.get(result.recording.format) == job.auto:
        names.append(job.auto)
    if result.recording.cut is not None:
        report.warnings.append(f"warning: {result.recording.cut.message}")
    report.warnings += [f"warning: {f.message}" for f in result.findings if f.severity.value == "warning"]
    report.magnetometers = _mag_numbers(result)
    if o.history:                                   # made here, written once by the client (cli/batch.py)
        from magcal_cli.history.entry import entries

        report.history = entries(result, o.vehicle)
    failed = gate_failures(result, o.fail_on)
    if failed:
        report.status, report.exit_code, report.error = "gate_failed", 3, f"fit --fail-on: {'; '.join(failed)}"
    def complete(final: list[Path]) -> None:
        # with the renames, Ctrl-C held back: a folder of outputs always has its batch.json (it had not, once)
        report.outputs, report.seconds = [str(p) for p in final], time.perf_counter() - start
        try:
            write_status(job, report)
        except BaseException:
            report.outputs = []                    # not marked complete: run_one reports the failure
            raise

    write_fit_outputs(result, job.outdir, names, job.auto, report.warnings.append, complete)


def _stopped_by(name: str | None) -> Hook:
    """A Dask task's progress hook: KeyboardInterrupt, as Ctrl-C in a process, once the batch has set the Dask
    Event `name` (checked at most every STOP_POLL_S; a scheduler that cannot be asked stops nothing). A task
    runs in a worker's thread, which no signal reaches: the fit stops at its next progress report, a figure or a
    step of an estimator, and renames nothing into place."""
    if name is None:
        return noop
    distributed = importlib.import_module("distributed")        # untyped: as batch.dask has it

    event, last, lock = distributed.Event(name), [-float("inf")], threading.Lock()

    def check(stage: str, done: float | None = None, total: float | None = None) -> None:
        with lock:
            now = time.monotonic()
            if now - last[0] < STOP_POLL_S:
                return
            last[0] = now
        try:
            stop = event.is_set()
        except Exception:  # noqa: BLE001 - the scheduler gone or busy: the fit goes on
            return
        if stop:
            raise KeyboardInterrupt
    return check


def run_one(job: Job) -> LogReport:
    """Fit one log; every outcome but Ctrl-C is a report with the exit code `magcal fit` would have given."""
    report = LogReport(str(job.log), job.name, str(job.outdir), "ok", 0)
    start = time.perf_counter()
    try:
        with _interruptible(), active(_stopped_by(job.stop)):
            _fit(job, report, start)
    except KeyboardInterrupt:
        if not report.outputs:
            report.status, report.exit_code, report.error = "interrupted", 130, "interrupted"
            return report                           # no batch.json: the log is fitted again on the next run
    except MagcalError as exc:
        report.status, report.exit_code, report.error = "failed", 1, str(exc)
    except OSError as exc:
        if exc.errno in USER_ERRNOS:
            report.status, report.exit_code = "failed", 1
            report.error = f"{exc.filename or job.log}: {exc.strerror or exc}. Check the path, its permissions and free space"
        else:
            _internal(report, exc)
    except Exception as exc:  # noqa: BLE001 - one log's bug must not stop the others
        _internal(report, exc)
    if report.outputs:                              # marked complete with the outputs (`_fit`)
        return report
    report.seconds = time.perf_counter() - start
    try:
        write_status(job, report)
    except (MagcalError, OSError) as exc:
        report.status, report.exit_code, report.error = "failed", 1, str(exc)
    return report


def _internal(report: LogReport, exc: BaseException) -> None:
    """A bug while fitting: exit 123 with fit's message, the traceback kept for -v."""
    report.status, report.exit_code = "failed", 123
    report.error = (f"internal error ({type(exc).__name__}: {exc}). This is a bug in magcal; please report it "
                    "with the command and log")
    report.traceback = "".join(traceback.format_exception(exc))


def died(job: Job, why: str = WORKER_DIED) -> LogReport:
    """The report of a log whose worker process died under it."""
    return LogReport(str(job.log), job.name, str(job.outdir), "failed", 123, error=f"{job.log}: {why}")


def stopped(job: Job) -> LogReport:
    """The report of a log whose fit Ctrl-C stopped before it answered (nothing of it is left)."""
    return LogReport(str(job.log), job.name, str(job.outdir), "interrupted", 130, error="interrupted")


def _context() -> Any:
    """forkserver with magcal preloaded where available (workers start in milliseconds), else spawn; never
    fork, which max_tasks_per_child refuses and which would copy the parent's threads."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    from multiprocessing import forkserver

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(preload_modules())
    # the server starts with Ctrl-C ignored (inherited through exec): it preloads for seconds before it
    # ignores SIGINT itself, and a Ctrl-C then would print its traceback. Blocked meanwhile, a Ctrl-C at
    # magcal stays pending (Linux keeps a blocked signal though ignored) and arrives at the unblocking; the
    # workers take Ctrl-C in run_one
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    # wait for the preload with a bare process: a pool worker queued behind it and served after a Ctrl-C'd
    # magcal has exited would fail on the pool's vanished semaphores and print that traceback. Started on a thread:
    # the start waits for the preload, and a Ctrl-C meanwhile (main thread only) must neither wait for it nor cut
    # the start between asking for the child and sending it its data (`_starting_processes`)
    ready = threading.Thread(target=_start_ready, args=(ctx,), daemon=True)
    ready.start()
    try:
        ready.join()
    except KeyboardInterrupt:
        # a start on the thread when the Ctrl-C came sends its child's data before magcal exits. Not join(timeout):
        # an interrupted join has already marked the thread ended (bpo-45274), and would return at once
        time.sleep(START_GRACE_S)
        raise
    return ctx


def preload_modules() -> list[str]:
    """PRELOAD and every module of PRELOAD_PACKAGES, found by file name (nothing imported here)."""
    root = Path(__file__).parent
    return PRELOAD + [f"magcal_cli.{pkg}" + ("" if f.stem == "__init__" else f".{f.stem}")
                      for pkg in PRELOAD_PACKAGES for f in sorted((root / pkg).glob("*.py"))]


def _start_ready(ctx: Any) -> None:
    """Start `_ready` in the forkserver and wait for it."""
    ready = ctx.Process(target=_ready, daemon=True)
    ready.start()
    ready.join()


def _ready() -> None:
    """The forkserver's first child: it returns at once; its start means the preload is done."""


def _single_threaded_blas() -> None:
    """N workers on N cores: BLAS threads in each would only compete (a user's own setting is kept)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _pool(workers: int) -> ProcessPoolExecutor:
    """A pool of `workers` processes, each replaced after TASKS_PER_WORKER logs (Python >= 3.11)."""
    extra: dict[str, Any] = {"max_tasks_per_child": TASKS_PER_WORKER} if sys.version_info >= (3, 11) else {}
    from magcal_cli.diagnose import parallel

    return ProcessPoolExecutor(max_workers=workers, mp_context=_context(), initializer=_worker_init,
                               initargs=(max(1, parallel.JOBS // workers),), **extra)


def _signal_workers(pool: ProcessPoolExecutor, sig: int) -> None:
    """Send `sig` to every worker process of `pool` now."""
    for pid in list(getattr(pool, "_processes", None) or {}):
        with contextlib.suppress(OSError):
            os.kill(pid, sig)


def _stop(pool: ProcessPoolExecutor, futures: dict[Future[LogReport], Job], since: float, existed: set[Path]
          ) -> list[LogReport]:
    """Ctrl-C: drop the queued fits and interrupt the running ones, which clean up and report; a worker that has not
    reported within STOP_GRACE_S is killed, and what its fit left in its folder is removed (`_discard`). Returns the
    reports of the logs that were running: interrupted, or complete when the Ctrl-C came during their last renames."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)   # a second Ctrl-C must not abandon the clean-up
    try:
        for fut in futures:
            fut.cancel()                    # the queued ones
        pending = {f for f in futures if not f.done()}
        deadline = time.monotonic() + STOP_GRACE_S
        while pending and (now := time.monotonic()) < deadline:
            # again and again: a log already queued to a fresh worker starts after the first signal, and
            # `kill -INT` on magcal alone must reach the workers too (a worker takes only the first)
            _signal_workers(pool, signal.SIGINT)
            pending = wait(pending, timeout=min(STOP_POLL_S, deadline - now)).not_done
        if pending:
            _signal_workers(pool, signal.SIGKILL)
        pool.shutdown(wait=True, cancel_futures=True)       # at once: every worker has ended or been killed
    finally:
        signal.signal(signal.SIGINT, previous)
    reports = []
    for fut, job in futures.items():
        if fut.cancelled():
            continue
        try:
            reports.append(fut.result())
        except Exception:  # noqa: BLE001 - killed (BrokenProcessPool): its fit may have left files behind
            _discard(job, since, job.outdir not in existed)
            reports.append(stopped(job))
    return reports


def _discard(job: Job, since: float, created: bool) -> None:
    """What a killed worker's fit left in the log's folder: its staging folder and temporary files, and outputs it
    had renamed into place without the batch.json that marks them complete (all newer than `since`, the batch's
    start: nothing older is touched); then the folder itself when the batch `created` it and it is empty."""
    from magcal_cli.batch.plan import STATUS_FILE
    from magcal_cli.writers import get_writer

    folder = job.outdir
    if not folder.is_dir():
        return

    def ours(p: Path) -> bool:
        with contextlib.suppress(OSError):
            return p.stat().st_mtime >= since
        return False

    for p in (p for p in folder.glob(".*.part") if ours(p)):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    if not ours(folder / STATUS_FILE):          # an unfinished set of renames: not complete, not kept
        names = (*job.names, *([job.auto] if job.auto else []))
        for f in (folder / f for n in names for f in get_writer(n).files):
            if ours(f):
                f.unlink(missing_ok=True)
    if created:
        with contextlib.suppress(OSError):
            folder.rmdir()                      # only when empty


def run_local(jobs: list[Job], workers: int, done: Done) -> list[LogReport]:
    """Fit `jobs` in `workers` local processes, calling `done` as each finishes; a log whose worker dies
    (killed out of memory, a crash) is reported failed and the others go on. Ctrl-C raises Interrupted once the
    workers have stopped, within about STOP_GRACE_S, leaving no fit's files half-written."""
    _single_threaded_blas()
    reports: list[LogReport] = []
    order = {id(j): i for i, j in enumerate(jobs)}
    try:
        broken = _run_pool(jobs, workers, done, reports)
        while broken:
            # a dying worker breaks the whole pool and fails every unfinished log with it, the queued ones too.
            # The earliest submitted was running, so the likeliest culprit: it is retried alone (and reported
            # if its worker dies again), the rest go back to a full pool
            suspect, *rest = sorted(broken, key=lambda j: order[id(j)])
            if _run_pool([suspect], 1, done, reports):
                reports.append(died(suspect))
                done(reports[-1])
            broken = _run_pool(rest, workers, done, reports)
    except KeyboardInterrupt:
        raise Interrupted(reports) from None
    return reports


def _run_pool(jobs: list[Job], workers: int, done: Done, reports: list[LogReport]) -> list[Job]:
    """One pool over `jobs`; returns the jobs whose futures the pool's breaking took with it."""
    if not jobs:
        return []
    broken: list[Job] = []
    since = time.time()                   # what a killed fit leaves is newer than this (_discard)
    existed = {j.outdir for j in jobs if j.outdir.exists()}
    pool = _pool(max(1, min(workers, len(jobs))))
    futures: dict[Future[LogReport], Job] = {}
    seen: set[Future[LogReport]] = set()      # the futures whose outcome is in `reports` or `broken`
    try:
        for i, j in enumerate(jobs):
            try:
                with _starting_processes():             # a submit may start a worker
                    futures[pool.submit(run_one, j)] = j
            except (BrokenProcessPool, OSError):
                # a worker died while the rest were being queued: those go back too. OSError is the same death
                # seen a moment earlier, as the pool spawns a worker on fds its breaking has just closed (EBADF)
                broken.extend(jobs[i:])
                break
        for fut in as_completed(futures):
            seen.add(fut)
            try:
                report = fut.result()
            except BrokenProcessPool:
                broken.append(futures[fut])
                continue
            except Exception as exc:  # noqa: BLE001 - e.g. a job the worker could not unpickle: that log only
                report = died(futures[fut], f"the worker could not run it ({type(exc).__name__}: {exc})")
            reports.append(report)
            done(report)
    except KeyboardInterrupt:
        reports += _stop(pool, {f: j for f, j in futures.items() if f not in seen}, since, existed)
        raise
    pool.shutdown(wait=True, cancel_futures=True)   # what a submit that raised had queued: dropped unless started
    return broken
