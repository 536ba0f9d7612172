"""ROS 1 `.bag` files and ROS 2 bag directories (sqlite3 or MCAP storage) through rosbags' AnyReader."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from ..errors import LogReadError
from ..streams import Recording
from . import ReadOptions
from .rosmsg import Collector, wanted

#: how many ignored topics a note names before it says "and N more"
IGNORED_LISTED = 5


def bag_path(path: Path) -> Path:
    """The path AnyReader takes: a `.bag` file, or the directory of a ROS 2 bag (also from a file inside it)."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            msg = f"{path}: a directory without metadata.yaml is not a ROS 2 bag. Pass the bag directory"
            raise LogReadError(msg)
        return path
    if path.suffix.lower() == ".bag":
        return path
    if (path.parent / "metadata.yaml").is_file():
        return path.parent
    msg = (f"{path}: a ROS bag storage file without its metadata.yaml. Pass the ROS 2 bag directory, or rename a "
           "ROS 1 bag to end in .bag")
    raise LogReadError(msg)


def ignored_note(topics: list[str]) -> str:
    """One note naming the topics of types magcal does not read."""
    shown = ", ".join(topics[:IGNORED_LISTED])
    more = f" and {len(topics) - IGNORED_LISTED} more" if len(topics) > IGNORED_LISTED else ""
    return f"ignored {len(topics)} topics of types magcal does not read: {shown}{more}"


class RosbagReader:
    """Reads Imu, MagneticField, Vector3Stamped (field), BatteryState, Temperature and NavSatFix topics."""

    name: ClassVar[str] = "rosbag"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Decode every message of a type magcal reads; a corrupt bag is an error unless truncation is allowed."""
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.rosbag1 import ReaderError as Reader1Error
        from rosbags.rosbag2 import ReaderError as Reader2Error
        from rosbags.serde import SerdeError
        from rosbags.typesys import Stores, TypesysError, get_typestore

        errors = (AnyReaderError, Reader1Error, Reader2Error, SerdeError, TypesysError, KeyError, ValueError,
                  EOFError, OSError)
        bag = bag_path(path)
        fmt = "rosbag" if bag.is_file() else "rosbag2"
        collector, notes = Collector(), []
        try:
            reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except errors as exc:
            msg = f"{path}: cannot open the {fmt} ({_reason(exc)}). {_advice(exc)}"
            raise LogReadError(msg) from None
        try:
            conns = [c for c in reader.connections if wanted(c.topic, c.msgtype)]
            ignored = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections if c not in conns})
            if ignored:
                notes.append(ignored_note(ignored))
            try:
                for conn, recv_ns, raw in reader.messages(connections=conns) if conns else ():  # () means all
                    collector.add(conn.topic, conn.msgtype, recv_ns, reader.deserialize(raw, conn.msgtype))
            except errors as exc:
                if not options.allow_truncated:
                    msg = (f"{path}: the {fmt} is truncated or corrupt ({_reason(exc)}) after {len(collector)} "
                           "messages. Re-copy the log, or pass --allow-truncated to use the complete part")
                    raise LogReadError(msg) from None
                notes.append(f"truncated or corrupt: read {len(collector)} complete messages")
        finally:
            reader.close()
        return collector.recording(path, fmt, options, notes)


def _reason(exc: BaseException) -> str:
    """A library exception as a short phrase."""
    text = str(exc).strip().rstrip(".") or type(exc).__name__
    return text.splitlines()[0][:200]


def _advice(exc: BaseException) -> str:
    """How to fix the usual reasons a bag does not open."""
    text = str(exc).lower()
    if "index" in text:
        return ("The bag is truncated or was not closed cleanly; run `rosbag reindex` on a copy and read that "
                "(magcal needs the bag's index)")
    if "metadata" in text or "yaml" in text:
        return "metadata.yaml is damaged; rebuild it with `ros2 bag reindex`"
    return "Check that the bag is complete and was written by rosbag/ros2 bag"
