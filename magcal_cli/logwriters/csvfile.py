"""CSV writer in the canonical layout of spec/cli.md: one row per sample time, empty cells where a sensor has none."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .. import units
from ..atomic import atomic_path
from ..streams import Kind, Recording
from ..synth import Simulation

#: (kind, header cells, unit, printf format) in column order; kinds absent from the recording are left out
COLUMNS: tuple[tuple[Kind, tuple[str, ...], str, str], ...] = (
    (Kind.GYROSCOPE, ("gx", "gy", "gz"), "rad/s", "%.9g"),
    (Kind.ACCELEROMETER, ("ax", "ay", "az"), "m/s^2", "%.9g"),
    (Kind.MAGNETOMETER, ("mx", "my", "mz"), "uT", "%.9g"),
    (Kind.TEMPERATURE, ("temperature",), "degC", "%.6g"),
    (Kind.BATTERY_CURRENT, ("current",), "A", "%.6g"),
    (Kind.BATTERY_VOLTAGE, ("voltage",), "V", "%.6g"),
    (Kind.THROTTLE, ("throttle",), "1", "%.6g"),
)


def table(rec: Recording) -> tuple[str, np.ndarray, list[str]]:
    """Header line, the (rows, columns) table with NaN for "no sample" and the per-column formats."""
    present = [(kind, cells, unit, fmt, rec.of_kind(kind)[0]) for kind, cells, unit, fmt in COLUMNS
               if rec.of_kind(kind)]
    t = np.unique(np.concatenate([s.t for *_, s in present]))
    header = ["t [s]"] + [f"{c} [{unit}]" for _, cells, unit, _, _ in present for c in cells]
    out = np.full((t.size, len(header)), np.nan)
    out[:, 0] = t
    col = 1
    for _, cells, unit, _, s in present:
        rows = np.searchsorted(t, s.t)
        out[rows, col:col + len(cells)] = s.values * units.from_si(unit)
        col += len(cells)
    fmts = ["%.6f"] + [fmt for _, cells, _, fmt, _ in present for _ in cells]
    return ",".join(header), out, fmts


def write_csv(sim: Simulation, path: Path) -> None:
    """The simulation's streams as CSV, times in seconds from the first sample."""
    header, out, fmts = table(sim.recording)
    buf = io.StringIO()
    np.savetxt(buf, out, fmt=fmts, delimiter=",", header=header, comments="")
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue().replace("nan", ""), encoding="utf-8")
