"""How a sensor's samples relate to their time stamps, and the one conversion into the estimator's convention.

Readers state each stream's `Sampling` (docs/timing.md gives every format's default and its source):
- `INSTANT`: the value at the stamp (ROS `sensor_msgs/Imu`, ArduPilot's IMU, a magnetometer read out once);
- `PRECEDING`: the mean over the interval that ends at the stamp (PX4 `sensor_combined`, delta-angle IMUs);
- `FOLLOWING`: the mean over the interval that starts at the stamp (magcal 0.1's own simulator; no real log).

Inside the estimators a gyro sample k is the mean rate over [t_k, t_k+1) (zero-order hold, the preintegration's
form) and every other sample is the value at its stamp. `for_estimator` converts both, so that no estimator
needs to know the format: an instantaneous rate is held over the half-way points to its neighbours (the
midpoint rule, second order in the sample period), a preceding mean over the interval it was averaged on.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from magcal_cli.streams import FloatArray, Kind, Sampling, Stream

#: the names of the choices, for options and messages
CHOICES = tuple(s.value for s in Sampling)


def _spacing(t: FloatArray) -> FloatArray:
    """(N,) the time to the previous sample (the first takes the second's)."""
    if t.size < 2:
        return np.zeros(t.size)
    d = np.diff(t)
    return np.concatenate([d[:1], d])


def effective_times(s: Stream) -> FloatArray:
    """(N,) the instant each sample stands for: its stamp, or the middle of the window it was averaged over.

    The window is `s.window_s` where the reader knows it (PX4's integral dt), else the spacing to the neighbour on
    the averaged side.
    """
    if s.sampling is Sampling.INSTANT or s.t.size < 2:
        return np.asarray(s.t, dtype=np.float64)
    spacing = _spacing(s.t)
    if s.sampling is Sampling.PRECEDING:
        width = spacing if s.window_s is None else np.minimum(spacing, s.window_s)
        out = s.t - 0.5 * width
    else:
        following = np.concatenate([spacing[1:], spacing[-1:]])
        width = following if s.window_s is None else np.minimum(following, s.window_s)
        out = s.t + 0.5 * width
    return np.maximum.accumulate(out)


def as_instants(s: Stream) -> Stream:
    """`s` re-stamped at the instants its samples stand for (unchanged when already instantaneous)."""
    if s.sampling is Sampling.INSTANT:
        return s
    return replace(s, t=effective_times(s), sampling=Sampling.INSTANT, window_s=None)


def gyro_intervals(gyr: Stream) -> Stream:
    """The gyro in the estimator's convention: sample k is the mean rate over [t_k, t_k+1).

    A preceding mean over its own spacing moves to the start of that interval (exact); a following mean stays;
    an instantaneous rate (or a mean over a window shorter than the spacing) is held from half-way after the
    previous sample's instant to half-way before the next one's.
    """
    if gyr.kind is not Kind.GYROSCOPE:
        msg = f"{gyr.source}: gyro_intervals needs a gyroscope stream, got {gyr.kind.value}"
        raise ValueError(msg)
    t = np.asarray(gyr.t, dtype=np.float64)
    if gyr.sampling is Sampling.FOLLOWING or t.size < 2:
        starts = t
    elif gyr.sampling is Sampling.PRECEDING and gyr.window_s is None:
        starts = t - _spacing(t)
    else:
        mid = effective_times(gyr)
        starts = np.concatenate([[mid[0] - 0.5 * (mid[1] - mid[0])], 0.5 * (mid[:-1] + mid[1:])])
    return replace(gyr, t=np.maximum.accumulate(starts), sampling=Sampling.FOLLOWING, window_s=None)


def describe(s: Sampling) -> str:
    """A phrase for reports: what a sample stands for."""
    return {Sampling.INSTANT: "the value at its stamp",
            Sampling.PRECEDING: "the mean over the interval that ends at its stamp",
            Sampling.FOLLOWING: "the mean over the interval that starts at its stamp"}[s]


def sentence(record: dict[str, str]) -> str:
    """The document's source.timing as one line for reports ('' when it has none)."""
    def what(value: str | None) -> str:
        return describe(Sampling(value)) if value in CHOICES else str(value)

    if not record:
        return ""
    return (f"each IMU sample taken as {what(record.get('imu'))}, each magnetometer sample as "
            f"{what(record.get('magnetometer'))} (set by {record.get('set_by', 'the log')})")


def stated(s: Stream, override: Sampling | None) -> Stream:
    """`s` with the sampling an option states instead of the reader's (the reader's window only for its own)."""
    if override is None or override is s.sampling:
        return s
    return replace(s, sampling=override, window_s=None)


def for_estimator(acc: Stream, gyr: Stream, mags: tuple[Stream, ...], imu: Sampling | None = None,
                  mag: Sampling | None = None) -> tuple[Stream, Stream, tuple[Stream, ...], dict[str, str]]:
    """The IMU and magnetometers in the estimators' convention, and the record the document keeps.

    `imu`/`mag` override what the reader stated (--imu-timing, --mag-timing). The record says what each sample
    was taken to stand for and who said so: {"imu": ..., "magnetometer": ..., "set_by": ...}.
    """
    acc, gyr = stated(acc, imu), stated(gyr, imu)
    mags = tuple(stated(m, mag) for m in mags)
    kinds = sorted({m.sampling.value for m in mags})
    set_by = [name for name, given in (("--imu-timing", imu), ("--mag-timing", mag)) if given is not None]
    record = {"imu": gyr.sampling.value, "magnetometer": kinds[0] if len(kinds) == 1 else ",".join(kinds),
              "set_by": " and ".join(set_by) if set_by else "the log's format"}
    return as_instants(acc), gyro_intervals(gyr), tuple(as_instants(m) for m in mags), record
