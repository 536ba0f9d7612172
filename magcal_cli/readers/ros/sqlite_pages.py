"""The `messages` table of a ROS 2 sqlite3 bag read straight from the SQLite file's table B-tree, with numpy.

Python's sqlite3 costs ~1.7 us a fetched row, as much as decoding the message; here the cells of all leaf pages
are parsed together (varints, record headers, integers gathered as arrays) and the blobs stay in a memory map.
Only the plain case is read: anything else (a WAL or journal beside the file, another table layout, a page
that is not a table page, a wanted row spilling onto overflow pages) is declined, and the caller uses sqlite3.
"""

from __future__ import annotations

import mmap
import sqlite3
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]

MAGIC = b"SQLite format 3\x00"
#: (name, declared type, primary key) of rosbag2's messages columns, in order
LAYOUT = [("id", "INTEGER", 1), ("topic_id", "INTEGER", 0), ("timestamp", "INTEGER", 0), ("data", "BLOB", 0)]
INTERIOR, LEAF = 0x05, 0x0D
#: bytes of leaf pages parsed at a time: bounds the temporaries (a few MB, faster in cache than larger ones)
#: and the file's pages mapped at once
CHUNK_BYTES = 8 << 20
#: bytes of an integer value by serial type (0 NULL, 8 and 9 the constants 0 and 1); -1: not an integer
INT_SIZE = np.array([0, 1, 2, 3, 4, 6, 8, -1, 0, 0], dtype=np.int64)
#: bytes copied from the start of each leaf cell: the row's prefix to its timestamp (+ 8) fits 32 bytes but in
#: odd cases (long varints, an id column stored in the record), never 96
WIDTHS = (32, 96)
#: a payload larger than this is corrupt (SQLite's own limit is 1e9 bytes)
MAX_PAYLOAD = 1 << 31


@dataclass(frozen=True)
class Rows:
    """Rows of the wanted topics; row i's data is buf[start[i]:start[i] + length[i]] (buf maps the file)."""

    topic_id: I64
    timestamp: I64
    start: I64
    length: I64
    buf: U8
    mapped: mmap.mmap


def message_rows(db: Path, topic_ids: Collection[int]) -> Rows | None:
    """The `messages` rows of `topic_ids` from rosbag2's sqlite3 file `db` in timestamp order (ties in rowid
    order, as ORDER BY timestamp gives them); None when it is not the plain case."""
    parts: list[Rows] = []
    if not scan_rows(db, topic_ids, parts.append) or not parts:
        return None
    tid, stamp, start, length = (np.concatenate([getattr(p, k) for p in parts])
                                 for k in ("topic_id", "timestamp", "start", "length"))
    order = np.argsort(stamp, kind="stable")
    return Rows(tid[order], stamp[order], start[order], length[order], parts[0].buf, parts[0].mapped)


def scan_rows(db: Path, topic_ids: Collection[int], visit: Callable[[Rows], object]) -> bool:
    """Pass `visit` the `messages` rows of `topic_ids` a chunk of leaf pages at a time, in rowid order, while the
    chunk's pages are mapped; False when the file is not the plain case (the chunks passed are then void)."""
    geometry = _geometry(db)
    root = _root(db) if geometry is not None else None
    if geometry is None or root is None or not 1 <= root <= geometry[2]:
        return False
    page, usable, pages = geometry
    try:
        with db.open("rb") as fh:               # a mapping: the blobs are not read into memory
            mapped = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError):
        return False
    buf: U8 = np.frombuffer(mapped, dtype=np.uint8)
    leaves = _leaves(buf, root, page, usable, pages)
    if leaves is None:
        return False
    ids = np.array(sorted(topic_ids), dtype=np.int64)
    step = max(1, CHUNK_BYTES // page)
    for lo in range(0, leaves.size, step):
        got = _leaf_rows(buf, leaves[lo:lo + step], page, usable, ids)
        if got is None:
            return False
        visit(Rows(*got, buf, mapped))          # decoded while its pages are mapped: each is read in once
        _release(mapped)                        # the resident set holds one chunk's pages of the file
    return True


def _release(mapped: mmap.mmap) -> None:
    """Unmap the file's pages read so far (they stay in the page cache, and map again when read).

    Touched pages of a file mapping count in the resident set: without this it grows to the file's size."""
    if hasattr(mmap, "MADV_DONTNEED"):     # Linux, macOS; elsewhere the pages stay mapped
        mapped.madvise(mmap.MADV_DONTNEED)


def _geometry(db: Path) -> tuple[int, int, int] | None:
    """(page size, usable bytes a page, page count) from the header, or None when not a plain, settled file."""
    if Path(f"{db}-journal").exists() or (Path(f"{db}-wal").exists() and Path(f"{db}-wal").stat().st_size):
        return None                         # committed rows may still be in the WAL, or a hot journal undo them
    with db.open("rb") as fh:
        head = fh.read(100)
    if len(head) < 100 or not head.startswith(MAGIC):
        return None
    size = int.from_bytes(head[16:18], "big")
    page = 65536 if size == 1 else size
    usable = page - head[20]                # reserved bytes (checksums, encryption) end every page
    count = int.from_bytes(head[28:32], "big")
    if page < 512 or page & (page - 1) or usable < 480 or head[19] not in (1, 2):
        return None
    # the page count is only valid when written by the same change as the change counter (SQLite >= 3.7.0)
    if head[24:28] != head[92:96] or count * page != db.stat().st_size:
        return None
    return page, usable, count


def _root(db: Path) -> int | None:
    """The messages table's root page, or None when the table is not rosbag2's (id, topic_id, timestamp, data)."""
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        try:
            found = con.execute("SELECT rootpage FROM sqlite_master WHERE type = 'table' AND name = 'messages'")
            roots = found.fetchall()
            cols = con.execute("PRAGMA table_info(messages)").fetchall()
        finally:
            con.close()
    except sqlite3.Error:
        return None
    layout = [(str(c[1]), str(c[2]).upper(), int(c[5])) for c in cols]
    if len(roots) != 1 or not isinstance(roots[0][0], int) or layout != LAYOUT:
        return None
    return int(roots[0][0])


def _head(pages: I64, page: int) -> I64:
    """File offset of each page's B-tree header (page 1 has the 100-byte file header first)."""
    return (pages - 1) * page + np.where(pages == 1, 100, 0)


def _bytes(buf: U8, at: I64) -> I64:
    """The byte at each offset; one past the file reads its last byte (callers' range checks catch those)."""
    if at.size and not 0 <= int(at.min()) <= int(at.max()) < buf.size:
        at = np.clip(at, 0, buf.size - 1)
    return buf[at].astype(np.int64)


def _u16(buf: U8, at: I64) -> I64:
    """Big-endian u16 at each offset."""
    return _bytes(buf, at) << 8 | _bytes(buf, at + 1)


def _u32(buf: U8, at: I64) -> I64:
    """Big-endian u32 at each offset."""
    return _u16(buf, at) << 16 | _u16(buf, at + 2)


def _windows(buf: U8, at: I64, width: int) -> U8:
    """The `width` bytes from each offset, one after the other (past the file: zeros), gathered as items.

    Every later read is in this small array, in order: gathering from the file one byte at a time misses the
    cache on each row, again for each byte."""
    span = np.ndarray((buf.size - width + 1,), dtype=f"V{width}", buffer=buf, strides=(1,))
    inside = at <= buf.size - width
    out: U8 = span[np.where(inside, at, 0)].view(np.uint8)
    for i in np.flatnonzero(~inside).tolist():          # cells in the file's last bytes: a few at most
        tail = buf[at[i]:at[i] + width]
        out[i * width:(i + 1) * width] = 0
        out[i * width:i * width + tail.size] = tail
    return out


def _varint(win: U8, at: I64) -> tuple[I64, I64]:
    """SQLite varints at flat offsets `at` of `win`: (value, bytes); 7 bits a byte while the top bit is set, the
    9th byte gives all 8. Bytes are gathered only while some varint goes on (most here are 1-3 bytes)."""
    b = np.take(win, at, mode="clip")
    value, more = (b & 0x7F).astype(np.uint64), b >= 0x80
    size = np.ones(at.size, dtype=np.int64)
    for k in range(1, 9):
        if not more.any():
            break
        b = np.take(win, at + k, mode="clip")
        step = b.astype(np.uint64) if k == 8 else (b & 0x7F).astype(np.uint64)
        value = np.where(more, value << np.uint64(8 if k == 8 else 7) | step, value)
        size += more
        more &= b >= 0x80
    return value.view(np.int64), size


def _ints(win: U8, at: I64, stype: I64) -> I64:
    """Integers of serial types 0-6, 8, 9 at flat offsets `at` of `win` (big-endian two's complement; NULL 0).

    The 8 bytes from each value's start are gathered as one big-endian word (the caller keeps them in the
    row's window); its top `size` bytes are the value, sign-extended by an arithmetic shift down, a shift per
    size present (one shift count per element is several times slower)."""
    size = INT_SIZE[stype]
    sizes = np.flatnonzero(np.bincount(size, minlength=9)).tolist()
    if sizes == [1]:                                        # one-byte integers (topic ids): a byte each
        out: I64 = np.take(win, at, mode="clip").view(np.int8).astype(np.int64)
        return out
    words = np.ndarray((win.size - 7,), dtype="V8", buffer=win, strides=(1,))
    word = words[np.minimum(at, win.size - 8)].view(">i8").astype(np.int64)
    if len(sizes) == 1 and sizes[0]:
        out = word >> (64 - 8 * sizes[0])
    else:
        out = (stype == 9).astype(np.int64)                 # the constants 0 and 1 (and NULL, read 0)
        for k in sizes:
            if k:
                sel = size == k
                out[sel] = word[sel] >> (64 - 8 * k)
    return out


def _int_size(stype: I64) -> I64:
    """Bytes of each integer serial type; -1 for any other type."""
    out: I64 = np.where((stype >= 0) & (stype < 10), INT_SIZE[np.clip(stype, 0, 9)], -1)
    return out


def _cells(buf: U8, pages: I64, page: int, header: int, usable: int) -> tuple[I64, I64] | None:
    """File offsets of every cell of `pages` in key order, and which of them each is in; None when out of range."""
    head = _head(pages, page)
    base = (pages - 1) * page                                    # cell pointers count from the page's start
    n = _u16(buf, head + 3)
    content = head - base + header + 2 * n                       # cells lie after the pointer array
    if (content > usable).any():
        return None                     # more cells than fit: do not allocate for them
    of = np.repeat(np.arange(pages.size), n)
    k = np.arange(of.size) - np.repeat(np.cumsum(n) - n, n)
    ptr = _u16(buf, head[of] + header + 2 * k)
    if ((ptr < content[of]) | (ptr >= usable)).any():
        return None
    return base[of] + ptr, of


def _leaves(buf: U8, root: int, page: int, usable: int, pages: int) -> I64 | None:
    """Leaf pages of the table B-tree from `root`, left to right; None on a page that is not a table page.

    The leaf level is the one whose first page is a leaf: the others are checked as they are read (reading a
    byte of every page here would map the whole file at once)."""
    level, seen = np.array([root], dtype=np.int64), 0
    while True:
        seen += level.size
        if seen > pages or ((level < 1) | (level > pages)).any():
            return None                 # a loop or a wild pointer: no tree has more pages than the file
        if buf[_head(level[:1], page)][0] == LEAF:
            return level
        if not (buf[_head(level, page)] == INTERIOR).all():
            return None                 # all leaves of a B-tree are at one depth; anything else is damage
        cells = _cells(buf, level, page, 12, usable)
        if cells is None:
            return None
        cell, of = cells
        n = np.bincount(of, minlength=level.size)
        ends = np.cumsum(n + 1) - 1     # each page's right-most child follows its cells' left children
        children = np.empty(int(ends[-1]) + 1, dtype=np.int64)
        children[np.arange(of.size) + of] = _u32(buf, cell)
        children[ends] = _u32(buf, _head(level, page) + 8)
        level = children


def _local(p: I64, usable: int) -> I64:
    """Bytes of each table-leaf payload stored in its cell (the rest is on overflow pages)."""
    most = usable - 35
    least = (usable - 12) * 32 // 255 - 23
    k = least + (p - least) % (usable - 4)
    out: I64 = np.where(p <= most, p, np.where(k <= most, k, least))
    return out


def _leaf_rows(buf: U8, leaves: I64, page: int, usable: int, ids: I64) -> tuple[I64, I64, I64, I64] | None:
    """(topic_id, timestamp, data start, data length) of the wanted rows on `leaves`, in rowid order."""
    cells = _cells(buf, leaves, page, 8, usable) if (buf[_head(leaves, page)] == LEAF).all() else None
    if cells is None:
        return None
    cell, of = cells
    if not cell.size:
        return cell, cell, cell, cell
    room = ((leaves - 1) * page + usable)[of] - cell            # bytes from each cell to its page's usable end
    for width in WIDTHS:
        win = _windows(buf, cell, width)
        row = np.arange(cell.size) * width                      # flat offsets below are row + offset in cell
        p, w = _varint(win, row)
        payload = w + _varint(win, row + w)[1]                  # past the rowid: the record
        local_end = payload + _local(p, usable)                 # past it the payload is on overflow pages
        hsize, w = _varint(win, row + payload)
        at, types = payload + w, []
        for _ in range(4):
            t, w = _varint(win, row + at)
            types.append(t)
            at = at + w
        idsize, tsize, ssize = _int_size(types[0]), _int_size(types[1]), _int_size(types[2])
        topic_at = payload + hsize + idsize
        tid = _ints(win, row + topic_at, np.where(tsize < 0, 0, types[1]))
        want = np.isin(tid, ids)
        stamp_at = topic_at + tsize
        reach = np.where(want, stamp_at, topic_at) + 8          # integers are read as 8 bytes
        if width < WIDTHS[-1] and (reach > width).any():
            continue                    # an odd row's prefix is longer than the window: read wider ones
        if ((p < 0) | (p > MAX_PAYLOAD) | (local_end > room) | (at != payload + hsize) | (idsize < 0)
                | (tsize < 0) | (types[1] == 0) | (stamp_at > local_end) | (reach > width)).any():
            return None                 # not 4 columns, a non-integer topic id, a header past the local part
        p, stamp_t, blob_t, stamp_at, ssize = p[want], types[2][want], types[3][want], stamp_at[want], ssize[want]
        start, length = stamp_at + ssize, (blob_t - 12) // 2
        if ((p > usable - 35) | (ssize < 0) | (stamp_t == 0) | (blob_t < 12) | (blob_t % 2 == 1)
                | (start + length != payload[want] + p)).any():
            return None                 # an overflowing wanted row, a NULL or non-integer time, data not a blob
        return tid[want], _ints(win, row[want] + stamp_at, stamp_t), cell[want] + start, length
    return None
