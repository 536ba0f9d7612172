"""phidgets_spatial (ros-drivers/phidgets_drivers): the cc_* compass-correction parameters.

The node passes cc_mag_field, cc_offset0..2, cc_gain0..2 and cc_t0..5 (all thirteen, or none) to libphidget22's
PhidgetSpatial_setMagnetometerCorrectionParameters. libphidget22 (src/device/spatialdevice.c, getCorrectedField)
corrects each reading y, in gauss, as

    out_x = magField (gain0 (y_x - offset0) + T0 (y_y - offset1) + T1 (y_z - offset2))
    out_y = magField (T2 (y_x - offset0) + gain1 (y_y - offset1) + T3 (y_z - offset2))
    out_z = magField (T4 (y_x - offset0) + T5 (y_y - offset1) + gain2 (y_z - offset2))

i.e. out = magField M (y - offset) with M = [[gain0, T0, T1], [T2, gain1, T3], [T4, T5, gain2]]: a full 3x3, so
magcal's A = D^-1 and o fit exactly. The node publishes out * 1e-4 (tesla) in the device's axes (imu_link).
PhidgetSpatialDevice_setCompassCorrectionParameters refuses magField outside 0.1..1000, an offset outside -5..5,
a gain outside 0..15 and a T outside -5..5 (LIMITS); the 1042/1044 store gains and T in 1/65536 steps and offsets
in whole sensor counts, the VINT MOT0109/MOT0110 as float32.
"""

from __future__ import annotations

from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.firmware.common import check_limits
from magcal_cli.firmware.drivers.common import (
    DriverFile,
    header,
    held_line,
    in_unit,
    not_held,
    num,
    ros2_params,
)

NAME = "phidgets_spatial"
#: the (row, column) of M each cc_t* parameter fills (getCorrectedField)
T_CELLS = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))
#: parameter prefix -> (low, high) that libphidget22 accepts (setCompassCorrectionParameters)
LIMITS = {"cc_mag_field": (0.1, 1000.0), "cc_offset": (-5.0, 5.0), "cc_gain": (0.0, 15.0), "cc_t": (-5.0, 5.0)}


def _limits(mag: MagCalibration, values: dict[str, float]) -> None:
    """Refuse values libphidget22 would reject (a negative gain: an axis the correction would have to flip)."""
    errors = []
    for name, value in values.items():
        lo, hi = LIMITS[name.rstrip("012345")]
        if not lo <= value <= hi:
            errors.append(f"{name}={value:.4g} is outside libphidget22's {lo:g}..{hi:g}")
    check_limits(f"export --driver {NAME}: {mag.id}", errors + (
        ["the device cannot load these; check the compass's axes (a flipped axis needs a negative gain)"]
        if errors else []))


def parameters(mag: MagCalibration) -> dict[str, float]:
    """cc_* values: magField = F (gauss), offset = o (gauss), M = F A / magField so magField M = F A."""
    s, h, field = in_unit(mag, "gauss")
    m = s / field
    values = {"cc_mag_field": field}
    values.update({f"cc_offset{i}": float(h[i]) for i in range(3)})
    values.update({f"cc_gain{i}": float(m[i, i]) for i in range(3)})
    values.update({f"cc_t{n}": float(m[r, c]) for n, (r, c) in enumerate(T_CELLS)})
    _limits(mag, values)
    return values


def export(mag: MagCalibration, cal: Calibration) -> DriverFile:
    """A ROS 2 parameter file for the phidgets_spatial node (any node name: /**)."""
    values = parameters(mag)
    formula = ["libphidget22 getCorrectedField: out = cc_mag_field * M (y - cc_offset), y in gauss,",
               "M = [[cc_gain0, cc_t0, cc_t1], [cc_t2, cc_gain1, cc_t3], [cc_t4, cc_t5, cc_gain2]]",
               held_line(mag), f"the field comes out at cc_mag_field = {values['cc_mag_field']:.5g} gauss",
               "load on a device with its correction reset (resetMagnetometerCorrectionParameters): magcal "
               "calibrated the readings as logged, after any correction the device applied then",
               "the device's temperature is not an input of this correction"]
    text = header(cal, mag, NAME, formula, []) + ros2_params({k: num(v) for k, v in values.items()})
    return DriverFile(NAME, mag.id, text, tuple(not_held(cal, mag, NAME)))
