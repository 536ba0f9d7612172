"""CSV logs: a header naming each column and its unit, one row per sample (spec/cli.md "CSV input").

Columns are recognised by name (canonical `gx [rad/s]`, x-io `Gyroscope X (deg/s)`, `gyro_x [deg/s]`, ...);
an empty cell means "no sample of that sensor in this row". Details: docs/readers-ros-csv.md.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import IO, ClassVar

import numpy as np

from magcal_cli import units
from magcal_cli.align import clean_time
from magcal_cli.errors import LogReadError, StreamError
from magcal_cli.progress import active, current, within
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.checks import (
    drop_held,
    nan_throughout,
    normalised_field,
    normalised_note,
    sensor_checks,
)
from magcal_cli.readers.cut import mark_cut, refuse_if_strict
from magcal_cli.streams import Cut, FloatArray, Kind, Recording, Sampling, Stream

#: family -> name prefixes of its x/y/z columns (compared without case, spaces or punctuation)
AXIS_PREFIXES: dict[str, tuple[str, ...]] = {
    "gyroscope": ("gyroscope", "angularvelocity", "gyro", "gyr", "omega", "g", "w"),
    "accelerometer": ("accelerometer", "linearacceleration", "accel", "acc", "a"),
    "magnetometer": ("magnetometer", "magneticfield", "magnetic", "mag", "m"),
}
#: family -> whole column names of single-valued columns
SCALAR_NAMES: dict[str, tuple[str, ...]] = {
    "time": ("t", "time", "timestamp", "stamp"),
    "temperature": ("temperature", "temp"),
    "current": ("current", "batterycurrent"),
    "voltage": ("voltage", "batteryvoltage"),
    "throttle": ("throttle",),
}
#: family -> units it may be declared in (canonical names of units.py)
ALLOWED_UNITS: dict[str, tuple[str, ...]] = {
    "time": ("s", "ms", "us", "ns"), "gyroscope": ("rad/s", "deg/s"), "accelerometer": ("m/s^2", "g"),
    "magnetometer": units.MAG_UNITS, "temperature": ("degC",), "current": ("A", "cA"), "voltage": ("V",),
    "throttle": ("1",),
}
#: family -> (kind, stream id)
STREAMS: dict[str, tuple[Kind, str]] = {
    "gyroscope": (Kind.GYROSCOPE, "imu"), "accelerometer": (Kind.ACCELEROMETER, "imu"),
    "magnetometer": (Kind.MAGNETOMETER, "mag"), "temperature": (Kind.TEMPERATURE, "temperature"),
    "current": (Kind.BATTERY_CURRENT, "battery"), "voltage": (Kind.BATTERY_VOLTAGE, "battery"),
    "throttle": (Kind.THROTTLE, "throttle"),
}
#: above this share of rows that do not parse, the file is malformed rather than damaged here and there
BAD_ROW_SHARE = 0.01
#: bytes of text parsed at a time: at ~20 MB/s a few progress reports a second, as fast as 16 MB blocks
CSV_BLOCK = 1 << 22
#: the share of a read that parsing the rows takes; building the streams takes the rest (0.86 on a 30 MB file)
PARSE_SHARE = 0.85
CANONICAL_HEADER = "t [s],gx [rad/s],gy [rad/s],gz [rad/s],ax [m/s^2],ay [m/s^2],az [m/s^2],mx [uT],my [uT],mz [uT]"
_CELL = re.compile(r"\s*(?P<name>.*?)\s*(?:[\[(]\s*(?P<unit>[^\])]*?)\s*[\])])?\s*")


@dataclass(frozen=True)
class Column:
    """One recognised header cell: its position, family, axis (0-2, or 0 for scalars) and unit."""

    index: int
    cell: str
    family: str
    axis: int
    unit: str


def _family(name: str) -> tuple[str, int] | None:
    """(family, axis) of a column name, or None when magcal does not use it."""
    key = re.sub(r"[^a-z0-9]", "", name.lower())
    for family, names in SCALAR_NAMES.items():
        if key in names:
            return family, 0
    for family, prefixes in AXIS_PREFIXES.items():
        for prefix in prefixes:
            if len(key) == len(prefix) + 1 and key.startswith(prefix) and key[-1] in "xyz":
                return family, "xyz".index(key[-1])
    return None


def parse_header(line: str, where: str) -> tuple[list[Column], list[str]]:
    """Recognised columns and the names of the ignored ones; errors name the cell and the fix."""
    cols, ignored = [], []
    for i, cell in enumerate(line.split(",")):
        m = _CELL.fullmatch(cell)
        name, unit = (m.group("name"), m.group("unit")) if m else (cell.strip(), None)
        fam = _family(name)
        if fam is None:
            ignored.append(cell.strip())
            continue
        family, axis = fam
        allowed = ALLOWED_UNITS[family]
        if not unit:
            if family != "throttle":
                msg = (f"{where}: column {cell.strip()!r} declares no unit; write it as '{name} [unit]' with "
                       f"one of: {', '.join(allowed)}")
                raise LogReadError(msg)
            unit = "1"
        try:
            canon = units.canonical(unit)
        except StreamError:
            canon = ""
        if canon not in allowed:
            msg = (f"{where}: column {cell.strip()!r}: {unit!r} is not a {family} unit magcal knows; "
                   f"use one of: {', '.join(allowed)}")
            raise LogReadError(msg)
        cols.append(Column(i, cell.strip(), family, axis, canon))
    return cols, ignored


def _check_columns(cols: list[Column], where: str) -> dict[str, list[Column]]:
    """Columns by family, each complete (x, y, z) and unique; a time column and one sensor are required."""
    by: dict[str, list[Column]] = {}
    for c in cols:
        by.setdefault(c.family, []).append(c)
    for family, cs in by.items():
        axes = sorted(c.axis for c in cs)
        want = [0, 1, 2] if family in AXIS_PREFIXES else [0]
        if axes != want:
            names = ", ".join(c.cell for c in cs)
            msg = (f"{where}: the {family} columns are {names}; give each axis exactly once "
                   f"({'x, y and z' if len(want) == 3 else 'one column'})")
            raise LogReadError(msg)
        if len({c.unit for c in cs}) > 1:
            msg = f"{where}: the {family} columns declare different units ({', '.join(c.cell for c in cs)})"
            raise LogReadError(msg)
        cs.sort(key=lambda c: c.axis)
    if "time" not in by:
        msg = f"{where}: no time column in the header; name it 't [s]' (canonical header: {CANONICAL_HEADER})"
        raise LogReadError(msg)
    if not set(by) & set(AXIS_PREFIXES):
        msg = (f"{where}: no gyroscope, accelerometer or magnetometer columns in the header; "
               f"expected e.g. {CANONICAL_HEADER}")
        raise LogReadError(msg)
    return by


def fill_empty(body: str) -> str:
    """Write 'nan' into empty cells so numpy's C parser reads the table (str.replace is ~10x a regex)."""
    body = body.replace("\r\n", "\n")
    for _ in range(2):                                   # ",,," needs two passes: matches do not overlap
        body = body.replace(",,", ",nan,")
    body = body.replace("\n,", "\nnan,").replace(",\n", ",nan\n")
    if body.startswith(","):
        body = "nan" + body
    return body + "nan" if body.endswith(",") else body


def parse_rows(body: str, first_line: int, width: int) -> tuple[FloatArray, list[tuple[int, str]]]:
    """The numeric rows of a block of lines and the rows that do not parse: (line number, why) -- a cell that is
    not a number, or a wrong number of cells. numpy's C parser reads an undamaged block in one call."""
    if not body.strip():
        return np.zeros((0, width)), []
    lines = fill_empty(body).splitlines()
    try:
        return np.loadtxt(lines, delimiter=",", ndmin=2, dtype=np.float64), []
    except ValueError:
        pass
    rows: list[list[float]] = []
    bad: list[tuple[int, str]] = []
    for k, line in enumerate(lines):              # only for a damaged block: find the rows that do not parse
        if not line.strip():
            continue
        cells = line.split(",")
        if len(cells) != width:
            bad.append((first_line + k, f"the number of columns changed from {width} to {len(cells)}"))
            continue
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            cell = next(c for c in cells if not _is_number(c))
            bad.append((first_line + k, f"could not convert string {cell.strip()!r} to a number"))
    return np.array(rows, dtype=np.float64).reshape(-1, width), bad


def read_rows(fh: IO[bytes], first_line: int, where: str, width: int, cuts: list[Cut],
              notes: list[str]) -> FloatArray:
    """The table below the header, read in blocks of CSV_BLOCK bytes (memory: one block of text plus the numbers).

    Rows that do not parse are skipped and counted when they are few (corrupt data); when more than
    BAD_ROW_SHARE are, the file is not in the expected form and the error names the first such line. The bytes
    parsed are reported per block as the "reading" fraction of `progress.current()`.
    """
    parts: list[FloatArray] = []
    bad: list[tuple[int, str]] = []
    line, replaced, lines_read = first_line, 0, 0
    first_exc: UnicodeDecodeError | None = None
    hook, at, size = current(), fh.tell(), os.fstat(fh.fileno()).st_size
    chunk = fh.readlines(CSV_BLOCK)
    while chunk:
        hook("reading", at, size)
        following = fh.readlines(CSV_BLOCK)
        data = b"".join(chunk)
        at += len(data)
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            text = data.decode("utf-8", errors="replace")          # corrupt bytes: their rows will not parse
            replaced += text.count("\ufffd")
            first_exc = first_exc or exc
        if not following:
            text = _cut_last_row(text, width, line + len(chunk) - 1, os.fstat(fh.fileno()).st_size, cuts)
        rows, bad_rows = parse_rows(text, line, width)
        if rows.shape[1] != width:
            msg = (f"{where}: rows have {rows.shape[1]} cells but the header names {width} columns; make the header "
                   "and the rows agree")
            raise LogReadError(msg)
        parts.append(rows)
        bad += bad_rows
        line += len(chunk)
        lines_read += len(chunk)
        chunk = following
    hook("reading", at, max(at, 1))
    if first_exc is not None and replaced > BAD_ROW_SHARE * lines_read:
        msg = f"{where}: cannot read the CSV file ({first_exc}). Save it as UTF-8 text"
        raise LogReadError(msg)
    table = np.concatenate(parts) if parts else np.zeros((0, width))
    if len(bad) > BAD_ROW_SHARE * (len(table) + len(bad)):
        msg = f"{where}: line {bad[0][0]}: {bad[0][1]}. Fix or delete that row"
        raise LogReadError(msg)
    if bad:
        notes.append(f"skipped {len(bad)} rows that do not parse (corrupt data; the first is line {bad[0][0]}: "
                     f"{bad[0][1]})")
    return table


def _is_number(cell: str) -> bool:
    """Whether float() reads the cell."""
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _header_line(fh: IO[bytes], where: str) -> tuple[str, int]:
    """The header (the first line that is neither blank nor a '#' comment) and its line number."""
    for line_no, raw in enumerate(iter(fh.readline, b""), start=1):
        try:
            line = raw.decode("utf-8-sig" if line_no == 1 else "utf-8")
        except UnicodeDecodeError as exc:          # often a binary log taken for CSV by its name
            msg = (f"{where}: cannot read the CSV file ({exc}). Save it as UTF-8 text, or pass --format if it is "
                   "another log type")
            raise LogReadError(msg) from None
        if line.strip() and not line.lstrip().startswith("#"):
            return line.rstrip("\r\n"), line_no
    msg = f"{where}: no header line; the first line must name the columns, e.g. {CANONICAL_HEADER}"
    raise LogReadError(msg)


def _cut_last_row(body: str, width: int, last_line: int, size: int, cuts: list[Cut]) -> str:
    """The body without a last row cut off by the end of the file (no newline, too few cells), noted in `cuts`
    (a cut inside the last number cannot be seen, as in any text log)."""
    if not body or body.endswith("\n"):
        return body
    head, _, last = body.rpartition("\n")
    cells = last.rstrip("\r").count(",") + 1
    if cells >= width or not last.strip():
        return body
    lost = len(last.encode("utf-8"))
    cuts.append(Cut(size - lost, size, f"line {last_line}, {cells} of its {width} cells present"))
    return head + "\n"


class CsvReader:
    """Reads gyroscope, accelerometer, magnetometer and optional temperature, current, voltage, throttle."""

    name: ClassVar[str] = "csv"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Parse the header, the table, and build one stream per sensor (empty cells are no sample); the fraction
        read is reported as the "reading" stage of `progress.current()` (the bytes parsed, then the streams)."""
        hook = current()
        where = str(path)
        try:
            fh = path.open("rb")
        except OSError as exc:
            msg = f"{where}: cannot read the CSV file ({exc.strerror or exc}). Check the path and its permissions"
            raise LogReadError(msg) from None
        with fh:
            header, line_no = _header_line(fh, where)
            if "," not in header and (";" in header or "\t" in header):
                msg = f"{where}: the header is not comma-separated; magcal reads comma-separated files (CSV)"
                raise LogReadError(msg)
            cols, ignored = parse_header(header, where)
            by = _check_columns(cols, where)
            notes: list[str] = [f"ignored columns: {', '.join(ignored)}"] if ignored else []
            cuts: list[Cut] = []
            with active(within(hook, 0.0, PARSE_SHARE)):
                table = read_rows(fh, line_no + 1, where, header.count(",") + 1, cuts, notes)
        cut = cuts[0] if cuts else None
        refuse_if_strict(path, options, cut)
        if table.shape[0] == 0:
            msg = f"{where}: the CSV file has a header but no rows"
            raise LogReadError(msg)
        return mark_cut(self._recording(path, table, by, notes), cut)

    @staticmethod
    def _recording(path: Path, table: FloatArray, by: dict[str, list[Column]], notes: list[str]) -> Recording:
        """Time relative to the first row, then one cleaned SI stream per family present."""
        tcol = by["time"][0]
        t_abs = table[:, tcol.index] * units.to_si(tcol.unit)
        t0 = float(np.nanmin(t_abs)) if np.isfinite(t_abs).any() else 0.0
        imu = [f for f in by if f in ("accelerometer", "gyroscope")]         # one IMU: rows kept or dropped together
        groups = ([imu] if imu else []) + [[f] for f in by if f != "time" and f not in imu]
        streams = []
        for families in groups:
            kinds = tuple(STREAMS[f][0] for f in families)
            sid = STREAMS[families[0]][1]
            names = "/".join(families)
            vals = np.concatenate([table[:, [c.index for c in by[f]]] * units.to_si(by[f][0].unit)
                                   for f in families], axis=1)
            where = f"{sid} {names}" if sid in ("imu", "battery") else sid
            given = ~np.isnan(vals)                      # an empty cell (NaN) is "no sample"; inf is a bad value
            complete = np.all(given, axis=1) & ~np.isnan(t_abs)
            partial = np.any(given, axis=1) & ~complete
            if partial.any():
                notes.append(f"{where}: dropped {int(partial.sum())} rows with some {names} cells or the time empty")
            if not complete.any():
                # a magnetometer whose every cell is empty or nan is kept as logged, for fit to refuse by name
                dead = nan_throughout(t_abs - t0, vals, where) if kinds == (Kind.MAGNETOMETER,) else None
                if dead is not None:
                    notes += dead[2]
                    cs = by[families[0]]
                    src = f"{path.name}#{', '.join(c.cell for c in cs)}"
                    streams.append(Stream(kinds[0], sid, dead[0], dead[1], src, cs[0].unit, sampling=Sampling.INSTANT))
                else:
                    notes.append(f"{where}: no row has every {names} cell and the time; no {names} stream")
                continue
            t, v, cleaned = clean_time(t_abs[complete] - t0, vals[complete], where)
            notes += cleaned
            if kinds == (Kind.MAGNETOMETER,):
                t, v, held = drop_held(t, v, where)
                notes += held
            t, v, checked = sensor_checks(kinds, t, v, where)
            notes += checked
            if kinds == (Kind.MAGNETOMETER,) and normalised_field(v):
                notes.append(normalised_note(sid, v, "T"))
            if not len(t):
                continue
            col = 0
            for f in families:
                cs = by[f]
                src = f"{path.name}#{', '.join(c.cell for c in cs)}"
                # a row is one instant (x-io and phone exporters log the samples as read; docs/timing.md)
                streams.append(Stream(STREAMS[f][0], sid, t, v[:, col:col + len(cs)], src, cs[0].unit,
                                      sampling=Sampling.INSTANT))
                col += len(cs)
        return Recording(path, "csv", tuple(streams), t0=t0, notes=tuple(notes))
