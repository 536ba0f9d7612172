"""A ROS 1 bag without its index (cut at power-off, a recorder killed): its records read in file order.

rosbag writes the index (connections and chunk infos) at the end of the file, so a cut bag has none and
rosbags cannot open it. The records before the cut are still whole: connection records carry the message
definitions, chunks the messages (a cut chunk gives the messages its present bytes decompress to), as
`rosbag reindex` would find them. Format: http://wiki.ros.org/Bags/Format/2.0.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import IO, NamedTuple

from magcal_cli.errors import LogReadError
from magcal_cli.readers.cut import a_record
from magcal_cli.readers.ros.msg import Collector, wanted
from magcal_cli.readers.ros.nested import Nested, may_hold
from magcal_cli.readers.ros.partial import decompress_prefix
from magcal_cli.streams import Cut

MAGIC = b"#ROSBAG V2.0\n"
OP_MSGDATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 0x02, 0x05, 0x06, 0x07
#: a record header longer than this is corrupt (rosbag's headers are a few hundred bytes; a connection's
#: message definition is in its data)
MAX_HEADER = 1 << 20


class Record(NamedTuple):
    """One bag record: its header fields, its data, and whether all of the data was there."""

    fields: dict[str, bytes]
    data: bytes
    whole: bool


class _Scan:
    """The connections, type definitions and counts of one scan."""

    def __init__(self, collector: Collector) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.collector = collector
        self.store = get_typestore(Stores.EMPTY)
        self.conns: dict[int, tuple[str, str] | None] = {}
        self.nested: dict[int, Nested] = {}         # connections of custom types holding standard ones
        self.bad = 0
        self.last_op = 0

    def connection(self, rec: Record) -> None:
        """Learn a connection's topic and type and register its message definition."""
        from rosbags.typesys import get_types_from_msg
        from rosbags.typesys.msg import normalize_msgtype

        conn = struct.unpack("<I", rec.fields["conn"])[0]
        inner = header_fields(rec.data)
        topic = rec.fields.get("topic", inner.get("topic", b"")).decode()
        msgtype = normalize_msgtype(inner["type"].decode())
        if not wanted(topic, msgtype):
            self.conns[conn] = None
            self._nested(conn, topic, msgtype, inner["message_definition"].decode())
            return
        try:
            self.store.register(get_types_from_msg(inner["message_definition"].decode(), msgtype))
        except Exception:  # noqa: BLE001 - a definition rosbags cannot parse: the connection's messages are lost
            self.conns[conn] = None
            return
        self.conns[conn] = (topic, msgtype)

    def _nested(self, conn: int, topic: str, msgtype: str, definition: str) -> None:
        """Register a custom type that holds standard messages as fields (nested.py)."""
        from rosbags.typesys import get_types_from_msg

        if not may_hold(definition):
            return
        try:
            self.store.register(get_types_from_msg(definition, msgtype))
        except Exception:  # noqa: BLE001 - a definition rosbags cannot parse holds nothing magcal can read
            return
        store = self.store
        found = Nested(topic, store.fielddefs, msgtype, lambda data: store.deserialize_ros1(data, msgtype))
        if found:
            self.nested[conn] = found

    def message(self, rec: Record) -> None:
        """Decode one message of a connection magcal reads (a corrupt one is counted)."""
        cid = struct.unpack("<I", rec.fields["conn"])[0]
        conn = self.conns.get(cid)
        sec, nsec = struct.unpack("<II", rec.fields["time"])
        if cid in self.nested:
            self.nested[cid].add(sec * 1_000_000_000 + nsec, rec.data)
        if conn is None:
            return
        try:
            self.collector.add(conn[0], conn[1], sec * 1_000_000_000 + nsec,
                               self.store.deserialize_ros1(rec.data, conn[1]))
        except Exception:  # noqa: BLE001 - rosbags' deserializers raise anything on corrupt bytes
            self.bad += 1

    def handle(self, rec: Record) -> None:
        """One whole record: a connection, a message, or a chunk of them (its present part when it is cut)."""
        self.last_op = op = (rec.fields.get("op") or b"\0")[0]
        if op == OP_CONNECTION:
            self.connection(rec)
        elif op == OP_MSGDATA:
            self.message(rec)
        elif op == OP_CHUNK:
            src = io.BytesIO(decompress_prefix(rec.data, rec.fields.get("compression", b"none").decode("latin-1")))
            while True:
                try:
                    inner = read_record(src)
                    if inner is None or not inner.whole:
                        return
                    self.handle(inner)
                except (ValueError, KeyError, UnicodeDecodeError, struct.error, IndexError):
                    self.bad += 1          # a corrupt record inside the chunk: the rest of the chunk is lost
                    return


def header_fields(binary: bytes) -> dict[str, bytes]:
    """The `name=value` fields of a record header (each prefixed by its uint32 length)."""
    out: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(binary):
        (n,) = struct.unpack_from("<I", binary, pos)
        name, sep, value = binary[pos + 4:pos + 4 + n].partition(b"=")
        if not sep or pos + 4 + n > len(binary):
            msg = "a record header field does not parse"
            raise ValueError(msg)
        out[name.decode()] = value
        pos += 4 + n
    return out


def read_record(src: IO[bytes]) -> Record | None:
    """The next record (`whole` False when the source ends inside its data), or None at the end or a cut header."""
    head = src.read(4)
    if len(head) < 4:
        return None
    (n,) = struct.unpack("<I", head)
    if n > MAX_HEADER:
        msg = f"a record header claims {n} bytes"
        raise ValueError(msg)
    binary = src.read(n)
    size = src.read(4)
    if len(binary) < n or len(size) < 4:
        return None if not binary else Record(_fields_or_empty(binary), b"", whole=False)
    data = src.read(struct.unpack("<I", size)[0])
    return Record(header_fields(binary), data, whole=len(data) == struct.unpack("<I", size)[0])


def _fields_or_empty(binary: bytes) -> dict[str, bytes]:
    """The fields of a header that may itself be cut."""
    try:
        return header_fields(binary)
    except ValueError:
        return {}


def scan_bag1(path: Path, collector: Collector, notes: list[str]) -> Cut | None:
    """Read the messages of an unindexed ROS 1 bag into `collector`; where it is cut, or None when it is not."""
    scan = _Scan(collector)
    size = path.stat().st_size
    with path.open("rb") as fh:
        if fh.read(len(MAGIC)) != MAGIC:
            msg = f"{path}: not a ROS 1 bag (no '#ROSBAG V2.0' line at the start). Check the file"
            raise LogReadError(msg)
        cut: Cut | None = None
        while True:
            start = fh.tell()
            try:
                rec = read_record(fh)
            except (ValueError, struct.error) as exc:
                cut = Cut(start, size, f"a record that does not parse ({exc}): the bag is corrupt from there on")
                break
            if rec is None or not rec.whole:
                cut = _cut(scan, rec, start, size)
                break
            try:
                scan.handle(rec)
            except (ValueError, KeyError, UnicodeDecodeError, struct.error, IndexError):
                scan.bad += 1
    for found in scan.nested.values():
        found.flush(collector)
        scan.bad += found.bad
    if scan.bad:
        notes.append(f"corrupt data: skipped {scan.bad} records or messages that did not decode")
    return cut


def _cut(scan: _Scan, rec: Record | None, start: int, size: int) -> Cut | None:
    """Where the scan stopped: None after a whole index (the end of a complete bag), else the Cut there."""
    if rec is None and start >= size:
        return None if scan.last_op == OP_CHUNK_INFO else Cut(size, size, "it stops between records, before its index")
    if rec is None:
        return Cut(start, size, f"a record header, {size - start} bytes present")
    before = len(scan.collector)
    op = (rec.fields.get("op") or b"\0")[0]
    if op == OP_CHUNK:
        scan.handle(rec)
    got = len(scan.collector) - before
    name = {OP_CHUNK: "chunk", OP_MSGDATA: "message", OP_CONNECTION: "connection", 0x03: "bag header",
            0x04: "index data", OP_CHUNK_INFO: "chunk info"}.get(op, "unknown")
    return Cut(start, size, f"{a_record(name)}, {size - start} bytes present"
               + (f"; {got} messages recovered from it" if got else ""))
