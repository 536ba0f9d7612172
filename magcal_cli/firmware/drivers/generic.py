"""A driver-neutral `hard_iron` / `soft_iron` YAML: m = S (y - h), in the unit of the readings magcal calibrated.

Many hobby drivers read these two names; S (row major) maps a reading y minus the hard-iron offset h to the field
of strength `field_strength` in the IMU's axes. Drivers that want a unit-length field divide S by it.
"""

from __future__ import annotations

import json

from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.firmware.drivers.common import DriverFile, header, held_line, in_unit, not_held, num, vector

NAME = "generic"


def export(mag: MagCalibration, cal: Calibration) -> DriverFile:
    """hard_iron, soft_iron (3x3 nested rows), field_strength and unit, in the document's magnetometer unit."""
    s, h, field = in_unit(mag, mag.unit)
    formula = ["m = soft_iron (y - hard_iron): y a reading in `unit`, m the field in the IMU's axes, |m| = "
               "field_strength",
               held_line(mag),
               "temperature is not an input of this correction"]
    rows = ", ".join(vector(row) for row in s)
    text = (header(cal, mag, NAME, formula, [])
            + f"magnetometer: {json.dumps(mag.id)}\nunit: {mag.unit}\nfield_strength: {num(field)}\n"
            + f"hard_iron: {vector(h)}\nsoft_iron: [{rows}]\n")
    return DriverFile(NAME, mag.id, text, tuple(not_held(cal, mag, NAME)))
