"""The two firmwares' compass corrections, re-implemented from ../shared/design/firmware-export.md only (and, for
the EKF's magnetometer delay, PX4's thermal compensation and ArduPilot's per-motor compensation, from the sources
[S7] and [S32]-[S35] docs/firmware-export.md quotes).

Nothing here imports magcal's exporter: parameter files are read with a few lines of string handling, rotation
enums are built from the angle tables with elementary matrices (roll applied first: Rz(yaw) Ry(pitch) Rx(roll)),
and the formulas follow sections 1 and 2 of the design note literally.
"""

from __future__ import annotations

import numpy as np

AXES = "XYZ"
#: (roll, pitch, yaw) of rotation ids 0..40 without 38, typed in from the design note's section 1 table
ANGLES = {0: (0, 0, 0), 1: (0, 0, 45), 2: (0, 0, 90), 3: (0, 0, 135), 4: (0, 0, 180), 5: (0, 0, 225),
          6: (0, 0, 270), 7: (0, 0, 315), 8: (180, 0, 0), 9: (180, 0, 45), 10: (180, 0, 90), 11: (180, 0, 135),
          12: (0, 180, 0), 13: (180, 0, 225), 14: (180, 0, 270), 15: (180, 0, 315), 16: (90, 0, 0),
          17: (90, 0, 45), 18: (90, 0, 90), 19: (90, 0, 135), 20: (270, 0, 0), 21: (270, 0, 45),
          22: (270, 0, 90), 23: (270, 0, 135), 24: (0, 90, 0), 25: (0, 270, 0), 26: (0, 180, 90),
          27: (0, 180, 270), 28: (90, 90, 0), 29: (180, 90, 0), 30: (270, 90, 0), 31: (90, 180, 0),
          32: (270, 180, 0), 33: (90, 270, 0), 34: (180, 270, 0), 35: (270, 270, 0), 36: (90, 180, 90),
          37: (90, 0, 270), 39: (0, 315, 0), 40: (90, 315, 0)}


def rx(deg: float) -> np.ndarray:
    """Rotation about x by `deg`."""
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(deg: float) -> np.ndarray:
    """Rotation about y by `deg`."""
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(deg: float) -> np.ndarray:
    """Rotation about z by `deg`."""
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """v_body = Rz(yaw) Ry(pitch) Rx(roll) v (Euler 3-2-1, roll first) [S9][S19]."""
    return rz(yaw) @ ry(pitch) @ rx(roll)


def enum(rot_id: int) -> np.ndarray:
    """The matrix of a rotation id from ANGLES."""
    return euler(*ANGLES[rot_id])


def read_param_file(text: str) -> dict[str, float]:
    """Mission Planner NAME,VALUE, MAVProxy NAME VALUE, QGC five columns or `param set NAME VALUE` lines."""
    out = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.replace(",", " ").replace("\t", " ").split()
        if parts[:2] == ["param", "set"]:
            parts = parts[2:]
        elif len(parts) == 5:
            parts = parts[2:4]
        out[parts[0]] = float(np.float32(float(parts[1])))        # the firmware holds float32
    return out


def ardupilot_rotation(p: dict[str, float], suffix: str, board: np.ndarray) -> np.ndarray:
    """rotate_field: COMPASS_ORIENTn for an external compass (custom 101/102 via CUST_ROTn_*), else the board."""
    if p.get({"": "COMPASS_EXTERNAL", "2": "COMPASS_EXTERN2", "3": "COMPASS_EXTERN3"}[suffix], 0) < 1:
        return board
    orient = int(p.get(f"COMPASS_ORIENT{suffix}", 0))
    if orient in (101, 102):
        n = orient - 100
        return euler(p[f"CUST_ROT{n}_ROLL"], p[f"CUST_ROT{n}_PITCH"], p[f"CUST_ROT{n}_YAW"])
    return enum(orient)


def ardupilot_per_motor(p: dict[str, float], pwm: np.ndarray, volts: np.ndarray) -> np.ndarray:
    """Compass_PerMotor::compensate [S7]: sum over motors 1-4 of COMPASS_PMOTn times
    ((scale_esc_to_unity(pwm) + 1) / 2 * voltage)^COMPASS_PMOT_EXP, 0 where the output is <= 0 (N, 3) mGauss;
    pwm (N, 4) us over MOT_PWM_MIN..MAX."""
    lo, hi = p.get("MOT_PWM_MIN", 1000.0), p.get("MOT_PWM_MAX", 2000.0)
    out = np.zeros((len(pwm), 3))
    for n in range(4):
        unity = 2.0 * (pwm[:, n] - lo) / (hi - lo) - 1.0                   # scale_esc_to_unity
        output = (unity + 1.0) * 0.5
        scaled = np.zeros(len(pwm))
        on = output > 0
        scaled[on] = (output[on] * volts[on]) ** p.get("COMPASS_PMOT_EXP", 0.65)
        out += scaled[:, None] * np.array([p.get(f"COMPASS_PMOT{n + 1}_{a}", 0.0) for a in AXES])
    return out


def ardupilot_field(sensor: np.ndarray, p: dict[str, float], suffix: str = "", board: np.ndarray | None = None,
                    signal: np.ndarray | None = None, pwm: np.ndarray | None = None,
                    volts: np.ndarray | None = None) -> np.ndarray:
    """Body field (N, 3) mGauss of sensor-frame readings (N, 3) mGauss: rotate_field, then correct_field [S3]; the
    first compass takes the per-motor offsets instead of MOT when COMPASS_PMOT_EN (pwm (N, 4), volts (N,))."""
    r = ardupilot_rotation(p, suffix, np.eye(3) if board is None else board)
    mag = sensor @ r.T
    dia = np.array([p.get(f"COMPASS_DIA{suffix}_{a}", 0.0) for a in AXES])
    if np.all(dia == 0):
        dia = np.ones(3)
    odi = [p.get(f"COMPASS_ODI{suffix}_{a}", 0.0) for a in AXES]
    mag = mag + np.array([p[f"COMPASS_OFS{suffix}_{a}"] for a in AXES])              # offsets added
    scale = p.get(f"COMPASS_SCALE{suffix}", 0.0)
    if 0.85 <= scale <= 1.4:                                                            # have_scale_factor
        mag = mag * scale
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    mag = mag @ M.T
    motct = int(p.get("COMPASS_MOTCT", 0))
    if p.get("COMPASS_PMOT_EN", 0) and suffix == "":                                    # first compass only
        if pwm is not None and volts is not None:
            mag = mag + ardupilot_per_motor(p, pwm, volts)
    elif motct in (1, 2) and signal is not None:                                        # after the matrix
        mag = mag + signal[:, None] * np.array([p.get(f"COMPASS_MOT{suffix}_{a}", 0.0) for a in AXES])
    return mag


def px4_thermal_offset(temperature: np.ndarray, p: dict[str, float], device_id: int) -> np.ndarray:
    """TemperatureCompensation::calc_thermal_offsets_3D [S34]: with TC_M_ENABLE = 1 and the slot j whose TC_Mj_ID is
    the device, X0 + X1 dT + X2 dT^2 + X3 dT^3 per axis, dT = T clipped to [TMIN, TMAX] minus TREF (N, 3) gauss."""
    out = np.zeros((len(temperature), 3))
    if int(p.get("TC_M_ENABLE", 0)) != 1:
        return out
    for j in range(4):
        if int(p.get(f"TC_M{j}_ID", 0)) != device_id or not device_id:
            continue
        q = f"TC_M{j}_"
        t = np.where(temperature > p[f"{q}TMAX"], p[f"{q}TMAX"],
                     np.where(temperature < p[f"{q}TMIN"], p[f"{q}TMIN"], temperature))
        d = t - p[f"{q}TREF"]
        for i in range(3):
            out[:, i] = (p[f"{q}X0_{i}"] + p[f"{q}X1_{i}"] * d + p[f"{q}X2_{i}"] * d**2 + p[f"{q}X3_{i}"] * d**3)
        return out
    return out


def ekf_mag_time(stamp_s: np.ndarray, p: dict[str, float]) -> np.ndarray:
    """The time PX4's EKF fuses a magnetometer sample stamped `stamp_s` at: time_us - EKF2_MAG_DELAY * 1000
    (EstimatorInterface::setMagData [S33]; the half EKF period it also subtracts is the same for every sensor)."""
    return stamp_s - p.get("EKF2_MAG_DELAY", 0.0) / 1000.0


def px4_field(raw: np.ndarray, p: dict[str, float], n: int = 0, current_a: np.ndarray | None = None,
              throttle: np.ndarray | None = None, temperature: np.ndarray | None = None,
              device_id: int = 0) -> np.ndarray:
    """m_body = R S ((raw + P COMP) - OFF - thermal offset), gauss [S16][S34]; R = Dcm(Euler(SENS_BOARD_*_OFF))
    rot(ROT or board)."""
    q = f"CAL_MAG{n}_"
    d = [p[f"{q}{a}SCALE"] for a in AXES]
    o = [p[f"{q}{a}ODIAG"] for a in AXES]
    S = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    rot = int(p[f"{q}ROT"])
    if rot == -1:
        inner = enum(int(p.get("SENS_BOARD_ROT", 0)))
    elif rot == 100:
        inner = euler(p[f"{q}ROLL"], p[f"{q}PITCH"], p[f"{q}YAW"])
    else:
        inner = enum(rot)
    R = euler(*(p.get(f"SENS_BOARD_{a}_OFF", 0.0) for a in AXES)) @ inner
    typ = int(p.get("CAL_MAG_COMP_TYP", 0))
    P = np.zeros(len(raw))
    if typ == 1 and throttle is not None:
        P = throttle
    elif typ in (2, 3) and current_a is not None:
        P = current_a / 1000.0                                                          # kA
    comp = np.array([p.get(f"{q}{a}COMP", 0.0) for a in AXES])
    off = np.array([p[f"{q}{a}OFF"] for a in AXES])
    thermal = 0.0 if temperature is None else px4_thermal_offset(temperature, p, device_id)
    return ((raw + P[:, None] * comp) - off - thermal) @ S.T @ R.T
