"""From decoded DataFlash tables to streams: message times, instances, and the Recording in SI units."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from magcal_cli import so3
from magcal_cli.align import clean_rows
from magcal_cli.progress import current
from magcal_cli.readers.checks import dead_field, drop_held, kind_columns, sensor_rows
from magcal_cli.readers.dataflash.format import IntArray, MessageFormat, RawLog, Table
from magcal_cli.streams import FloatArray, Kind, Recording, Sampling, Stream


class Clock:
    """Time of messages that carry none (old PARM, px4log): that of the latest timed message before them.

    Built from a RawLog, the (position, time) table of every timed message is made only when a message without
    its own time asks (modern logs never do), which spares memory on gigantic logs.
    """

    def __init__(self, pos: IntArray, t: FloatArray, raw: RawLog | None = None) -> None:
        order = np.argsort(pos, kind="stable")
        self._pos, self._t = pos[order], t[order]
        self._raw = raw

    def _table(self) -> tuple[IntArray, FloatArray]:
        """Positions and times of the timed messages, sorted by position."""
        if self._raw is not None:
            pos, ts = [], []
            for table in self._raw.tables.values():
                t = own_time(table)
                if t is not None and len(table):
                    pos.append(table.pos)
                    ts.append(t)
            p, t = np.concatenate(pos), np.concatenate(ts)
            order = np.argsort(p, kind="stable")
            self._pos, self._t, self._raw = p[order], t[order], None
        return self._pos, self._t

    def __bool__(self) -> bool:
        return self._raw is not None or bool(self._pos.size)

    def at(self, pos: IntArray) -> FloatArray:
        """The time (s) in force at each file position; before the first timed message, the first time."""
        times_pos, times = self._table()
        if not times_pos.size:
            return np.full(pos.shape, np.nan)
        i = np.searchsorted(times_pos, pos, side="right") - 1
        return times[np.clip(i, 0, None)]


def own_time(table: Table) -> FloatArray | None:
    """A message's boot time (s) from its own fields: TimeUS, TimeMS, or T of old GPS (TimeMS is GPS time)."""
    f = table.fmt
    if f.has("TimeUS"):
        return table.num("TimeUS") * 1e-6
    if f.name.startswith("GPS"):
        return table.num("T") * 1e-3 if f.has("T") else None
    if f.has("TimeMS"):
        return table.num("TimeMS") * 1e-3
    return None


def time_of(table: Table, clock: Clock) -> FloatArray:
    """Seconds on the log's boot clock for every message of `table`."""
    t = own_time(table)
    return t if t is not None else clock.at(table.pos)


def clock_from(raw: RawLog) -> Clock:
    """A clock made of every decoded message that carries its own time (empty when none does)."""
    if not any(own_time_known(t) for t in raw.tables.values()):
        return Clock(np.zeros(0, dtype=np.int64), np.zeros(0))
    return Clock(np.zeros(0, dtype=np.int64), np.zeros(0), raw)


def own_time_known(table: Table) -> bool:
    """Whether the messages of `table` carry their own time (and there are any)."""
    f = table.fmt
    return bool(len(table)) and (f.has("TimeUS") or f.has("TimeMS") or (f.name.startswith("GPS") and f.has("T")))


#: ArduPilot logs at most this many instances of a sensor (COMPASS/INS/GPS_MAX_INSTANCES; BATT up to 16)
MAX_INSTANCES = 16


def instances(raw: RawLog, names: tuple[str, ...], columns: tuple[str, ...] = ("I", "Inst"),
              notes: list[str] | None = None, limit: int = MAX_INSTANCES) -> list[tuple[int, Table]]:
    """(instance, messages) of a sensor logged as NAME, NAME2, NAME3 or one NAME with an instance column.

    Records whose instance is outside 0..limit-1 are corrupt: dropped, and counted in `notes`.
    """
    out: list[tuple[int, Table]] = []
    for k, name in enumerate(names):
        table = raw.table(name)
        if table is None:
            continue
        col = next((c for c in columns if table.fmt.has(c)), None)
        if col is None:
            out.append((k, table))
            continue
        inst = np.nan_to_num(table.num(col), nan=-1.0).astype(np.int64)
        bad = (inst < 0) | (k + inst >= limit)
        if bad.any() and notes is not None:
            notes.append(f"{name}: dropped {int(bad.sum())} records with instance {col} outside 0..{limit - 1} "
                         "(corrupt data)")
        out += [(k + int(i), table.where(inst == i)) for i in np.unique(inst[~bad]).tolist()]
    return sorted(out, key=lambda x: x[0])


def euler_quat(roll_deg: FloatArray, pitch_deg: FloatArray, yaw_deg: FloatArray) -> FloatArray:
    """(N, 4) quaternions wxyz (body to NED) of ArduPilot/PX4 Euler angles, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    rpy = np.deg2rad(np.stack([roll_deg, pitch_deg, yaw_deg], axis=1))
    if not rpy.size:
        return np.zeros((0, 4))
    return so3.as_quat(so3.from_rpy(rpy))


def logged_columns(table: Table, names: tuple[str, ...]) -> FloatArray:
    """`stack_columns`, kept in float32 when every column was logged so (an IMU's `f` fields): the width a Stream
    holds them in, so an hour's IMU is never held in float64 beside its compact copy (issue 39: 69 MB of a 60-min
    flight's reading). Typed as what `Stream.values` reads back: the same values in float64."""
    logged = [table.logged32(c) for c in names]
    if any(col is None for col in logged):
        return stack_columns(table, names)
    out = np.empty((len(table), len(names)), dtype=np.float32)
    for i, col in enumerate(logged):
        out[:, i] = col
    return cast(FloatArray, out)


def instance_tag(fmt: MessageFormat, inst: int) -> str:
    """`[I=n]` for instanced record types (4.x), else nothing."""
    return f"[I={inst}]" if fmt.has("I") else ""


def stack_columns(table: Table, names: tuple[str, ...], factor: float = 1.0) -> FloatArray:
    """(N, len(names)) float columns times a factor, filled a column at a time (not a list of columns, then a copy)."""
    out = np.empty((len(table), len(names)))
    for i, c in enumerate(names):
        out[:, i] = table.num(c) * factor
    return out


def int_factor(table: Table, column: str, integer_default: float) -> float:
    """Factor to the base unit: an FMTU multiplier for integer fields, else the firmware convention."""
    char = table.fmt.char(column)
    if char in "bBhHiIqQ":
        return table.fmt.mults.get(column, integer_default)
    return 1.0


@dataclass(frozen=True, eq=False)
class Pending:
    """Samples of streams that share their times (an IMU's accelerometer and gyro), absolute time (s): `values`
    (N, sum of the kinds' widths), or one (N, width) array per kind (made so by the reader: no copy to split)."""

    kinds: tuple[Kind, ...]
    id: str
    t: FloatArray
    values: FloatArray | tuple[FloatArray, ...]
    source: str
    units: tuple[str, ...]
    resolution: FloatArray | None = None      # Stream.resolution, for a single-kind stream

    def blocks(self) -> list[FloatArray]:
        """Each kind's (N, width) values: the reader's own arrays, or views of the one array."""
        return list(self.values) if isinstance(self.values, tuple) else kind_columns(self.kinds, self.values)


def finish(path: Path, fmt: str, pending: list[Pending], params: dict[str, float],
           notes: list[str], dead: dict[str, str] | None = None) -> Recording:
    """Recording with times relative to the first IMU or magnetometer sample, cleaned and noted.

    A magnetometer in `dead` (id -> why, judged by the caller on the field as logged), or one whose readings
    `dead_field` finds no field in, is kept as logged, uncleaned, and listed in `Recording.dead` for the pipeline
    to refuse by name (cleaning would drop an all-NaN one, and the compass would vanish).

    `pending` is emptied as its streams are built, so each one's arrays are freed once copied (memory); the
    samples done are reported per stream as the "reading" fraction of `progress.current()`."""
    anchor = [p.t for p in pending if Kind.MAGNETOMETER in p.kinds or Kind.ACCELEROMETER in p.kinds]
    t0 = min((float(np.nanmin(t)) for t in (anchor or [p.t for p in pending]) if np.isfinite(t).any()), default=0.0)
    del anchor
    streams: list[Stream] = []
    dead = dict(dead or {})
    hook, done, total = current(), 0, sum(len(p.t) for p in pending)
    pending.reverse()
    while pending:
        hook("reading", done, total)
        p = pending.pop()
        done += len(p.t)
        where = p.id if len(p.kinds) > 1 else f"{p.id} {p.kinds[0].value}"
        if not len(p.t):                # every record dropped before (unhealthy, no time): nothing to clean
            notes.append(f"{p.id}: no usable {'/'.join(k.value for k in p.kinds)} samples")
            continue
        blocks = p.blocks()
        why = dead.get(p.id) or dead_field(blocks[0], "tesla") if p.kinds == (Kind.MAGNETOMETER,) else None
        if why:
            dead[p.id] = why
            ok = np.isfinite(p.t)
            order = np.argsort(p.t[ok], kind="stable")
            streams.append(Stream(Kind.MAGNETOMETER, p.id, p.t[ok][order] - t0, blocks[0][ok][order], p.source,
                                  p.units[0], None, Sampling.INSTANT))
            continue
        # the rows cleaning keeps, taken from each kind's array once: an IMU record's samples are never held twice
        # (issue 39: a (N, 6) array beside its two halves was a two-hour log's peak)
        t = p.t - t0
        finite = np.isfinite(t)
        for b in blocks:
            finite &= np.all(np.isfinite(b), axis=1)
        t, rows, cleaned = clean_rows(t, finite, where)
        del finite
        blocks = [b if rows is None else b[rows] for b in blocks]
        if p.kinds == (Kind.MAGNETOMETER,):
            t, held_values, held = drop_held(t, blocks[0], p.id)
            blocks = [held_values]
            cleaned += held
        t, rows, checked = sensor_rows(p.kinds, t, blocks, where)
        blocks = [b if rows is None else b[rows] for b in blocks]
        cleaned += checked
        notes.extend(cleaned)
        if t.size == 0:
            notes.append(f"{p.id}: no usable {'/'.join(k.value for k in p.kinds)} samples")
            continue
        # the stamps of a record read before (an IMU's temperature is the IMU's own): one array, not two (issue 39)
        t = next((s.t for s in streams if s.t.shape == t.shape and np.array_equal(s.t, t)), t)
        t.flags.writeable = False               # handed over frozen: the kinds of one record share it, uncopied
        for kind, unit, block in zip(p.kinds, p.units, blocks, strict=False):
            own = np.ascontiguousarray(block)   # the reader's own array as it is; a view of a wider one copied
            own.flags.writeable = False
            # IMU/GYR/ACC and MAG hold the (filtered) value at the stamp (docs/timing.md)
            streams.append(Stream(kind, p.id, t, own, p.source, unit, p.resolution, Sampling.INSTANT))
        del blocks
    return Recording(path, fmt, tuple(streams), t0=t0, params=params, notes=tuple(notes), dead=dead)
