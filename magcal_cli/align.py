"""Time alignment: streams sampled on other clocks or rates are interpolated onto the IMU time base."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.errors import StreamError
from magcal_cli.streams import FloatArray, Kind, Stream

BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]


def interpolate(stream: Stream, t: npt.ArrayLike) -> FloatArray:
    """Linear interpolation of `stream` at times `t` (s), which must lie inside the stream's span.

    Interpolation, not nearest-sample lookup: picking the nearest sample adds up to half a sample period
    of time offset. Attitude quaternions are slerped (geodesic on SO(3)), everything else is linear.
    """
    t = np.asarray(t, dtype=np.float64)
    if stream.t.size < 2:
        msg = f"{stream.source}: needs at least two samples to interpolate, has {stream.t.size}"
        raise StreamError(msg)
    if t.size and (t.min() < stream.t[0] or t.max() > stream.t[-1]):
        msg = (f"{stream.source}: asked for times {t.min():.3f}..{t.max():.3f} s outside the stream's "
               f"{stream.t[0]:.3f}..{stream.t[-1]:.3f} s; cut the other streams to the common window first")
        raise StreamError(msg)
    if stream.kind is Kind.ATTITUDE:
        return _slerp(stream, t)
    return columns(t, stream.t, stream.values)


def columns(t: FloatArray, ts: FloatArray, values: FloatArray, left: float | None = None,
            right: float | None = None) -> FloatArray:
    """Each column of `values` (sampled at `ts`) linearly interpolated at `t`: the one per-column `np.interp`."""
    return np.stack([np.interp(t, ts, values[:, i], left=left, right=right) for i in range(values.shape[1])], axis=1)


#: times interpolated at once by `_slerp`: each rotation on its own (the same digits in any block), and a whole
#: two-hour log's readings at once made seven log-sized stacks, the heading check's peak (issue 39)
SLERP_BLOCK = 1 << 16


def _slerp(stream: Stream, t: FloatArray) -> FloatArray:
    """Quaternions (w, x, y, z) at `t`, along the geodesic between the neighbouring samples (`so3.slerp`)."""
    rots = so3.from_quat(stream.values)
    if t.size <= SLERP_BLOCK:
        return so3.as_quat(so3.slerp(rots, stream.t, t))
    out = np.empty((t.size, 4))
    for a in range(0, t.size, SLERP_BLOCK):
        out[a:a + SLERP_BLOCK] = so3.as_quat(so3.slerp(rots, stream.t, t[a:a + SLERP_BLOCK]))
    return out


def onto(stream: Stream, t: npt.ArrayLike, max_gap_s: float | None = None) -> tuple[BoolArray, FloatArray]:
    """`stream` interpolated onto the epochs `t` (e.g. the IMU's): (mask of usable epochs, values there).

    An epoch is usable when it lies inside the stream's span and its two neighbouring samples are at most
    `max_gap_s` apart (default: 4 median sample periods), so dropouts are never bridged and nothing is
    extrapolated.
    """
    t = np.asarray(t, dtype=np.float64)
    if stream.t.size < 2:
        return np.zeros(t.size, dtype=bool), np.zeros((0, stream.kind.width))
    gap = max_gap_s if max_gap_s is not None else 4.0 * float(np.median(np.diff(stream.t)))
    inside = (t >= stream.t[0]) & (t <= stream.t[-1])
    j = np.clip(np.searchsorted(stream.t, t, side="right") - 1, 0, stream.t.size - 2)
    dt = stream.t[j + 1] - stream.t[j]
    on_sample = (t == stream.t[j]) | (t == stream.t[j + 1])
    mask = inside & ((dt <= gap) | on_sample)
    return mask, interpolate(stream, t[mask])


def common_window(*streams: Stream) -> tuple[float, float]:
    """The time span (s) that every stream covers."""
    start = max(float(s.t[0]) for s in streams)
    end = min(float(s.t[-1]) for s in streams)
    if end <= start:
        names = ", ".join(s.source for s in streams)
        msg = f"{names}: the streams do not overlap in time; check the log's clocks or --start/--end"
        raise StreamError(msg)
    return start, end


#: a time step larger than this many median sample periods (and than JUMP_MIN_S) is a jump, not jitter
JUMP_PERIODS, JUMP_MIN_S = 100.0, 1.0


def _time_faults(t: FloatArray, where: str) -> tuple[FloatArray, IntArray | None, list[str]]:
    """Drop lone samples whose stamp lies far from both neighbours' (corrupt stamps), then, if the clock jumps
    back (a reboot or clock reset), keep the longest part: sorting would interleave two recordings. Returns the
    kept stamps and which rows they are (None: all)."""
    if t.size < 3:
        return t, None, []
    d = np.diff(t)
    pos = d[d > 0]
    jump = max(JUMP_MIN_S, JUMP_PERIODS * float(np.median(pos))) if pos.size else JUMP_MIN_S
    del pos
    notes = []
    far_prev = np.concatenate([[np.abs(t[1] - t[0]) > jump and np.abs(t[2] - t[1]) <= jump], np.abs(d) > jump])
    far_next = np.concatenate([np.abs(d) > jump, [np.abs(t[-1] - t[-2]) > jump and np.abs(t[-2] - t[-3]) <= jump]])
    bridged = np.concatenate([[True], np.abs(t[2:] - t[:-2]) <= jump, [True]])
    lone = far_prev & far_next & bridged
    rows = None
    if lone.any():
        notes.append(f"{where}: dropped {int(lone.sum())} samples whose time stamp lies far from both neighbours' "
                     "(corrupt time stamps)")
        rows = np.flatnonzero(~lone)
        t = t[rows]
        d = np.diff(t)
    back = np.flatnonzero(d < -jump)
    if back.size:
        bounds = np.concatenate([[0], back + 1, [t.size]])
        k = int(np.argmax(np.diff(bounds)))
        lo, hi = int(bounds[k]), int(bounds[k + 1])
        notes.append(f"{where}: the clock jumps back {back.size} time{'s' * (back.size > 1)} (by up to "
                     f"{float(-d[back].min()):.3g} s: a reboot or clock reset); kept the longest part, {hi - lo} of "
                     f"{t.size} samples")
        rows = np.arange(lo, hi) if rows is None else rows[lo:hi]
        t = t[lo:hi]
    return t, rows, notes


def clean_rows(t: npt.ArrayLike, finite: BoolArray, where: str) -> tuple[FloatArray, IntArray | None, list[str]]:
    """`clean_time` for values held elsewhere (`finite`: the rows whose stamp and values are all finite): the
    cleaned stamps, the rows they are, in order (None: every row, as it was), and the notes. A reader whose sensors
    share stamps across several arrays (an IMU's accelerometer and gyro) takes the same rows from each, copying
    nothing when nothing is dropped."""
    tt: FloatArray = np.asarray(t, dtype=np.float64)
    notes: list[str] = []
    rows = None
    if not finite.all():
        notes.append(f"{where}: dropped {int((~finite).sum())} samples with NaN or inf")
        rows = np.flatnonzero(finite)
        tt = tt[rows]
    tt, kept, jumped = _time_faults(tt, where)
    notes += jumped
    if kept is not None:
        rows = kept if rows is None else rows[kept]
    if tt.size > 1 and np.any(np.diff(tt) < 0):
        notes.append(f"{where}: {int(np.sum(np.diff(tt) < 0))} timestamps went backwards; samples were sorted by time")
        order = np.argsort(tt, kind="stable")
        tt = tt[order]
        rows = order if rows is None else rows[order]
    if tt.size > 1:
        dup = np.concatenate([[False], np.diff(tt) == 0])
        if dup.any():
            notes.append(f"{where}: dropped {int(dup.sum())} samples with duplicated timestamps")
            keep = np.flatnonzero(~dup)
            tt = tt[keep]
            rows = keep if rows is None else rows[keep]
    return tt, rows, notes


def clean_time(t: npt.ArrayLike, values: npt.ArrayLike, where: str) -> tuple[FloatArray, FloatArray, list[str]]:
    """Sort samples by time, drop exact duplicate stamps (keeping the first) and non-finite rows; say what was done.

    Returns (t, values, notes); readers pass the notes on to `Recording.notes` so the report repeats them.
    """
    tt: FloatArray = np.asarray(t, dtype=np.float64)
    vals: FloatArray = np.asarray(values, dtype=np.float64)
    values2 = vals.reshape(tt.size, -1)
    tt, rows, notes = clean_rows(tt, np.isfinite(tt) & np.all(np.isfinite(values2), axis=1), where)
    if rows is not None:
        values2 = values2[rows]
    return tt, values2.reshape((tt.size, *vals.shape[1:])), notes
