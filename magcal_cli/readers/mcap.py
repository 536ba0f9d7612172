"""MCAP reader: ROS 2 (CDR), ROS 1 and JSON channels of the ROS sensor types; zstd or lz4 chunks.

Decoding uses rosbags' typestore built from each channel's own schema, so ROS 1 and ROS 2 messages share
one code path with the bag reader (rosmsg.py). JSON channels follow docs/readers-ros-csv.md: the schema
name is the ROS type, the message object has the ROS field names.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

from ..errors import LogReadError
from ..streams import Recording
from . import ReadOptions
from .rosbag import ignored_note
from .rosmsg import Collector, normalise_type, wanted

Decode = Callable[[bytes], Any]
_SEP = "=" * 80 + "\n"


def _namespace(obj: dict[str, Any]) -> SimpleNamespace:
    return SimpleNamespace(**obj)


def decode_json(data: bytes) -> Any:
    """A JSON message as nested namespaces, so the ROS field accessors apply unchanged."""
    return json.loads(data, object_hook=_namespace)


def ros_decoder(schema: Any, encoding: str) -> Decode:
    """Deserializer of `schema` (ros2msg/ros2idl with cdr, ros1msg with ros1) from its own definition."""
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
    if encoding == "ros1":
        return lambda data: store.deserialize_ros1(data, name)
    return lambda data: store.deserialize_cdr(data, name)


def decoder(schema: Any, channel: Any) -> tuple[Decode | None, str]:
    """How to decode a channel magcal reads, or None and why it is skipped."""
    if schema is None:
        return None, f"{channel.topic} (no schema)"
    enc, sch = channel.message_encoding, schema.encoding
    if not wanted(channel.topic, schema.name):
        return None, f"{channel.topic} ({schema.name})"
    if enc == "json":
        return decode_json, ""
    if (enc, sch) in {("cdr", "ros2msg"), ("cdr", "ros2idl"), ("ros1", "ros1msg")}:
        from rosbags.typesys import TypesysError

        try:
            return ros_decoder(schema, enc), ""
        except (TypesysError, ValueError, IndexError, UnicodeDecodeError) as exc:
            return None, f"{channel.topic} ({schema.name}: its schema does not parse: {str(exc)[:80]})"
    return None, f"{channel.topic} ({schema.name} in {enc or 'no'} encoding)"


def _why(exc: BaseException) -> str:
    """Why reading stopped, in words (a cut file ends inside a record; anything else names the library error)."""
    from mcap.exceptions import EndOfFile

    if isinstance(exc, (EndOfFile, EOFError, struct.error)):
        return "it ends inside a record"
    return f"{type(exc).__name__}: {str(exc).splitlines()[0][:80] if str(exc) else 'no detail'}"


class McapReader:
    """Reads Imu, MagneticField, Vector3Stamped (field), BatteryState, Temperature and NavSatFix channels."""

    name: ClassVar[str] = "mcap"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Decode every channel magcal reads; a truncated file is an error unless allowed."""
        from mcap.exceptions import McapError
        from mcap.reader import NonSeekingReader
        from rosbags.serde import SerdeError
        from zstandard import ZstdError

        collector, notes = Collector(), []
        decoders: dict[int, Decode | None] = {}
        skipped: list[str] = []
        try:
            with path.open("rb") as fh:
                try:
                    for schema, channel, message in NonSeekingReader(fh, validate_crcs=True).iter_messages(
                            log_time_order=False):
                        if channel.id not in decoders:
                            decoders[channel.id], why = decoder(schema, channel)
                            skipped += [why] if why else []
                        decode = decoders[channel.id]
                        if decode is not None and schema is not None:
                            self._add(path, collector, schema.name, channel, message, decode)
                except (McapError, SerdeError, EOFError, KeyError, struct.error, UnicodeDecodeError,
                        IndexError, ValueError, RuntimeError, ZstdError) as exc:
                    where = f"after {len(collector)} complete messages"
                    if not options.allow_truncated:
                        msg = (f"{path}: the MCAP file is truncated or corrupt ({_why(exc)}) {where}. "
                               "Re-copy the log, or pass --allow-truncated to use the complete part")
                        raise LogReadError(msg) from None
                    notes.append(f"truncated or corrupt: read {len(collector)} complete messages")
        except OSError as exc:
            msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
            raise LogReadError(msg) from None
        if skipped:
            notes.append(ignored_note(sorted(set(skipped))))
        return collector.recording(path, "mcap", options, notes)

    @staticmethod
    def _add(path: Path, collector: Collector, msgtype: str, channel: Any, message: Any, decode: Decode) -> None:
        """Decode one message; one without the type's ROS fields is an error naming the channel."""
        is_json = channel.message_encoding == "json"
        try:
            collector.add(channel.topic, msgtype, message.log_time, decode(message.data))
        except (AttributeError, TypeError, ValueError) as exc:
            if isinstance(exc, ValueError) and not is_json:
                raise                                   # a corrupt CDR/ROS 1 message: handled as corruption
            hint = " See docs/readers-ros-csv.md for the JSON layout magcal reads" if is_json else ""
            msg = (f"{path}: channel {channel.topic} ({msgtype}, {channel.message_encoding}): the message at log "
                   f"time {message.log_time} ns does not have the ROS fields of {msgtype} "
                   f"({type(exc).__name__}: {exc}).{hint}")
            raise LogReadError(msg) from None
