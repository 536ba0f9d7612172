"""MCAP reader for ROS 2 (CDR) sensor messages; header stamps are the sample times."""

from __future__ import annotations

import struct
from collections import defaultdict
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..errors import LogReadError
from ..streams import Kind, Recording, Stream
from . import ReadOptions

IMU_TYPES = {"sensor_msgs/msg/Imu", "sensor_msgs/Imu"}
MAG_TYPES = {"sensor_msgs/msg/MagneticField", "sensor_msgs/MagneticField"}


def _stamp_ns(msg: Any) -> int:
    """Header stamp in integer nanoseconds (exact; a float of 1.7e9 s only resolves 0.24 us)."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


class McapReader:
    """Reads sensor_msgs Imu (accelerometer + gyroscope) and MagneticField (tesla) channels."""

    name: ClassVar[str] = "mcap"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Decode every IMU and magnetometer message; a truncated file is an error unless allowed."""
        from mcap.exceptions import McapError
        from mcap.reader import NonSeekingReader
        from mcap_ros2.decoder import DecoderFactory

        rows: dict[tuple[str, str], list[tuple[int, tuple[float, ...]]]] = defaultdict(list)
        notes: list[str] = []
        count = 0
        try:
            with path.open("rb") as fh:
                reader = NonSeekingReader(fh, decoder_factories=[DecoderFactory()])
                try:
                    for schema, channel, message, decoded in reader.iter_decoded_messages(
                            topics=None, log_time_order=False):
                        count += 1
                        self._collect(rows, schema.name, channel.topic, message.log_time, decoded, options)
                except (McapError, EOFError, ValueError, KeyError, struct.error) as exc:
                    where = f"after {count} complete messages"
                    if not options.allow_truncated:
                        msg = (f"{path}: the MCAP file is truncated or corrupt ({type(exc).__name__}) {where}. "
                               "Re-copy the log, or pass --allow-truncated to use the complete part")
                        raise LogReadError(msg) from None
                    notes.append(f"truncated or corrupt: read {count} complete messages")
        except OSError as exc:
            msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
            raise LogReadError(msg) from None
        return self._recording(path, rows, notes)

    @staticmethod
    def _collect(rows: dict[tuple[str, str], list[Any]], schema: str, topic: str, log_time: int, msg: Any,
                 options: ReadOptions) -> None:
        """Append one decoded message's sample(s) to the per-(kind, topic) row lists."""
        t_ns = log_time if options.receive_time else _stamp_ns(msg)
        if schema in IMU_TYPES:
            a, w = msg.linear_acceleration, msg.angular_velocity
            rows[("imu", topic)].append((t_ns, (a.x, a.y, a.z, w.x, w.y, w.z)))
        elif schema in MAG_TYPES:
            m = msg.magnetic_field
            rows[("mag", topic)].append((t_ns, (m.x, m.y, m.z)))

    @staticmethod
    def _recording(path: Path, rows: dict[tuple[str, str], list[Any]], notes: list[str]) -> Recording:
        """Sort, drop non-finite samples and build the streams relative to the earliest stamp."""
        stamps = {key: np.array([r[0] for r in val], dtype=np.int64) for key, val in rows.items() if val}
        t0_ns = min((int(ts.min()) for ts in stamps.values()), default=0)
        streams: list[Stream] = []
        for key in sorted(stamps, key=lambda k: (k[0] != "imu", k[1])):
            kind, topic = key
            order = np.argsort(stamps[key], kind="stable")
            t = (stamps[key][order] - t0_ns) * 1e-9
            arr = np.array([r[1] for r in rows[key]], dtype=np.float64)[order]
            good = np.all(np.isfinite(arr), axis=1)
            if not good.all():
                notes.append(f"{topic}: dropped {int((~good).sum())} samples with NaN or inf")
                arr, t = arr[good], t[good]
            src = f"{path.name}#{topic}"
            if kind == "imu":
                streams.append(Stream(Kind.ACCELEROMETER, topic, t, arr[:, 0:3], src, "m/s^2"))
                streams.append(Stream(Kind.GYROSCOPE, topic, t, arr[:, 3:6], src, "rad/s"))
            else:
                streams.append(Stream(Kind.MAGNETOMETER, topic, t, arr, src, "tesla"))
        return Recording(path, "mcap", tuple(streams), t0=t0_ns * 1e-9, notes=tuple(notes))

