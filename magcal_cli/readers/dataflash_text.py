"""Parser of text DataFlash logs (`NAME, v1, v2, ...` lines, as Mission Planner and old firmware write)

Values are printed already scaled (`c` centi-degrees appear as degrees, `L` as degrees), so the tables
are marked `prescaled`. Lines that are not records (banners such as "Free RAM: 1331") are ignored.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Collection
from pathlib import Path

import numpy as np

from ..errors import LogReadError
from .dataflash_binary import META_TYPES, attach_units
from .dataflash_format import STRING_CHARS, MessageFormat, RawLog, Table, valid_format


def _format(parts: list[str]) -> MessageFormat | None:
    """A MessageFormat from the fields of one `FMT, type, length, name, format, columns...` line."""
    if len(parts) < 5:
        return None
    try:
        type_id, length = int(parts[1]), int(parts[2])
    except ValueError:
        return None
    name, fmt = parts[3], parts[4]
    cols = tuple(c for c in parts[5:] if c)
    return MessageFormat(type_id, name, length, fmt, cols) if valid_format(name, fmt, cols, length) else None


def parse_text(path: Path, wanted: Collection[str] | None = None) -> RawLog:
    """Parse a text DataFlash log; decode the record types in `wanted` (all when None)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
        raise LogReadError(msg) from None
    lines = raw.decode("latin-1").splitlines()
    truncated = _cut_last_line(raw, lines)
    formats: dict[str, MessageFormat] = {}
    by_name: dict[str, list[int]] = defaultdict(list)
    for i, line in enumerate(lines):             # text logs are small (a few MB); one pass to group records
        head, sep, _ = line.partition(",")
        if not sep:
            continue
        name = head.strip()
        if name == "FMT":
            f = _format([p.strip() for p in line.split(",")])
            if f is not None and f.name != "FMT":
                formats.setdefault(f.name, f)
        else:
            by_name[name].append(i)
    want = None if wanted is None else set(wanted) | set(META_TYPES)
    tables: dict[str, Table] = {}
    counts: dict[str, int] = {}
    notes: list[str] = []
    bad_total = 0
    for name, idx in by_name.items():
        f = formats.get(name)
        if f is None:
            continue
        counts[name] = len(idx)
        if want is not None and name not in want:
            continue
        width = len(f.format) + 1
        rows = [[p.strip() for p in lines[i].split(",", width - 1)] for i in idx]
        good = [len(r) == width for r in rows]
        bad_total += len(rows) - sum(good)
        arr = np.array([r[1:] for r, g in zip(rows, good, strict=True) if g], dtype=str)
        arr = arr.reshape(-1, width - 1)
        pos = np.array([i for i, g in zip(idx, good, strict=False) if g], dtype=np.int64)
        ok = np.ones(len(pos), dtype=bool)
        cols: dict[str, np.ndarray] = {}
        for j, col in enumerate(f.columns[:width - 1]):
            if f.format[j] in STRING_CHARS:
                values = arr[:, j]
            else:
                values, parsed = _numbers(arr[:, j])
                ok &= parsed
            cols.setdefault(col, values)
        bad_total += int((~ok).sum())
        cols = {k: v[ok] for k, v in cols.items()}
        tables[name] = Table(f, pos[ok], cols, prescaled=True)
    if bad_total:
        notes.append(f"skipped {bad_total} malformed text records (wrong number of fields, or a field that is not "
                     "a number)")
    try:
        formats = attach_units(formats, tables.get("FMTU"), tables.get("UNIT"), tables.get("MULT"))
    except ValueError:
        notes.append("ignored FMTU/UNIT/MULT records that are not in the expected text form")
    if truncated:
        notes.append(f"the file ends inside a record ({truncated} bytes after the last line break): the log is "
                     "truncated; read the complete lines")
    return RawLog(formats, tables, counts, len(raw), 0, truncated, notes)


def _cut_last_line(raw: bytes, lines: list[str]) -> int:
    """Bytes of a last line cut off by the end of the file (no line break, fewer fields than its FMT), which is
    removed from `lines`; 0 when the file ends cleanly."""
    if not lines or raw.endswith((b"\n", b"\r")):
        return 0
    name, sep, rest = lines[-1].partition(",")
    fields = rest.count(",") + 1 if sep else 0
    fmt = next((_format([p.strip() for p in line.split(",")]) for line in lines
                if line.startswith("FMT") and f", {name.strip()}," in line), None)
    if name.strip() != "FMT" and (fmt is None or fields >= len(fmt.format)):
        return 0
    return len(lines.pop().encode("latin-1"))


def _numbers(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Numeric cells as float64 and which of them parsed (a cell that is not a number is corrupt text)."""
    try:
        return cells.astype(np.float64), np.ones(cells.shape, dtype=bool)
    except ValueError:
        out, ok = np.full(cells.shape, np.nan), np.zeros(cells.shape, dtype=bool)
        for i, cell in enumerate(cells.tolist()):       # only for a damaged column: one pass to find the bad cells
            try:
                out[i], ok[i] = float(cell), True
            except ValueError:
                continue
        return out, ok


def looks_like_text(head: bytes) -> bool:
    """True when the first bytes read as text containing a FMT record."""
    try:
        text = head.decode("ascii")
    except UnicodeDecodeError:
        return False
    return "FMT," in text or "FMT ," in text
