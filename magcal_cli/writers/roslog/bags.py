"""ROS 1 `.bag` and ROS 2 bag folder copies (rosbags' readers and writers) with the calibrated topics added.

Every original connection is re-created with its own type, definition, digest and (ROS 1) caller id and latching,
or (ROS 2) serialization format and QoS profiles; every message is written back as the raw bytes read, so its
payload is unchanged. The calibrated topics are `sensor_msgs/MagneticField`, serialised by rosbags' typestore.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli.atomic import atomic_dir, atomic_path
from magcal_cli.errors import LogReadError
from magcal_cli.writers.roslog.series import Series, refuse_clash, snapped

MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
#: the fallback frame when neither the IMU's nor the magnetometer's messages name one
DEFAULT_FRAME = "imu_link"


def walk(msg: Any, path: tuple[str, ...]) -> Any:
    """The field at `path` inside a decoded message (the message itself for ())."""
    for name in path:
        msg = getattr(msg, name)
    return msg


def frame_of(msg: Any, path: tuple[str, ...]) -> str:
    """The frame_id of a (nested) message: its own header's, else the nearest enclosing header's."""
    for depth in range(len(path), -1, -1):
        frame = getattr(getattr(walk(msg, path[:depth]), "header", None), "frame_id", None)
        if frame:
            return str(frame)
    return ""


def stamp_of(header: Any) -> int:
    """A std_msgs/Header's stamp in integer ns."""
    st = header.stamp
    return int(st.sec) * 1_000_000_000 + int(getattr(st, "nanosec", getattr(st, "nsec", 0)))


def header_stamps(msg: Any, path: tuple[str, ...]) -> list[int]:
    """Every header stamp on the way to a nested message (the times the reader may have used)."""
    out = []
    for depth in range(len(path) + 1):
        header = getattr(walk(msg, path[:depth]), "header", None)
        if header is not None:
            out.append(stamp_of(header))
    return out


def field_message(types: Any, ros1: bool, s: Series, i: int, frame: str) -> Any:
    """sensor_msgs/MagneticField `i` of a series (tesla; covariance row-major, as ROS stores it)."""
    ns = int(s.stamps[i])
    stamp = types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    header = (types["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id=frame) if ros1
              else types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame))
    x, y, z = (float(v) for v in s.field[i])
    vec = types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)
    return types[MAGNETIC_FIELD](header=header, magnetic_field=vec,
                                 magnetic_field_covariance=np.ascontiguousarray(s.cov[i], dtype=np.float64).ravel())


def _scan(reader: Any, series: list[Series], imu_id: str
          ) -> tuple[dict[str, str], list[Series], dict[int, int]]:
    """(frame per calibrated topic, series with stamps snapped to the logged ones, receive time per header
    stamp of the magnetometers' messages) from one pass over the magnetometers' and the IMU's topics."""
    from magcal_cli.writers.roslog.series import split_id

    topics = {c.topic for c in reader.connections}
    imu_topic, imu_path = split_id(imu_id, topics)
    wanted = {s.source_topic for s in series} | {imu_topic}
    logged: dict[str, list[int]] = {s.source_topic: [] for s in series}
    frames: dict[str, str] = {}
    received: dict[int, int] = {}
    for conn, ts, raw in reader.messages([c for c in reader.connections if c.topic in wanted]):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.topic == imu_topic and "imu" not in frames:
            frames["imu"] = frame_of(msg, imu_path)
        for s in series:
            if conn.topic == s.source_topic:
                stamps = header_stamps(msg, s.path)
                logged[s.source_topic] += [ts, *stamps]
                for st in stamps:         # a calibrated message goes where its reading was received
                    received.setdefault(st, ts)
                frames.setdefault(s.mag_id, frame_of(msg, s.path))
    imu = frames.get("imu", "")
    out = [Series(s.mag_id, s.source_topic, s.path, s.topic, snapped(s.stamps, np.array(logged[s.source_topic])),
                  s.field, s.cov) for s in series]
    return {s.topic: imu or frames.get(s.mag_id) or DEFAULT_FRAME for s in out}, out, received


def _merged(reader: Any, drop: set[str], extra: list[tuple[int, int, str, int]]) -> Iterator[tuple[Any, int, Any]]:
    """The log's messages (less the `drop` topics) and the calibrated ones, in time order: (conn or
    (topic, series index, message index), time, raw bytes or None)."""
    originals = ((ts, 0, conn, raw) for conn, ts, raw in reader.messages() if conn.topic not in drop)
    added = ((ts, 1, (topic, k, i), None) for ts, k, topic, i in extra)
    for ts, _, what, raw in heapq.merge(originals, added, key=lambda e: (e[0], e[1])):
        yield what, ts, raw


def copy_bag(src: Path, out: Path, series: list[Series], imu_id: str, replace: bool) -> None:
    """Copy the ROS 1 bag or ROS 2 bag folder `src` to `out` with the calibrated topics added (or, with
    `replace`, in place of the magnetometers' topics)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([src], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds on a damaged bag
        msg = f"{src}: cannot open the bag to copy it ({exc}). Check the log with magcal inspect"
        raise LogReadError(msg) from None
    try:
        frames, series, received = _scan(reader, series, imu_id)
        ros1 = src.is_file()
        store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        drop = {s.source_topic for s in series} if replace else set()
        refuse_clash(series, {c.topic for c in reader.connections} - drop)
        extra = sorted((received.get(int(ns), int(ns)), k, s.topic, i)
                       for k, s in enumerate(series) for i, ns in enumerate(s.stamps))
        (_write_bag1 if ros1 else _write_bag2)(reader, out, store, series, frames, drop, extra)
    finally:
        reader.close()


def _write_bag1(reader: Any, out: Path, store: Any, series: list[Series], frames: dict[str, str], drop: set[str],
                extra: list[tuple[int, int, str, int]]) -> None:
    """The ROS 1 copy, built under a temporary name and renamed into place."""
    from rosbags.rosbag1 import Writer

    with atomic_path(out) as tmp:
        tmp.unlink()                                  # rosbags refuses to overwrite the placeholder
        writer = Writer(tmp)
        writer.set_compression(Writer.CompressionFormat.LZ4)
        with writer:
            _write_all(reader, writer, store, series, frames, drop, extra, ros1=True)


def _write_bag2(reader: Any, out: Path, store: Any, series: list[Series], frames: dict[str, str], drop: set[str],
                extra: list[tuple[int, int, str, int]]) -> None:
    """The ROS 2 copy (the source's storage: MCAP or sqlite3), built in a temporary folder and renamed."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    mcap = any(p.suffix == ".mcap" for p in reader.paths[0].iterdir())
    with atomic_dir(out) as tmp:
        writer = Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3)
        if mcap:
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with writer:
            _write_all(reader, writer, store, series, frames, drop, extra, ros1=False)


def _write_all(reader: Any, writer: Any, store: Any, series: list[Series], frames: dict[str, str], drop: set[str],
               extra: list[tuple[int, int, str, int]], ros1: bool) -> None:
    """Every connection re-created, every message written: originals raw, calibrated ones serialised."""
    conns: dict[Any, Any] = {}
    for c in reader.connections:
        if c.topic in drop:
            continue
        key = (c.topic, c.msgtype, c.digest, repr(c.ext))   # ROS 1 bags repeat a topic per caller
        if key not in conns:
            ext = c.ext
            opts = ({"md5sum": c.digest, "callerid": ext.callerid, "latching": ext.latching} if ros1 else
                    {"rihs01": c.digest or None, "serialization_format": ext.serialization_format,
                     "offered_qos_profiles": ext.offered_qos_profiles})
            conns[key] = writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, **opts)
        conns[c.id] = conns[key]
    added = {s.topic: writer.add_connection(s.topic, MAGNETIC_FIELD, typestore=store) for s in series}
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    for what, ts, raw in _merged(reader, drop, extra):
        if raw is not None:
            writer.write(conns[what.id], ts, raw)
            continue
        topic, k, i = what
        msg = field_message(store.types, ros1, series[k], i, frames[topic])
        writer.write(added[topic], ts, bytes(serialize(msg, MAGNETIC_FIELD)))
