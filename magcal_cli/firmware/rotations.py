"""Sensor rotation enums of ArduPilot and PX4 as matrices, generated from their (roll, pitch, yaw) tables.

Both firmwares map sensor to body as v_body = Rz(yaw) Ry(pitch) Rx(roll) v (Euler 3-2-1, roll applied first;
firmware-export.md [S9][S19]), which is `so3.from_rpy`. ArduPilot 38 (ROLL_90_PITCH_68_YAW_293) is an explicit
matrix in vector3.cpp, PX4 38 uses the integer angles (90, 68, 293).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.firmware import FirmwareError
from magcal_cli.streams import FloatArray

#: (roll, pitch, yaw) in degrees of the ids 0..37 and 39..40, identical in ArduPilot rotations.h and PX4
#: rotation.h (firmware-export.md section 1 table, [S9][S19]); 38 is per firmware below
COMMON: dict[int, tuple[str, float, float, float]] = {
    0: ("NONE", 0, 0, 0), 1: ("YAW_45", 0, 0, 45), 2: ("YAW_90", 0, 0, 90), 3: ("YAW_135", 0, 0, 135),
    4: ("YAW_180", 0, 0, 180), 5: ("YAW_225", 0, 0, 225), 6: ("YAW_270", 0, 0, 270), 7: ("YAW_315", 0, 0, 315),
    8: ("ROLL_180", 180, 0, 0), 9: ("ROLL_180_YAW_45", 180, 0, 45), 10: ("ROLL_180_YAW_90", 180, 0, 90),
    11: ("ROLL_180_YAW_135", 180, 0, 135), 12: ("PITCH_180", 0, 180, 0), 13: ("ROLL_180_YAW_225", 180, 0, 225),
    14: ("ROLL_180_YAW_270", 180, 0, 270), 15: ("ROLL_180_YAW_315", 180, 0, 315), 16: ("ROLL_90", 90, 0, 0),
    17: ("ROLL_90_YAW_45", 90, 0, 45), 18: ("ROLL_90_YAW_90", 90, 0, 90), 19: ("ROLL_90_YAW_135", 90, 0, 135),
    20: ("ROLL_270", 270, 0, 0), 21: ("ROLL_270_YAW_45", 270, 0, 45), 22: ("ROLL_270_YAW_90", 270, 0, 90),
    23: ("ROLL_270_YAW_135", 270, 0, 135), 24: ("PITCH_90", 0, 90, 0), 25: ("PITCH_270", 0, 270, 0),
    26: ("PITCH_180_YAW_90", 0, 180, 90), 27: ("PITCH_180_YAW_270", 0, 180, 270),
    28: ("ROLL_90_PITCH_90", 90, 90, 0), 29: ("ROLL_180_PITCH_90", 180, 90, 0),
    30: ("ROLL_270_PITCH_90", 270, 90, 0), 31: ("ROLL_90_PITCH_180", 90, 180, 0),
    32: ("ROLL_270_PITCH_180", 270, 180, 0), 33: ("ROLL_90_PITCH_270", 90, 270, 0),
    34: ("ROLL_180_PITCH_270", 180, 270, 0), 35: ("ROLL_270_PITCH_270", 270, 270, 0),
    36: ("ROLL_90_PITCH_180_YAW_90", 90, 180, 90), 37: ("ROLL_90_YAW_270", 90, 0, 270),
    39: ("PITCH_315", 0, 315, 0), 40: ("ROLL_90_PITCH_315", 90, 315, 0),
}
#: ArduPilot-only ids beyond the common set (rotations.h [S9]); MAVLink numbers these differently
ARDUPILOT_EXTRA = {41: ("PITCH_7", 0, 7, 0), 42: ("ROLL_45", 45, 0, 0), 43: ("ROLL_315", 315, 0, 0)}
#: PX4-only ids (rotation.h @019b5654 [S19])
PX4_EXTRA = {41: ("ROLL_270_YAW_180", 270, 0, 180), 42: ("ROLL_270_YAW_270", 270, 0, 270),
             43: ("PITCH_90_YAW_180", 0, 90, 180), 44: ("PITCH_9_YAW_180", 0, 9, 180), 45: ("PITCH_45", 0, 45, 0),
             46: ("ROLL_270_YAW_225", 270, 0, 225), 47: ("ROLL_270_YAW_315", 270, 0, 315)}
#: ArduPilot ROTATION_ROLL_90_PITCH_68_YAW_293, the explicit matrix of vector3.cpp `rotate` [S9]
ARDUPILOT_38 = np.array([
    [0.14303897231223747232853327204793, 0.36877648650320382639478111741482, -0.91844638134308709265241077446262],
    [-0.33213277779664740485543461545603, -0.85628942146641884303193137384369, -0.39554550256296522325882847326284],
    [-0.93232380121551217122544130688766, 0.36162457008209242248497616856184, 0.0]])
#: ids magcal chooses from: 0..40, the set both firmwares, their documented parameter values and MAVLink's
#: MAV_SENSOR_ORIENTATION agree on (41+ differ between them and are missing from older firmware)
EXPORTABLE = tuple(range(41))
FIRMWARES = ("ardupilot", "px4")


def table(firmware: str) -> dict[int, tuple[str, float, float, float]]:
    """id -> (name, roll, pitch, yaw in degrees) of one firmware's enum."""
    if firmware == "ardupilot":
        return COMMON | {38: ("ROLL_90_PITCH_68_YAW_293", 90.0, 68.8, 293.3)} | ARDUPILOT_EXTRA
    if firmware == "px4":
        return COMMON | {38: ("ROLL_90_PITCH_68_YAW_293", 90, 68, 293)} | PX4_EXTRA
    msg = f"firmware {firmware!r} is not known; use one of {', '.join(FIRMWARES)}"
    raise FirmwareError(msg)


def name(firmware: str, rot_id: int) -> str:
    """The enum's name, e.g. ROTATION_YAW_90."""
    return "ROTATION_" + table(firmware)[rot_id][0]


def matrix(firmware: str, rot_id: int) -> FloatArray:
    """The 3x3 matrix (sensor to body) of enum `rot_id`."""
    entries = table(firmware)
    if rot_id not in entries:
        msg = (f"{firmware} rotation {rot_id} is not in the enum (0..{max(entries)}); check the orientation "
               "parameter")
        raise FirmwareError(msg)
    if firmware == "ardupilot" and rot_id == 38:
        return ARDUPILOT_38.copy()
    _, roll, pitch, yaw = entries[rot_id]
    return so3.from_rpy(np.deg2rad([roll, pitch, yaw]))


def nearest(firmware: str, target: npt.ArrayLike, ids: Iterable[int] = EXPORTABLE) -> tuple[int, float]:
    """The enum id whose matrix is closest to the rotation `target`, and the angle (deg) between them."""
    target = np.asarray(target, dtype=np.float64)
    best, best_angle = -1, np.inf
    for rot_id in ids:
        angle = float(np.rad2deg(so3.angle(matrix(firmware, rot_id).T @ target)))
        if angle < best_angle - 1e-9:
            best, best_angle = rot_id, angle
    return best, best_angle


def euler_deg(rot: npt.ArrayLike) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in degrees, each in (-180, 180], with rot = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = np.rad2deg(so3.as_rpy(np.asarray(rot, dtype=np.float64)))
    return float(r), float(p), float(y)
