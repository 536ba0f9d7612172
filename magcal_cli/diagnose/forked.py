"""Items run side by side in forked worker processes (Linux): the diagnosis' magnetometers, folds and replicates.

Threads bought 1.2x on two cores: a fit is thousands of small numpy calls that hold the interpreter lock. A
forked worker shares the problem's arrays copy-on-write, so nothing is pickled on the way in; each item's result
and its progress reports come back pickled through a pipe. The workers and this process take the items' indices
from one pipe, so a long item does not hold up the short ones. Every item runs as it would in turn (one BLAS
thread, its own seeds), so the results are the same digits as `[fn(x) for x in items]`.

Cores are counted as make's jobserver counts them: a pipe holds one byte per core beyond the first, a section
forks one worker per byte it can take, a worker gives its byte back when it is done, and a process that only
waits for its workers lends its own. So a section nested in an item (a magnetometer's folds) gets a core as soon
as a sibling item (another magnetometer) has ended, and the working processes never outnumber the cores.

Workers are also no more than the memory left holds (`memory.py`): with none, the items run here in turn.

Forking is skipped (the caller runs the items another way) off Linux (macOS' Accelerate BLAS is not fork-safe)
and when threads other than this module's are running (a fork copies their locks in whatever state they are
in: a Dask worker).
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import suppress
from typing import Any, TypeVar

from magcal_cli.diagnose import memory
from magcal_cli.progress import Hook, active

T = TypeVar("T")
R = TypeVar("R")

#: items a pipe of 4-byte indices holds without blocking the writer (64 KiB, Linux's default pipe size)
MAX_ITEMS = 16384
#: the pipe of free cores (read end, write end), made by the first section
_CORES: list[int] = []
#: the name of this module's relay threads: the only threads beside which a fork is safe
RELAY = "magcal-forked-relay"


def available(count: int) -> bool:
    """Whether `count` items could run in forked processes here and now."""
    # the live threads, by name: a relay whose worker has ended is gone from the list at once, so a section nested
    # in the caller's last item forks again (counting relays started minus ended ones missed those that had ended,
    # and such a section ran on threads: log171's last magnetometer's folds took 0.93 s instead of 0.55 s)
    others = sum(1 for t in threading.enumerate() if t.name != RELAY)
    return 1 < count <= MAX_ITEMS and sys.platform.startswith("linux") and hasattr(os, "fork") and others == 1


def _take(jobs: int, wanted: int) -> int:
    """Take up to `wanted` free cores of the `jobs` counted (the pipe is filled on first use)."""
    if not _CORES:
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.write(w, b"+" * (jobs - 1))
        _CORES[:] = [r, w]
    if wanted <= 0:
        return 0
    try:
        return len(os.read(_CORES[0], wanted))
    except BlockingIOError:
        return 0


def _give(count: int = 1) -> None:
    """Give `count` cores back."""
    if count > 0:
        os.write(_CORES[1], b"+" * count)


def _take_back() -> None:
    """Wait for a free core and take it (the one this process lent while it waited for its workers)."""
    while True:
        select.select([_CORES[0]], [], [])
        with suppress(BlockingIOError):
            if os.read(_CORES[0], 1):
                return


def run(fn: Callable[[T], R], items: Sequence[T], jobs: int, hook_for: Callable[[int], Hook],
        ended: Callable[[int], None]) -> list[R]:
    """[fn(x) for x in items] here and on as many forked workers as free cores allow (`available` must hold; at
    most `jobs` processes in all). Item i runs with `current()` = hook_for(i) (a worker's reports are relayed to it
    here), and `ended(i)` is called after it. An item's exception is raised here; an item whose worker died is run
    here."""
    tokens_r, tokens_w = os.pipe()
    os.write(tokens_w, struct.pack(f"<{len(items)}i", *range(len(items))))
    os.close(tokens_w)
    kids: list[tuple[int, int]] = []
    results: dict[int, tuple[bool, Any]] = {}
    lock = threading.Lock()
    readers: list[threading.Thread] = []
    finished = False
    parent = os.getpid()
    try:
        # no more workers than cores free now, and than the memory left holds (a long log on a small machine)
        for _ in range(_take(jobs, memory.workers(min(jobs, len(items)) - 1))):
            out_r, out_w = os.pipe()
            with warnings.catch_warnings():
                # Python >= 3.12 warns of a fork beside threads: here only this module's relays, whose locks no
                # worker touches (`available` refuses to fork beside anyone else's)
                warnings.simplefilter("ignore", DeprecationWarning)
                pid = os.fork()
            if pid == 0:                                        # the worker: never returns
                os.close(out_r)
                _worker(fn, items, tokens_r, out_w, parent)
            os.close(out_w)
            kids.append((pid, out_r))
        readers = [threading.Thread(target=_relay, args=(fd, hook_for, ended, results, lock), name=RELAY, daemon=True)
                   for _, fd in kids]
        for r in readers:
            r.start()
        for i in _indices(tokens_r):
            with active(hook_for(i)):
                outcome = _outcome(fn, items[i])
            with lock:
                results[i] = outcome
            ended(i)
        if readers:
            _give()                     # this process only waits now: its core goes to the workers' own sections
            for r in readers:
                r.join()
            _take_back()
        finished = True
    finally:
        os.close(tokens_r)
        for pid, fd in kids:
            if not finished:                                     # Ctrl-C or an error here: stop the workers now
                with suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
            with suppress(OSError):
                os.close(fd)
            with suppress(ChildProcessError):
                _, status = os.waitpid(pid, 0)
                if not (os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0):
                    _give()                                      # it died before giving its core back
    out: list[R] = []
    for i, x in enumerate(items):
        ok, value = results.get(i) or _outcome(fn, x)          # its worker died before it ended: run it here
        if not ok:
            raise value
        out.append(value)
    return out


def _indices(fd: int) -> Iterator[int]:
    """The item indices this process takes from the shared pipe, until it is empty (reads of 4 bytes are atomic)."""
    while len(b := os.read(fd, 4)) == 4:
        yield struct.unpack("<i", b)[0]


def _outcome(fn: Callable[[T], R], item: T) -> tuple[bool, Any]:
    """(True, fn(item)) or (False, the exception it raised)."""
    try:
        return True, fn(item)
    except Exception as exc:      # noqa: BLE001 - raised again by the caller, in the items' order
        return False, exc


def _worker(fn: Callable[[T], R], items: Sequence[T], tokens: int, out: int, parent: int) -> None:
    """A forked worker: run the items it takes, send each report and result, give its core back and exit without
    running the parent's clean-up (atexit handlers, stdio buffers). Ctrl-C is the parent's to handle: it kills the
    workers; a parent killed outright (SIGKILL, a CI job's timeout) takes them with it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with(parent)
    code = 1
    try:
        for i in _indices(tokens):
            def report(stage: str, done: float | None = None, total: float | None = None, i: int = i) -> None:
                _send(out, ("step", i, stage, done, total))
            with active(report):
                ok, value = _outcome(fn, items[i])
            try:
                _send(out, ("end", i, ok, value))
            except Exception as exc:  # noqa: BLE001 - a result that cannot be pickled: said as an error
                _send(out, ("end", i, False, RuntimeError(f"item {i}'s result could not be sent back: {exc}")))
        os.close(out)                 # the parent's relay sees the end before this core is taken again
        _give()
        code = 0
    except BaseException:             # noqa: BLE001 - the parent runs whatever this worker did not end
        code = 1
    finally:
        os._exit(code)


def _die_with(parent: int) -> None:
    """Ask Linux to kill this process when its parent dies (prctl PR_SET_PDEATHSIG), and exit if it already has:
    a worker left computing for nobody would hold a core for seconds. The signal follows the forking thread, which
    is the parent's only one (`available`), so it ends only with the process."""
    import ctypes

    with suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)     # 1: PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)


def _send(fd: int, message: tuple[Any, ...]) -> None:
    """One length-prefixed pickled message."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(struct.pack("<Q", len(data)) + data)
    while view:
        view = view[os.write(fd, view):]


def _relay(fd: int, hook_for: Callable[[int], Hook], ended: Callable[[int], None],
           results: dict[int, tuple[bool, Any]], lock: threading.Lock) -> None:
    """Read a worker's messages until it exits: its reports go to the items' hooks, its results into `results`."""
    with os.fdopen(os.dup(fd), "rb") as stream:
        while len(head := stream.read(8)) == 8:
            size = struct.unpack("<Q", head)[0]
            body = stream.read(size)
            if len(body) < size:                # the worker died mid-message: its items are run by the caller
                return
            kind, i, *rest = pickle.loads(body)
            if kind == "step":
                hook_for(i)(*rest)
            else:
                with lock:
                    results[i] = (rest[0], rest[1])
                ended(i)
