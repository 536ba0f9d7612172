"""Driver-ready exports: a calibration as the parameters an IMU driver loads (`magcal export --driver NAME`).

One module per driver, each with `export(mag, cal) -> DriverFile`; DRIVERS maps the name users type to it as an
import string (registry.resolve). The driver's own correction formula, units and source are in each module's
docstring and in docs/firmware-export.md section "IMU drivers".
"""

from __future__ import annotations

from collections.abc import Sequence

from magcal_cli.calibration.types import Calibration
from magcal_cli.firmware import FirmwareError
from magcal_cli.firmware.drivers.common import DriverFile, pick
from magcal_cli.registry import resolve

#: driver name -> "module:function(mag, cal) -> DriverFile"
DRIVERS: dict[str, str] = {
    "phidgets_spatial": "magcal_cli.firmware.drivers.phidgets:export",
    "microstrain_inertial_driver": "magcal_cli.firmware.drivers.microstrain:export",
    "generic": "magcal_cli.firmware.drivers.generic:export",
}


def export_driver(cal: Calibration, driver: str, mag_ids: Sequence[str] = ()) -> DriverFile:
    """The file `driver` loads for the one magnetometer `mag_ids` selects (the only one when empty)."""
    if driver not in DRIVERS:
        msg = f"export: no driver {driver!r}; --driver takes {', '.join(DRIVERS)}"
        raise FirmwareError(msg)
    mag = pick(cal, mag_ids, driver)
    out: DriverFile = resolve(DRIVERS[driver], f"--driver {driver}")(mag, cal)
    return out


__all__ = ["DRIVERS", "DriverFile", "export_driver"]
