"""Parser of text DataFlash logs (`NAME, v1, v2, ...` lines, as Mission Planner and old firmware write)

Values are printed already scaled (`c` centi-degrees appear as degrees, `L` as degrees), so the tables
are marked `prescaled`. Lines that are not records (banners such as "Free RAM: 1331") are ignored.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Collection
from pathlib import Path

import numpy as np

from magcal_cli.errors import LogReadError
from magcal_cli.progress import current
from magcal_cli.readers.dataflash.binary import META_TYPES, attach_units
from magcal_cli.readers.dataflash.format import STRING_CHARS, MessageFormat, RawLog, Table, valid_format

#: bytes of text parsed at a time: at ~6 MB/s a few progress reports a second, as fast as 16 MB blocks
TEXT_BLOCK = 1 << 22
#: format characters printed as text: strings, and the flight mode `M`, which text logs print by name
TEXT_CHARS = STRING_CHARS | {"M"}


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


def parse_text(path: Path, wanted: Collection[str] | None = None, block: int = TEXT_BLOCK) -> RawLog:
    """Parse a text DataFlash log in blocks of about `block` bytes (memory: one block plus the decoded records);
    decode the record types in `wanted` (all when None)."""
    try:
        fh = path.open("rb")
    except OSError as exc:
        msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
        raise LogReadError(msg) from None
    acc = _Blocks(None if wanted is None else set(wanted) | set(META_TYPES))
    size, truncated, first = 0, 0, 0
    hook = current()
    with fh:
        total = os.fstat(fh.fileno()).st_size
        chunk = fh.readlines(block)
        while chunk:
            hook("reading", size, total)
            following = fh.readlines(block)
            data = b"".join(chunk)
            size += len(data)
            lines = data.decode("latin-1").splitlines()
            if not following:
                truncated = _cut_last_line(data, lines, acc.formats)
            acc.add(lines, first)
            first += len(lines)
            chunk = following
    hook("reading", size, max(size, 1))
    tables, counts, notes = acc.tables()
    try:
        formats = attach_units(dict(acc.formats), tables.get("FMTU"), tables.get("UNIT"), tables.get("MULT"))
    except (ValueError, KeyError, TypeError, IndexError):
        formats = acc.formats
        notes.append("ignored FMTU/UNIT/MULT records that are not in the expected text form")
    lost = f"a line without its line break and some fields, {truncated} bytes" if truncated else ""
    return RawLog(formats, tables, counts, size, 0, truncated, notes, lost, text=True)


class _Blocks:
    """The formats seen so far and the decoded records of the wanted types, block by block."""

    def __init__(self, want: set[str] | None) -> None:
        self.want = want
        self.formats: dict[str, MessageFormat] = {}
        self.counts: dict[str, int] = defaultdict(int)
        self.parts: dict[str, list[tuple[np.ndarray, dict[str, np.ndarray]]]] = defaultdict(list)
        self.bad = 0

    def add(self, lines: list[str], first: int) -> None:
        """Group one block's lines by record name and decode the wanted ones (lines before their FMT are lost)."""
        by_name: dict[str, list[int]] = defaultdict(list)
        for i, line in enumerate(lines):         # one pass per block to group records
            head, sep, _ = line.partition(",")
            if not sep:
                continue
            name = head.strip()
            if name == "FMT":
                f = _format([p.strip() for p in line.split(",")])
                if f is not None and f.name != "FMT":
                    self.formats.setdefault(f.name, f)
            else:
                by_name[name].append(i)
        for name, idx in by_name.items():
            f = self.formats.get(name)
            if f is None:
                continue
            self.counts[name] += len(idx)
            if self.want is None or name in self.want:
                self._decode(f, [lines[i] for i in idx], np.asarray(idx, dtype=np.int64) + first)

    def _decode(self, f: MessageFormat, rows_text: list[str], pos: np.ndarray) -> None:
        """The rows of one type: fields split, numbers parsed, malformed rows dropped and counted."""
        width = len(f.format) + 1
        rows = [[p.strip() for p in line.split(",", width - 1)] for line in rows_text]
        good = np.array([len(r) == width for r in rows], dtype=bool)
        self.bad += int((~good).sum())
        arr = np.array([r[1:] for r, g in zip(rows, good.tolist(), strict=True) if g], dtype=str)
        arr = arr.reshape(-1, width - 1)
        pos = pos[good]
        ok = np.ones(len(pos), dtype=bool)
        cols: dict[str, np.ndarray] = {}
        for j, col in enumerate(f.columns[:width - 1]):
            if f.format[j] in TEXT_CHARS:
                values = arr[:, j]
            else:
                values, parsed = _numbers(arr[:, j])
                ok &= parsed
            cols.setdefault(col, values)
        self.bad += int((~ok).sum())
        self.parts[f.name].append((pos[ok], {k: v[ok] for k, v in cols.items()}))

    def tables(self) -> tuple[dict[str, Table], dict[str, int], list[str]]:
        """The decoded tables, the record counts and the notes."""
        tables = {}
        for name, parts in self.parts.items():
            cols = {c: np.concatenate([p[1][c] for p in parts]) for c in parts[0][1]}
            tables[name] = Table(self.formats[name], np.concatenate([p[0] for p in parts]), cols, prescaled=True)
        notes = [f"skipped {self.bad} malformed text records (wrong number of fields, or a field that is not a "
                 "number)"] if self.bad else []
        return tables, dict(self.counts), notes


def _cut_last_line(data: bytes, lines: list[str], formats: dict[str, MessageFormat]) -> int:
    """Bytes of a last line cut off by the end of the file (no line break, fewer fields than its FMT), which is
    removed from `lines`; 0 when the file ends cleanly."""
    if not lines or data.endswith((b"\n", b"\r")):
        return 0
    name, sep, rest = lines[-1].partition(",")
    fields = rest.count(",") + 1 if sep else 0
    fmt = formats.get(name.strip()) or _defined_in(lines, name.strip())    # a log of one block: its FMTs are here
    if name.strip() != "FMT" and (fmt is None or fields >= len(fmt.format)):
        return 0
    return len(lines.pop().encode("latin-1"))


def _defined_in(lines: list[str], name: str) -> MessageFormat | None:
    """The format of `name` from the FMT lines among `lines`, or None."""
    for line in lines:
        if line.startswith("FMT") and f" {name}," in line:
            f = _format([p.strip() for p in line.split(",")])
            if f is not None and f.name == name:
                return f
    return None


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
