"""PX4 ULog reader: raw `sensor_mag` per instance, the IMU, attitude, battery, throttle, GPS and parameters.

Which topic is raw and which calibrated, frames, time stamps, ids and the truncation policy are in
docs/readers-px4.md; field meanings follow PX4's msg/*.msg definitions.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from magcal_cli import units
from magcal_cli.align import clean_time, onto
from magcal_cli.errors import LogReadError, StreamError
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.checks import normalised_field, normalised_note, sensor_checks
from magcal_cli.readers.cut import mark_cut, refuse_if_strict
from magcal_cli.readers.ulog.load import Loaded, load_ulog
from magcal_cli.streams import Cut, FloatArray, Kind, Recording, Sampling, Stream

IntArray = npt.NDArray[np.int64]

#: the topics magcal reads; pyulog skips the others while parsing
TOPICS = ["sensor_mag", "sensor_combined", "sensor_accel", "sensor_gyro", "vehicle_attitude",
          "battery_status", "vehicle_gps_position", "sensor_gps", "vehicle_magnetometer",
          "vehicle_thrust_setpoint", "actuator_controls_0"]
#: msg/SensorCombined.msg: an `*_timestamp_relative` with this value means "no sample of that sensor"
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
#: a `timestamp_sample` further than this before the publication `timestamp` is not trusted (us)
MAX_SAMPLE_LAG_US = 1_000_000
#: a GPS UTC time (us since 1970) before this (2001-09) is a receiver that has no time yet, not a date
MIN_UTC_US = 1_000_000_000_000_000
#: bus types of PX4's DeviceStructure (src/lib/drivers/device/Device.hpp, DeviceBusType)
BUS_TYPES = {0: "unknown bus", 1: "I2C", 2: "SPI", 3: "UAVCAN", 4: "simulation", 5: "serial", 6: "MAVLink"}
#: the parameter holding the device id of calibration slot n (src/lib/sensor_calibration/Utilities.cpp)
CAL_MAG_ID = re.compile(r"CAL_MAG(\d)_ID")
#: below this rate (Hz) a raw sensor_mag is the logger's default 1 Hz sample, too slow to calibrate well
SLOW_MAG_HZ = 5.0


@dataclass(frozen=True, eq=False)
class Piece:
    """One stream before the log's zero time is known: integer microseconds and SI values."""

    kind: Kind
    id: str
    t_us: IntArray
    values: FloatArray
    source: str
    unit: str
    sampling: Sampling = Sampling.INSTANT
    window_s: float | None = None


@dataclass(frozen=True, eq=False)
class ImuPiece:
    """An IMU's gyro and accelerometer on their own stamps; the accelerometer moves onto the gyro's later."""

    id: str
    gyr: Piece
    acc: Piece


def device_text(device_id: int) -> str:
    """A PX4 device id in words: bus type, bus, address and device type (DeviceStructure bit fields)."""
    bus_type, bus = device_id & 0x7, (device_id >> 3) & 0x1F
    address, devtype = (device_id >> 8) & 0xFF, (device_id >> 16) & 0xFF
    bus_name = BUS_TYPES.get(bus_type, f"bus type {bus_type}")
    return (f"device_id {device_id} (0x{device_id:06x}: {bus_name} bus {bus}, address 0x{address:02x}, "
            f"devtype 0x{devtype:02x})")


class _Topics:
    """The parsed data sets by (topic, instance), with helpers that read fields as numpy arrays."""

    def __init__(self, loaded: Loaded, path: Path, options: ReadOptions) -> None:
        self.sets = {(d.name, int(d.multi_id)): d for d in loaded.ulog.data_list if "timestamp" in d.data}
        self.name = path.name
        self.use_sample = not options.receive_time
        self.notes: list[str] = []
        untimed = sorted({d.name for d in loaded.ulog.data_list if "timestamp" not in d.data})
        if untimed:                             # a format definition damaged: its data cannot be placed in time
            self.notes.append(f"ignored {', '.join(untimed)}: the format has no timestamp field (corrupt definition)")

    def instances(self, topic: str) -> list[int]:
        """The multi-instance indices logged for `topic`, in order."""
        return sorted(i for name, i in self.sets if name == topic)

    def get(self, topic: str, instance: int = 0) -> Any:
        """pyulog's data set of one topic instance, or None."""
        return self.sets.get((topic, instance))

    def stamps(self, ds: Any, label: str) -> IntArray:
        """Sample times (us): `timestamp_sample` (when the sensor sampled) where present and plausible, else
        `timestamp` (when the message was published); `--receive-time` asks for the publication time."""
        ts = np.asarray(ds.data["timestamp"], dtype=np.int64)
        if "timestamp_sample" not in ds.data or not self.use_sample:
            return ts
        tss = np.asarray(ds.data["timestamp_sample"], dtype=np.int64)
        lag = ts - tss
        if np.all((tss > 0) & (lag >= 0) & (lag <= MAX_SAMPLE_LAG_US)):
            return tss
        self.notes.append(f"{label}: timestamp_sample is zero or not within 1 s before timestamp; "
                          "used timestamp")
        return ts

    @staticmethod
    def columns(ds: Any, names: list[str]) -> FloatArray | None:
        """The named fields as an (N, len(names)) float array, or None when one is missing."""
        if not all(n in ds.data for n in names):
            return None
        return np.stack([np.asarray(ds.data[n], dtype=np.float64) for n in names], axis=1)

    def source(self, label: str, fields: str) -> str:
        """Provenance shown by `inspect`: log name, topic instance and fields."""
        return f"{self.name}#{label}: {fields}"


def _vector(name: str) -> list[str]:
    """pyulog's names of a float[3] field's elements."""
    return [f"{name}[{i}]" for i in range(3)]


def _mag_pieces(tp: _Topics, params: dict[str, float]) -> list[Piece]:
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
    xyz = None if comb is None else tp.columns(comb, _vector("magnetometer_ga"))
    if xyz is not None:
        t = np.asarray(comb.data["timestamp"], dtype=np.int64)
        rel = _field(comb, "magnetometer_timestamp_relative", len(t))
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
        xyz = tp.columns(ds, _vector("magnetometer_ga"))
        if xyz is not None:
            tp.notes.append(f"{sid}: no raw sensor_mag in this log; vehicle_magnetometer is the "
                            "firmware-calibrated field in the body frame, so the fit is relative to the "
                            "vehicle's calibration")
            out.append(Piece(Kind.MAGNETOMETER, sid, tp.stamps(ds, sid), xyz * gauss,
                             tp.source(sid, "magnetometer_ga"), "gauss"))
    return out


def _field(ds: Any, name: str, n: int) -> IntArray:
    """An integer field as int64, zeros when the topic version lacks it."""
    return np.asarray(ds.data[name], dtype=np.int64) if name in ds.data else np.zeros(n, dtype=np.int64)


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


def _imu_pieces(tp: _Topics, params: dict[str, float]) -> tuple[list[ImuPiece], list[Piece]]:
    """sensor_combined (calibrated, body frame) first, then each sensor_accel[i]/sensor_gyro[i] (raw)."""
    imus: list[ImuPiece] = []
    temps: list[Piece] = []
    comb = tp.get("sensor_combined")
    gyr = None if comb is None else tp.columns(comb, _vector("gyro_rad"))
    acc = None if comb is None else tp.columns(comb, _vector("accelerometer_m_s2"))
    if comb is not None and gyr is not None and acc is not None:
        t = np.asarray(comb.data["timestamp"], dtype=np.int64)      # the gyro's sample time
        rel = _field(comb, "accelerometer_timestamp_relative", len(t))
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


def _other_pieces(tp: _Topics) -> list[Piece]:
    """vehicle_attitude, battery_status per instance, one throttle and one GPS position stream."""
    out: list[Piece] = []
    att = tp.get("vehicle_attitude")
    q = None if att is None else tp.columns(att, [f"q[{i}]" for i in range(4)])
    if q is not None:
        # msg/VehicleAttitude.msg: q is (w, x, y, z), rotation from the FRD body frame to NED
        out.append(Piece(Kind.ATTITUDE, "vehicle_attitude", tp.stamps(att, "vehicle_attitude"), q,
                         tp.source("vehicle_attitude", "q"), "quaternion wxyz"))
    for i in tp.instances("battery_status"):
        ds, sid = tp.get("battery_status", i), f"battery_status[{i}]"
        t = np.asarray(ds.data["timestamp"], dtype=np.int64)
        cur = tp.columns(ds, ["current_a"])
        if cur is not None:
            cur[cur == -1.0] = np.nan             # msg/BatteryStatus.msg: -1 means "current not measured"
            if np.isfinite(cur).any():
                out.append(Piece(Kind.BATTERY_CURRENT, sid, t, cur, tp.source(sid, "current_a"), "A"))
            else:
                tp.notes.append(f"{sid}: current_a is -1 throughout (no current sensor); "
                                "no current stream")
        volt = tp.columns(ds, ["voltage_v"])
        if volt is not None:
            out.append(Piece(Kind.BATTERY_VOLTAGE, sid, t, volt, tp.source(sid, "voltage_v"), "V"))
    gps, throttle = _gps_piece(tp), _throttle_piece(tp)
    return out + [p for p in (throttle, gps) if p is not None]


def _throttle_piece(tp: _Topics) -> Piece | None:
    """The throttle 0..1: |vehicle_thrust_setpoint[0].xyz| (PX4 >= 1.14, what CAL_MAG_COMP_TYP 1 uses), else
    actuator_controls_0.control[3] (INDEX_THROTTLE, older PX4)."""
    ds = tp.get("vehicle_thrust_setpoint")
    xyz = None if ds is None else tp.columns(ds, [f"xyz[{i}]" for i in range(3)])
    if ds is not None and xyz is not None:
        return Piece(Kind.THROTTLE, "vehicle_thrust_setpoint", tp.stamps(ds, "vehicle_thrust_setpoint"),
                     np.linalg.norm(xyz, axis=1)[:, None], tp.source("vehicle_thrust_setpoint", "|xyz|"), "1")
    ds = tp.get("actuator_controls_0")
    thr = None if ds is None else tp.columns(ds, ["control[3]"])
    if ds is not None and thr is not None:
        return Piece(Kind.THROTTLE, "actuator_controls_0", tp.stamps(ds, "actuator_controls_0"), thr,
                     tp.source("actuator_controls_0", "control[3]"), "1")
    return None


def _gps_piece(tp: _Topics) -> Piece | None:
    """vehicle_gps_position (the selected receiver), else sensor_gps; rows at (0, 0) (no fix) are dropped."""
    for topic in ("vehicle_gps_position", "sensor_gps"):
        for i in tp.instances(topic):
            ds = tp.get(topic, i)
            sid = topic if topic == "vehicle_gps_position" else f"{topic}[{i}]"
            fields = "latitude_deg, longitude_deg, altitude_msl_m"         # newer PX4: doubles, deg and m
            pos = tp.columns(ds, fields.split(", "))
            if pos is None:
                pos = tp.columns(ds, ["lat", "lon", "alt"])        # older: int32 1e-7 deg and int32 mm
                fields = "lat, lon (1e-7 deg), alt (mm)"
                if pos is None:
                    continue
                pos = pos * np.array([1e-7, 1e-7, 1e-3])
            fix = ~((pos[:, 0] == 0) & (pos[:, 1] == 0))
            if not fix.all():
                tp.notes.append(f"{sid}: dropped {int((~fix).sum())} samples at lat = lon = 0 (no fix)")
            t = tp.stamps(ds, sid)
            return Piece(Kind.POSITION, sid, t[fix], pos[fix], tp.source(sid, fields), "deg, deg, m")
    return None


def _utc_of_boot(tp: _Topics) -> float | None:
    """The Unix time (s) of the vehicle clock's zero, from the receiver's UTC time (`time_utc_usec`) in
    vehicle_gps_position, else sensor_gps: the median of UTC minus the message stamp over the messages that carry a
    time; None without one (the WMM is then evaluated at today's date)."""
    for topic in ("vehicle_gps_position", "sensor_gps"):
        for i in tp.instances(topic):
            ds = tp.get(topic, i)
            if "time_utc_usec" not in ds.data:
                continue
            utc = np.asarray(ds.data["time_utc_usec"], dtype=np.int64)
            ok = utc > MIN_UTC_US
            if ok.any():
                return float(np.median(utc[ok] - np.asarray(ds.data["timestamp"], dtype=np.int64)[ok])) * 1e-6
    return None


def _number(value: Any) -> float | None:
    """A parameter value as a float, or None when it is not a number."""
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        return None


def _params(ulog: Any, notes: list[str]) -> dict[str, float]:
    """Initial parameters updated by every change logged during the flight (last value wins)."""
    params = {str(k): v for k, v in ((k, _number(v)) for k, v in ulog.initial_parameters.items()) if v is not None}
    changed: set[str] = set()
    bad = len(ulog.initial_parameters) - len(params)
    for _, name, raw in ulog.changed_parameters:
        value = _number(raw)
        if value is None:                     # a parameter message found while resynchronising on corrupt bytes
            bad += 1
            continue
        if str(name).startswith("CAL_MAG") and params.get(str(name)) != value:
            changed.add(str(name))
        params[str(name)] = value
    if bad:
        notes.append(f"ignored {bad} parameter values that are not numbers (corrupt data)")
    if changed:
        names = ", ".join(sorted(changed))
        notes.append(f"magnetometer calibration parameters changed during the log ({names}); params hold the "
                     "last values")
    return params


class UlogReader:
    """Reads PX4 ULog (`.ulg`) files with pyulog into SI streams; see docs/readers-px4.md."""

    name: ClassVar[str] = "ulog"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Every stream magcal uses; a cut file up to its last complete message (--strict refuses it)."""
        loaded = load_ulog(path, TOPICS)
        ulog = loaded.ulog
        tp = _Topics(loaded, path, options)
        self._check_damage(path, loaded, options, tp.notes)
        params = _params(ulog, tp.notes)
        mags = _mag_pieces(tp, params)
        imus, temps = _imu_pieces(tp, params)
        pieces = mags + temps + _other_pieces(tp)
        if not imus and not pieces:
            have = ", ".join(loaded.topics[:25]) + (", ..." if len(loaded.topics) > 25 else "")
            msg = (f"{path}: no topic magcal reads ({', '.join(TOPICS)}); the log has: "
                   f"{have or 'no topics'}. Log sensor_mag and sensor_combined (PX4's default profile does)")
            raise StreamError(msg)
        if not mags:
            tp.notes.append("no magnetometer topic (sensor_mag, sensor_combined.magnetometer_ga or "
                            f"vehicle_magnetometer); the log has: {', '.join(loaded.topics)}")
        firsts = [int(p.t_us[0]) for p in pieces if len(p.t_us)]
        firsts += [int(p.t_us[0]) for imu in imus for p in (imu.gyr, imu.acc) if len(p.t_us)]
        t0_us = min([int(ulog.start_timestamp), *firsts])
        streams = [s for imu in imus for s in _imu_streams(imu, t0_us, tp.notes)]
        for p in pieces:
            stream = _stream(p, t0_us, tp.notes)
            if stream is not None:
                streams.append(stream)
        if ulog.dropouts:
            lost = sum(int(d.duration) for d in ulog.dropouts)
            times = "once" if len(ulog.dropouts) == 1 else f"{len(ulog.dropouts)} times"
            tp.notes.append(f"the logger dropped data {times} ({lost} ms in total); samples are missing "
                            "there")
        boot = _utc_of_boot(tp)
        return mark_cut(Recording(path, "ulog", tuple(streams), t0=t0_us * 1e-6, params=params,
                                  notes=tuple(tp.notes), utc0=None if boot is None else boot + t0_us * 1e-6),
                        _cut(loaded))

    @staticmethod
    def _check_damage(path: Path, loaded: Loaded, options: ReadOptions, notes: list[str]) -> None:
        """Raise for a file without decodable data, and for a cut one with --strict; note corrupt data."""
        ulog = loaded.ulog
        kept = sum(len(d.data["timestamp"]) for d in ulog.data_list if "timestamp" in d.data)
        if not ulog.data_list and not loaded.topics:
            if loaded.cut_at is not None and ulog.message_formats:      # definitions were read, then it ends
                msg = (f"{path}: the ULog is truncated at byte {loaded.cut_at} of {loaded.size}, before any "
                       "data message. Re-copy the log from the vehicle")
            else:
                msg = (f"{path}: no data messages could be decoded after the ULog header (the file is "
                       "corrupt or not a PX4 log). Re-copy the log from the vehicle")
            raise LogReadError(msg)
        refuse_if_strict(path, options, _cut(loaded))
        if ulog.file_corruption:          # corrupt bytes in the middle: skipped, as pymavlink does (issue 6)
            notes.append(f"corrupt data: pyulog skipped damaged bytes and resynchronised on the next message; "
                         f"read {kept} complete samples")
        notes.extend(f"pyulog: {line}" for line in loaded.printed[:3])


def _cut(loaded: Loaded) -> Cut | None:
    """Where a ULog ends inside a message (pyulog stops at the last complete one), or None."""
    if loaded.cut_at is None:
        return None
    return Cut(loaded.cut_at, loaded.size, f"a message, {loaded.size - loaded.cut_at} bytes present")


def _stream(p: Piece, t0_us: int, notes: list[str]) -> Stream | None:
    """Sort, de-duplicate and clean one piece into a Stream relative to t0; None when nothing is left."""
    label = p.source.split("#", 1)[-1].split(":", 1)[0]
    t, values, cleaned = clean_time((p.t_us - t0_us) * 1e-6, p.values, label)
    t, values, checked = sensor_checks((p.kind,), t, values, label)
    notes.extend(cleaned + checked)
    if not len(t):
        notes.append(f"{label}: no valid {p.kind.value} samples")
        return None
    if p.kind is Kind.MAGNETOMETER and normalised_field(values):
        notes.append(normalised_note(p.id, values / units.to_si(p.unit), p.unit))
    return Stream(p.kind, p.id, t, values, p.source, p.unit, sampling=p.sampling, window_s=p.window_s)


def _imu_streams(imu: ImuPiece, t0_us: int, notes: list[str]) -> list[Stream]:
    """Accelerometer and gyro on the gyro's time stamps: the accelerometer is interpolated onto them when
    its own stamps differ (align.onto never extrapolates or bridges dropouts)."""
    gyr, acc = _stream(imu.gyr, t0_us, notes), _stream(imu.acc, t0_us, notes)
    if gyr is None or acc is None:
        return []
    if len(gyr) == len(acc) and np.array_equal(gyr.t, acc.t):
        return [acc, gyr]
    mask, values = onto(acc, gyr.t)
    if not mask.any():
        notes.append(f"{imu.id}: accelerometer and gyro samples do not overlap in time; not usable as an "
                     "IMU")
        return []
    notes.append(f"{imu.id}: accelerometer interpolated onto the gyro's time stamps")
    if not mask.all():
        notes.append(f"{imu.id}: {int((~mask).sum())} of {len(gyr)} gyro epochs have no accelerometer "
                     "samples on both sides and were dropped")
    t = gyr.t[mask]
    return [replace(acc, t=t, values=values), replace(gyr, t=t, values=gyr.values[mask])]
