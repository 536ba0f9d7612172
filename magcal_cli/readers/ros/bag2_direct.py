"""A plain ROS 2 bag read straight from its storage files, without opening it through rosbags' AnyReader.

AnyReader.open costs what the read itself costs on a small bag: for sqlite3 storage it counts every topic's
messages with a query over the whole table (0.26 s of a 1.1 s read of 100 MB), and it builds a typestore that
MCAP storage does not need (each MCAP file carries its schemas). A bag whose metadata.yaml names uncompressed
sqlite3 or MCAP files is read here; anything else (compression, types outside the Humble typestore, another
serialisation, a database the pages reader declines) returns None and the AnyReader path reads the bag, with
nothing read twice.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from magcal_cli.readers import ReadOptions
from magcal_cli.readers.ros.bag_batch import Decoded, add_decoded, batch_decoder, read_db3, storage_files
from magcal_cli.readers.ros.msg import Collector, wanted
from magcal_cli.readers.ros.nested import may_hold
from magcal_cli.readers.ros.types2 import humble_subset
from magcal_cli.streams import Cut

#: metadata.yaml's storage identifier -> the storage files' suffix
STORAGE = {"sqlite3": ".db3", "mcap": ".mcap"}


class _Cdr:
    """What `batch_decoder` needs of a reader, for a bag read without rosbags' AnyReader (CDR, ROS 2 types)."""

    is2 = True

    def __init__(self, typestore: Any) -> None:
        self.typestore = typestore

    def deserialize(self, data: bytes, msgtype: str) -> Any:
        """One message, for layouts the vectorised decoder leaves to the generic one."""
        return self.typestore.deserialize_cdr(data, msgtype)


def read_direct(bag: Path, collector: Collector, options: ReadOptions, notes: list[str]
                ) -> tuple[list[str], Cut | None] | None:
    """Read a plain ROS 2 bag: (the topics of types magcal does not read, where its last file is cut), or None
    (nothing read) when it is not one."""
    import yaml

    try:
        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        storage = str(info.get("storage_identifier"))
        plain = not info.get("compression_mode") and not info.get("compression_format")
        topics = [(str(t["topic_metadata"]["name"]), str(t["topic_metadata"]["type"]))
                  for t in info.get("topics_with_message_count") or []]
    except (OSError, ValueError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        return None                         # not UTF-8 (ValueError), not YAML: AnyReader's error names it
    files = storage_files(bag, info)
    suffix = STORAGE.get(storage)
    if not plain or suffix is None or not files or not all(f.suffix == suffix and f.is_file() for f in files):
        return None
    if storage == "mcap":
        from magcal_cli.readers.ros.mcap import collect

        cut = None
        for f in files:
            cut = collect(f, collector, options, notes, note_ignored=False) or cut
        # a topic whose fields were read (`/imu.mag_field`) is not ignored; Collector is no dict (SIM118)
        nested = {k[0].split(".", 1)[0] for k in collector.keys() if "." in k[0]}  # noqa: SIM118
        return sorted({f"{n} ({t})" for n, t in topics if not wanted(n, t) and n not in nested}), cut
    ignored = _read_db3s(files, collector, notes)
    return None if ignored is None else (ignored, None)


def _read_db3s(dbs: list[Path], collector: Collector, notes: list[str]) -> list[str] | None:
    """The sqlite3 files through the pages reader: the ignored topics, or None when one of them is not plain."""
    reader = _Cdr(humble_subset())          # the wanted types of the AnyReader path's default typestore
    found: list[Decoded] = []
    ignored: set[str] = set()
    for db in dbs:
        try:
            con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
            try:
                topics = con.execute("SELECT id, name, type, serialization_format FROM topics").fetchall()
                if _holds_nested(con, {str(t) for _, n, t, _ in topics if not wanted(str(n), str(t))}):
                    return None             # custom types holding standard ones: AnyReader registers them
            finally:
                con.close()
        except (sqlite3.Error, ValueError):             # a damaged database, a name that is not UTF-8
            return None
        ids = {int(i): SimpleNamespace(topic=str(n), msgtype=str(t)) for i, n, t, _ in topics
               if wanted(str(n), str(t))}
        ignored |= {f"{n} ({t})" for _, n, t, _ in topics if not wanted(str(n), str(t))}
        for _, n, t, _ in topics:
            collector.saw(str(n), str(t), wanted(str(n), str(t)))
        if any(str(f) != "cdr" for i, _, _, f in topics if int(i) in ids) \
                or any(c.msgtype not in reader.typestore.fielddefs for c in ids.values()):
            return None
        if ids:
            rows = read_db3(db, ids, {i: batch_decoder(reader, c.msgtype) for i, c in ids.items()})
            if rows is None:
                return None
            found.append(rows)
    bad = sum(add_decoded(rows, collector) for rows in found)      # nothing is added before every file is read
    if bad:
        notes.append(f"corrupt data: skipped {bad} messages that did not decode")
    return sorted(ignored)


def _holds_nested(con: sqlite3.Connection, types: set[str]) -> bool:
    """Whether the embedded definition (Iron and later) of one of `types` names a standard sensor type."""
    if not types or not con.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = "
                                    "'message_definitions'").fetchone():
        return False
    rows = con.execute("SELECT topic_type, encoded_message_definition FROM message_definitions").fetchall()
    return any(str(t) in types and may_hold(str(d)) for t, d in rows)
