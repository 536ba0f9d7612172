"""The calibrated topics' contents: per magnetometer, the stamps, the field in tesla and its covariance.

The values are `apply`'s CSV rows (`calibration.apply.apply_rows`, unrounded), so the topic and the CSV agree;
the covariance is the calibration's, propagated to each reading (`calibration.fieldcov`).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.apply import apply_rows
from magcal_cli.calibration.fieldcov import field_covariance
from magcal_cli.calibration.types import Calibration
from magcal_cli.errors import OutputError
from magcal_cli.streams import FloatArray, Recording

#: a stamp within this of one of the source topic's own times (ns) is taken to be that time (rec.t0 is a float
#: of ~1.7e9 s, resolving only ~0.24 us, so t0 + t misses the logged integer stamp by up to ~120 ns)
SNAP_NS = 1000


@dataclass(frozen=True)
class Series:
    """One calibrated magnetometer: where it came from, the topic it goes to, and its readings."""

    mag_id: str
    #: the topic its readings were logged on, and the field path inside that message ((): the message itself)
    source_topic: str
    path: tuple[str, ...]
    topic: str
    #: stamps (N,) integer ns on the log's clock, field (N, 3) tesla, covariance (N, 3, 3) tesla^2
    stamps: np.ndarray
    field: FloatArray
    cov: FloatArray


def split_id(stream_id: str, topics: set[str]) -> tuple[str, tuple[str, ...]]:
    """(topic, field path) of a stream id: a topic itself, or `TOPIC.FIELD[.FIELD]` (readers/ros/nested.py)."""
    if stream_id in topics or "." not in stream_id:
        return stream_id, ()
    head, *rest = stream_id.split(".")
    return head, tuple(rest)


def ros_name(stream_id: str) -> str:
    """A valid ROS topic for a stream id: `/imu.mag_field` -> `/imu/mag_field`, `MAG[0]` -> `/MAG0`."""
    name = stream_id.replace(".", "/").replace("[", "").replace("]", "")
    name = "".join(c if c.isalnum() or c in "/_" else "_" for c in name)
    return name if name.startswith("/") else f"/{name}"


def out_topic(stream_id: str, topic: str | None, replace: bool) -> str:
    """The calibrated topic: --topic, the original topic with --replace, else `<topic>/calibrated`."""
    if topic:
        return topic if topic.startswith("/") else f"/{topic}"
    return ros_name(stream_id) if replace else f"{ros_name(stream_id)}/calibrated"


def calibrated_series(cal: Calibration, rec: Recording, mags: list[str] | None, topics: set[str],
                      topic: str | None = None, replace: bool = False) -> tuple[list[Series], list[str]]:
    """(one Series per calibrated magnetometer found in `rec`, apply's notes); `topics` are the log's topics."""
    rows, _, notes = apply_rows(cal, rec, mags)
    by_id: dict[str, list[tuple[float, FloatArray]]] = defaultdict(list)
    for t, mid, v in rows:
        by_id[mid].append((t, v))
    t0_ns = round(rec.t0 * 1e9)
    out = []
    for mid, got in by_id.items():
        mag = cal.magnetometer(mid)
        ts = np.array([r[0] for r in got])
        m = np.array([r[1] for r in got]).reshape(-1, 3)
        si = units.to_si(mag.unit)
        src, path = split_id(mid, topics)
        out.append(Series(mid, src, path, out_topic(mid, topic, replace), t0_ns + np.round(ts * 1e9).astype(np.int64),
                          m * si, field_covariance(mag, m) * si**2))
    return out, notes


def snapped(stamps: np.ndarray, logged: np.ndarray) -> np.ndarray:
    """`stamps` (ns) shifted by the one offset (under SNAP_NS) that lands them on the `logged` times of their
    source topic (header stamps or receive times); unchanged when none is that close."""
    logged = np.unique(np.asarray(logged, dtype=np.int64))
    if not logged.size or not stamps.size:
        return stamps
    at = np.clip(np.searchsorted(logged, stamps), 1, max(logged.size - 1, 1))
    lo, hi = logged[at - 1], logged[np.minimum(at, logged.size - 1)]
    near = np.where(np.abs(stamps - lo) <= np.abs(hi - stamps), lo, hi)
    off = near - stamps
    close = np.abs(off) <= SNAP_NS
    if not np.any(close):
        return stamps
    shift = int(np.median(off[close]))
    return stamps + shift


def refuse_clash(series: list[Series], kept: set[str]) -> None:
    """OutputError when a calibrated topic would join a topic the copy keeps (two types, or two streams, on one
    name)."""
    for s in series:
        if s.topic in kept:
            msg = f"{s.topic}: the log has this topic already. Choose another --topic, or use --replace"
            raise OutputError(msg)
