"""The small typestore of the ROS 2 messages magcal reads: the same definitions and decoding as rosbags' Humble."""

from __future__ import annotations

from magcal_cli.readers.ros.msg import ROS_TYPES
from magcal_cli.readers.ros.types2 import DEFINITIONS, humble_subset


def test_the_subset_is_humbles_wanted_types_and_what_they_contain() -> None:
    """Every type magcal reads that Humble has, the types inside them, each with Humble's fields; nothing else."""
    from rosbags.typesys import Stores, get_typestore

    humble, store = get_typestore(Stores.ROS2_HUMBLE), humble_subset()
    wanted = [t for t in ROS_TYPES if t in humble.fielddefs]
    assert set(wanted) == {t for t in ROS_TYPES if t in store.fielddefs}
    assert set(DEFINITIONS) == set(store.fielddefs)
    for name in DEFINITIONS:
        assert store.fielddefs[name][1] == humble.fielddefs[name][1], name
    inside = {spec for name in DEFINITIONS for _, (node, spec) in humble.fielddefs[name][1] if node.name == "NAME"}
    assert inside <= set(DEFINITIONS)


def test_messages_decode_as_humble_decodes_them() -> None:
    """A message of each type serialised by the Humble store decodes to the same values."""
    from rosbags.typesys import Stores, get_typestore

    humble, store = get_typestore(Stores.ROS2_HUMBLE), humble_subset()
    for name in [t for t in ROS_TYPES if t in DEFINITIONS]:
        raw = bytes(humble.serialize_cdr(_sample(humble, name), name))
        assert _fields(store.deserialize_cdr(raw, name)) == _fields(humble.deserialize_cdr(raw, name)), name


def _fields(msg: object) -> object:
    """A decoded message's field values (nested messages as dicts, arrays as lists); constants left out."""
    if hasattr(msg, "__msgtype__"):
        return {k: _fields(v) for k, v in vars(msg).items() if not k.isupper() and k != "__msgtype__"}
    return msg.tolist() if hasattr(msg, "tolist") else msg


def _sample(store: object, name: str) -> object:
    """A message of `name` whose numeric fields are 1, 2, 3, ... and strings "s1", "s2", ... (arrays of 2)."""
    import numpy as np

    count = iter(range(1, 1000))
    fields = {}
    for field, (node, spec) in store.fielddefs[name][1]:  # type: ignore[attr-defined]
        if node.name == "NAME":
            fields[field] = _sample(store, spec)
        elif node.name == "BASE":
            fields[field] = f"s{next(count)}" if spec[0] == "string" else (spec[0] == "bool") or next(count)
        else:
            first, size = next(count), spec[1] or 2
            fields[field] = np.arange(first, first + size, dtype=np.dtype(spec[0][1][0]))
    return store.types[name](**fields)  # type: ignore[attr-defined]
