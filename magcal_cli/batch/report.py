"""The batch's results: the summary table, the --json document, and one progress line per finished log."""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from magcal_cli import __version__, progress
from magcal_cli.batch.plan import LogReport, exit_code

STATUS_TEXT = {"ok": "ok", "skipped": "skipped (up to date)", "failed": "failed", "gate_failed": "gate failed",
               "interrupted": "interrupted"}
COLUMNS = ("LOG", "STATUS", "EXIT", "MAGS", "FIELD-NORM %", "DIP deg", "TIME s", "ERROR")


@dataclass(frozen=True)
class Runner:
    """Where the fits ran: 'local' with N processes, or 'dask' at a scheduler address with N workers."""

    kind: str
    workers: int
    scheduler: str | None = None

    def __str__(self) -> str:
        if self.kind == "dask":
            return f"{self.workers} Dask worker{'s' * (self.workers != 1)} at {self.scheduler}"
        return f"{self.workers} local worker{'s' * (self.workers != 1)}"


def _numbers(r: LogReport, key: str, fmt: str) -> str:
    """One number per magnetometer, '/'-separated; '-' when there are none."""
    values = [m.get(key) for m in r.magnetometers]
    return "/".join("-" if v is None else format(v, fmt) for v in values) or "-"


def _row(r: LogReport) -> tuple[str, ...]:
    """A table row."""
    return (r.name, STATUS_TEXT.get(r.status, r.status), str(r.exit_code), str(len(r.magnetometers) or "-"),
            _numbers(r, "field_norm_rms_pct", ".2f"), _numbers(r, "dip_deg", ".1f"),
            "-" if r.status == "skipped" else f"{r.seconds:.1f}", f"Error: {r.error}" if r.error else _refused(r))


def _refused(r: LogReport) -> str:
    """The compasses of a fitted log that were refused, by name."""
    ids = [m["id"] for m in r.magnetometers if m.get("status") == "refused"]
    return f"refused: {', '.join(ids)}" if ids else ""


def counts(reports: list[LogReport]) -> dict[str, int]:
    """Logs per status, and the total."""
    c = Counter(r.status for r in reports)
    return {"logs": len(reports), **{s: c.get(s, 0) for s in STATUS_TEXT}}


def throughput(reports: list[LogReport], wall_s: float) -> float | None:
    """Logs fitted (skipped ones left out) per minute of wall time."""
    fitted = sum(r.status != "skipped" for r in reports)
    return 60.0 * fitted / wall_s if fitted and wall_s > 0 else None


def duration(seconds: float) -> str:
    """'8.2 s', '4 min 05 s'."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    s = int(round(seconds))
    return f"{s // 60} min {s % 60:02d} s"


def footer(reports: list[LogReport], wall_s: float, runner: Runner) -> str:
    """'100 logs: 98 ok, 1 skipped (up to date), 1 failed in 4 min 10 s with 2 local workers (23.5 logs/min)'."""
    c = counts(reports)
    parts = ", ".join(f"{c[s]} {STATUS_TEXT[s]}" for s in STATUS_TEXT if c[s])
    rate = throughput(reports, wall_s)
    per_min = f" ({rate:.1f} logs/min)" if rate is not None else ""
    return f"{c['logs']} log{'s' * (c['logs'] != 1)}: {parts} in {duration(wall_s)} with {runner}{per_min}"


def table(reports: list[LogReport], wall_s: float, runner: Runner) -> str:
    """The summary on stdout: one aligned row per log, then the totals."""
    rows = [COLUMNS, *(_row(r) for r in reports)]
    widths = [max(len(row[i]) for row in rows) for i in range(len(COLUMNS) - 1)]
    lines = ["  ".join([*(cell.ljust(w) for cell, w in zip(row, widths, strict=False)), row[-1]]).rstrip()
             for row in rows]
    return "\n".join([*lines, footer(reports, wall_s, runner)]) + "\n"


def document(reports: list[LogReport], wall_s: float, runner: Runner, outdir: Path) -> str:
    """The --json document: the run, the counts and one entry per log in input order."""
    doc: dict[str, Any] = {
        "format": "magcal-batch", "format_version": 1, "magcal_version": __version__,
        "outdir": str(outdir.absolute()),
        "runner": {"kind": runner.kind, "workers": runner.workers, "scheduler": runner.scheduler},
        "seconds": wall_s, "logs_per_min": throughput(reports, wall_s), "counts": counts(reports),
        "exit_code": exit_code(reports), "logs": [r.to_dict() for r in reports]}
    return json.dumps(doc, indent=2, default=float) + "\n"


def progress_line(r: LogReport, done: int, total: int, left: float | None = None) -> str:
    """'[3/100] log7: ok in 4.2 s' (stderr), with the error of a failed log and, when known, the time left of the
    batch: '[3/100, about 6 min left] ...'."""
    tail = f": {STATUS_TEXT.get(r.status, r.status)}" + ("" if r.status == "skipped" else f" in {r.seconds:.1f} s")
    head = f"{done}/{total}" + (f", about {progress.duration(left)} left" if left is not None else "")
    return f"[{head}] {r.name}{tail}" + (f" (exit {r.exit_code}): Error: {r.error}" if r.error else "")


class Tally:
    """The batch's progress lines, one per log that ends, with the batch's time left once a log was fitted: the
    logs left at the rate logs were fitted so far (on all workers together; skipped logs aside)."""

    def __init__(self, total: int, clock: Callable[[], float] = time.monotonic) -> None:
        """`total` logs, skipped ones included; `clock` is injectable for tests."""
        self.total, self.clock, self.start = total, clock, clock()
        self.ended = self.fitted = 0

    def line(self, r: LogReport) -> str:
        """The progress line of the next log that ended."""
        self.ended += 1
        self.fitted += r.status != "skipped"
        rest = self.total - self.ended
        left = (self.clock() - self.start) / self.fitted * rest if self.fitted and rest else None
        return progress_line(r, self.ended, self.total, left if left is None or left >= 1.0 else None)


def interrupted_line(reports: list[LogReport], total: int) -> str:
    """Ctrl-C's line: the logs done, stopped (nothing of theirs written) and not started, and how to go on."""
    stopped = sum(r.status == "interrupted" for r in reports)
    done = len(reports) - stopped
    skip = "the one done is skipped" if done == 1 else f"the {done} done are skipped"
    rest = f"; run the same command again to fit the other {total - done} ({skip})" if done else \
        "; run the same command again to fit them"
    return (f"interrupted: {done} of {total} logs done, {stopped} stopped with nothing of theirs written, "
            f"{total - done - stopped} not started{rest}")
