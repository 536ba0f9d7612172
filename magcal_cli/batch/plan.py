"""magcal batch: find the logs in files, folders and globs, plan one `magcal fit` per log into DIR/<name>/, skip
the logs whose outputs are up to date, and summarise the results as a table or one JSON document.

The fits themselves run in `batch.run` (local processes) or `batch.dask` (a Dask cluster); this module decides
what to run and reports it. No click: cli/batch.py parses the command line.
"""

from __future__ import annotations

import glob
import json
import os
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from magcal_cli import __version__
from magcal_cli.errors import MagcalError

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling

#: the per-log status file, written last (atomically): its presence means the log's outputs are complete
STATUS_FILE = "batch.json"
FORMAT_VERSION = 1
#: what --effects auto parses to (as in cli.common.AUTO): the diagnosis chooses the effects
AUTO_EFFECTS = ("auto",)
DEFAULT_OUTPUTS = ("json", "yaml", "report", "html")
GLOB_CHARS = frozenset("*?[")
#: statuses whose outputs are complete (a gate verdict does not change on a rerun with the same options)
COMPLETE = ("ok", "gate_failed")


class BatchUsageError(MagcalError):
    """The command line cannot be run (no log found, an output exists without --force): exit 2."""


@dataclass(frozen=True)
class FitOptions:
    """The `magcal fit` options batch passes through; the same for every log."""

    method: str = "auto"
    effects: tuple[str, ...] = AUTO_EFFECTS
    outputs: tuple[str, ...] | None = None          # None: fit's default, plus the firmware file for its logs
    mags: tuple[str, ...] = ()                      # (): every magnetometer
    fail_on: tuple[Any, ...] = ()                   # gates.Condition
    strict: bool = False
    imu_timing: Sampling | None = None              # None: the log format's own (timing.py)
    mag_timing: Sampling | None = None
    start_s: float | None = None                    # --start/--end: the part of every log to fit
    end_s: float | None = None
    history: bool = False                           # --history: each report carries its store entries
    vehicle: str | None = None                      # --vehicle: the entries' vehicle instead of the log's

    def fingerprint(self) -> dict[str, Any]:
        """What batch.json records: outputs fitted with other options (or another magcal) are not up to date.
        --history and --vehicle change no output, so they are left out (batch.json keeps the entries)."""
        return {"magcal_version": __version__, "method": self.method, "effects": list(self.effects),
                "outputs": None if self.outputs is None else list(self.outputs), "mags": list(self.mags),
                "fail_on": [str(c) for c in self.fail_on], "strict": self.strict,
                **{k: getattr(self, k).value for k in ("imu_timing", "mag_timing") if getattr(self, k) is not None},
                **{k: getattr(self, k) for k in ("start_s", "end_s") if getattr(self, k) is not None}}


@dataclass(frozen=True)
class Job:
    """One log to fit: everything a worker needs, picklable (it travels to processes and Dask workers)."""

    log: Path
    name: str
    outdir: Path
    names: tuple[str, ...]                          # outputs to write
    auto: str | None                                # the firmware output added when the log's format takes it
    options: FitOptions
    stop: str | None = None                         # on a Dask cluster: the Event whose setting stops the fit


@dataclass
class LogReport:
    """One log's outcome: a row of the summary, an entry of --json and the content of its batch.json."""

    log: str
    name: str
    outdir: str
    status: str                                     # ok, skipped, failed, gate_failed, interrupted
    exit_code: int                                  # what `magcal fit` would have exited with
    seconds: float = 0.0
    error: str | None = None                        # the one-line error, as fit prints it after 'Error: '
    format: str | None = None
    method: str | None = None
    magnetometers: list[dict[str, Any]] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    traceback: str | None = None                    # for an internal error (123): printed with -v
    history: list[dict[str, Any]] = field(default_factory=list)   # --history: the store entries (history.entry)

    def to_dict(self, history: bool = False) -> dict[str, Any]:
        """The JSON entry (the store entries only in batch.json, with `history`)."""
        out = asdict(self)
        if not history:
            del out["history"]
        return out


@dataclass
class Plan:
    """The logs to fit and those skipped as up to date, in input order."""

    jobs: list[Job]
    skipped: list[LogReport]
    order: list[str]                                # every log, as LogReport.log, in input order


def is_bag_dir(path: Path) -> bool:
    """A ROS 2 bag directory: a log itself, not a folder to search."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _looks_like_log(path: Path) -> bool:
    """A file a folder search takes: one magcal can sniff, or one with a log's extension (a corrupt log is
    then reported, not silently passed over)."""
    from magcal_cli.readers import EXTENSIONS, sniff

    if path.suffix.lower() in EXTENSIONS:
        return True
    try:
        sniff(path)
    except MagcalError:
        return False
    return True


def _search(folder: Path, exclude: Path) -> list[Path]:
    """Every log under `folder` (recursively; bag directories whole; hidden entries and DIR left out)."""
    found: list[Path] = []
    for root, dirs, files in os.walk(folder):
        here = Path(root)
        dirs.sort()
        keep = []
        for d in dirs:
            sub = here / d
            if d.startswith(".") or sub.resolve() == exclude:
                continue                            # staging folders and our own outputs are not logs
            if is_bag_dir(sub):
                found.append(sub)
            else:
                keep.append(d)
        dirs[:] = keep
        found += [here / f for f in sorted(files) if not f.startswith(".") and _looks_like_log(here / f)]
    return found


def discover(inputs: list[str], exclude: Path) -> list[Path]:
    """The logs named by INPUT... (files, folders, globs), absolute, each once, in input order.

    A file named explicitly is taken as it is (a corrupt one is reported); folders and globs keep what looks
    like a log. An input that names nothing is a usage error.
    """
    logs: dict[Path, None] = {}
    exclude = exclude.resolve()
    for raw in inputs:
        path = Path(raw)
        if path.exists():
            matches, explicit = [path], True
        elif GLOB_CHARS & set(raw) and (hits := sorted(glob.glob(raw, recursive=True))):  # noqa: PTH207 - absolute patterns
            matches, explicit = [Path(m) for m in hits], False
        else:
            msg = f"{raw}: no such file, folder or glob match. Check the path"
            raise BatchUsageError(msg)
        found: list[Path] = []
        for m in matches:
            if m.is_dir() and not is_bag_dir(m):
                found += _search(m, exclude)
            elif m.is_dir() or explicit or _looks_like_log(m):
                found.append(m)
        if not found:
            msg = f"{raw}: no log magcal can read there. Give log files, folders of logs or a glob such as 'logs/**/*.bin'"
            raise BatchUsageError(msg)
        logs.update((p.resolve(), None) for p in found)
    return list(logs)


def output_names(logs: list[Path]) -> dict[Path, str]:
    """Each log's folder in DIR: its stem, or its path below the logs' common folder when stems collide."""
    stems = Counter(p.stem for p in logs)
    root = Path(os.path.commonpath([str(p.parent) for p in logs])) if logs else Path()
    names: dict[Path, str] = {}
    taken: set[str] = set()
    for p in logs:
        name = p.stem if stems[p.stem] == 1 else "__".join(p.relative_to(root).parts)
        base, n = name, 2
        while name in taken:                        # a stem equal to another log's flattened path
            name, n = f"{base}-{n}", n + 1
        taken.add(name)
        names[p] = name
    return names


def log_stamp(log: Path) -> tuple[int, int]:
    """(size, mtime in ns) of a log; a bag directory's total size and newest file."""
    if not log.is_dir():
        st = log.stat()
        return st.st_size, st.st_mtime_ns
    stats = [f.stat() for f in log.rglob("*") if f.is_file()]
    return sum(s.st_size for s in stats), max((s.st_mtime_ns for s in stats), default=0)


def read_status(outdir: Path) -> dict[str, Any] | None:
    """A log folder's batch.json, or None when absent or unreadable (then the log is fitted again)."""
    try:
        doc = json.loads((outdir / STATUS_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and doc.get("format_version") == FORMAT_VERSION else None


def up_to_date(job: Job) -> LogReport | None:
    """The skipped report when the log's outputs are complete for these options and newer than the log."""
    doc = read_status(job.outdir)
    if doc is None or doc.get("options") != job.options.fingerprint() or doc.get("log") != str(job.log):
        return None
    size, mtime = log_stamp(job.log)
    report = doc.get("report", {})
    if doc.get("log_stamp") != [size, mtime] or report.get("status") not in COMPLETE:
        return None
    if job.options.history and not report.get("history"):
        return None                                 # fitted before without --history: its entries are needed
    outputs = [Path(p) for p in report.get("outputs", [])]
    if not outputs or any(not p.is_file() or p.stat().st_mtime_ns < mtime for p in outputs):
        return None
    fields = {k: v for k, v in report.items() if k in LogReport.__dataclass_fields__}
    return LogReport(**{**fields, "status": "skipped"})


def write_status(job: Job, report: LogReport) -> None:
    """batch.json, atomically and after every output: it marks the log's outputs complete."""
    from magcal_cli.atomic import write_text

    doc = {"format": "magcal-batch-log", "format_version": FORMAT_VERSION, "log": str(job.log),
           "log_stamp": list(log_stamp(job.log)), "options": job.options.fingerprint(),
           "report": report.to_dict(history=True)}
    job.outdir.mkdir(parents=True, exist_ok=True)
    write_text(job.outdir / STATUS_FILE, json.dumps(doc, indent=2, default=float) + "\n")


def _targets(log: Path, options: FitOptions) -> tuple[tuple[str, ...], str | None]:
    """(outputs to write, the firmware output added if the log's format takes it) as `magcal fit` decides."""
    from magcal_cli.writers.fitrun import firmware_output

    if options.outputs is not None:
        return options.outputs, None
    return DEFAULT_OUTPUTS, firmware_output(log, None, list(DEFAULT_OUTPUTS))


def plan(logs: list[Path], outdir: Path, options: FitOptions, force: bool) -> Plan:
    """Jobs for the logs to fit, reports for those up to date; an output that would be overwritten without
    --force is a usage error before any work."""
    from magcal_cli.atomic import check_writable
    from magcal_cli.writers import get_writer

    check_writable(outdir, create=True, hint="Choose another -o")
    names = output_names(logs)
    jobs, skipped, clashes = [], [], []
    for log in logs:
        outputs, auto = _targets(log, options)
        job = Job(log, names[log], (outdir / names[log]).absolute(), outputs, auto, options)
        done = up_to_date(job)
        if done is not None:
            skipped.append(done)
            continue
        files = [job.outdir / f for n in (*outputs, *([auto] if auto else [])) for f in get_writer(n).files]
        clashes += [f for f in files if f.exists()]
        jobs.append(job)
    if clashes and not force:
        more = f" (and {len(clashes) - 1} more)" if len(clashes) > 1 else ""
        msg = (f"{clashes[0]}{more}: exists already and is not up to date (another log, other options, or a "
               "newer log). Pass --force to overwrite, or choose another -o")
        raise BatchUsageError(msg)
    return Plan(jobs, skipped, [str(p) for p in logs])


def exit_code(reports: list[LogReport]) -> int:
    """The batch's exit: 1 when a log could not be fitted, else 3 when one failed a --fail-on gate, else 0."""
    codes = {r.exit_code for r in reports}
    if codes - {0, 3}:
        return 1
    return 3 if 3 in codes else 0
