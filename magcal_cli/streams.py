"""The data model: typed, frozen streams in SI units with provenance, and the recording that holds them."""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path
from types import MappingProxyType
from typing import NamedTuple, cast

import numpy as np
import numpy.typing as npt

from magcal_cli.errors import SelectionError, StreamError

FloatArray = npt.NDArray[np.float64]
#: samples as a stream holds them: float32 where that is exact, else float64 (`Stream.stored`)
Samples = npt.NDArray[np.float32] | FloatArray


class Kind(Enum):
    """What a stream measures; the value is the name `magcal inspect` prints."""

    MAGNETOMETER = "magnetometer"
    ACCELEROMETER = "accelerometer"
    GYROSCOPE = "gyroscope"
    ATTITUDE = "attitude"
    BATTERY_CURRENT = "battery_current"
    BATTERY_VOLTAGE = "battery_voltage"
    THROTTLE = "throttle"
    TEMPERATURE = "temperature"
    POSITION = "position"
    #: one motor's output, 0..1 of its PWM range (one stream per motor, ids motor[1], motor[2], ...)
    MOTOR_OUTPUT = "motor_output"

    @property
    def width(self) -> int:
        """Number of columns of `Stream.values` for this kind."""
        return _WIDTH.get(self, 1)

    @property
    def si_unit(self) -> str:
        """The SI unit the values are stored in."""
        return _SI_UNIT[self]


class Sampling(Enum):
    """What one sample stands for relative to its stamp (timing.py converts; docs/timing.md per format).

    INSTANT: the value at the stamp; PRECEDING: the mean over the interval that ends at the stamp (delta-angle
    IMUs); FOLLOWING: the mean over the interval that starts at it (magcal 0.1's simulator, no real log).
    """

    INSTANT = "instant"
    PRECEDING = "preceding"
    FOLLOWING = "following"

    @classmethod
    def parse(cls, text: str) -> Sampling:
        """The member named `text` (its value, any case)."""
        return cls(text.strip().lower())


_WIDTH = {Kind.MAGNETOMETER: 3, Kind.ACCELEROMETER: 3, Kind.GYROSCOPE: 3, Kind.ATTITUDE: 4, Kind.POSITION: 3}
_SI_UNIT = {
    Kind.MAGNETOMETER: "tesla", Kind.ACCELEROMETER: "m/s^2", Kind.GYROSCOPE: "rad/s",
    Kind.ATTITUDE: "quaternion wxyz, body to nav", Kind.BATTERY_CURRENT: "A", Kind.BATTERY_VOLTAGE: "V",
    Kind.THROTTLE: "1", Kind.TEMPERATURE: "degC", Kind.POSITION: "deg, deg, m (lat, lon, alt)",
    Kind.MOTOR_OUTPUT: "1",
}


def _frozen(a: npt.ArrayLike) -> FloatArray:
    """`a` as float64 that no one can write: an array already read-only float64 (a slice of another stream's, or one
    a reader handed over frozen) is kept as it is rather than copied, which doubled a long log's memory (issue 39)."""
    if isinstance(a, np.ndarray) and a.dtype == np.float64 and not a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64)


#: samples below which a stream is not worth compacting (`_compact`)
COMPACT_MIN = 4096


def _compact(a: npt.ArrayLike) -> Samples:
    """`a` read-only, held in float32 where that is exact (a float32 log's samples, the logged width: half the memory
    of an hour's IMU, issue 39), else as `_frozen` holds it. Read back as float64 it has the same digits."""
    if isinstance(a, np.ndarray) and a.dtype == np.float32:
        out32 = a if not a.flags.writeable else a.copy()
        out32.flags.writeable = False
        return out32
    held = _READ.get(id(a))
    if held is not None and held[0]() is a:          # a stream's own samples read back (`dataclasses.replace`)
        return held[1]
    a64 = _frozen(a)
    if a64.size < COMPACT_MIN:
        return a64
    head = a64.reshape(-1)[:256]
    with np.errstate(over="ignore", invalid="ignore"):           # beyond float32's range: inf, not equal, kept
        if not np.array_equal(head.astype(np.float32), head):    # most float64 data fail here, at no cost
            return a64
        a32 = a64.astype(np.float32)
    if not np.array_equal(a32, a64):                            # NaN too: kept in float64, as it came
        return a64
    a32.flags.writeable = False
    return a32


#: the float64 copies `Stream.values` handed out that are still alive (id -> (the copy, the samples held)): a stream
#: made from another's values (`dataclasses.replace`) holds the same compact array, not a second one
_READ: dict[int, tuple[weakref.ref[FloatArray], Samples]] = {}


class _Samples:
    """`Stream.values`: stored as `_compact` holds it, read as float64 (a fresh read-only copy of compact samples)."""

    def __get__(self, obj: Stream | None, owner: type | None = None) -> FloatArray:
        if obj is None:
            msg = "values is an attribute of each stream"
            raise AttributeError(msg)
        stored: Samples = obj.__dict__["_values"]
        if stored.dtype == np.float64:
            return cast(FloatArray, stored)
        out = stored.astype(np.float64)
        out.flags.writeable = False
        key = id(out)
        _READ[key] = (weakref.ref(out, lambda _: _READ.pop(key, None)), stored)
        return out

    def __set__(self, obj: Stream, value: npt.ArrayLike) -> None:
        obj.__dict__["_values"] = value


@dataclass(frozen=True, eq=False)
class Stream:
    """Samples of one sensor channel: SI units, sensor frame, non-decreasing time in seconds.

    `t` is relative to the recording's `t0`; `values` has `kind.width` columns; `native_unit` is the
    unit the log used (the calibration document reports magnetometer quantities in it).
    """

    kind: Kind
    id: str
    t: FloatArray
    values: FloatArray
    source: str
    native_unit: str
    #: per-axis quantisation noise std (SI) where the log's integer counts were transformed (so the samples no
    #: longer lie on a grid the detector could measure); None: judged from the samples
    resolution: FloatArray | None = None
    #: what each sample stands for relative to its stamp, as the log's format defines it (timing.py)
    sampling: Sampling = Sampling.INSTANT
    #: the averaging window (s) of a PRECEDING/FOLLOWING sample where the log states it; None: the sample spacing
    window_s: float | None = None

    def __post_init__(self) -> None:
        t, values = _frozen(self.t), _compact(self.__dict__["_values"])
        if values.ndim == 1 and self.kind.width == 1:
            values = values[:, None]
        if t.ndim != 1 or values.shape != (t.size, self.kind.width):
            msg = (f"{self.source}: expected t (N,) and values (N, {self.kind.width}) for a {self.kind.value} "
                   f"stream, got {t.shape} and {values.shape}")
            raise StreamError(msg)
        if t.size > 1 and np.any(np.diff(t) < 0):
            msg = f"{self.source}: timestamps go backwards; sort the samples before building the stream"
            raise StreamError(msg)
        t.flags.writeable = False
        values.flags.writeable = False
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "values", values)

    @property
    def xyz(self) -> FloatArray:
        """The (N, 3) samples of a three-axis stream."""
        if self.kind.width != 3:
            msg = f"{self.source}: a {self.kind.value} stream has no xyz columns"
            raise StreamError(msg)
        return self.values

    @property
    def rate_hz(self) -> float:
        """Median sample rate in Hz (0 for fewer than two samples)."""
        if self.t.size < 2:
            return 0.0
        dt = float(np.median(np.diff(self.t)))
        return 1.0 / dt if dt > 0 else 0.0

    def __len__(self) -> int:
        return int(self.t.size)

    def between(self, start: float | None, end: float | None) -> Stream:
        """The samples with start <= t <= end (either bound may be None)."""
        lo = 0 if start is None else int(np.searchsorted(self.t, start, side="left"))
        hi = self.t.size if end is None else int(np.searchsorted(self.t, end, side="right"))
        return replace(self, t=self.t[lo:hi], values=cast(FloatArray, self.stored[lo:hi]))   # as held: no copy

    @property
    def stored(self) -> Samples:
        """The samples as held: float32 where that is exact (`_compact`), else float64; `values` reads them as float64."""
        out: Samples = self.__dict__["_values"]
        return out


#: installed after the dataclass is made, which would take a class attribute for the field's default
Stream.values = _Samples()  # type: ignore[assignment]


class Cut(NamedTuple):
    """Where a log ends inside a record: the byte that record starts at, the file size and what was lost."""

    offset: int | None     # the first byte of the incomplete record (None: not known, e.g. inside a bag's chunk)
    size: int              # bytes in the file (for a bag directory: in its storage files)
    lost: str              # what the incomplete record held, e.g. "an IMU record, 47 of its 54 bytes present"
    end_s: float | None = None   # time of the last complete sample, s from the start of the recording

    @property
    def where(self) -> str:
        """Where the log ends inside a record, as words."""
        at = f" at byte {self.offset} of {self.size}" if self.offset is not None else ""
        return f"it ends inside a record{at} ({self.lost})"

    @property
    def message(self) -> str:
        """One sentence for the warning and the report."""
        end = f"; the data end at {self.end_s:.3f} s" if self.end_s is not None else ""
        return f"the log is cut: {self.where}; read up to its last complete record{end}"


@dataclass(frozen=True, eq=False)
class Recording:
    """Everything a reader found in one log; nothing downstream knows the file format.

    `t0` is the absolute time (s, the log's clock) that stream times are relative to; `params` are
    firmware parameters (name -> value, last value in the log); `notes` are the reader's remarks
    (dropped samples, truncation) that the report repeats; `cut` says where a log that ends inside a record
    was cut (None for a complete log); `info` is what the log says about the vehicle as text (an ArduPilot
    boot message's `board` and `board_uid`), which the history keys a vehicle by.
    """

    path: Path
    format: str
    streams: tuple[Stream, ...]
    t0: float = 0.0
    params: Mapping[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    cut: Cut | None = None
    #: the Unix time of t = 0 where the log states it (GPS week and time of week) although its clock is a boot
    #: clock; None where unknown (then `t0` is a Unix time or the date is not known)
    utc0: float | None = None
    info: Mapping[str, str] = field(default_factory=dict)
    #: magnetometers judged dead or stuck on their readings as logged, before any correction was undone (id -> why,
    #: e.g. "all readings are zero"): their streams hold the readings as logged, and the pipeline refuses them
    dead: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "streams", tuple(self.streams))
        object.__setattr__(self, "dead", MappingProxyType(dict(self.dead)))
        object.__setattr__(self, "params", MappingProxyType(dict(self.params)))
        object.__setattr__(self, "info", MappingProxyType(dict(self.info)))
        object.__setattr__(self, "notes", tuple(self.notes))

    def of_kind(self, kind: Kind) -> list[Stream]:
        """All streams of one kind, in reader order."""
        return [s for s in self.streams if s.kind is kind]

    def ids(self, kind: Kind) -> list[str]:
        """The ids of the streams of one kind."""
        return [s.id for s in self.of_kind(kind)]

    def select(self, kind: Kind, stream_id: str | None = None, flag: str = "") -> Stream:
        """The stream of `kind` with `stream_id` (the first one when None), or a StreamError that lists the others."""
        found = self.of_kind(kind)
        if not found:
            have = ", ".join(sorted({f"{s.id} ({s.kind.value})" for s in self.streams})) or "none"
            msg = f"{self.path.name}: no {kind.value} stream; available: {have}"
            raise StreamError(msg)
        if stream_id is None:
            return found[0]
        for s in found:
            if s.id == stream_id:
                return s
        hint = f" Use {flag} with one of them." if flag else ""
        msg = (f"{self.path.name}: no {kind.value} stream {stream_id!r}; "
               f"available: {', '.join(s.id for s in found)}.{hint}")
        raise SelectionError(msg) if flag else StreamError(msg)
