"""A ROS 2 sqlite3 bag whose database file was cut (a recorder killed, a copy stopped): the rows still present.

SQLite refuses a file shorter than its header says ("database disk image is malformed"). A copy padded with
zero pages to the declared size opens, and the rows on pages before the cut read by id; rows on lost pages
fail and are counted.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import struct
import tempfile
from pathlib import Path

from magcal_cli.readers.ros.msg import Collector, wanted
from magcal_cli.readers.ros.types2 import humble_subset
from magcal_cli.streams import Cut

#: ids queried at once; a range that fails is retried id by id
ID_BLOCK = 256
#: this many id ranges in a row without a readable row end the scan
EMPTY_RANGES = 8


def declared_size(db: Path) -> int | None:
    """Bytes the database header declares (page size x page count), or None when the header is not SQLite's."""
    with db.open("rb") as fh:
        head = fh.read(32)
    if len(head) < 32 or not head.startswith(b"SQLite format 3\x00"):
        return None
    page, pages = int(struct.unpack(">H", head[16:18])[0]), int(struct.unpack(">I", head[28:32])[0])
    return (65536 if page == 1 else page) * pages


def read_cut_db3(db: Path, collector: Collector, notes: list[str]) -> Cut | None:
    """Read the rows of a cut .db3 into `collector`; None when the file is not shorter than declared."""
    declared, size = declared_size(db), db.stat().st_size
    if declared is None or declared <= size:
        return None
    with tempfile.TemporaryDirectory(prefix="magcal-db3-") as tmp:
        padded = Path(tmp) / db.name
        try:
            shutil.copyfile(db, padded)
            # a sparse extension, not zero bytes in memory: a damaged header may declare terabytes (the fuzzer's
            # find: MemoryError), which the file system then refuses
            os.truncate(padded, declared)
        except (OSError, OverflowError):
            return None
        read, rows = _read_rows(padded, collector)
    expected = _message_count(db.parent / "metadata.yaml")
    lost = f"{expected - rows} of its {expected} messages lost" if expected is not None else "messages lost"
    notes.append(f"{db.name}: read the {read} messages of the topics magcal uses on the pages before the cut")
    return Cut(None, size, f"the database file has {size} of the {declared} bytes its header declares; {lost}")


def read_damaged_db3(db: Path, collector: Collector, notes: list[str], why: str) -> None:
    """Read the readable rows of a damaged .db3 into `collector` by id ranges: its indexes are not trusted (a
    query through a damaged timestamp index ran for ever inside SQLite on a fuzzed bag)."""
    read, _ = _read_rows(db, collector)
    notes.append(f"corrupt data: {db.name} is damaged ({why}); read the {read} readable messages of the topics "
                 "magcal uses by their row ids")


def _read_rows(db: Path, collector: Collector) -> tuple[int, int]:
    """`_rows` of the database file `db`, opened read-only; (0, 0) when its topics table is damaged (a name not
    UTF-8, a bad page): no row can be named."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return _rows(con, collector)
    except (sqlite3.DatabaseError, ValueError):
        return 0, 0
    finally:
        con.close()


def _message_count(metadata: Path) -> int | None:
    """The bag's message count from metadata.yaml, or None when it cannot be read."""
    import yaml

    try:
        info = yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]
        return int(info["message_count"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None


def _topics(con: sqlite3.Connection) -> dict[int, tuple[str, str]]:
    """Topic id -> (name, type) of the topics magcal reads."""
    rows = con.execute("SELECT id, name, type FROM topics").fetchall()
    return {int(i): (str(n), str(t)) for i, n, t in rows if wanted(str(n), str(t))}


def _rows(con: sqlite3.Connection, collector: Collector) -> tuple[int, int]:
    """Decode every readable message row by id ranges; (messages magcal reads decoded, rows read)."""
    store = humble_subset()                 # the wanted types of the Humble store the AnyReader path uses
    topics = _topics(con)
    read = total = empty = 0
    lo = 1
    while empty < EMPTY_RANGES:
        rows = _block(con, lo)
        total += len(rows)
        empty = 0 if rows else empty + 1
        for topic_id, stamp, data in rows:
            if topic_id in topics:
                name, msgtype = topics[topic_id]
                try:
                    collector.add(name, msgtype, int(stamp), store.deserialize_cdr(bytes(data), msgtype))
                    read += 1
                except Exception:  # noqa: BLE001 - a row on a half-written page is corrupt: skipped
                    total -= 1
        lo += ID_BLOCK
    return read, total


def _block(con: sqlite3.Connection, lo: int) -> list[tuple[int, int, bytes]]:
    """The readable rows with lo <= id < lo + ID_BLOCK (id by id when the range as a whole fails)."""
    query = "SELECT topic_id, timestamp, data FROM messages WHERE id >= ? AND id < ?"
    try:
        return list(con.execute(query, (lo, lo + ID_BLOCK)).fetchall())
    except sqlite3.DatabaseError:
        rows = []
        for i in range(lo, lo + ID_BLOCK):
            with contextlib.suppress(sqlite3.DatabaseError):
                rows += con.execute(query, (i, i + 1)).fetchall()
        return rows
