"""`magcal inspect`: what a reader found in a log, as rows for a table or a JSON document."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.streams import Recording, Stream

COLUMNS = ("id", "kind", "count", "rate_hz", "start_s", "end_s", "units", "source")
HEADINGS = ("id", "kind", "count", "rate Hz", "start s", "end s", "units", "source")


@dataclass(frozen=True)
class Row:
    """One stream (or the parameter set) as `inspect` lists it; rate is samples per second over the span."""

    id: str
    kind: str
    count: int
    rate_hz: float | None
    start_s: float | None
    end_s: float | None
    units: str
    source: str


def stream_row(rec: Recording, s: Stream) -> Row:
    """The row of one stream; the source loses the log-name prefix the table's title already gives."""
    n = len(s)
    span = float(s.t[-1] - s.t[0]) if n else 0.0
    rate = (n - 1) / span if n > 1 and span > 0 else None
    source = s.source.removeprefix(f"{rec.path.name}#")
    return Row(s.id, s.kind.value, n, rate, float(s.t[0]) if n else None, float(s.t[-1]) if n else None,
               s.native_unit, source)


def rows(rec: Recording) -> list[Row]:
    """Every stream in reader order, then a `parameters` row when the log carries firmware parameters."""
    out = [stream_row(rec, s) for s in rec.streams]
    if rec.params:
        out.append(Row("parameters", "parameters", len(rec.params), None, None, None, "",
                       "firmware parameters (last value of each)"))
    return out


def inspect_log(path: Path, fmt: str | None = None, receive_time: bool = False) -> Recording:
    """Read a log for listing: the complete part of a truncated log is shown, with the reader's note."""
    return open_recording(path, fmt, ReadOptions(allow_truncated=True, receive_time=receive_time))


def to_dict(rec: Recording) -> dict[str, Any]:
    """The JSON document: log, format, t0, streams, parameters and the reader's notes."""
    return {"log": str(rec.path), "format": rec.format, "t0_s": rec.t0,
            "streams": [asdict(r) for r in rows(rec)], "parameters": dict(rec.params), "notes": list(rec.notes)}


def to_json(rec: Recording) -> str:
    """`to_dict` as indented JSON (NaN-free: missing numbers are null)."""
    return json.dumps(to_dict(rec), indent=2, allow_nan=False)


def _cell(value: Any, column: str) -> str:
    if value is None:
        return "-"
    if column == "rate_hz":
        return f"{value:.1f}"
    if column in ("start_s", "end_s"):
        return f"{value:.3f}"
    return str(value)


def to_table(rec: Recording) -> str:
    """A title line, the aligned table and the notes, for people."""
    body = [[_cell(getattr(r, c), c) for c in COLUMNS] for r in rows(rec)]
    widths = [max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(HEADINGS)]
    right = {"count", "rate_hz", "start_s", "end_s"}

    def line(cells: list[str] | tuple[str, ...]) -> str:
        parts = [c.rjust(w) if col in right else c.ljust(w) for c, w, col in zip(cells, widths, COLUMNS, strict=True)]
        return "  ".join(parts).rstrip()

    out = [f"{rec.path.name}: {rec.format}, {len(rec.streams)} streams, t0 = {rec.t0:.6f} s (log clock)",
           line(HEADINGS)]
    out += [line(b) for b in body] or ["(no streams magcal can use)"]
    if rec.notes:
        out += ["notes:"] + [f"  - {n}" for n in rec.notes]
    return "\n".join(out)
