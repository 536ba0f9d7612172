"""Export a calibration document as firmware parameters: the dispatch to the ArduPilot or PX4 exporter.

A calibration document holds D and o in the magnetometer's unit; the firmware should output the body field
b = A (y - o - c p) with A = F D^-1 (F = field_strength), i.e. a field of strength F in the firmware's unit
(firmware-export.md section 3). The exporters choose the slot, the rotation and the symmetric factor; the split
says what is lost. Their shared types and helpers are in `common`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from magcal_cli.calibration.types import Calibration
from magcal_cli.firmware import FirmwareError
from magcal_cli.firmware.ardupilot import export_ardupilot
from magcal_cli.firmware.common import Export, Options
from magcal_cli.firmware.px4 import export_px4


def export(cal: Calibration, firmware: str, params: Mapping[str, float], options: Options | None = None,
           mag_ids: Sequence[str] | None = None) -> Export:
    """Export a calibration document for `firmware` ("ardupilot" or "px4") given the vehicle's parameters."""
    options = options or Options()
    if firmware == "ardupilot":
        return export_ardupilot(cal, params, options, mag_ids)
    if firmware == "px4":
        return export_px4(cal, params, options, mag_ids)
    msg = f"firmware {firmware!r} is not known; use ardupilot or px4"
    raise FirmwareError(msg)
