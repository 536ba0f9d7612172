"""Which vehicle and which compass a recording comes from, as the log itself says (docs/fleet.md).

- ArduPilot (.bin): the board's processor unique id from its boot message (ChibiOS and NuttX boards), else
  SYSID_THISMAV with BRD_SERIAL_NUM where set, else SYSID_THISMAV alone (vehicles sharing it merge); a compass
  MAG[i] by COMPASS_DEV_ID(i+1).
- PX4 (.ulg): the `sys_uuid` info message (pyulog reads the header only); a compass by CAL_MAGi_ID.
- ROS and others: no vehicle id is logged. The first name of a namespaced topic (/uav3/imu/mag -> uav3), else
  the log's folder; a compass by its topic.

`--vehicle` overrides the vehicle. A compass's key names its device id where the log has it, so a replaced
compass starts a new series.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import NamedTuple

from magcal_cli.streams import Recording

#: how a vehicle was found (the store's vehicle_source) -> the words `magcal fleet` says it with; "board uid"
#: is followed by the board's name in parentheses
HOW = {"board uid": "board unique id", "sys_uuid": "board unique id (PX4 sys_uuid)",
       "SYSID_THISMAV + BRD_SERIAL_NUM": "serial number (BRD_SERIAL_NUM)", "SYSID_THISMAV": "SYSID only",
       "--vehicle": "--vehicle", "topic": "topic namespace", "folder": "log folder"}
#: the source that does not tell an ArduPilot fleet's vehicles apart: most leave SYSID_THISMAV at 1
SYSID_ONLY = "SYSID_THISMAV"


class Identity(NamedTuple):
    """A vehicle (and how it was found: "board uid (NAME)", "SYSID_THISMAV + BRD_SERIAL_NUM", "SYSID_THISMAV",
    "sys_uuid", "--vehicle", "topic", "folder")."""

    vehicle: str
    source: str


def identified_by(source: str) -> str:
    """A stored vehicle_source in words: "board unique id (fmuv3)", "serial number (BRD_SERIAL_NUM)", ..."""
    head, _, rest = source.partition(" (")
    return HOW.get(head, source) + (f" ({rest}" if rest and head in HOW else "")


def _int(params: object, name: str) -> int:
    """An integer firmware parameter, 0 when absent."""
    value = getattr(params, "get", lambda _k: None)(name)
    return int(value) if isinstance(value, int | float) else 0


def sys_uuid(path: Path) -> str | None:
    """PX4's `sys_uuid` info message of a ULog (header and definitions only), or None."""
    try:
        from pyulog import ULog
    except ImportError:
        return None
    with contextlib.suppress(Exception):        # a header pyulog cannot read: no uuid, the folder then names it
        info = ULog(str(path), message_name_filter_list=[], parse_header_only=True).msg_info_dict
        uuid = info.get("sys_uuid")
        return None if uuid in (None, "") else str(uuid)
    return None


def vehicle_of(rec: Recording, override: str | None = None, mag_ids: tuple[str, ...] = ()) -> Identity:
    """The vehicle a recording comes from."""
    if override:
        return Identity(override, "--vehicle")
    uid = rec.info.get("board_uid")
    if uid:                                   # the processor's id: unique, and kept across firmware and SYSID
        return Identity(f"uid {uid}", f"board uid ({rec.info.get('board') or 'board'})")
    if rec.format in ("dataflash", "px4log"):
        sysid = _int(rec.params, "SYSID_THISMAV")
        serial = _int(rec.params, "BRD_SERIAL_NUM")
        if sysid or serial:
            name = f"sysid {sysid}" + (f" serial {serial}" if serial else "")
            return Identity(name, "SYSID_THISMAV" + (" + BRD_SERIAL_NUM" if serial else ""))
    if rec.format == "ulog":
        uuid = sys_uuid(rec.path)
        if uuid:
            return Identity(f"uuid {uuid}", "sys_uuid")
    for topic in mag_ids:
        parts = [p for p in topic.split("/") if p]
        if topic.startswith("/") and len(parts) >= 3:
            return Identity(parts[0], "topic")
    return Identity(rec.path.resolve().parent.name or "unknown", "folder")


def sensor_of(rec: Recording, mag_id: str) -> str:
    """A compass's key: its stream id, with the device id the firmware gives it where logged."""
    index = mag_id.rpartition("[")[2].rstrip("]")
    if not index.isdigit():
        return mag_id
    i = int(index)
    if rec.format in ("dataflash", "px4log"):
        dev = _int(rec.params, "COMPASS_DEV_ID" + (str(i + 1) if i else ""))
    elif rec.format == "ulog":
        dev = _int(rec.params, f"CAL_MAG{i}_ID")
    else:
        dev = 0
    return f"{mag_id} dev {dev}" if dev else mag_id
