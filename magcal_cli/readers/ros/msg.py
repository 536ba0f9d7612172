"""ROS sensor messages magcal reads (ROS 1, ROS 2, JSON), shared by the rosbag and MCAP readers.

`Collector.add` takes one decoded message (rosbags object or JSON namespace with the same field names) and
keeps its header stamp, receive time and values; `Collector.recording` turns them into SI streams.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli import units
from magcal_cli.align import clean_time
from magcal_cli.errors import StreamError
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.checks import (
    drop_held,
    field_spread,
    nan_throughout,
    normalised_field,
    normalised_note,
    sensor_checks,
)
from magcal_cli.streams import FloatArray, Kind, Recording, Sampling, Stream

IntArray = npt.NDArray[np.int64]


def _xyz(v: Any) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


#: normalised ROS type -> (group, fields read, values of one message)
ROS_TYPES: dict[str, tuple[str, str, Callable[[Any], tuple[float, ...]]]] = {
    "sensor_msgs/msg/Imu": ("imu", "linear_acceleration, angular_velocity",
                            lambda m: _xyz(m.linear_acceleration) + _xyz(m.angular_velocity)),
    "sensor_msgs/msg/MagneticField": ("mag", "magnetic_field", lambda m: _xyz(m.magnetic_field)),
    "geometry_msgs/msg/Vector3Stamped": ("vec3", "vector", lambda m: _xyz(m.vector)),
    "sensor_msgs/msg/BatteryState": ("battery", "current, voltage", lambda m: (m.current, m.voltage)),
    "sensor_msgs/msg/Temperature": ("temperature", "temperature", lambda m: (m.temperature,)),
    "sensor_msgs/msg/NavSatFix": ("navsat", "latitude, longitude, altitude",
                                  lambda m: (m.latitude, m.longitude, m.altitude, m.status.status)),
    "mavros_msgs/msg/ActuatorControl": ("throttle", "controls[3] of group_mix 0",
                                        lambda m: (m.controls[3], m.group_mix)),
}
#: a Vector3Stamped is the field only on a topic whose name contains this (older drivers, e.g. /imu/mag)
VEC3_TOPIC_HINT = "mag"
#: below this median magnitude a Vector3Stamped field is in tesla, else gauss (Earth: 0.25-0.65 G, 25-65 uT)
VEC3_TESLA_BELOW = 1e-2
#: header-stamp clocks that differ from the reference topic's by more than this (s) are another clock
CLOCK_MISMATCH_S = 1.0
#: how many ignored topics a note names before it says "and N more"
IGNORED_LISTED = 5
#: how many topics the error for a log without any stream magcal reads names
TOPICS_LISTED = 12


def normalise_type(name: str) -> str:
    """ROS 1 `pkg/Type` -> ROS 2 `pkg/msg/Type` (rosbags' naming)."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def wanted(topic: str, msgtype: str) -> bool:
    """Whether magcal reads messages of `msgtype` on `topic`."""
    entry = ROS_TYPES.get(normalise_type(msgtype))
    return entry is not None and (entry[0] != "vec3" or VEC3_TOPIC_HINT in topic.lower())


def ignored_note(topics: list[str]) -> str:
    """One note naming the topics of types magcal does not read."""
    shown = ", ".join(topics[:IGNORED_LISTED])
    more = f" and {len(topics) - IGNORED_LISTED} more" if len(topics) > IGNORED_LISTED else ""
    return f"ignored {len(topics)} topics of types magcal does not read: {shown}{more}"


def no_stream_error(path: Path, topics: dict[str, str]) -> StreamError:
    """The error for a log none of whose topics is, or holds as a field, a type magcal reads."""
    names = [f"{t} ({ty})" for t, ty in topics.items()]
    more = f" and {len(names) - TOPICS_LISTED} more" if len(names) > TOPICS_LISTED else ""
    looked = ", ".join(f"{ty} ({fields}{'; on a topic named *mag*' if group == 'vec3' else ''})"
                       for ty, (group, fields, _) in ROS_TYPES.items())
    msg = (f"{path}: no stream magcal reads; its topics are {', '.join(names[:TOPICS_LISTED])}{more}; looked for "
           f"these types as topics or as fields of any message at any depth: {looked}. Publish the sensors as "
           "these standard messages, or export them to CSV (docs/readers-ros-csv.md)")
    return StreamError(msg)


def stamp_ns(msg: Any) -> int:
    """Header stamp in integer ns (exact; a float of 1.7e9 s only resolves 0.24 us); JSON spellings too."""
    st = msg.header.stamp
    sec = st.sec if hasattr(st, "sec") else st.secs
    nsec = st.nanosec if hasattr(st, "nanosec") else (st.nsec if hasattr(st, "nsec") else st.nsecs)
    return int(sec) * 1_000_000_000 + int(nsec)


class Collector:
    """Per (topic, type) header stamps, receive times and values of the messages magcal reads.

    Batches (vec) are kept as arrays; single messages are buffered in lists and become a block before the
    next batch of their topic, so each topic keeps its arrival order."""

    def __init__(self) -> None:
        self.blocks: dict[tuple[str, str], list[tuple[IntArray, IntArray, FloatArray]]] = defaultdict(list)
        self.stamps: dict[tuple[str, str], list[int]] = defaultdict(list)
        self.recv: dict[tuple[str, str], list[int]] = defaultdict(list)
        self.values: dict[tuple[str, str], list[tuple[float, ...]]] = defaultdict(list)
        #: every topic of the log -> its type, and whether one is read (the error for a log with none)
        self.topics: dict[str, str] = {}
        self.used = False

    def saw(self, topic: str, msgtype: str, used: bool) -> None:
        """Note a topic of the log, and whether it is read (itself or fields nested in it)."""
        self.topics.setdefault(topic, msgtype)
        self.used |= used

    def clear(self) -> None:
        """Forget everything collected (a read that failed midway starts again another way)."""
        for d in (self.blocks, self.stamps, self.recv, self.values):
            d.clear()

    def add(self, topic: str, msgtype: str, recv_ns: int, msg: Any) -> None:
        """Keep one decoded message of a type in ROS_TYPES."""
        key = (topic, normalise_type(msgtype))
        values, stamp = ROS_TYPES[key[1]][2](msg), stamp_ns(msg)       # both first: a bad message adds nothing
        self.values[key].append(values)
        self.stamps[key].append(stamp)
        self.recv[key].append(recv_ns)

    def add_batch(self, topic: str, msgtype: str, recv_ns: IntArray, stamps: IntArray, values: FloatArray) -> None:
        """Keep many messages of one topic: receive and header times (ns) and their ROS_TYPES values."""
        if not recv_ns.size:
            return
        key = (topic, normalise_type(msgtype))
        self._flush(key)
        # kept as given when of these types: every caller passes arrays of its own (copies were 7 % of a read)
        self.blocks[key].append((stamps.astype(np.int64, copy=False), recv_ns.astype(np.int64, copy=False),
                                 values.astype(np.float64, copy=False)))

    def _flush(self, key: tuple[str, str]) -> None:
        """Turn the buffered single messages of `key` into a block."""
        if self.values.get(key):
            self.blocks[key].append((np.array(self.stamps.pop(key), dtype=np.int64),
                                     np.array(self.recv.pop(key), dtype=np.int64),
                                     np.array(self.values.pop(key), dtype=np.float64)))

    def arrays(self, key: tuple[str, str]) -> tuple[IntArray, IntArray, FloatArray]:
        """(header stamps, receive times, values) of one topic, in arrival order."""
        self._flush(key)
        blocks = self.blocks[key]
        if len(blocks) > 1:         # one block from now on: the pieces are freed as soon as they are joined
            joined = (np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks]),
                      np.concatenate([b[2].reshape(len(b[0]), -1) for b in blocks]))
            blocks[:] = [joined]
        return blocks[0]

    def keys(self) -> list[tuple[str, str]]:
        """The topics that have messages."""
        return [k for k in dict.fromkeys([*self.blocks, *self.values]) if self.blocks.get(k) or self.values.get(k)]

    def __len__(self) -> int:
        return sum(len(v) for v in self.values.values()) + sum(len(b[0]) for bs in self.blocks.values() for b in bs)

    def recording(self, path: Path, fmt: str, options: ReadOptions, notes: list[str]) -> Recording:
        """Streams relative to the earliest sample, cleaned, in SI, with every remark in `notes`.

        Empties the collector: each topic's arrays are freed once its streams are built (peak memory). A log
        whose topics were listed (`saw`) but none of which is read is refused, naming them."""
        if self.topics and not self.used and not len(self):
            raise no_stream_error(path, self.topics)
        keys = sorted(self.keys(), key=lambda k: (ROS_TYPES[k[1]][0] != "imu", k[0]))
        arrays = {k: self.arrays(k) for k in keys}
        times = _time_bases(arrays, options, notes)
        t0 = min((int(ts.min()) for ts in times.values() if ts.size), default=0)
        streams: list[Stream] = []
        for key in keys:
            t = (times.pop(key) - t0).astype(np.float64) * 1e-9
            values = arrays.pop(key)[2]
            self.blocks.pop(key, None)
            streams += _streams(path, key, t, values, notes)
            del t, values
        return Recording(path, fmt, tuple(streams), t0=t0 * 1e-9, notes=tuple(notes))


def _time_bases(arrays: dict[tuple[str, str], tuple[IntArray, IntArray, FloatArray]], options: ReadOptions,
                notes: list[str]) -> dict[tuple[str, str], IntArray]:
    """Header stamps, or receive time when asked, when a topic's stamps are zero or on another clock."""
    keys = list(arrays)
    recv = {k: arrays[k][1] for k in keys}
    if options.receive_time:
        return recv
    stamps = {k: arrays[k][0] for k in keys}
    offsets = {k: float(np.median(stamps[k] - recv[k])) * 1e-9 for k in keys if np.any(stamps[k])}
    ref = next(iter(offsets), None)
    out = {}
    for k in keys:
        if k not in offsets:
            notes.append(f"{k[0]}: every header stamp is zero; using the bag's receive time for this topic")
            out[k] = recv[k]
        elif ref is not None and abs(offsets[k] - offsets[ref]) > CLOCK_MISMATCH_S:
            notes.append(f"{k[0]}: header stamps are {offsets[k] - offsets[ref]:+.3f} s off the clock of "
                         f"{ref[0]}; using receive time shifted onto that clock for this topic")
            out[k] = recv[k] + int(round(offsets[ref] * 1e9))
        else:
            out[k] = stamps[k]
    return out


def _streams(path: Path, key: tuple[str, str], t: FloatArray, values: FloatArray, notes: list[str]) -> list[Stream]:
    """The streams of one topic: cleaned time, dropped NaN, SI units, checks on the field."""
    topic, msgtype = key
    group, fields, _ = ROS_TYPES[msgtype]
    src = f"{path.name}#{topic} [{msgtype} {fields}]"
    if group == "navsat":
        fix = values[:, 3] >= 0
        if not fix.all():
            notes.append(f"{topic}: dropped {int((~fix).sum())} samples without a GNSS fix")
        t, values = t[fix], values[fix, :3]
    if group == "throttle":                     # PX4 mixer group 0 holds the throttle at index 3
        group0 = values[:, 1] == 0
        if not group0.any():
            notes.append(f"{topic}: no ActuatorControl of mixer group 0 (flight control); no throttle stream")
            return []
        t, values = t[group0], values[group0, :1]
    if group == "battery":
        return [s for s in (_one(Kind.BATTERY_CURRENT, topic, t, values[:, 0], src, "A", notes),
                            _one(Kind.BATTERY_VOLTAGE, topic, t, values[:, 1], src, "V", notes)) if s]
    dead = nan_throughout(t, values, topic) if group in ("mag", "vec3") else None
    if dead is not None:
        notes += dead[2]
        return [Stream(Kind.MAGNETOMETER, topic, dead[0], dead[1], src, "tesla", sampling=Sampling.INSTANT)]
    t, values, cleaned = clean_time(t, values, topic)
    notes += cleaned
    if not len(t):
        notes.append(f"{topic}: no valid samples")
        return []
    if group == "imu":
        t, values, checked = sensor_checks((Kind.ACCELEROMETER, Kind.GYROSCOPE), t, values, topic)
        notes += checked
        # sensor_msgs/Imu and REP 145: the stamp is the time of the measurement (docs/timing.md)
        return [Stream(Kind.ACCELEROMETER, topic, t, values[:, :3], src, "m/s^2", sampling=Sampling.INSTANT),
                Stream(Kind.GYROSCOPE, topic, t, values[:, 3:], src, "rad/s", sampling=Sampling.INSTANT)]
    if group == "temperature":
        return [Stream(Kind.TEMPERATURE, topic, t, values, src, "degC")]
    if group == "navsat":
        return [Stream(Kind.POSITION, topic, t, values, src, "deg")]
    if group == "throttle":
        return [Stream(Kind.THROTTLE, topic, t, values, src, "1")]
    unit = "tesla"
    if group == "mag" and (median := field_spread(values)[0]) >= VEC3_TESLA_BELOW:
        # MagneticField is tesla by definition, but some drivers (VectorNav's) publish gauss: 0.3 T is no Earth
        # field, 0.3 G is; docs/decisions.md "Standard messages wherever a bag holds them"
        unit = "gauss"
        notes.append(f"{topic}: sensor_msgs/msg/MagneticField read as the field in gauss, not the tesla it is "
                     f"defined in (median magnitude {median:.4g}: 1e4 times the Earth's field in tesla)")
        values = values * units.to_si(unit)
    if group == "vec3":
        median = field_spread(values)[0]
        unit = "tesla" if median < VEC3_TESLA_BELOW else "gauss"
        notes.append(f"{topic}: geometry_msgs/msg/Vector3Stamped read as the field in {unit} "
                     f"(median magnitude {median:.4g}; old drivers publish gauss)")
        values = values * units.to_si(unit)
    t, values, held = drop_held(t, values, topic)
    t, values, checked = sensor_checks((Kind.MAGNETOMETER,), t, values, topic)
    notes += held + checked
    if normalised_field(values):
        notes.append(normalised_note(topic, values, "T"))
    return [Stream(Kind.MAGNETOMETER, topic, t, values, src, unit, sampling=Sampling.INSTANT)]


def _one(kind: Kind, topic: str, t: FloatArray, v: FloatArray, src: str, unit: str,
         notes: list[str]) -> Stream | None:
    """One scalar battery stream; ROS current is negative when discharging, magcal's is the current drawn."""
    t, v, cleaned = clean_time(t, v, f"{topic} {kind.value}")
    notes += cleaned
    if not len(t):
        return None
    if kind is Kind.BATTERY_CURRENT and np.median(v) < 0:
        notes.append(f"{topic}: current negated (ROS reports discharge as negative; magcal uses the current drawn)")
        v = -v
    return Stream(kind, topic, t, v, src, unit)
