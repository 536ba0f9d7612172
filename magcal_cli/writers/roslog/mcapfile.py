"""MCAP outputs: a copy of an MCAP log with the calibrated topics added (mcap's reader and writer, the original
records' bytes unchanged), and, from any other log (DataFlash, ULog, CSV), a new ROS 2 MCAP file of the IMU and
the magnetometers as standard messages (mcap-ros2-support's writer)."""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli.atomic import atomic_path
from magcal_cli.errors import LogReadError
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.writers.roslog.bags import (
    DEFAULT_FRAME,
    MAGNETIC_FIELD,
    field_message,
    frame_of,
    header_stamps,
)
from magcal_cli.writers.roslog.series import Series, refuse_clash, ros_name, snapped, split_id

IMU = "sensor_msgs/msg/Imu"


def _scan(path: Path, series: list[Series], imu_id: str) -> tuple[dict[str, str], list[Series], dict[int, int]]:
    """(frame per calibrated topic, series snapped to the logged stamps, receive time per header stamp), as
    bags._scan, with mcap-ros2-support's decoder."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    logged: dict[str, list[int]] = {s.source_topic: [] for s in series}
    frames: dict[str, str] = {}
    received: dict[int, int] = {}
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()} if summary is not None else set()
        imu_topic, imu_path = split_id(imu_id, topics)
        wanted = [*{s.source_topic for s in series}, imu_topic]
        for _, channel, message, msg in reader.iter_decoded_messages(topics=wanted):
            if channel.topic == imu_topic and "imu" not in frames:
                frames["imu"] = frame_of(msg, imu_path)
            for s in series:
                if channel.topic == s.source_topic:
                    stamps = header_stamps(msg, s.path)
                    logged[s.source_topic] += [message.log_time, *stamps]
                    for st in stamps:
                        received.setdefault(st, message.log_time)
                    frames.setdefault(s.mag_id, frame_of(msg, s.path))
    out = [Series(s.mag_id, s.source_topic, s.path, s.topic, snapped(s.stamps, np.array(logged[s.source_topic])),
                  s.field, s.cov) for s in series]
    return {s.topic: frames.get("imu") or frames.get(s.mag_id) or DEFAULT_FRAME for s in out}, out, received


def copy_mcap(src: Path, out: Path, series: list[Series], imu_id: str, replace: bool) -> None:
    """Copy the MCAP file `src` to `out`: every schema, channel and message as read (less the magnetometers'
    topics with `replace`), plus the calibrated topics (CDR, or ROS 1 for a ROS 1 MCAP), in log-time order."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer
    from rosbags.typesys import Stores, get_typestore

    try:
        frames, series, received = _scan(src, series, imu_id)
    except (McapError, ValueError, KeyError, EOFError) as exc:
        msg = f"{src}: cannot read the MCAP file to copy it ({exc}). Check the log with magcal inspect"
        raise LogReadError(msg) from None
    drop = {s.source_topic for s in series} if replace else set()
    with src.open("rb") as fh, atomic_path(out) as tmp, tmp.open("wb") as dst:
        reader = make_reader(fh)
        header = reader.get_header()
        ros1 = header.profile == "ros1"
        store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        writer = Writer(dst, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library or "magcal apply")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}

        def originals() -> Iterator[tuple[int, int, Any, None]]:
            """The source's messages in log-time order, their schema and channel registered on first sight."""
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                if channel.topic in drop:
                    continue
                if channel.id not in channels:
                    refuse_clash(series, {channel.topic})
                    if schema is not None and schema.id not in schemas:
                        schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                    channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                                   schemas[schema.id] if schema else 0,
                                                                   dict(channel.metadata))
                yield message.log_time, 0, (channels[channel.id], message), None

        text = store.generate_msgdef(MAGNETIC_FIELD, ros_version=1 if ros1 else 2)[0]
        sid = writer.register_schema(MAGNETIC_FIELD, "ros1msg" if ros1 else "ros2msg", text.encode())
        added = {s.topic: writer.register_channel(s.topic, "ros1" if ros1 else "cdr", sid) for s in series}
        extra = sorted((received.get(int(ns), int(ns)), 1, (k, i), None)
                       for k, s in enumerate(series) for i, ns in enumerate(s.stamps))
        serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
        for ts, kind, what, _ in heapq.merge(originals(), extra, key=lambda e: (e[0], e[1])):
            if kind == 0:
                cid, m = what
                writer.add_message(cid, log_time=m.log_time, data=m.data, publish_time=m.publish_time,
                                   sequence=m.sequence)
                continue
            k, i = what
            s = series[k]
            data = bytes(serialize(field_message(store.types, ros1, s, i, frames[s.topic]), MAGNETIC_FIELD))
            writer.add_message(added[s.topic], log_time=ts, data=data, publish_time=int(s.stamps[i]), sequence=i)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap ships no annotations for finish


def _msg(ns: int, frame: str) -> dict[str, Any]:
    """A std_msgs/Header as mcap-ros2-support's encoder takes it."""
    return {"stamp": {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}, "frame_id": frame}


def _vec(v: np.ndarray) -> dict[str, float]:
    """geometry_msgs/Vector3."""
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def new_mcap(rec: Recording, out: Path, series: list[Series], imu_id: str, replace: bool) -> None:
    """A ROS 2 MCAP file of a non-ROS log: the IMU (sensor_msgs/Imu), each magnetometer as logged (tesla; not
    with `replace`) and calibrated (sensor_msgs/MagneticField), stamped t0 + t on the log's clock."""
    from mcap_ros2.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    frame = ros_name(imu_id).strip("/").replace("/", "_")
    t0_ns = round(rec.t0 * 1e9)
    acc = [s for s in rec.of_kind(Kind.ACCELEROMETER) if s.id == imu_id] or rec.of_kind(Kind.ACCELEROMETER)
    gyr = [s for s in rec.of_kind(Kind.GYROSCOPE) if s.id == imu_id] or rec.of_kind(Kind.GYROSCOPE)
    sources: list[Iterator[tuple[int, str, dict[str, Any]]]] = []
    if acc and gyr:
        sources.append(_imu_messages(acc[0], gyr[0], t0_ns, ros_name(imu_id), frame))
    for s in series:
        if not replace:
            raw = rec.select(Kind.MAGNETOMETER, s.mag_id)
            sources.append(_field_messages(t0_ns + np.round(raw.t * 1e9).astype(np.int64), raw.values, None,
                                           ros_name(s.mag_id), frame))
        sources.append(_field_messages(s.stamps, s.field, s.cov, s.topic, frame))
    with atomic_path(out) as tmp, tmp.open("wb") as fh:
        writer = Writer(fh)
        schemas = {t: writer.register_msgdef(t, store.generate_msgdef(t, ros_version=2)[0])
                   for t in (IMU, MAGNETIC_FIELD)}
        # each source is in time order: merged as they are written, not a list of every message's dict (a 60-min
        # 400 Hz log's 1.44 M IMU messages held 3.7 GB, issue 39). Equal stamps keep the sources' order, as the
        # stable sort of one list did
        for seq, (ns, topic, msg) in enumerate(heapq.merge(*sources, key=lambda e: e[0])):
            schema = schemas[IMU if "linear_acceleration" in msg else MAGNETIC_FIELD]
            writer.write_message(topic, schema, msg, log_time=ns, publish_time=ns, sequence=seq)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap-ros2-support ships no annotations for finish


def _imu_messages(a: Stream, g: Stream, t0_ns: int, topic: str, frame: str
                  ) -> Iterator[tuple[int, str, dict[str, Any]]]:
    """The accelerometer's samples as sensor_msgs/Imu, with the gyro interpolated to their times, in time order."""
    w = np.column_stack([np.interp(a.t, g.t, g.values[:, j]) for j in range(3)])
    for ti, ai, wi in zip(a.t, a.values, w, strict=True):
        ns = t0_ns + round(float(ti) * 1e9)
        yield ns, topic, {
            "header": _msg(ns, frame), "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            "orientation_covariance": [-1.0] + [0.0] * 8, "angular_velocity": _vec(wi),
            "angular_velocity_covariance": [0.0] * 9, "linear_acceleration": _vec(ai),
            "linear_acceleration_covariance": [0.0] * 9}


def _field_messages(stamps: np.ndarray, field: np.ndarray, cov: np.ndarray | None, topic: str, frame: str
                    ) -> Iterator[tuple[int, str, dict[str, Any]]]:
    """A field series as sensor_msgs/MagneticField at `stamps` (ns), in time order (equal stamps in series order);
    `cov` None: unknown (zeros)."""
    for i in np.argsort(stamps, kind="stable").tolist():
        ns = int(stamps[i])
        yield ns, topic, {"header": _msg(ns, frame), "magnetic_field": _vec(field[i]),
                          "magnetic_field_covariance": [0.0] * 9 if cov is None else cov[i].ravel().tolist()}
