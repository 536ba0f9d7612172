"""Items in forked worker processes: results in order, reports relayed, errors raised, dead workers covered, cores
counted as a jobserver counts them, and a fit whose magnetometers run side by side gives the same digits."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from magcal_cli.diagnose import forked
from magcal_cli.progress import Hook, current, noop

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked workers run on Linux only")


@pytest.fixture(autouse=True)
def _own_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test counts its cores afresh (the pipe is made by the first section of a process)."""
    monkeypatch.setattr(forked, "_CORES", [])


def _free_cores() -> int:
    """The cores free in the pipe now (taken and given back)."""
    n = forked._take(2, 64)
    forked._give(n)
    return n


def _none(_: int) -> Hook:
    return noop


def _slow(x: int) -> tuple[int, int]:
    time.sleep(0.15)
    return x * x, os.getpid()


def test_items_come_back_in_order_from_two_processes() -> None:
    """Six slow items on two processes: every result in the items' order, both processes worked, and the core
    the worker took is free again."""
    ended: list[int] = []
    out = forked.run(_slow, list(range(6)), 2, _none, ended.append)
    assert [v for v, _ in out] == [x * x for x in range(6)]
    assert len({pid for _, pid in out}) == 2 and os.getpid() in {pid for _, pid in out}
    assert sorted(ended) == list(range(6))
    assert _free_cores() == 1


def test_a_workers_reports_reach_its_items_hook() -> None:
    """An item's reports through `current()` reach hook_for(i) here, whichever process ran it."""
    seen: list[tuple[int, str, float | None]] = []
    lock = threading.Lock()

    def hook_for(i: int) -> Hook:
        def hook(stage: str, done: float | None = None, total: float | None = None) -> None:
            with lock:
                seen.append((i, stage, done))
        return hook

    def item(x: int) -> int:
        time.sleep(0.1)
        for k in range(3):
            current()(f"item {x}", k, 3)
        return x

    assert forked.run(item, list(range(4)), 2, hook_for, lambda i: None) == [0, 1, 2, 3]
    for i in range(4):
        assert [(s, d) for j, s, d in seen if j == i] == [(f"item {i}", k) for k in range(3)]


def test_the_first_error_in_item_order_is_raised() -> None:
    """An item's exception is raised here after all ended, the first in the items' order, with its own type."""
    def item(x: int) -> int:
        time.sleep(0.1)
        if x == 1:
            raise ValueError("item one")
        if x == 3:
            raise KeyError("item three")
        return x

    with pytest.raises(ValueError, match="item one"):
        forked.run(item, list(range(5)), 2, _none, lambda i: None)
    assert _free_cores() == 1


def test_a_dead_workers_items_run_here() -> None:
    """A worker killed mid-item (out of memory, a crash): its items run in this process; its core is given back."""
    parent = os.getpid()

    def item(x: int) -> tuple[int, int]:
        time.sleep(0.1)
        if os.getpid() != parent:
            os._exit(9)
        return x, os.getpid()

    out = forked.run(item, list(range(4)), 2, _none, lambda i: None)
    assert out == [(x, parent) for x in range(4)]
    assert _free_cores() == 1


def test_an_unpicklable_result_is_said_as_an_error() -> None:
    """A result a worker cannot send back is an error naming it, not a hang or a lost item."""
    def item(x: int) -> Callable[[], int]:
        time.sleep(0.15)
        return lambda: x

    with pytest.raises(RuntimeError, match="could not be sent back"):
        forked.run(item, list(range(6)), 2, _none, lambda i: None)


def test_nested_sections_share_the_cores(tmp_path: Path) -> None:
    """A section inside an item takes a core only when one is free (the other item has ended, or this process
    lent its own while it waited): never more working processes than cores, and every core back at the end."""
    def inner(x: int) -> int:
        marker = tmp_path / f"{os.getpid()}-{x}"
        marker.touch()
        working = len(list(tmp_path.iterdir()))
        time.sleep(0.1)
        marker.unlink()
        return working

    def outer(x: int) -> list[int]:
        if x == 0:
            time.sleep(0.05)
            return []
        time.sleep(0.3)                  # by now the other item has ended and its process gave or lent its core
        return forked.run(inner, list(range(6)), 2, _none, lambda i: None)

    out = forked.run(outer, [0, 1], 2, _none, lambda i: None)
    assert max(out[1]) == 2
    assert _free_cores() == 1


def test_not_available_beside_other_threads() -> None:
    """Another library's threads (a Dask worker's) rule forking out: their locks would be copied mid-use. This
    module's relays do not."""
    assert forked.available(2) and not forked.available(1)
    stop = threading.Event()
    for name, allowed in (("someone-elses", False), (forked.RELAY, True)):
        other = threading.Thread(target=stop.wait, name=name, daemon=True)
        other.start()
        try:
            assert forked.available(2) is allowed
        finally:
            stop.set()
            other.join()
        stop.clear()


def test_a_section_in_this_process_forks_again_once_its_workers_have_ended() -> None:
    """After the workers have taken the other items and ended, an item still running here may fork its own nested
    section (it once could not, and ran the nested section on threads: log171's last folds 0.93 s, not 0.55 s)."""
    parent = os.getpid()

    def item(x: int) -> bool | None:
        if os.getpid() != parent:
            time.sleep(0.05)             # the worker takes the other items and ends
            return None
        time.sleep(0.4)
        return forked.available(2)

    out = forked.run(item, list(range(4)), 2, _none, lambda i: None)
    here = [o for o in out if o is not None]
    assert here and all(here)


def test_magnetometers_side_by_side_give_the_same_digits() -> None:
    """Three magnetometers fitted and diagnosed with MAGCAL_JOBS=1 and =2 in a fresh process (one thread, so the
    work is forked): the same document, created_utc aside; the second run did fork."""
    script = textwrap.dedent("""
        import json, sys
        from magcal_cli.calibration.document import dumps_json
        from magcal_cli.config import Config
        from magcal_cli.diagnose import forked, parallel
        from magcal_cli.pipeline import calibrate_recording
        from magcal_cli.synth.effects import EffectSpec
        from magcal_cli.synth.simulate import simulate

        sim = simulate("handheld", 3, duration=40.0, rate=100.0, mag_rate=25.0, n_mags=3,
                       effects=(EffectSpec("time_offset", {"tau_s": 0.02}),))
        taken = []
        real = forked._take
        forked._take = lambda jobs, wanted: taken.append(real(jobs, wanted)) or taken[-1]
        docs = []
        for jobs in (1, 2):
            parallel.JOBS = jobs
            doc = json.loads(dumps_json(calibrate_recording(sim.recording, Config(diagnose=True)).calibration))
            doc.pop("created_utc", None)
            docs.append(doc)
        print(json.dumps({"same": docs[0] == docs[1], "forked": sum(taken),
                          "sensors": [d["sensor"] for d in docs[1]["diagnosis"]["sensors"]]}))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=600)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["forked"] > 0
    assert got["sensors"] == ["/imu/mag", "/imu/mag1", "/imu/mag2"]
    assert got["same"]


def test_workers_die_with_a_killed_parent(tmp_path: Path) -> None:
    """A fit killed outright (SIGKILL: a CI job's timeout) leaves no worker computing for nobody."""
    script = textwrap.dedent(f"""
        import os, time
        from pathlib import Path
        from magcal_cli.diagnose import forked

        def item(x):
            Path({str(tmp_path)!r}, str(os.getpid())).touch()
            time.sleep(30)
            return x

        forked.run(item, [0, 1], 2, lambda i: (lambda *a: None), lambda i: None)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script])
    deadline = time.monotonic() + 60
    while len(list(tmp_path.iterdir())) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    workers = [int(p.name) for p in tmp_path.iterdir() if int(p.name) != proc.pid]
    assert len(workers) == 1
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 10
    while Path(f"/proc/{workers[0]}").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    status = Path(f"/proc/{workers[0]}/stat")
    assert not status.exists() or status.read_text().split()[2] == "Z"      # gone, or a zombie awaiting its reaper


def test_no_worker_when_the_memory_left_holds_none(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the memory left too small for one more process like this one, every item runs here, in order, and the
    core stays free (a two-hour log in a 1 GB container: a fold worker beside its parent was killed out of memory)."""
    from magcal_cli.diagnose import memory

    monkeypatch.setattr(memory, "available", lambda *_: memory.MARGIN + 2**20)     # 1 MiB beyond the margin
    out = forked.run(_slow, list(range(3)), 2, _none, lambda i: None)
    assert [v for v, _ in out] == [0, 1, 4] and {pid for _, pid in out} == {os.getpid()}
    assert _free_cores() == 1
