"""The history store: one SQLite file (stdlib sqlite3), safe under concurrent writers, with a versioned schema.

Write-ahead logging lets readers go on while one process writes; `busy_timeout` makes a second writer wait for
the first instead of failing, and every `record` is one `BEGIN IMMEDIATE` transaction (all of a batch's entries
or none). A result is keyed by (log content hash, magnetometer): recording the same log again, under any name,
changes nothing (`INSERT OR IGNORE`). WAL needs a local file system (SQLite's own caveat): keep the store off
network drives; on a Dask cluster the client alone writes it.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from magcal_cli.errors import MagcalError

SCHEMA_VERSION = 1
#: how long a writer waits for another's transaction (ms)
BUSY_TIMEOUT_MS = 60_000
#: the statements that bring a store from version n-1 to n
MIGRATIONS: dict[int, tuple[str, ...]] = {
    1: ("""CREATE TABLE results (
             id INTEGER PRIMARY KEY,
             sha256 TEXT NOT NULL, mag_id TEXT NOT NULL,
             vehicle TEXT NOT NULL, vehicle_source TEXT NOT NULL, sensor TEXT NOT NULL,
             log_utc REAL, path TEXT NOT NULL, format TEXT NOT NULL, method TEXT NOT NULL, unit TEXT NOT NULL,
             magcal_version TEXT NOT NULL, recorded_utc TEXT NOT NULL,
             params TEXT NOT NULL, quality TEXT NOT NULL, covariance TEXT NOT NULL, effects TEXT NOT NULL,
             UNIQUE (sha256, mag_id))""",
        "CREATE INDEX results_series ON results (vehicle, sensor, log_utc)"),
}
COLUMNS = ("sha256", "mag_id", "vehicle", "vehicle_source", "sensor", "log_utc", "path", "format", "method", "unit",
           "magcal_version", "recorded_utc")
JSON_COLUMNS = ("params", "quality", "covariance", "effects")


class HistoryError(MagcalError):
    """The history store cannot be opened, read or written."""


def _fail(path: Path, exc: Exception, what: str) -> HistoryError:
    """A one-line error for a store problem."""
    return HistoryError(f"{path}: cannot {what} the history store ({exc}). Check the path and its permissions, or "
                        "give another --history file")


def _migrate(con: sqlite3.Connection, path: Path) -> None:
    """Create or upgrade the schema, in one transaction (concurrent openers wait for it)."""
    con.execute("BEGIN IMMEDIATE")
    try:
        con.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
        row = con.execute("SELECT max(version) FROM schema_version").fetchone()
        have = int(row[0]) if row and row[0] is not None else 0
        if have > SCHEMA_VERSION:
            msg = (f"{path}: history store schema {have} is newer than this magcal reads ({SCHEMA_VERSION}). "
                   "Upgrade magcal")
            raise HistoryError(msg)
        for version in range(have + 1, SCHEMA_VERSION + 1):
            for statement in MIGRATIONS[version]:
                con.execute(statement)
            con.execute("INSERT INTO schema_version (version) VALUES (?)", (version,))
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def _wal(con: sqlite3.Connection) -> None:
    """Put the store in WAL mode, waiting out another opener doing the same: SQLite answers that switch with
    "database is locked" at once, without the busy handler, when two processes open a new store together."""
    deadline = time.monotonic() + BUSY_TIMEOUT_MS / 1000
    while True:
        try:
            if con.execute("PRAGMA journal_mode").fetchone()[0] != "wal":     # WAL persists: set once per file
                con.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.02)


@contextlib.contextmanager
def connect(path: Path, create: bool = True) -> Iterator[sqlite3.Connection]:
    """An open store (created and migrated when `create`), closed on exit."""
    if not create and not path.is_file():
        msg = f"{path}: no such history store. Record one with magcal fit --history {path} or batch --history"
        raise HistoryError(msg)
    try:
        con = sqlite3.connect(path, timeout=BUSY_TIMEOUT_MS / 1000, isolation_level=None)
    except sqlite3.Error as exc:
        raise _fail(path, exc, "open") from None
    try:
        con.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
        _wal(con)
        _migrate(con, path)
        yield con
    except sqlite3.DatabaseError as exc:
        raise _fail(path, exc, "use") from None
    finally:
        con.close()


def record(path: Path, entries: list[dict[str, Any]]) -> int:
    """Add `entries` (history.entry) in one transaction; returns how many were new (known logs change nothing)."""
    if not entries:
        return 0
    names = (*COLUMNS, *JSON_COLUMNS)
    sql = f"INSERT OR IGNORE INTO results ({', '.join(names)}) VALUES ({', '.join('?' * len(names))})"
    rows = [tuple(e[c] for c in COLUMNS) + tuple(json.dumps(e[c]) for c in JSON_COLUMNS) for e in entries]
    with connect(path) as con:
        con.execute("BEGIN IMMEDIATE")
        try:
            before = con.total_changes
            con.executemany(sql, rows)
            added = con.total_changes - before
            con.execute("COMMIT")
        except BaseException:
            con.execute("ROLLBACK")
            raise
    return added


def load(path: Path) -> list[dict[str, Any]]:
    """Every entry of the store, ordered by vehicle, sensor, log time and path."""
    names = (*COLUMNS, *JSON_COLUMNS)
    with connect(path, create=False) as con:
        rows = con.execute(f"SELECT {', '.join(names)} FROM results "
                           "ORDER BY vehicle, sensor, log_utc IS NULL, log_utc, path").fetchall()
    return [dict(zip(COLUMNS, r[:len(COLUMNS)], strict=True))
            | {c: json.loads(v) for c, v in zip(JSON_COLUMNS, r[len(COLUMNS):], strict=True)} for r in rows]
