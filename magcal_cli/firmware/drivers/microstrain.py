"""microstrain_inertial_driver (LORD-MicroStrain/microstrain_inertial): the device's hard-iron offset and soft-iron
matrix.

MIP commands 0x0C3A (Magnetometer Hard Iron Offset, float[3]) and 0x0C3B (Soft Iron Matrix, float[9], row major),
mip_sdk src/mip/definitions/commands_3dm.h: both are "applied to the scaled magnetometer vector prior to output",
which is in gauss; MicroStrain's own calibration tools apply them as M (y - offset) (offset first, then the
matrix). The ROS driver sets them through its set_hard_iron_values (bias: Vector3) and set_soft_iron_matrix
(soft_iron_1..3: the rows) services; its params.yml has no parameter for them, so the file carries them as
`mag_hard_iron_offset` / `mag_soft_iron_matrix` for a launch file or script, and the header gives the two calls.
"""

from __future__ import annotations

import numpy as np

from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.firmware.drivers.common import (
    DriverFile,
    header,
    held_line,
    in_unit,
    not_held,
    num,
    ros2_params,
    vector,
)

NAME = "microstrain_inertial_driver"


def parameters(mag: MagCalibration) -> tuple[np.ndarray, np.ndarray, float]:
    """(hard-iron offset in gauss, soft-iron matrix F A, F in gauss): M (y - offset) is the field of strength F."""
    return in_unit(mag, "gauss")


def _calls(h: np.ndarray, s: np.ndarray) -> list[str]:
    """The two service calls that set the values on a running driver (ROS 2)."""
    rows = ", ".join(f"soft_iron_{i + 1}: {{x: {num(s[i, 0])}, y: {num(s[i, 1])}, z: {num(s[i, 2])}}}"
                     for i in range(3))
    return ["set them on the running driver (node namespace as launched), then save_settings if wanted:",
            f"  ros2 service call set_hard_iron_values microstrain_inertial_msgs/srv/SetHardIronValues "
            f"\"{{bias: {{x: {num(h[0])}, y: {num(h[1])}, z: {num(h[2])}}}}}\"",
            f"  ros2 service call set_soft_iron_matrix microstrain_inertial_msgs/srv/SetSoftIronMatrix \"{{{rows}}}\""]


def export(mag: MagCalibration, cal: Calibration) -> DriverFile:
    """A ROS 2 parameter file with the offset and matrix, and the service calls in its header."""
    s, h, field = parameters(mag)
    formula = ["MIP 0x0C3A/0x0C3B: out = mag_soft_iron_matrix (y - mag_hard_iron_offset), y in gauss, matrix row "
               "major",
               held_line(mag), f"the field comes out at {field:.5g} gauss",
               "axes: those of the readings magcal calibrated; a log recorded with use_enu_frame: true holds the "
               "driver's ROS axes, not the device's, so check the driver's axis convention before loading",
               "load with the device's iron values at their defaults (zero offset, identity matrix): magcal "
               "calibrated the readings as logged, after any correction the device applied then",
               "the device's temperature is not an input of this correction", *_calls(h, s)]
    values = {"mag_hard_iron_offset": vector(h), "mag_soft_iron_matrix": vector(s)}
    text = header(cal, mag, NAME, formula, []) + ros2_params(values)
    return DriverFile(NAME, mag.id, text, tuple(not_held(cal, mag, NAME)))
