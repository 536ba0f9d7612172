"""Sensor topics of a ULog: the raw magnetometer per instance (or the calibrated field) and the IMUs."""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.readers.ulog.topics import ImuPiece, IntArray, Piece, Topics, int_field, vector_fields
from magcal_cli.streams import Kind, Sampling

#: msg/SensorCombined.msg: an `*_timestamp_relative` with this value means "no sample of that sensor"
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
#: bus types of PX4's DeviceStructure (src/lib/drivers/device/Device.hpp, DeviceBusType)
BUS_TYPES = {0: "unknown bus", 1: "I2C", 2: "SPI", 3: "UAVCAN", 4: "simulation", 5: "serial", 6: "MAVLink"}
#: the parameter holding the device id of calibration slot n (src/lib/sensor_calibration/Utilities.cpp)
CAL_MAG_ID = re.compile(r"CAL_MAG(\d)_ID")
#: below this rate (Hz) a raw sensor_mag is the logger's default 1 Hz sample, too slow to calibrate well
SLOW_MAG_HZ = 5.0


def device_text(device_id: int) -> str:
    """A PX4 device id in words: bus type, bus, address and device type (DeviceStructure bit fields)."""
    bus_type, bus = device_id & 0x7, (device_id >> 3) & 0x1F
    address, devtype = (device_id >> 8) & 0xFF, (device_id >> 16) & 0xFF
    bus_name = BUS_TYPES.get(bus_type, f"bus type {bus_type}")
    return (f"device_id {device_id} (0x{device_id:06x}: {bus_name} bus {bus}, address 0x{address:02x}, "
            f"devtype 0x{devtype:02x})")


def mag_pieces(tp: Topics, params: dict[str, float]) -> list[Piece]:
    """Raw sensor_mag per instance; without it the corrected sensor_combined or vehicle_magnetometer field."""
    gauss = units.to_si("gauss")
    out: list[Piece] = []
    for i in tp.instances("sensor_mag"):
        ds, sid = tp.get("sensor_mag", i), f"sensor_mag[{i}]"
        xyz = tp.columns(ds, ["x", "y", "z"])
        if xyz is None:
            continue
        t = tp.stamps(ds, sid)
        out.append(Piece(Kind.MAGNETOMETER, sid, t, xyz * gauss, tp.source(sid, "x, y, z"), "gauss"))
        if "x_raw" in ds.data:
            # PX4 <= 1.10 drivers (PX4Magnetometer::update) logged x,y,z after CAL_MAGn offsets and scales
            tp.notes.append(f"{sid}: this PX4 version logs x, y, z with the driver's CAL_MAG offsets and "
                            "scales applied (x_raw.. are ADC counts); the fit is relative to that "
                            "calibration")
        temp = tp.columns(ds, ["temperature"])
        if temp is not None and np.isfinite(temp).any():
            out.append(Piece(Kind.TEMPERATURE, sid, t, temp, tp.source(sid, "temperature"), "degC"))
        if "device_id" in ds.data and len(t):
            dev = int(ds.data["device_id"][-1])
            params[f"{sid}.device_id"] = float(dev)
            slot = [m.group(1) for k, v in params.items()
                    if (m := CAL_MAG_ID.fullmatch(k)) and int(v) == dev != 0]
            where = f"calibration slot CAL_MAG{slot[0]}_*" if slot else "no CAL_MAGn_ID matches it"
            tp.notes.append(f"{sid}: {device_text(dev)}, {where}")
    if out:
        slow = [p.id for p in out if p.kind is Kind.MAGNETOMETER and _rate(p.t_us) < SLOW_MAG_HZ]
        if slow and tp.instances("vehicle_magnetometer"):
            tp.notes.append(f"{', '.join(slow)}: raw field logged at about 1 Hz (the logger's default); set "
                            "SDLOG_PROFILE bit 6 (sensor comparison) to log sensor_mag at 10 Hz. The faster "
                            "vehicle_magnetometer is calibrated by the firmware and not used")
        return out
    comb = tp.get("sensor_combined")
    xyz = None if comb is None else tp.columns(comb, vector_fields("magnetometer_ga"))
    if xyz is not None:
        t = np.asarray(comb.data["timestamp"], dtype=np.int64)
        rel = int_field(comb, "magnetometer_timestamp_relative", len(t))
        valid = rel != RELATIVE_TIMESTAMP_INVALID
        tm = t + np.where(valid, rel, 0)
        # every IMU message repeats the latest field sample; one row per new magnetometer time stamp
        new = valid & np.concatenate([[True], tm[1:] != tm[:-1]])
        tp.notes.append("sensor_combined: magnetometer_ga is the firmware-calibrated field in the body "
                        "frame (CAL_MAG offsets/scales and board rotation applied; no raw sensor_mag in this "
                        f"log); kept {int(new.sum())} distinct samples of {len(t)} IMU messages")
        return [Piece(Kind.MAGNETOMETER, "sensor_combined", tm[new], xyz[new] * gauss,
                      tp.source("sensor_combined", "magnetometer_ga"), "gauss")]
    for i in tp.instances("vehicle_magnetometer"):
        ds, sid = tp.get("vehicle_magnetometer", i), f"vehicle_magnetometer[{i}]"
        xyz = tp.columns(ds, vector_fields("magnetometer_ga"))
        if xyz is not None:
            tp.notes.append(f"{sid}: no raw sensor_mag in this log; vehicle_magnetometer is the "
                            "firmware-calibrated field in the body frame, so the fit is relative to the "
                            "vehicle's calibration")
            out.append(Piece(Kind.MAGNETOMETER, sid, tp.stamps(ds, sid), xyz * gauss,
                             tp.source(sid, "magnetometer_ga"), "gauss"))
    return out


def _rate(t_us: IntArray) -> float:
    """Mean sample rate (Hz) over the span."""
    span = float(t_us[-1] - t_us[0]) * 1e-6 if len(t_us) > 1 else 0.0
    return (len(t_us) - 1) / span if span > 0 else 0.0


def _window(ds: Any, name: str, t_us: IntArray) -> float | None:
    """The averaging window (s) of sensor_combined's samples where it is shorter than their spacing (a logger
    that keeps every n-th message), else None (the spacing). Older logs give it in seconds, newer in us."""
    if name not in ds.data or len(t_us) < 2:
        return None
    dt = float(np.median(np.asarray(ds.data[name], dtype=np.float64)))
    window = dt if dt < 1.0 else dt * 1e-6
    spacing = float(np.median(np.diff(t_us))) * 1e-6
    return window if 0.0 < window < 0.9 * spacing else None


def imu_pieces(tp: Topics, params: dict[str, float]) -> tuple[list[ImuPiece], list[Piece]]:
    """sensor_combined (calibrated, body frame) first, then each sensor_accel[i]/sensor_gyro[i] (raw)."""
    imus: list[ImuPiece] = []
    temps: list[Piece] = []
    comb = tp.get("sensor_combined")
    gyr = None if comb is None else tp.columns(comb, vector_fields("gyro_rad"))
    acc = None if comb is None else tp.columns(comb, vector_fields("accelerometer_m_s2"))
    if comb is not None and gyr is not None and acc is not None:
        t = np.asarray(comb.data["timestamp"], dtype=np.int64)      # the gyro's sample time
        rel = int_field(comb, "accelerometer_timestamp_relative", len(t))
        ok = rel != RELATIVE_TIMESTAMP_INVALID
        src = "sensor_combined"
        # SensorCombined.msg: "average ... over the last gyro (accelerometer) sampling period", ending at the stamp
        gyr_piece = Piece(Kind.GYROSCOPE, src, t, gyr, tp.source(src, "gyro_rad"), "rad/s", Sampling.PRECEDING,
                          _window(comb, "gyro_integral_dt", t))
        acc_piece = Piece(Kind.ACCELEROMETER, src, t[ok] + rel[ok], acc[ok],
                          tp.source(src, "accelerometer_m_s2"), "m/s^2", Sampling.PRECEDING,
                          _window(comb, "accelerometer_integral_dt", t))
        imus.append(ImuPiece(src, gyr_piece, acc_piece))
    gyro_instances = set(tp.instances("sensor_gyro"))
    for i in tp.instances("sensor_accel"):
        ds, sid = tp.get("sensor_accel", i), f"sensor_accel[{i}]"
        a = tp.columns(ds, ["x", "y", "z"])
        if a is None:
            continue
        ta = tp.stamps(ds, sid)
        temp = tp.columns(ds, ["temperature"])
        if temp is not None and np.isfinite(temp).any():
            temps.append(Piece(Kind.TEMPERATURE, sid, ta, temp, tp.source(sid, "temperature"), "degC"))
        if "device_id" in ds.data and len(ta):
            params[f"{sid}.device_id"] = float(int(ds.data["device_id"][-1]))
        gds = tp.get("sensor_gyro", i)
        g = None if gds is None else tp.columns(gds, ["x", "y", "z"])
        if g is None:
            tp.notes.append(f"{sid}: no sensor_gyro[{i}] to pair it with, so it is not usable as an IMU")
            continue
        # sensors.cpp creates VehicleIMU(i, i, i): accelerometer instance i and gyro instance i are one IMU
        gyro_instances.discard(i)
        gid = f"sensor_gyro[{i}]"
        if "device_id" in gds.data and len(gds.data["device_id"]):
            params[f"{gid}.device_id"] = float(int(gds.data["device_id"][-1]))
        gyr_piece = Piece(Kind.GYROSCOPE, sid, tp.stamps(gds, gid), g, tp.source(gid, "x, y, z"), "rad/s")
        acc_piece = Piece(Kind.ACCELEROMETER, sid, ta, a, tp.source(sid, "x, y, z"), "m/s^2")
        imus.append(ImuPiece(sid, gyr_piece, acc_piece))
    for i in sorted(gyro_instances):
        tp.notes.append(f"sensor_gyro[{i}]: no sensor_accel[{i}] to pair it with, so it is not usable as "
                        "an IMU")
    return imus, temps
