"""Time alignment: streams sampled on other clocks or rates are interpolated onto the IMU time base."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .errors import StreamError
from .streams import Stream

FloatArray = npt.NDArray[np.float64]


def interpolate(stream: Stream, t: npt.ArrayLike) -> FloatArray:
    """Linear interpolation of `stream` at times `t` (s), which must lie inside the stream's span.

    Interpolation, not nearest-sample lookup: picking the nearest sample adds up to half a sample period
    of time offset. Attitude quaternions should be slerped instead (not done here).
    """
    t = np.asarray(t, dtype=np.float64)
    if stream.t.size < 2:
        msg = f"{stream.source}: needs at least two samples to interpolate, has {stream.t.size}"
        raise StreamError(msg)
    if t.size and (t.min() < stream.t[0] or t.max() > stream.t[-1]):
        msg = (f"{stream.source}: asked for times {t.min():.3f}..{t.max():.3f} s outside the stream's "
               f"{stream.t[0]:.3f}..{stream.t[-1]:.3f} s; cut the other streams to the common window first")
        raise StreamError(msg)
    return np.stack([np.interp(t, stream.t, stream.values[:, i]) for i in range(stream.values.shape[1])], axis=1)


def common_window(*streams: Stream) -> tuple[float, float]:
    """The time span (s) that every stream covers."""
    start = max(float(s.t[0]) for s in streams)
    end = min(float(s.t[-1]) for s in streams)
    if end <= start:
        names = ", ".join(s.source for s in streams)
        msg = f"{names}: the streams do not overlap in time; check the log's clocks or --start/--end"
        raise StreamError(msg)
    return start, end


def clean_time(t: npt.ArrayLike, values: npt.ArrayLike, where: str) -> tuple[FloatArray, FloatArray, list[str]]:
    """Sort samples by time, drop exact duplicate stamps (keeping the first) and non-finite rows; say what was done.

    Returns (t, values, notes); readers pass the notes on to `Recording.notes` so the report repeats them.
    """
    t = np.asarray(t, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    values2 = values.reshape(len(t), -1)
    notes: list[str] = []
    finite = np.isfinite(t) & np.all(np.isfinite(values2), axis=1)
    if not finite.all():
        notes.append(f"{where}: dropped {int((~finite).sum())} samples with NaN or inf")
        t, values2 = t[finite], values2[finite]
    if t.size > 1 and np.any(np.diff(t) < 0):
        notes.append(f"{where}: {int(np.sum(np.diff(t) < 0))} timestamps went backwards; samples were sorted by time")
        order = np.argsort(t, kind="stable")
        t, values2 = t[order], values2[order]
    if t.size > 1:
        dup = np.concatenate([[False], np.diff(t) == 0])
        if dup.any():
            notes.append(f"{where}: dropped {int(dup.sum())} samples with duplicated timestamps")
            t, values2 = t[~dup], values2[~dup]
    return t, values2.reshape((len(t),) + values.shape[1:]), notes
