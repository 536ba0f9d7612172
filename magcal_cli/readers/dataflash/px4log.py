"""Legacy PX4 sdlog2 `.px4log` logs: DataFlash records grouped behind TIME.StartTime (us) stamps.

sdlog2 writes one TIME record per logging cycle followed by that cycle's records, which carry no time of
their own. IMU, IMU1, IMU2 hold accelerometer, gyro and the field (`MagX..Z`, gauss) of each sensor group.
The field is sensor_combined's: already corrected by the driver with CAL_MAGn offsets and scales and rotated
to the body frame; magcal calibrates it as logged (the result is relative to the calibration flown).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magcal_cli.errors import LogReadError, StreamError
from magcal_cli.readers.dataflash.format import RawLog, Table
from magcal_cli.readers.dataflash.streams import Clock, Pending, euler_quat, finish
from magcal_cli.streams import FloatArray, Kind, Recording

GAUSS_TO_T = 1e-4


def _clock(raw: RawLog, path: Path) -> Clock:
    """The TIME.StartTime stamps (s) by file position."""
    time = raw.table("TIME")
    if time is None or not time.fmt.has("StartTime"):
        msg = f"{path}: a PX4 sdlog2 log without TIME records; magcal needs them to time the samples"
        raise LogReadError(msg)
    return Clock(time.pos, time.num("StartTime") * 1e-6)


def _xyz(table: Table, *cols: str) -> FloatArray:
    """(N, len(cols)) float columns."""
    return np.stack([table.num(c) for c in cols], axis=1)


def _sensor_groups(path: Path, raw: RawLog, clock: Clock, notes: list[str]) -> list[Pending]:
    """IMU[i] (accelerometer + gyro), MAG[i] (gauss) and their temperatures from IMU, IMU1, IMU2."""
    out: list[Pending] = []
    for inst, name in enumerate(("IMU", "IMU1", "IMU2")):
        table = raw.table(name)
        if table is None or not table.fmt.has("AccX", "GyroX", "MagX"):
            continue
        t = clock.at(table.pos)
        acc, gyr = _xyz(table, "AccX", "AccY", "AccZ"), _xyz(table, "GyroX", "GyroY", "GyroZ")
        mag = _xyz(table, "MagX", "MagY", "MagZ")
        src = f"{path.name}#{name}"
        if np.any(acc) or np.any(gyr):
            out.append(Pending((Kind.ACCELEROMETER, Kind.GYROSCOPE), f"IMU[{inst}]", t,
                               np.concatenate([acc, gyr], axis=1), f"{src}.Acc/Gyro", ("m/s^2", "rad/s")))
        if np.any(mag):
            out.append(Pending((Kind.MAGNETOMETER,), f"MAG[{inst}]", t, mag * GAUSS_TO_T,
                               f"{src}.MagX/MagY/MagZ", ("gauss",)))
            notes.append(f"MAG[{inst}]: the px4log field is sensor_combined's, already corrected by the "
                         f"driver (CAL_MAG{inst} offsets/scales) and rotated to the body frame; it is "
                         "calibrated as logged")
        else:
            notes.append(f"{name}: the field is all zero (no magnetometer in this sensor group)")
        for col, sid in (("tA", f"IMU[{inst}]"), ("tM", f"MAG[{inst}]")):
            if table.fmt.has(col) and (sid.startswith("IMU") or np.any(mag)):
                out.append(Pending((Kind.TEMPERATURE,), sid, t, table.num(col)[:, None], f"{src}.{col}",
                                   ("degC",)))
    return out


def _others(path: Path, raw: RawLog, clock: Clock) -> list[Pending]:
    """ATT (quaternion, else Euler angles in rad), BAT[0] (BATT.C/V), ATTC throttle, GPS[0] with a 3D fix."""
    out: list[Pending] = []
    att = raw.table("ATT")
    if att is not None and att.fmt.has("Roll", "Pitch", "Yaw"):
        q = _xyz(att, "qw", "qx", "qy", "qz") if att.fmt.has("qw", "qx", "qy", "qz") else None
        if q is None or not np.all(np.abs(np.linalg.norm(q, axis=1) - 1.0) < 1e-3):
            q = euler_quat(*(np.rad2deg(att.num(c)) for c in ("Roll", "Pitch", "Yaw")))
        out.append(Pending((Kind.ATTITUDE,), "ATT", clock.at(att.pos), q, f"{path.name}#ATT",
                           ("quaternion wxyz",)))
    batt = raw.table("BATT")
    if batt is not None and batt.fmt.has("C", "V"):
        t = clock.at(batt.pos)
        cur = np.where(batt.num("C") >= 0, batt.num("C"), np.nan)        # -1: current unknown
        out.append(Pending((Kind.BATTERY_CURRENT,), "BAT[0]", t, cur[:, None], f"{path.name}#BATT.C", ("A",)))
        out.append(Pending((Kind.BATTERY_VOLTAGE,), "BAT[0]", t, batt.num("V")[:, None],
                           f"{path.name}#BATT.V", ("V",)))
    attc = raw.table("ATTC")
    if attc is not None and attc.fmt.has("Thrust"):
        out.append(Pending((Kind.THROTTLE,), "ATTC", clock.at(attc.pos), attc.num("Thrust")[:, None],
                           f"{path.name}#ATTC.Thrust", ("1",)))
    gps = raw.table("GPS")
    if gps is not None and gps.fmt.has("Lat", "Lon", "Alt", "Fix"):
        fix = gps.num("Fix") >= 3
        if fix.any():
            out.append(Pending((Kind.POSITION,), "GPS[0]", clock.at(gps.pos)[fix],
                               _xyz(gps, "Lat", "Lon", "Alt")[fix], f"{path.name}#GPS.Lat/Lon/Alt",
                               ("deg, deg, m",)))
    return out


def build_px4log(path: Path, raw: RawLog) -> Recording:
    """IMU[i] and MAG[i] per sensor group, temperatures, ATT, BAT[0], ATTC throttle, GPS[0], parameters."""
    clock = _clock(raw, path)
    notes = list(raw.notes)
    pending = _sensor_groups(path, raw, clock, notes)
    if not any(Kind.MAGNETOMETER in p.kinds for p in pending):
        msg = (f"{path}: no magnetometer data in the IMU records (MagX..Z all zero or absent); "
               "nothing to calibrate")
        raise StreamError(msg)
    parm = raw.table("PARM")
    params = dict(zip(parm.text("Name"), parm.num("Value").tolist(), strict=True)) if parm is not None else {}
    return finish(path, "px4log", pending + _others(path, raw, clock), params, notes)
