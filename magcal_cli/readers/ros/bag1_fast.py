"""An indexed ROS 1 bag read chunk by chunk with numpy: the index rosbags parsed gives each message's offset.

rosbags' `messages()` seeks, parses a record header and copies the data of every message in Python; here
each chunk is decompressed once and the message records of each connection in it are located from the index
offsets, checked (op, connection and time in the record header agree with the index) and decoded by vec.
Anything unexpected (a corrupt chunk, an index that points elsewhere) returns False and the caller reads
the bag the slow way, which resumes after damaged chunks.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli.progress import current
from magcal_cli.readers.ros.bag1_scan import header_fields
from magcal_cli.readers.ros.bag_batch import batch_decoder
from magcal_cli.readers.ros.msg import Collector
from magcal_cli.readers.ros.vec import BatchDecoder

I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]
OP_MSGDATA = 2


class _Conn:
    """One wanted connection: its index as arrays and its decoded output, filled chunk by chunk."""

    def __init__(self, conn: Any, index: list[Any], decoder: BatchDecoder) -> None:
        flat = np.fromiter(itertools.chain.from_iterable(index), dtype=np.int64, count=3 * len(index))
        self.conn, self.decoder = conn, decoder
        self.time, self.chunk, self.offset = flat.reshape(-1, 3).T      # index order: rosbags' message order
        n = len(index)
        self.ok, self.stamps = np.zeros(n, dtype=bool), np.zeros(n, dtype=np.int64)
        self.values = np.zeros((n, len(decoder.paths) - 2))


def read_indexed_bag1(path: Path, reader: Any, conns: list[Any], collector: Collector) -> int | None:
    """Decode the messages of `conns` of an indexed ROS 1 bag; how many did not decode, or None to fall back."""
    readers = getattr(reader, "readers", [])
    if len(readers) != 1 or not hasattr(readers[0], "indexes") or not hasattr(readers[0], "chunks"):
        return None
    bag = readers[0]
    try:
        wanted = [_Conn(c, bag.indexes[c.id], batch_decoder(reader, c.msgtype)) for c in conns]
        hook = current()
        with path.open("rb") as fh:
            todo = sorted({int(p) for w in wanted for p in np.unique(w.chunk)})
            for k, pos in enumerate(todo):
                hook("reading", k, len(todo))
                chunk = bag.chunks[pos]
                fh.seek(chunk.datapos)
                raw = fh.read(chunk.datasize)
                data = np.frombuffer(chunk.decompressor(raw), dtype=np.uint8)
                for w in wanted:
                    if not _chunk(data, pos, w):
                        return None
    except Exception:  # noqa: BLE001 - any surprise (corrupt chunk, odd index): the per-message path decides
        return None
    for topic in dict.fromkeys((w.conn.topic, w.conn.msgtype) for w in wanted):
        _add_topic(collector, [w for w in wanted if (w.conn.topic, w.conn.msgtype) == topic])
    return sum(int((~w.ok).sum()) for w in wanted)


def _add_topic(collector: Collector, conns: list[_Conn]) -> None:
    """The messages of a topic's connections in rosbags' order: by time, ties in connection then index order."""
    time = np.concatenate([w.time for w in conns])
    rank = np.concatenate([np.full(w.time.size, i) for i, w in enumerate(conns)])
    order = np.lexsort((np.concatenate([np.arange(w.time.size) for w in conns]), rank, time))
    ok = np.concatenate([w.ok for w in conns])[order]
    stamps = np.concatenate([w.stamps for w in conns])[order]
    values = np.concatenate([w.values for w in conns])[order]
    first = conns[0].conn
    collector.add_batch(first.topic, first.msgtype, time[order][ok], stamps[ok], values[ok])


def _chunk(data: U8, pos: int, w: _Conn) -> bool:
    """Decode the messages of one connection in one decompressed chunk; False when a record does not check out."""
    sel = np.flatnonzero(w.chunk == pos)
    if not sel.size:
        return True
    off = w.offset[sel]
    if int(off.max()) + 4 > data.size:
        return False
    head_len = _u32(data, off)
    start = np.zeros(sel.size, dtype=np.int64)
    length = np.zeros(sel.size, dtype=np.int64)
    for hl in np.unique(head_len).tolist():
        group = np.flatnonzero(head_len == hl)
        at = off[group]
        if int(at.max()) + 8 + hl > data.size or not _headers_agree(data, at, hl, w, sel[group]):
            return False
        start[group] = at + 8 + hl
        length[group] = _u32(data, at + 4 + hl)
    if int((start + length).max()) > data.size:
        return False
    ok, stamps, values = w.decoder(data, start, length)
    w.ok[sel], w.stamps[sel], w.values[sel] = ok, stamps, values
    return True


def _headers_agree(data: U8, at: I64, hl: int, w: _Conn, rows: I64) -> bool:
    """The record headers of length `hl` at `at` are message data of this connection at the index's times.

    The first header is parsed to find where op, conn and time lie; all are then compared at those places."""
    first = bytes(data[at[0] + 4:at[0] + 4 + hl])
    fields = header_fields(first)
    if fields.get("op") != bytes([OP_MSGDATA]) or "conn" not in fields or len(fields.get("time", b"")) != 8:
        return False
    where = {name: first.index(name.encode() + b"=") + len(name) + 1 for name in ("op", "conn", "time")}
    op = data[at + 4 + where["op"]]
    conn = _u32(data, at + 4 + where["conn"])
    sec, nsec = _u32(data, at + 4 + where["time"]), _u32(data, at + 8 + where["time"])
    return bool(np.all(op == OP_MSGDATA) and np.all(conn == w.conn.id)
                and np.array_equal(sec * 1_000_000_000 + nsec, w.time[rows]))


def _u32(data: U8, pos: I64) -> I64:
    """The little-endian uint32 at each offset, as int64."""
    out: I64 = data[pos[:, None] + np.arange(4)].view("<u4").reshape(-1).astype(np.int64)
    return out
