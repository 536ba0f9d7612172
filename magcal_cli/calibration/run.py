"""What one `fit` produced: the document, what it was computed from, what was noticed, and its stamps."""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

from magcal_cli.calibration.types import Calibration
from magcal_cli.detect import StillResult
from magcal_cli.findings import Finding
from magcal_cli.streams import FloatArray, Recording


@dataclass(frozen=True, eq=False)
class MagSeries:
    """A magnetometer's readings and calibrated unit field over time, for reports and plots."""

    t: FloatArray
    raw: FloatArray
    calibrated: FloatArray


@dataclass(frozen=True, eq=False)
class RunResult:
    """Everything one `fit` produced: the document, what it was computed from and what was noticed."""

    calibration: Calibration
    recording: Recording
    still: StillResult
    findings: tuple[Finding, ...]
    series: dict[str, MagSeries]
    #: the names of the files this run writes (`writers.write_outputs` fills it): the report's provenance lists them
    outputs: tuple[str, ...] = ()


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file, or of a bag directory's files in name order."""
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        with f.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def utc_now() -> str:
    """ISO-8601 UTC timestamp; SOURCE_DATE_EPOCH makes it reproducible (as reproducible builds do)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    stamp = float(epoch) if epoch and epoch.isdigit() else time.time()
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(stamp))
