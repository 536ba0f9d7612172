"""ROS 1 `.bag` files and ROS 2 bag directories (sqlite3 or MCAP storage), opened with rosbags' AnyReader.

The messages are then read by the fast paths of bag1_fast / bag_batch (chunks or storage rows decoded
together by vec); rosbags' own per-message iteration remains for damaged or rosbag2-compressed bags."""

from __future__ import annotations

import contextlib
import struct
from pathlib import Path
from typing import Any, ClassVar

from magcal_cli.errors import LogReadError
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.cut import mark_cut, refuse_if_strict
from magcal_cli.readers.ros.bag1_fast import read_indexed_bag1
from magcal_cli.readers.ros.bag2_direct import read_direct
from magcal_cli.readers.ros.bag_batch import Batcher, read_ros2_storage
from magcal_cli.readers.ros.msg import Collector, ignored_note, wanted
from magcal_cli.readers.ros.nested import nested_of, read_nested
from magcal_cli.streams import Cut, Recording

#: first step (ns) past a corrupt chunk when resuming; it doubles until a message reads (1 ms .. ~18 min)
RESUME_STEP_NS = 1_000_000
RESUME_PROBES = 40


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


class RosbagReader:
    """Reads Imu, MagneticField, Vector3Stamped (field), BatteryState, Temperature, NavSatFix, ActuatorControl."""

    name: ClassVar[str] = "rosbag"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Decode every message of a type magcal reads; a cut bag up to its last complete message."""
        bag = bag_path(path)
        fmt = "rosbag" if bag.is_file() else "rosbag2"
        collector = Collector()
        notes: list[str] = []
        if bag.is_dir() and (direct := read_direct(bag, collector, options, notes)) is not None:
            ignored, cut = direct
            return mark_cut(collector.recording(path, fmt, options, ([ignored_note(ignored)] if ignored else [])
                                                + notes), cut)
        # imported here, not above: a plain ROS 2 bag does not need them (rosbags.highlevel alone is 0.1 s)
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.rosbag1 import ReaderError as Reader1Error
        from rosbags.rosbag2 import ReaderError as Reader2Error
        from rosbags.serde import SerdeError
        from rosbags.typesys import Stores, TypesysError, get_typestore

        errors = (AnyReaderError, Reader1Error, Reader2Error, SerdeError, TypeError, TypesysError, KeyError,
                  ValueError, EOFError, OSError, MemoryError, OverflowError, struct.error)
        try:
            reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags also raises AssertionError, MemoryError... on damage
            rec = _read_unindexed(path, bag, options, _reason(exc))
            if rec is None:
                msg = f"{path}: cannot open the {fmt} ({_reason(exc)}). {_advice(exc)}"
                raise LogReadError(msg) from None
            return rec
        try:
            conns = [c for c in reader.connections if wanted(c.topic, c.msgtype)]
            nested = nested_of(reader, [c for c in reader.connections if c not in conns])
            ignored = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections
                              if c not in conns and c.id not in nested})
            if ignored:
                notes.append(ignored_note(ignored))
            done, cut = _fast(bag, reader, conns, fast := Collector(), options, notes) if conns else (False, None)
            if done:
                collector = fast
            why = _read_messages(reader, conns, collector, notes) if conns and not done else ""
            cut = _db3_cut(bag) or cut
            if why:                 # damage that reaches the end of the bag is a cut (its index was whole)
                cut = Cut(None, _size(bag), f"the data are unreadable from a chunk on to the end ({why})")
            read_nested(reader, nested, collector, notes)
            for c in reader.connections:
                collector.saw(c.topic, c.msgtype, c in conns or c.id in nested)
            refuse_if_strict(path, options, cut)
        finally:
            with contextlib.suppress(*errors):
                reader.close()
        return mark_cut(collector.recording(path, fmt, options, notes), cut)


def _fast(bag: Path, reader: Any, conns: list[Any], collector: Collector, options: ReadOptions,
          notes: list[str]) -> tuple[bool, Cut | None]:
    """Read the bag chunk by chunk (ROS 1 index) or from its ROS 2 storage; (False, None) when that is no help."""
    if bag.is_dir():
        return read_ros2_storage(bag, reader, conns, collector, options, notes)
    bad = read_indexed_bag1(bag, reader, conns, collector)
    if bad:
        notes.append(f"corrupt data: skipped {bad} messages that did not decode")
    return bad is not None, None


def _db3_cut(bag: Path) -> Cut | None:
    """A ROS 2 sqlite3 bag whose database is shorter than its header declares (SQLite still opened it)."""
    from magcal_cli.readers.ros.bag2_sqlite import declared_size

    for db in sorted(bag.glob("*.db3")) if bag.is_dir() else []:
        declared, size = declared_size(db), db.stat().st_size
        if declared is not None and declared > size:
            return Cut(None, size, f"{db.name} has {size} of the {declared} bytes its header declares")
    return None


def _size(bag: Path) -> int:
    """Bytes in a bag file, or in the storage files of a bag directory."""
    return bag.stat().st_size if bag.is_file() else sum(f.stat().st_size for f in bag.iterdir() if f.is_file())


def _read_unindexed(path: Path, bag: Path, options: ReadOptions, why: str) -> Recording | None:
    """A bag rosbags cannot open (a cut one has no index) read record by record; None when that is no help."""
    from magcal_cli.readers.ros.bag1_scan import scan_bag1
    from magcal_cli.readers.ros.bag2_sqlite import read_cut_db3, read_damaged_db3
    from magcal_cli.readers.ros.mcap import collect

    collector, cut, notes = Collector(), None, list[str]()
    if bag.is_file():
        cut = scan_bag1(bag, collector, notes)
        fmt = "rosbag"
    elif storage := sorted(bag.glob("*.db3")):
        for f in storage:
            if (lost := read_cut_db3(f, collector, notes)) is None:      # whole length, damaged inside
                read_damaged_db3(f, collector, notes, why)
            cut = lost or cut
        fmt = "rosbag2"
    else:
        storage = sorted(bag.glob("*.mcap"))
        notes.append(f"rosbags cannot open the bag ({why}); read its MCAP storage file{'s' * (len(storage) > 1)} "
                     "record by record instead")
        for f in storage:
            cut = collect(f, collector, options, notes) or cut
        fmt = "rosbag2"
    if not len(collector):
        return None
    refuse_if_strict(path, options, cut)
    return mark_cut(collector.recording(path, fmt, options, notes), cut)


def _read_messages(reader: Any, conns: list[Any], collector: Collector, notes: list[str]) -> str:
    """Decode every message on `conns`, skipping (and noting) corrupt chunks and messages in the middle.

    rosbags stops at the first corrupt chunk, raising whatever its parsers hit (ReaderError, AssertionError,
    RuntimeError from lz4, ZstdError, MemoryError, ...), so reading resumes after it, as pymavlink does.
    Returns why reading stopped early when nothing after the damage could be read (a truncated bag), else "".
    """
    expected = sum(int(c.msgcount) for c in conns)
    last, start, regions, why = int(reader.start_time) - 1, None, 0, ""
    batcher = Batcher(reader, collector)             # decodes with vec; corrupt messages are counted
    while True:
        try:
            for conn, recv_ns, raw in reader.messages(connections=conns, start=start):
                last = max(last, int(recv_ns))
                batcher.add(conn, recv_ns, raw)
            break
        except Exception as exc:  # noqa: BLE001 - anything rosbags raises while reading a chunk is corrupt data
            start = _resume_after(reader, conns, last)
            if start is None:
                why = _reason(exc)
                break
            regions += 1
    batcher.flush()
    bad_msgs = batcher.bad
    if regions or bad_msgs:
        notes.append(f"corrupt data: skipped {regions} unreadable chunks and {bad_msgs} messages that did not "
                     f"decode ({expected - len(collector)} of {expected} messages lost); reading resumed after "
                     "each")
    return why


def _resume_after(reader: Any, conns: list[Any], last: int) -> int | None:
    """The earliest probed time after `last` (ns) from which messages read again, or None (nothing readable)."""
    step = RESUME_STEP_NS
    for _ in range(RESUME_PROBES):
        start = last + step
        if start > int(reader.end_time):
            return None
        try:
            next(iter(reader.messages(connections=conns, start=start)), None)
        except Exception:  # noqa: BLE001 - still inside the corrupt chunk: step further
            step *= 2
            continue
        return start
    return None


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
