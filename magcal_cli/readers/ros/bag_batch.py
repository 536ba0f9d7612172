"""Batched decoding for the bag reader: rosbags' message iteration with vec decoding, and ROS 2 storage read
directly (sqlite3 rows from the file's B-tree pages or else in blocks through sqlite3, MCAP chunks through the
MCAP reader), bypassing the per-message iteration.

rosbags' own iteration costs several microseconds a message, as much as the whole vectorised decoding, so
ROS 2 bags whose index rosbags accepted are read from their storage files by these faster paths; ROS 1
bags keep rosbags' iteration (its index and chunk resumption) and only batch the decoding.
"""

from __future__ import annotations

import sqlite3
from collections import defaultdict
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli.readers import ReadOptions
from magcal_cli.readers.ros.msg import Collector
from magcal_cli.readers.ros.sqlite_pages import Rows, scan_rows
from magcal_cli.readers.ros.vec import BatchDecoder
from magcal_cli.streams import Cut

#: messages of one connection decoded at a time (bounds the raw bytes held: a few MB)
BATCH = 8192
#: per (topic, type) of a sqlite3 file, blocks of (receive times, decoded?, header stamps, values)
Decoded = dict[tuple[str, str], list[tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_], npt.NDArray[np.int64],
                                           npt.NDArray[np.float64]]]]


def batch_decoder(reader: Any, msgtype: str) -> BatchDecoder:
    """A vec decoder of `msgtype` from an open AnyReader's typestore (ROS 1 or CDR as the bag is)."""
    return BatchDecoder(reader.typestore.fielddefs, msgtype, not reader.is2,
                        lambda data: reader.deserialize(data, msgtype))


def decode_into(collector: Collector, decoder: BatchDecoder, topic: str, raws: list[bytes],
                recv: list[int]) -> int:
    """Decode raw messages of one topic into `collector`; how many did not decode."""
    if not raws:
        return 0
    length = np.fromiter(map(len, raws), dtype=np.int64, count=len(raws))
    start = np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64)
    buf = np.frombuffer(b"".join(raws), dtype=np.uint8)
    return decode_rows(collector, decoder, topic, buf, start, length, np.array(recv, dtype=np.int64))


def decode_rows(collector: Collector, decoder: BatchDecoder, topic: str, buf: npt.NDArray[np.uint8],
                start: npt.NDArray[np.int64], length: npt.NDArray[np.int64], recv: npt.NDArray[np.int64]) -> int:
    """Decode the messages buf[start:start + length] of one topic into `collector`; how many did not decode."""
    if not start.size:
        return 0
    ok, stamps, values = decoder(buf, start, length)
    collector.add_batch(topic, decoder.msgtype, recv[ok], stamps[ok], values[ok])
    return int(ok.size - ok.sum())


class Batcher:
    """Raw messages of AnyReader connections, decoded a batch per connection at a time."""

    def __init__(self, reader: Any, collector: Collector) -> None:
        self.reader, self.collector = reader, collector
        self.decoders: dict[int, BatchDecoder] = {}
        self.raws: dict[int, list[bytes]] = defaultdict(list)
        self.recv: dict[int, list[int]] = defaultdict(list)
        self.topics: dict[int, str] = {}
        self.bad = 0

    def add(self, conn: Any, recv_ns: int, raw: bytes) -> None:
        """Queue one raw message; a full queue is decoded."""
        key = hash((conn.topic, conn.msgtype))     # one queue per topic: its connections stay interleaved in time
        if key not in self.decoders:
            self.decoders[key] = batch_decoder(self.reader, conn.msgtype)
            self.topics[key] = conn.topic
        self.raws[key].append(bytes(raw))
        self.recv[key].append(int(recv_ns))
        if len(self.raws[key]) >= BATCH:
            self.flush(key)

    def flush(self, key: int | None = None) -> None:
        """Decode the queued messages (of one connection, or of all)."""
        for k in [key] if key is not None else list(self.raws):
            self.bad += decode_into(self.collector, self.decoders[k], self.topics[k], self.raws.pop(k, []),
                                    self.recv.pop(k, []))


def read_ros2_storage(bag: Path, reader: Any, conns: list[Any], collector: Collector, options: ReadOptions,
                      notes: list[str]) -> tuple[bool, Cut | None]:
    """Read a ROS 2 bag's MCAP or sqlite3 storage directly: (done, cut); not done when sqlite fails midway."""
    from magcal_cli.readers.ros.mcap import collect

    if any(getattr(r, "compression_mode", None) for r in getattr(reader, "readers", [None])):
        return False, None                  # rosbag2 compressed the files or each message: rosbags undoes it
    files = storage_files(bag)
    if files and all(f.suffix == ".mcap" for f in files):
        cut = None
        for f in files:
            cut = collect(f, collector, options, notes, note_ignored=False) or cut
        return True, cut
    dbs = [f for f in files if f.suffix == ".db3"]
    if not dbs or len(dbs) != len(files):
        return False, None
    bad = 0
    try:
        for db in dbs:
            bad += _read_db3(db, reader, conns, collector)
    except ValueError:                                  # a topic name that is not UTF-8: rosbags names it
        return False, None
    except sqlite3.DatabaseError as exc:
        # damaged: rows by id, not rosbags' query (a join ordered through the timestamp index, which on a damaged
        # index can run for ever)
        from magcal_cli.readers.ros.bag2_sqlite import read_damaged_db3

        collector.clear()
        for db in dbs:
            read_damaged_db3(db, collector, notes, str(exc))
        return True, None
    if bad:
        notes.append(f"corrupt data: skipped {bad} messages that did not decode")
    return True, None


def storage_files(bag: Path, info: Any = None) -> list[Path]:
    """The storage files metadata.yaml lists, in its (time) order; [] when it cannot say. `info`: its
    rosbag2_bagfile_information when the caller has parsed it already."""
    import yaml

    try:
        if info is None:
            info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return [bag / PurePath(str(x)).name for x in info["relative_file_paths"]]
    except (OSError, ValueError, yaml.YAMLError, KeyError, TypeError):
        return []


def _read_db3(db: Path, reader: Any, conns: list[Any], collector: Collector) -> int:
    """Rows of the wanted topics in time order, decoded a block at a time; how many did not decode."""
    wanted = {(c.topic, c.msgtype): c for c in conns}
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT id, name, type FROM topics").fetchall()
        ids = {int(i): wanted[(str(n), str(t))] for i, n, t in rows if (str(n), str(t)) in wanted}
        if not ids:
            return 0
        decoders = {i: batch_decoder(reader, c.msgtype) for i, c in ids.items()}
        if (found := read_db3(db, ids, decoders)) is not None:
            return add_decoded(found, collector)
        cur = con.execute(f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN "   # noqa: S608 - ints
                          f"({','.join(str(i) for i in ids)}) ORDER BY timestamp")
        bad = 0
        while block := cur.fetchmany(BATCH):
            topic_ids, stamps, datas = zip(*block, strict=True)
            tid = np.array(topic_ids, dtype=np.int64)
            for i in np.unique(tid).tolist():
                sel = np.flatnonzero(tid == i).tolist()
                bad += decode_into(collector, decoders[i], ids[i].topic, [datas[j] for j in sel],
                                   [stamps[j] for j in sel])
        return bad
    finally:
        con.close()


def read_db3(db: Path, ids: dict[int, Any], decoders: dict[int, BatchDecoder]) -> Decoded | None:
    """The rows of `ids` decoded from the file's pages a chunk at a time, while they are mapped: per (topic, type),
    blocks in rowid order; None when the file is not the plain case (sqlite_pages)."""
    groups: dict[tuple[str, str], list[int]] = defaultdict(list)
    for i, c in ids.items():            # two topic ids of one topic and type: one stream
        groups[(c.topic, c.msgtype)].append(i)
    found: Decoded = {key: [] for key in groups}

    def visit(rows: Rows) -> None:
        for key, group in groups.items():
            sel = np.flatnonzero(np.isin(rows.topic_id, group))
            if sel.size:
                decoder = decoders[group[0]]
                found[key].append((rows.timestamp[sel], *decoder(rows.buf, rows.start[sel], rows.length[sel])))

    return found if scan_rows(db, list(ids), visit) else None


def add_decoded(found: Decoded, collector: Collector) -> int:
    """Add each topic's decoded rows to `collector` in timestamp order, ties in rowid order (as ORDER BY
    timestamp gives them); how many did not decode."""
    bad = 0
    for (topic, msgtype), blocks in found.items():
        if not blocks:
            continue
        recv, ok, stamps, values = (np.concatenate([b[k] for b in blocks]) for k in range(4))
        if (recv[1:] < recv[:-1]).any():        # a recorder's rowid order is time order: sorted only when it is not
            order = np.argsort(recv, kind="stable")
            recv, ok, stamps, values = recv[order], ok[order], stamps[order], values[order]
        if not ok.all():
            recv, stamps, values = recv[ok], stamps[ok], values[ok]
        collector.add_batch(topic, msgtype, recv, stamps, values)
        bad += int(ok.size - ok.sum())
    return bad
