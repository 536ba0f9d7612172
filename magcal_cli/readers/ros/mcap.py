"""MCAP reader: ROS 2 (CDR), ROS 1 and JSON channels of the ROS sensor types; zstd or lz4 chunks.

Decoding uses rosbags' typestore built from each channel's own schema, so ROS 1 and ROS 2 messages share
one code path with the bag reader (msg.py); a chunk's messages of one channel are decoded together by
vec.BatchDecoder (numpy), rosbags only checking one message per layout or decoding the odd ones. JSON channels follow docs/readers-ros-csv.md: the schema
name is the ROS type, the message object has the ROS field names.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

import numpy as np

from magcal_cli.errors import LogReadError
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.cut import mark_cut, refuse_if_strict
from magcal_cli.readers.ros.mcap_chunk import Batch
from magcal_cli.readers.ros.mcap_stream import Damage, iter_batches
from magcal_cli.readers.ros.msg import Collector, ignored_note, normalise_type, wanted
from magcal_cli.readers.ros.nested import Nested, may_hold
from magcal_cli.readers.ros.vec import BatchDecoder
from magcal_cli.streams import Cut, Recording

Decode = Callable[[bytes], Any]
_SEP = "=" * 80 + "\n"


def _namespace(obj: dict[str, Any]) -> SimpleNamespace:
    return SimpleNamespace(**obj)


def decode_json(data: bytes) -> Any:
    """A JSON message as nested namespaces, so the ROS field accessors apply unchanged."""
    return json.loads(data, object_hook=_namespace)


def schema_store(schema: Any) -> tuple[Any, str]:
    """A typestore of `schema`'s own definition (ros2msg, ros2idl or ros1msg) and its normalised type name."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    text = schema.data.decode()
    name = normalise_type(schema.name)
    if schema.encoding == "ros2idl":
        types: dict[str, Any] = {}
        parts = text.split(_SEP)[1:] if text.startswith(_SEP + "IDL: ") else ["\n" + text]
        for part in parts:
            types.update(get_types_from_idl(part.split("\n", 1)[1]))
    else:
        types = get_types_from_msg(text, name)
    store = get_typestore(Stores.EMPTY)          # one store per schema: two schemas may define a type differently
    store.register(types)
    return store, name


def ros_decoder(schema: Any, encoding: str) -> BatchDecoder:
    """Batch decoder of `schema` (ros2msg/ros2idl with cdr, ros1msg with ros1) from its own definition."""
    store, name = schema_store(schema)
    if encoding == "ros1":
        return BatchDecoder(store.fielddefs, name, True, lambda data: store.deserialize_ros1(data, name))
    return BatchDecoder(store.fielddefs, name, False, lambda data: store.deserialize_cdr(data, name))


def nested_decoder(schema: Any, channel: Any) -> Nested | None:
    """The standard messages a custom type holds as fields (nested.py), or None when it holds none."""
    if not may_hold(schema.data.decode(errors="replace")):
        return None
    store, name = schema_store(schema)
    if channel.message_encoding == "ros1":
        return Nested(channel.topic, store.fielddefs, name, lambda data: store.deserialize_ros1(data, name)) or None
    return Nested(channel.topic, store.fielddefs, name, lambda data: store.deserialize_cdr(data, name)) or None


def decoder(schema: Any, channel: Any) -> tuple[Decode | BatchDecoder | Nested | None, str]:
    """How to decode a channel magcal reads, or None and why it is skipped."""
    if schema is None:
        return None, f"{channel.topic} (no schema)"
    enc, sch = channel.message_encoding, schema.encoding
    ros = (enc, sch) in {("cdr", "ros2msg"), ("cdr", "ros2idl"), ("ros1", "ros1msg")}
    if not wanted(channel.topic, schema.name):
        if ros:
            from rosbags.typesys import TypesysError

            try:
                found = nested_decoder(schema, channel)
            except (TypesysError, ValueError, IndexError, UnicodeDecodeError, KeyError):
                found = None             # a definition that does not parse holds nothing magcal can read
            if found is not None:
                return found, ""
        return None, f"{channel.topic} ({schema.name})"
    if enc == "json":
        return decode_json, ""
    if ros:
        from rosbags.typesys import TypesysError

        try:
            return ros_decoder(schema, enc), ""
        except (TypesysError, ValueError, IndexError, UnicodeDecodeError) as exc:
            return None, f"{channel.topic} ({schema.name}: its schema does not parse: {str(exc)[:80]})"
    return None, f"{channel.topic} ({schema.name} in {enc or 'no'} encoding)"


class McapReader:
    """Reads Imu, MagneticField, Vector3Stamped (field), BatteryState, Temperature, NavSatFix, ActuatorControl."""

    name: ClassVar[str] = "mcap"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Decode every channel magcal reads; corrupt chunks are skipped, a cut file is read to its end."""
        collector, notes = Collector(), list[str]()
        cut = collect(path, collector, options, notes)
        return mark_cut(collector.recording(path, "mcap", options, notes), cut)


def collect(path: Path, collector: Collector, options: ReadOptions, notes: list[str],
            note_ignored: bool = True) -> Cut | None:
    """Add the messages of one MCAP file to `collector` and its remarks to `notes` (also for ROS 2 bags).

    Returns where the file is cut (None when it is complete); --strict refuses a cut file. A ROS 2 bag's
    reader names the ignored topics itself (`note_ignored` False)."""
    decoders: dict[int, Decode | BatchDecoder | Nested | None] = {}
    skipped: list[str] = []
    damage = Damage()
    bad = 0
    try:
        with path.open("rb") as fh:
            size = fh.seek(0, 2)
            for schemas, channels, batch in iter_batches(fh, size, damage):
                topics: dict[tuple[str, str], list[tuple[Any, Any]]] = {}
                for cid in np.unique(batch.channel).tolist():
                    channel = channels[cid]
                    schema = schemas.get(channel.schema_id)
                    if cid not in decoders:
                        decoders[cid], why = decoder(schema, channel)
                        skipped += [why] if why else []
                        # a skipped channel's type with why it is skipped ("... in protobuf encoding")
                        kind = why[len(channel.topic) + 2:-1] if why or schema is None else schema.name
                        collector.saw(channel.topic, kind, decoders[cid] is not None)
                    if decoders[cid] is not None and schema is not None:
                        topics.setdefault((channel.topic, normalise_type(schema.name)), []).append((channel, schema))
                for chans in topics.values():
                    bad += _add_topic(path, collector, batch, chans, decoders)
    except OSError as exc:
        msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
        raise LogReadError(msg) from None
    cut = None
    if damage.truncated_at is not None:        # damage that reaches the end of the file is a cut
        lost = damage.lost if damage.why == "it ends inside a record" else f"{damage.why}; {damage.lost}"
        cut = Cut(damage.truncated_at, size, lost)
        refuse_if_strict(path, options, cut)
    if damage.note():
        notes.append(damage.note())
    if bad:
        notes.append(f"skipped {bad} messages that do not decode (corrupt data)")
    if skipped and note_ignored:
        notes.append(ignored_note(sorted(set(skipped))))
    return cut


def _add_topic(path: Path, collector: Collector, batch: Batch, chans: list[tuple[Any, Any]],
               decoders: dict[int, Decode | BatchDecoder | Nested | None]) -> int:
    """Decode the messages of one topic in a batch; how many are corrupt.

    Several ROS channels on one topic (two publishers) are merged back into file order, as one stream."""
    decs = [decoders[c.id] for c, _ in chans]
    vec = [d for d in decs if isinstance(d, BatchDecoder)]
    if len(chans) == 1 or len(vec) < len(decs):
        bad = 0
        for (channel, schema), dec in zip(chans, decs, strict=True):
            mask = batch.channel == channel.id
            if dec is not None:
                bad += _add(path, collector, schema.name, channel, batch if mask.all() else batch.select(mask), dec)
        return bad
    pos, stamps, values, bad = [], [], [], 0
    for (channel, _), vdec in zip(chans, vec, strict=True):
        idx = np.flatnonzero(batch.channel == channel.id)
        ok, st, va = vdec(batch.data, batch.start[idx], batch.length[idx])
        pos.append(idx[ok])
        stamps.append(st[ok])
        values.append(va[ok])
        bad += int(ok.size - ok.sum())
    order = np.argsort(np.concatenate(pos), kind="stable")
    at = np.concatenate(pos)[order]
    channel, schema = chans[0]
    collector.add_batch(channel.topic, schema.name, batch.log_time[at], np.concatenate(stamps)[order],
                        np.concatenate(values)[order])
    return bad


def _add(path: Path, collector: Collector, msgtype: str, channel: Any, batch: Batch,
         decode: Decode | BatchDecoder | Nested) -> int:
    """Decode one channel's messages of a batch; how many are corrupt. A JSON one without the ROS fields is an error."""
    if isinstance(decode, Nested):
        for at, length, log_time in zip(batch.start.tolist(), batch.length.tolist(), batch.log_time.tolist(),
                                        strict=True):
            decode.add(log_time, bytes(batch.data[at:at + length]))
        decode.flush(collector)
        bad, decode.bad = decode.bad, 0
        return bad
    if isinstance(decode, BatchDecoder):
        ok, stamps, values = decode(batch.data, batch.start, batch.length)
        collector.add_batch(channel.topic, msgtype, batch.log_time[ok], stamps[ok], values[ok])
        return int(ok.size - ok.sum())
    bad = 0
    for at, length, log_time in zip(batch.start.tolist(), batch.length.tolist(), batch.log_time.tolist(),
                                    strict=True):
        try:
            collector.add(channel.topic, msgtype, log_time, decode(bytes(batch.data[at:at + length])))
        except (AttributeError, TypeError, ValueError) as exc:
            if isinstance(exc, json.JSONDecodeError):
                bad += 1
                continue
            msg = (f"{path}: channel {channel.topic} ({msgtype}, {channel.message_encoding}): the message at log "
                   f"time {log_time} ns does not have the ROS fields of {msgtype} "
                   f"({type(exc).__name__}: {exc}). See docs/readers-ros-csv.md for the JSON layout magcal reads")
            raise LogReadError(msg) from None
        except Exception:  # noqa: BLE001 - anything else from a corrupt message: skipped, counted
            bad += 1
    return bad
