"""The sqlite3 bag storage read from the file's B-tree pages: the same rows as SQLite's, or None off the plain case.

Modules it covers (the mirrored test file aside): magcal_cli.readers.ros.bag2_direct,
magcal_cli.readers.ros.bag_batch, magcal_cli.readers.ros.sqlite_pages.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Collection, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import magcal_cli.readers.ros.bag as rosbag
import magcal_cli.readers.ros.bag_batch as rosbag_batch
import magcal_cli.readers.ros.sqlite_pages as sqlite_pages
from magcal_cli.errors import LogReadError
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.ros.bag import RosbagReader
from magcal_cli.readers.ros.bag2_direct import read_direct
from magcal_cli.readers.ros.msg import Collector
from magcal_cli.readers.ros.sqlite_pages import Rows, message_rows, scan_rows
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.synth.logs.rosbag import write_ros2
from magcal_cli.synth.simulate import Simulation, simulate

SCHEMA = ("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL, "
          "data BLOB NOT NULL)")
#: timestamps of every integer serial type: the constants 0 and 1, 1-8 byte values, negative, the int64 limits
ODD_STAMPS = [0, 1, -1, 127, -128, 300, -40000, 8_000_000, 2**31 - 1, -(2**31), 2**47 - 1, -(2**47), 2**63 - 1,
              -(2**63), 1_700_000_000_123_456_789]


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A 12 s simulation with battery and temperature topics besides the IMU and field."""
    base = simulate("paper", 3, rate=80.0, mag_rate=40.0, duration=12.0)
    t = base.recording.select(Kind.ACCELEROMETER).t[::8]
    extra = (Stream(Kind.BATTERY_CURRENT, "/battery", t, np.linspace(1, 20, t.size), "sim", "A"),
             Stream(Kind.BATTERY_VOLTAGE, "/battery", t, np.linspace(16.8, 15.0, t.size), "sim", "V"),
             Stream(Kind.TEMPERATURE, "/imu/temperature", t, np.linspace(20, 30, t.size), "sim", "degC"))
    rec = base.recording
    return replace(base, recording=Recording(rec.path, "simulation", rec.streams + extra, t0=rec.t0))


def truth(db: Path, ids: list[int]) -> list[tuple[int, int, bytes]]:
    """SQLite's rows of `ids` in timestamp order, ties in rowid order."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        query = f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({','.join(map(str, ids))}) " \
                "ORDER BY timestamp, id"
        return [(int(a), int(b), bytes(c)) for a, b, c in con.execute(query)]
    finally:
        con.close()


def as_list(rows: Rows) -> list[tuple[int, int, bytes]]:
    """The rows as (topic_id, timestamp, data)."""
    return [(int(i), int(t), bytes(rows.buf[s:s + n])) for i, t, s, n in
            zip(rows.topic_id, rows.timestamp, rows.start, rows.length, strict=True)]


def write_table(db: Path, rows: list[tuple[int, int, bytes]], page_size: int = 4096, schema: str = SCHEMA) -> None:
    """A database with a rosbag2-like messages table holding `rows` (topic_id, timestamp, data), ids 1, 2, ..."""
    con = sqlite3.connect(db)
    con.execute(f"PRAGMA page_size={page_size}")
    con.execute(schema)
    con.execute("CREATE INDEX timestamp_idx ON messages (timestamp ASC)")
    con.executemany("INSERT INTO messages (id, topic_id, timestamp, data) VALUES (?, ?, ?, ?)", [(k + 1, *r) for k, r in enumerate(rows)])
    con.commit()
    con.close()


def random_rows(n: int, seed: int, max_blob: int = 600) -> list[tuple[int, int, bytes]]:
    """Rows of topics 1-5, blobs of 0..max_blob bytes, timestamps with ties and of every integer size."""
    rng = np.random.default_rng(seed)
    stamps = rng.integers(0, n // 4, n) * 1000 + 1_600_000_000_000_000_000       # ties: ~4 rows a value
    odd = rng.integers(0, n, 200)
    stamps[odd] = rng.choice(ODD_STAMPS, odd.size)
    sizes = rng.integers(0, max_blob + 1, n)
    return [(int(rng.integers(1, 6)), int(s), rng.bytes(int(k))) for s, k in zip(stamps, sizes, strict=True)]


def depth(db: Path) -> int:
    """Levels of the messages B-tree, followed down its right-most pointers."""
    con = sqlite3.connect(db)
    root, page = con.execute("SELECT rootpage FROM sqlite_master WHERE name = 'messages'").fetchone()[0], \
        con.execute("PRAGMA page_size").fetchone()[0]
    con.close()
    data, levels, at = db.read_bytes(), 1, root
    while data[(at - 1) * page] == 0x05:
        at, levels = int.from_bytes(data[(at - 1) * page + 8:(at - 1) * page + 12], "big"), levels + 1
    return levels


@pytest.mark.parametrize(("page_size", "max_blob", "levels"), [(512, 440, 4), (1024, 600, 3), (4096, 600, 3)])
def test_rows_are_sqlites(tmp_path: Path, page_size: int, max_blob: int, levels: int) -> None:
    """20000 rows (on 512-byte pages a tree of three interior levels): the same rows, ties in rowid order."""
    db = tmp_path / "m.db3"
    rows = random_rows(20000, seed=1, max_blob=max_blob)
    write_table(db, rows, page_size=page_size)
    assert depth(db) == levels
    for ids in ([1, 2, 3, 4, 5], [2, 5], [4], [9]):
        got = message_rows(db, ids)
        assert got is not None
        assert as_list(got) == truth(db, ids)
        assert len(got.timestamp) == sum(r[0] in ids for r in rows)
    got = message_rows(db, [1, 2, 3, 4, 5])
    assert got is not None
    assert set(ODD_STAMPS) <= set(got.timestamp.tolist())        # every integer size was read


def test_an_id_column_stored_in_the_record_is_skipped(tmp_path: Path) -> None:
    """INTEGER PRIMARY KEY DESC is not the rowid: the id is stored in each record and must be stepped over."""
    db = tmp_path / "m.db3"
    write_table(db, random_rows(3000, seed=2), schema=SCHEMA.replace("PRIMARY KEY", "PRIMARY KEY DESC"))
    got = message_rows(db, [1, 3])
    assert got is not None
    assert as_list(got) == truth(db, [1, 3])


@pytest.mark.parametrize("first", [-100, -40_000, -(2**40), -(2**62)])
def test_negative_timestamps_of_one_size(tmp_path: Path, first: int) -> None:
    """Timestamps all of one serial type (1, 3, 5 or 6 bytes), negative: sign-extended as SQLite reads them."""
    db = tmp_path / "m.db3"
    write_table(db, [(2, first + k % 7, bytes([k % 256]) * (k % 50)) for k in range(500)])
    got = message_rows(db, [2])
    assert got is not None
    assert as_list(got) == truth(db, [2])


def overflow_rows(big_topic: int) -> list[tuple[int, int, bytes]]:
    """Small rows of topics 1 and 2 with 3000-byte rows of `big_topic` among them (512-byte pages)."""
    rng = np.random.default_rng(3)
    rows = []
    for k in range(3000):
        topic = big_topic if k % 7 == 3 else 1 + k % 2
        size = 3000 if topic == big_topic else int(rng.integers(0, 441))    # payload <= 477 = U - 35: local
        rows.append((topic, 1_000_000 + k * 10 - (k % 5) * 20, rng.bytes(size)))
    return rows


def test_unwanted_rows_may_overflow_but_a_wanted_one_may_not(tmp_path: Path) -> None:
    """Rows of an unwanted topic spilling onto overflow pages are skipped; a wanted one gives None."""
    db = tmp_path / "m.db3"
    write_table(db, overflow_rows(big_topic=3), page_size=512)
    got = message_rows(db, [1, 2])
    assert got is not None
    assert as_list(got) == truth(db, [1, 2])
    assert message_rows(db, [1, 3]) is None


@pytest.mark.parametrize(("extra", "fits"), [(0, True), (1, False)])
def test_a_payload_overflows_past_usable_size_minus_35(tmp_path: Path, extra: int, fits: bool) -> None:
    """On 512-byte pages a 477-byte payload is all in its cell, a 478-byte one overflows (file format 1.6)."""
    db = tmp_path / "m.db3"
    # payload = record header (6: its size, NULL id, topic, stamp, 2-byte blob type) + 1 (topic 2; topic 1
    # would be serial type 9, no byte) + 2 (stamp) + blob
    write_table(db, [(2, 1000, bytes(range(200))), (2, 1000, b"\x07" * (468 + extra))], page_size=512)
    got = message_rows(db, [2])
    assert (got is not None) == fits
    if got is not None:
        assert as_list(got) == truth(db, [2])


def test_a_wal_with_rows_gives_none(tmp_path: Path) -> None:
    """Rows committed to a WAL that no checkpoint has copied are not in the pages: None while the WAL has them."""
    db = tmp_path / "m.db3"
    write_table(db, random_rows(500, seed=4))
    con = sqlite3.connect(db)
    con.execute("PRAGMA journal_mode=WAL")
    con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)", random_rows(50, seed=5))
    con.commit()
    try:
        assert Path(f"{db}-wal").stat().st_size > 0
        assert message_rows(db, [1, 2]) is None
    finally:
        con.close()                     # the last connection checkpoints and removes the WAL
    got = message_rows(db, [1, 2])
    assert got is not None
    assert as_list(got) == truth(db, [1, 2])
    assert len(got.timestamp) == sum(r[0] in (1, 2) for r in random_rows(500, seed=4) + random_rows(50, seed=5))


def test_files_off_the_plain_case_give_none(tmp_path: Path) -> None:
    """Not SQLite, cut short, a journal beside it, another table layout, a text value as data: None."""
    (tmp_path / "text.db3").write_bytes(b"not a database at all" * 100)
    assert message_rows(tmp_path / "text.db3", [1]) is None
    db = tmp_path / "m.db3"
    write_table(db, random_rows(2000, seed=6))
    assert message_rows(db, [1]) is not None
    journal = Path(f"{db}-journal")
    journal.write_bytes(b"")
    assert message_rows(db, [1]) is None
    journal.unlink()
    cut = tmp_path / "cut.db3"
    cut.write_bytes(db.read_bytes()[:-1000])
    assert message_rows(cut, [1]) is None
    wide = tmp_path / "wide.db3"
    write_table(wide, random_rows(100, seed=7), schema=SCHEMA.replace(")", ", extra INTEGER)"))
    assert message_rows(wide, [1]) is None
    text = tmp_path / "textdata.db3"
    write_table(text, [(1, 5, b"ab"), (2, 6, b"cd")])
    con = sqlite3.connect(text)
    con.execute("INSERT INTO messages (topic_id, timestamp, data) VALUES (2, 7, 'a text value')")
    con.commit()
    con.close()
    assert message_rows(text, [1]) is not None                 # the text row is not wanted
    assert message_rows(text, [2]) is None
    index = tmp_path / "without_rowid.db3"                     # the same columns in an index B-tree
    write_table(index, random_rows(300, seed=8), schema=SCHEMA + " WITHOUT ROWID")
    assert truth(index, [1]) and message_rows(index, [1]) is None
    none = tmp_path / "none.db3"
    write_table(none, [])
    got = message_rows(none, [1])
    assert got is not None and got.timestamp.size == 0


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[bool]]:
    """Whether each scan of a database file by the bag reader read the pages (True) or fell back (False)."""
    calls: list[bool] = []

    def spy(db: Path, ids: Collection[int], visit: Callable[[Rows], object]) -> bool:
        done = scan_rows(db, ids, visit)
        calls.append(done)
        return done

    monkeypatch.setattr(rosbag_batch, "scan_rows", spy)     # the direct path's and the AnyReader path's
    yield calls


def test_bag_reads_the_same_from_the_pages_as_through_sqlite3(tmp_path: Path, sim: Simulation,
                                                             counted: list[bool],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """A ROS 2 sqlite3 bag of the project's writer: every stream identical by both paths (times and values)."""
    write_ros2(sim, tmp_path / "bag", storage="sqlite3")
    fast = RosbagReader().read(tmp_path / "bag", ReadOptions())
    assert counted == [True]
    monkeypatch.setattr(rosbag_batch, "scan_rows", lambda db, ids, visit: False)   # through AnyReader, then sqlite3
    slow = RosbagReader().read(tmp_path / "bag", ReadOptions())
    assert len(fast.streams) == len(sim.recording.streams) == len(slow.streams)
    assert fast.t0 == slow.t0 and fast.notes == slow.notes
    for a, b in zip(fast.streams, slow.streams, strict=True):
        assert (a.kind, a.id, a.native_unit) == (b.kind, b.id, b.native_unit)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.values, b.values)
    mag = sim.recording.select(Kind.MAGNETOMETER)
    np.testing.assert_allclose(fast.select(Kind.MAGNETOMETER).values, mag.values, rtol=0, atol=0)


def test_rows_out_of_time_order_are_read_in_time_order(tmp_path: Path, sim: Simulation, counted: list[bool],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Rowids out of time order and receive times with ties, read a page at a time: each topic's decoded rows are
    put in ORDER BY timestamp's order (ties in rowid order), the same streams and notes as through sqlite3."""
    write_ros2(sim, tmp_path / "bag", storage="sqlite3")
    db = next((tmp_path / "bag").glob("*.db3"))
    con = sqlite3.connect(db)
    rows = con.execute("SELECT topic_id, timestamp, data FROM messages").fetchall()
    con.execute("DELETE FROM messages")
    con.executemany("INSERT INTO messages (id, topic_id, timestamp, data) VALUES (?, ?, ?, ?)",
                    [(k + 1, rows[i][0], rows[i][1] // 50_000_000 * 50_000_000, rows[i][2])
                     for k, i in enumerate(np.random.default_rng(9).permutation(len(rows)).tolist())])
    con.commit()
    con.execute("VACUUM")
    con.close()
    monkeypatch.setattr(sqlite_pages, "CHUNK_BYTES", 4096)      # one leaf page at a time
    fast = RosbagReader().read(tmp_path / "bag", ReadOptions())
    assert counted == [True]
    monkeypatch.setattr(rosbag_batch, "scan_rows", lambda db, ids, visit: False)
    slow = RosbagReader().read(tmp_path / "bag", ReadOptions())
    assert any("went backwards" in n for n in fast.notes)
    assert fast.t0 == slow.t0 and fast.notes == slow.notes and len(fast.streams) == len(slow.streams)
    for a, b in zip(fast.streams, slow.streams, strict=True):
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.values, b.values)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_plain_bag_is_read_without_rosbags_anyreader(tmp_path: Path, sim: Simulation, storage: str,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """AnyReader.open counts every topic's messages over the whole table: a plain bag does not need it (the same
    streams as the AnyReader path); a bag whose metadata says compressed goes the AnyReader way."""
    from rosbags.highlevel import AnyReader

    write_ros2(sim, tmp_path / "bag", storage=storage)
    with monkeypatch.context() as m:
        m.setattr(rosbag, "read_direct", lambda *args: None)
        slow = RosbagReader().read(tmp_path / "bag", ReadOptions())             # through AnyReader

    def refuse(self: object) -> None:
        raise AssertionError("AnyReader opened")

    monkeypatch.setattr(AnyReader, "open", refuse)
    rec = RosbagReader().read(tmp_path / "bag", ReadOptions())
    assert len(rec.streams) == len(sim.recording.streams) == len(slow.streams) and rec.notes == slow.notes
    for a, b in zip(rec.streams, slow.streams, strict=True):
        assert (a.kind, a.id) == (b.kind, b.id)
        np.testing.assert_array_equal(a.values, b.values)
    meta = tmp_path / "bag" / "metadata.yaml"
    meta.write_text(meta.read_text().replace("compression_mode: ''", "compression_mode: FILE"))
    assert read_direct(tmp_path / "bag", Collector(), ReadOptions(), []) is None


def test_a_metadata_file_that_is_not_utf8_goes_the_anyreader_way(tmp_path: Path, sim: Simulation) -> None:
    """The fuzzer's find: one byte inserted before metadata.yaml's text made read_direct raise UnicodeDecodeError
    (exit 123); it now declines the bag, and the AnyReader path reads the storage file and says why."""
    write_ros2(sim, tmp_path / "bag", storage="mcap")
    meta = tmp_path / "bag" / "metadata.yaml"
    meta.write_bytes(b"\xa7" + meta.read_bytes())
    assert read_direct(tmp_path / "bag", Collector(), ReadOptions(), []) is None
    rec = RosbagReader().read(tmp_path / "bag", ReadOptions())
    assert len(rec.streams) == len(sim.recording.streams)
    assert any("utf-8" in n for n in rec.notes)


def test_a_cut_database_whose_header_declares_terabytes_is_refused_cleanly(tmp_path: Path, sim: Simulation) -> None:
    """The fuzzer's find: a damaged header declaring a page count of 2^32 - 1 made the cut-database reader
    allocate the padding in memory (MemoryError, exit 123). The padding is now a sparse file extension, and one
    the file system refuses leaves the bag to the 'cannot open' error."""
    write_ros2(sim, tmp_path / "bag", storage="sqlite3")
    db = next((tmp_path / "bag").glob("*.db3"))
    data = bytearray(db.read_bytes())
    data[16:18] = (1).to_bytes(2, "big")                 # 65536-byte pages
    data[28:32] = (2**32 - 1).to_bytes(4, "big")         # 2^32 - 1 of them: 281 TB declared
    db.write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(LogReadError, match="cannot open the rosbag2"):
        RosbagReader().read(tmp_path / "bag", ReadOptions())
