"""DataFlash message formats and decoded tables, shared by the binary and text parsers and the log writer.

Format characters follow AP_Logger/LogStructure.h and pymavlink DFReader.FORMAT_TO_STRUCT: `c`/`C`/`e`/`E`
carry a built-in factor 0.01 and `L` 1e-7 (degrees), which the writer's format character implies and
FMTU multipliers do not repeat.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

HEAD1, HEAD2 = 0xA3, 0x95
FMT_ID = 0x80
#: the FMT record: Type B, Length B, Name n, Format N, Columns Z (89 bytes with the 3-byte header)
FMT_LENGTH = 89

#: format character -> (numpy dtype, built-in multiplier)
FORMAT_CHARS: dict[str, tuple[str, float]] = {
    "a": ("(32,)<i2", 1.0), "b": ("i1", 1.0), "B": ("u1", 1.0), "g": ("<f2", 1.0), "h": ("<i2", 1.0),
    "H": ("<u2", 1.0), "i": ("<i4", 1.0), "I": ("<u4", 1.0), "f": ("<f4", 1.0), "d": ("<f8", 1.0),
    "n": ("S4", 1.0), "N": ("S16", 1.0), "Z": ("S64", 1.0), "c": ("<i2", 0.01), "C": ("<u2", 0.01),
    "e": ("<i4", 0.01), "E": ("<u4", 0.01), "L": ("<i4", 1e-7), "M": ("u1", 1.0), "q": ("<i8", 1.0),
    "Q": ("<u8", 1.0),
}
STRING_CHARS = frozenset("nNZ")
INTEGER_CHARS = frozenset("bBhHiIMqQ")


@dataclass(frozen=True)
class MessageFormat:
    """One FMT record: type id, name, total length (header included), format characters and column names.

    `units` and `mults` come from FMTU/UNIT/MULT records when the log has them (ArduPilot 3.6+).
    """

    type_id: int
    name: str
    length: int
    format: str
    columns: tuple[str, ...]
    units: Mapping[str, str] = field(default_factory=dict)
    mults: Mapping[str, float] = field(default_factory=dict)

    @property
    def payload_size(self) -> int:
        """Bytes the format characters occupy (may be less than length - 3)."""
        return int(sum(np.dtype(FORMAT_CHARS[c][0]).itemsize for c in self.format))

    def dtype(self) -> np.dtype[np.void]:
        """Packed little-endian record dtype of the payload (header excluded), padded to length - 3."""
        names: list[str] = []
        for i, col in enumerate(self.columns[:len(self.format)]):
            name = col or f"_{i}"
            names.append(name if name not in names else f"{name}_{i}")
        names += [f"_{i}" for i in range(len(names), len(self.format))]
        formats = [FORMAT_CHARS[c][0] for c in self.format]
        offsets = np.cumsum([0] + [np.dtype(f).itemsize for f in formats[:-1]]).tolist()
        spec: dict[str, Any] = {"names": names, "formats": formats, "offsets": offsets[:len(formats)],
                                "itemsize": max(self.length - 3, 0)}
        return np.dtype(spec)  # type: ignore[call-overload,no-any-return]

    def char(self, column: str) -> str:
        """The format character of a column."""
        return self.format[self.columns.index(column)]

    def has(self, *columns: str) -> bool:
        """True when every named column exists."""
        return all(c in self.columns for c in columns)


def valid_format(name: str, fmt: str, columns: tuple[str, ...], length: int) -> bool:
    """A plausible FMT record: printable name, known format characters that fit in the stated length."""
    if not name or not name.isascii() or not name.isprintable() or length < 3:
        return False
    if any(c not in FORMAT_CHARS for c in fmt):
        return False
    size = sum(np.dtype(FORMAT_CHARS[c][0]).itemsize for c in fmt)
    return size + 3 <= length and len(columns) <= 64


def _number(value: object) -> float:
    """A cell as a float, NaN when it is not a number."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return float("nan")


@dataclass(frozen=True, eq=False)
class Table:
    """The decoded messages of one type, in file order.

    `pos` orders messages across types (byte offset for binary logs, line number for text logs);
    `columns` holds one array per column: numbers as stored (binary) or already scaled (text), strings as str.
    """

    fmt: MessageFormat
    pos: IntArray
    columns: Mapping[str, np.ndarray]
    prescaled: bool = False

    def __len__(self) -> int:
        return int(self.pos.size)

    def num(self, column: str) -> FloatArray:
        """A numeric column as float64 with the format character's built-in multiplier applied."""
        try:
            with np.errstate(invalid="ignore"):         # a signalling NaN (a bit flip) raises the flag in the cast
                values = np.asarray(self.columns[column], dtype=np.float64)
        except (ValueError, TypeError):        # text where a number belongs (a damaged FMT): NaN, dropped later
            values = np.array([_number(v) for v in self.columns[column]], dtype=np.float64)
        factor = self._factor(column)
        return values * factor if factor != 1.0 else values

    def logged32(self, column: str) -> np.ndarray | None:
        """The column as logged when that is float32 with no multiplier (an IMU's `f` fields), else None."""
        values = self.columns[column]
        plain = self._factor(column) == 1.0
        return values if plain and isinstance(values, np.ndarray) and values.dtype == np.float32 else None

    def _factor(self, column: str) -> float:
        """The format character's built-in multiplier of a column (1 where the values come scaled)."""
        return 1.0 if self.prescaled else FORMAT_CHARS[self.fmt.char(column)][1]

    def text(self, column: str) -> list[str]:
        """A string column decoded as UTF-8 (Latin-1 for invalid bytes), NUL-terminated."""
        out: list[str] = []
        for v in self.columns[column]:
            if isinstance(v, bytes):
                raw = v.split(b"\0", 1)[0]
                try:
                    out.append(raw.decode("utf-8"))
                except UnicodeDecodeError:
                    out.append(raw.decode("latin-1"))
            else:
                out.append(str(v).strip())
        return out

    def where(self, mask: npt.NDArray[np.bool_]) -> Table:
        """The messages selected by a boolean mask (the table itself when it selects them all: a copy of a long
        log's IMU records was 0.15 GB, issue 39)."""
        if mask.all():
            return self
        return Table(self.fmt, self.pos[mask], {k: v[mask] for k, v in self.columns.items()}, self.prescaled)


@dataclass(eq=False)
class RawLog:
    """What a parser found: every format, the decoded tables asked for, message counts and damage."""

    formats: dict[str, MessageFormat]
    tables: dict[str, Table]
    counts: dict[str, int]
    size: int
    skipped_bytes: int = 0
    truncated_bytes: int = 0
    notes: list[str] = field(default_factory=list)
    cut_lost: str = ""          # what the bytes after the last complete record held (a cut log)
    text: bool = False          # parsed from a text log (its parse, not the streams, takes the time)

    def table(self, name: str) -> Table | None:
        """The decoded messages of `name`, or None when the log has none."""
        t = self.tables.get(name)
        return t if t is not None and len(t) else None
