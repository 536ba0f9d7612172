"""Checks every reader applies to decoded magnetometer samples: unit-length field, held (repeated) readings, a dead
or stuck sensor."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from magcal_cli.streams import FloatArray, Kind

IntArray = npt.NDArray[np.int64]

#: relative spread of |m| below which the field was normalised upstream; real sensors show >= 0.1 % noise
NORMALISED_SPREAD = 1e-4
#: share of readings that repeat their predecessor bit for bit above which the source holds stale values
HELD_SHARE = 0.5


def field_spread(xyz: npt.ArrayLike) -> tuple[float, float]:
    """Median magnitude and relative spread (std / median) of the field vectors (N, 3)."""
    norms = np.linalg.norm(np.asarray(xyz, dtype=np.float64).reshape(-1, 3), axis=1)
    if norms.size == 0:
        return 0.0, float("inf")
    median = float(np.median(norms))
    return median, float(np.std(norms) / median) if median > 0 else float("inf")


def normalised_field(xyz: npt.ArrayLike) -> bool:
    """True when at least 10 readings all have the same magnitude: the field was scaled to unit length upstream."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return xyz.shape[0] >= 10 and field_spread(xyz)[1] < NORMALISED_SPREAD


def normalised_note(stream_id: str, xyz: FloatArray, unit: str) -> str:
    """The reader note for a field normalised upstream."""
    median, spread = field_spread(xyz)
    return (f"{stream_id}: every field reading has magnitude {median:.6g} {unit} (relative spread {spread:.0e}): "
            "the field was normalised to a unit vector upstream, so hard iron is not recoverable in absolute terms")


def drop_held(t: FloatArray, xyz: FloatArray, where: str) -> tuple[FloatArray, FloatArray, list[str]]:
    """Drop readings that repeat the previous one exactly when most do (a source that holds its last value).

    A held value is a stale reading stamped later than it was taken; keeping it would add up to one update
    period of delay, the time offset interpolation avoids. Below HELD_SHARE repeats are kept (quantisation).
    """
    if len(t) < 3:
        return t, xyz, []
    same = np.concatenate([[False], np.all(xyz[1:] == xyz[:-1], axis=1)])
    if same.mean() < HELD_SHARE:
        return t, xyz, []
    if same[1:].all():
        return t, xyz, [f"{where}: all {len(t)} readings are identical; the sensor is stuck, disconnected or not "
                        "sampled"]
    keep = ~same
    note = (f"{where}: {int(same.sum())} of {len(t)} readings repeat the previous one exactly (the source holds "
            f"its last value between updates); kept the {int(keep.sum())} that changed")
    return t[keep], xyz[keep], [note]


#: a turn is the IMU rotating faster than this (rad/s, 20 deg/s): above vibration and any gyro bias, so a stuck
#: field is judged against real motion
TURN_RATE = np.deg2rad(20.0)
#: ... through at least this angle in all (rad, 90 deg): a live sensor's field then changes by tens of percent
TURN_ANGLE = np.deg2rad(90.0)
#: a field whose every axis spans at most this many counts while the vehicle turns is stuck, not measuring
STUCK_COUNTS = 2.0


def rotates(t: npt.ArrayLike, gyro: npt.ArrayLike) -> bool:
    """Whether a gyro (N, 3) rad/s at times t (N,) s shows the vehicle turning: TURN_ANGLE at rates above
    TURN_RATE."""
    tt, w = np.asarray(t, dtype=np.float64), np.linalg.norm(np.asarray(gyro, dtype=np.float64), axis=1)
    if tt.size < 2:
        return False
    dt = np.clip(np.diff(tt), 0.0, 1.0)                 # a gap in the log is no turn
    fast = np.nan_to_num(w[:-1]) > TURN_RATE
    return bool(np.sum(w[:-1][fast] * dt[fast]) >= TURN_ANGLE)


def dead_field(xyz: npt.ArrayLike, unit: str, quantum: float | None = None, rotated: bool = False) -> str | None:
    """Why a magnetometer's readings (N, 3) as logged, before any correction, measure no field, or None.

    Every reading NaN (or inf), all zero, every reading identical, or, with the sensor's count `quantum` known
    and the IMU showing the vehicle turning (`rotated`), every axis within STUCK_COUNTS counts: a live sensor's
    field swings by tens of percent when the vehicle turns through 90 degrees.
    """
    x = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if not len(x):
        return None
    x = x[np.isfinite(x).all(axis=1)]
    if not len(x):
        return "every reading is NaN"
    if not np.any(x):
        return "all readings are zero"
    if np.all(x == x[0]):
        return f"constant at ({', '.join(f'{v:.6g}' for v in x[0])}) {unit}"
    if rotated and quantum and float(np.ptp(x, axis=0).max()) <= STUCK_COUNTS * quantum:
        mid = 0.5 * (x.min(axis=0) + x.max(axis=0))
        spread = float(np.ptp(x, axis=0).max() / quantum)
        return (f"constant at ({', '.join(f'{v:.6g}' for v in mid)}) {unit} within {spread:.0f} "
                f"count{'s' * (spread != 1)} while the IMU shows the vehicle turning")
    return None


def nan_throughout(t: npt.ArrayLike, values: npt.ArrayLike, where: str) -> tuple[FloatArray, FloatArray, list[str]] | None:
    """A magnetometer with no finite reading, as logged: its finitely stamped samples in time order and a note, to
    keep it for the pipeline to refuse by name (cleaning drops every sample, and the compass vanished); None when
    any reading is finite."""
    x = np.asarray(values, dtype=np.float64)
    if not len(x) or np.isfinite(x).all(axis=1).any():
        return None
    tt = np.asarray(t, dtype=np.float64)
    ok = np.isfinite(tt)
    order = np.argsort(tt[ok], kind="stable")
    return tt[ok][order], x[ok][order], [f"{where}: every reading is NaN; kept as logged, to be refused by name"]


#: readings beyond these magnitudes (SI) are not physical, so they are corrupt (e.g. a bit flip in a float's
#: exponent): 10 T keeps fields normalised to 1 "tesla"; 2000 m/s^2 is 200 g; 200 rad/s is 11,000 deg/s
PLAUSIBLE_SI = {Kind.MAGNETOMETER: 10.0, Kind.ACCELEROMETER: 2000.0, Kind.GYROSCOPE: 200.0}
#: a field reading below this share of the median magnitude is corrupt (the Earth's field does not vanish)
VANISHED_SHARE = 0.01
#: a range wall holds at least this many readings (and this share of them) to count as saturation
SATURATED_MIN, SATURATED_SHARE = 10, 0.005
#: ... and more than this many times the readings in the band just inside it (a pile-up, not a tail)
SATURATED_PILEUP = 3.0


def _walls(x: FloatArray) -> list[float]:
    """The ends of one axis's range where readings pile up: the sensor's saturation values."""
    lo, hi = float(np.min(x)), float(np.max(x))
    span = hi - lo
    least = max(SATURATED_MIN, SATURATED_SHARE * x.size)
    if not span > 0 or max(np.count_nonzero(x == hi), np.count_nonzero(x == lo)) < least:
        return []                       # no pile-up at either end: skip the sort below (0.3 s a 100 MB bag)
    x = np.asarray(x, dtype=np.float64)     # a float32 IMU's samples (readers keep their width): float64 arithmetic
    distinct = np.unique(x)
    band = max(0.02 * span, 5.0 * float(np.min(np.diff(distinct))))
    out = []
    for wall, inside in ((hi, (x < hi) & (x >= hi - band)), (lo, (x > lo) & (x <= lo + band))):
        at = int(np.count_nonzero(x == wall))
        if at >= least and at > SATURATED_PILEUP * np.count_nonzero(inside):
            out.append(wall)
    return out


def sensor_checks(kinds: tuple[Kind, ...], t: FloatArray, values: FloatArray,
                  where: str) -> tuple[FloatArray, FloatArray, list[str]]:
    """Drop rows where a magnetometer, accelerometer or gyro (3 columns each, in `kinds` order) reads beyond
    physical limits (corrupt values) or sits at a wall of its range (saturated: the true value is beyond it)."""
    t, rows, notes = sensor_rows(kinds, t, kind_columns(kinds, values), where)
    return t, values if rows is None else values[rows], notes


def kind_columns(kinds: Sequence[Kind], values: FloatArray) -> list[FloatArray]:
    """Views of each kind's columns of `values` (N, sum of the kinds' widths), in `kinds` order."""
    edges = np.cumsum([0, *(k.width for k in kinds)])
    return [values[:, a:b] for a, b in zip(edges[:-1], edges[1:], strict=True)]


def sensor_rows(kinds: tuple[Kind, ...], t: FloatArray, blocks: Sequence[FloatArray], where: str
                ) -> tuple[FloatArray, IntArray | None, list[str]]:
    """`sensor_checks` of values held as one array per kind (`blocks`, in `kinds` order, sharing their rows): the
    kept stamps, which rows they are (None: all) and the notes."""
    notes: list[str] = []
    checked = [(kind, b) for kind, b in zip(kinds, blocks, strict=True) if kind in PLAUSIBLE_SI]
    if not checked or not len(t):
        return t, None, notes
    rows: IntArray | None = None

    def drop(mask: npt.NDArray[np.bool_]) -> None:
        nonlocal t, rows, checked
        keep = np.flatnonzero(~mask)
        t, rows = t[keep], keep if rows is None else rows[keep]
        checked = [(kind, b[keep]) for kind, b in checked]

    with np.errstate(all="ignore"):
        bad = np.zeros(len(t), dtype=bool)
        for kind, b in checked:
            bad |= ~(np.abs(b) <= PLAUSIBLE_SI[kind]).all(axis=1)
    if bad.any():
        names = "/".join(k.value for k, _ in checked)
        notes.append(f"{where}: dropped {int(bad.sum())} {names} samples beyond physical limits (corrupt values)")
        drop(bad)
    gone = np.zeros(len(t), dtype=bool)
    for kind, b in checked:
        if kind is Kind.GYROSCOPE:                     # a quantised gyro at rest may read exactly zero
            continue
        if kind is Kind.MAGNETOMETER:
            norm = np.linalg.norm(b, axis=1)
            vanished = (norm == 0.0) | (norm < (VANISHED_SHARE * float(np.median(norm)) if len(norm) else 0.0))
        else:                                          # exact in any width (a float32 IMU's squares may underflow)
            vanished = ~np.any(b, axis=1)
        if not vanished.all():                         # all zero: a dead sensor, which fit reports as such
            gone |= vanished
    if gone.any():
        notes.append(f"{where}: dropped {int(gone.sum())} samples whose field or specific force vanishes (exactly "
                     "zero, or the field below 1 % of its median: zeroed or corrupt records)")
        drop(gone)
    if len(t) < 2 * SATURATED_MIN:
        return t, rows, notes
    clipped = np.zeros(len(t), dtype=bool)
    for kind, b in checked:
        hits = []
        for axis in range(3):
            x = b[:, axis]
            for wall in _walls(x):
                clipped |= x == wall
                hits.append(f"{'xyz'[axis]} = {wall:.6g} {kind.si_unit}")
        if hits:
            notes.append(f"{where}: {kind.value} readings sit at the limit of the sensor's range ({', '.join(hits)}):"
                         " it saturated there, so the true value is unknown")
    if clipped.any():
        notes.append(f"{where}: dropped the {int(clipped.sum())} saturated samples")
        drop(clipped)
    return t, rows, notes
