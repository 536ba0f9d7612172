"""CSV writer in the canonical layout of spec/cli.md: one row per IMU sample, empty cells where a sensor has none.

The format has no row for a reading between IMU samples (spec/cli.md: "one row per IMU sample"; an empty
magnetometer cell is a slower magnetometer), so every other stream must be stamped on IMU stamps: the writer
refuses a simulation whose magnetometer has a phase or a rate that puts it between them rather than move a
reading to another time. `magcal simulate out.csv` simulates with phase 0 for that reason.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from magcal_cli import units
from magcal_cli.atomic import atomic_path
from magcal_cli.errors import MagcalError
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.synth.simulate import Simulation

#: a stamp within this (s) of an IMU stamp is on its row (times are written to 1 us)
ROW_TOLERANCE_S = 5e-7
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


def _rows(present: list[Stream], where: str) -> np.ndarray:
    """The row times: the IMU's stamps (every other stream's must be among them), or all stamps without an IMU."""
    imu = [s for s in present if s.kind in (Kind.GYROSCOPE, Kind.ACCELEROMETER)]
    if not imu:
        return np.unique(np.concatenate([s.t for s in present]))
    t = np.unique(np.concatenate([s.t for s in imu]))
    for s in present:
        at = np.clip(np.searchsorted(t, s.t), 1, max(1, t.size - 1))
        near = np.minimum(np.abs(s.t - t[at - 1]), np.abs(s.t - t[np.minimum(at, t.size - 1)]))
        off = near > ROW_TOLERANCE_S
        if off.any():
            msg = (f"{where}: a CSV log holds one row per IMU sample (spec/cli.md), but {int(off.sum())} of the "
                   f"{len(s)} {s.kind.value} stamps fall between IMU stamps (the first at {s.t[off][0]:.6f} s); "
                   "simulate with mag_phase_s=0 and a magnetometer rate that divides the IMU rate (magcal simulate "
                   "does so for .csv), or write another format")
            raise MagcalError(msg)
    return t


def table(rec: Recording, where: str = "CSV") -> tuple[str, np.ndarray, list[str]]:
    """Header line, the (rows, columns) table with NaN for "no sample" and the per-column formats."""
    present = [(kind, cells, unit, fmt, rec.of_kind(kind)[0]) for kind, cells, unit, fmt in COLUMNS
               if rec.of_kind(kind)]
    t = _rows([s for *_, s in present], where)
    header = ["t [s]"] + [f"{c} [{unit}]" for _, cells, unit, _, _ in present for c in cells]
    out = np.full((t.size, len(header)), np.nan)
    out[:, 0] = t
    col = 1
    for _, cells, unit, _, s in present:
        rows = np.clip(np.searchsorted(t, s.t - ROW_TOLERANCE_S), 0, t.size - 1)
        out[rows, col:col + len(cells)] = s.values * units.from_si(unit)
        col += len(cells)
    fmts = ["%.6f"] + [fmt for _, cells, _, fmt, _ in present for _ in cells]
    return ",".join(header), out, fmts


def write_csv(sim: Simulation, path: Path) -> None:
    """The simulation's streams as CSV, times in seconds from the first sample; MagcalError when a stream has
    stamps that are not IMU stamps."""
    header, out, fmts = table(sim.recording, str(path))
    buf = io.StringIO()
    np.savetxt(buf, out, fmt=fmts, delimiter=",", header=header, comments="")
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue().replace("nan", ""), encoding="utf-8")
