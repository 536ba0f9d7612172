"""Standard sensor messages held as fields of a custom message (`vn_driver/Vectornav.mag_field`), at any depth.

Many drivers publish one custom message that wraps a `sensor_msgs/Imu`, a `sensor_msgs/MagneticField` and the
like. The bag or MCAP file embeds the custom type's definition; rosbags registers it into a typestore, its
field tree says where the standard messages sit, and each message is decoded with rosbags' generic
deserializer (custom wrappers are small logs: no vectorised path). A nested message becomes the stream
`TOPIC.FIELD` (`/imu.mag_field`, deeper `/x.a.b`); its stamp is its own header's, or the nearest enclosing
header's where its own is zero (drivers often fill only the outer one).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from magcal_cli.readers.ros.msg import ROS_TYPES, Collector, normalise_type, stamp_ns, wanted

#: the standard types found nested (ActuatorControl is mavros', not a field drivers embed)
STANDARD = tuple(t for t in ROS_TYPES if t.startswith(("sensor_msgs/", "geometry_msgs/")))
#: their short names: a schema text without any of them holds none (skips parsing unrelated schemas)
SHORT_NAMES = tuple(t.rsplit("/", 1)[1] for t in STANDARD)
#: deeper than this a type tree refers to itself (rosbags forbids it; a damaged definition may not)
MAX_DEPTH = 8

FieldPath = tuple[str, ...]


def find(fielddefs: dict[str, Any], msgtype: str, depth: int = 0) -> list[tuple[FieldPath, str]]:
    """(field path, standard type) of every standard message that `msgtype` holds as a field, at any depth.

    Arrays and sequences of them are left out: one field, one stream."""
    defs = fielddefs.get(msgtype) or fielddefs.get(normalise_type(msgtype))
    if defs is None or depth > MAX_DEPTH:
        return []
    out: list[tuple[FieldPath, str]] = []
    for name, (node, spec) in defs[1]:
        if getattr(node, "name", str(node)) != "NAME":
            continue
        inner = normalise_type(str(spec))
        if inner in STANDARD:
            out.append(((name,), inner))
        else:
            out += [((name, *path), typ) for path, typ in find(fielddefs, str(spec), depth + 1)]
    return out


def may_hold(definition: str) -> bool:
    """Whether a message definition text names a standard type at all (cheap test before parsing it)."""
    return any(name in definition for name in SHORT_NAMES)


class Nested:
    """The standard messages nested in one topic's custom type, collected message by message."""

    def __init__(self, topic: str, fielddefs: dict[str, Any], msgtype: str,
                 decode: Callable[[bytes], Any]) -> None:
        self.topic, self.msgtype, self.decode = topic, msgtype, decode
        self.parts = [(f"{topic}.{'.'.join(path)}", path, typ) for path, typ in find(fielddefs, msgtype)]
        self.parts = [p for p in self.parts if wanted(p[0], p[2])]
        self.rows: list[tuple[int, list[tuple[int, tuple[float, ...]]]]] = []
        self.bad = 0

    def __bool__(self) -> bool:
        return bool(self.parts)

    def add(self, recv_ns: int, raw: bytes) -> None:
        """Decode one message and keep the stamp and values of each nested one (a corrupt message is counted)."""
        try:
            msg = self.decode(raw)
            self.rows.append((recv_ns, [_one(msg, path, typ) for _, path, typ in self.parts]))
        except Exception:  # noqa: BLE001 - rosbags' deserializers raise anything on corrupt bytes
            self.bad += 1

    def flush(self, collector: Collector) -> None:
        """Hand what was collected to `collector`, one stream group per nested message."""
        if not self.rows:
            return
        recv = np.array([r for r, _ in self.rows], dtype=np.int64)
        for k, (name, _, typ) in enumerate(self.parts):
            stamps = np.array([row[k][0] for _, row in self.rows], dtype=np.int64)
            values = np.array([row[k][1] for _, row in self.rows], dtype=np.float64)
            collector.add_batch(name, typ, recv, stamps, values)
        self.rows.clear()


def _one(msg: Any, path: FieldPath, typ: str) -> tuple[int, tuple[float, ...]]:
    """Stamp (own header, else the nearest enclosing non-zero one) and values of the message at `path`."""
    chain = [msg]
    for name in path:
        chain.append(getattr(chain[-1], name))
    stamp = 0
    for obj in reversed(chain):
        if hasattr(obj, "header") and (stamp := stamp_ns(obj)):
            break
    return stamp, tuple(float(v) for v in ROS_TYPES[typ][2](chain[-1]))


def nested_of(reader: Any, conns: list[Any]) -> dict[int, Nested]:
    """Connection id -> its nested standard messages, for the connections of an open AnyReader that hold any."""
    out = {}
    for c in conns:
        found = Nested(c.topic, reader.typestore.fielddefs, c.msgtype, _deserializer(reader, c.msgtype))
        if found:
            out[c.id] = found
    return out


def read_nested(reader: Any, nested: dict[int, Nested], collector: Collector, notes: list[str]) -> None:
    """Read the messages of the connections in `nested` (rosbags' iteration) into `collector`."""
    if not nested:
        return
    conns = [c for c in reader.connections if c.id in nested]
    try:
        for conn, recv_ns, raw in reader.messages(connections=conns):
            nested[conn.id].add(int(recv_ns), raw)
    except Exception as exc:  # noqa: BLE001 - a corrupt chunk: what was read before it is kept
        notes.append(f"corrupt data: reading the custom messages stopped early ({str(exc)[:80]})")
    bad = 0
    for found in nested.values():
        found.flush(collector)
        bad += found.bad
    if bad:
        notes.append(f"corrupt data: skipped {bad} custom messages that did not decode")


def _deserializer(reader: Any, msgtype: str) -> Callable[[bytes], Any]:
    """An open AnyReader's generic deserializer of `msgtype` (ROS 1 or CDR, as the bag is)."""
    def decode(raw: bytes) -> Any:
        return reader.deserialize(raw, msgtype)

    return decode
