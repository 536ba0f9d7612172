"""PX4 ULog writer for simulated recordings (`magcal simulate out.ulg`) and the small builder tests use.

Layout per the ULog specification (PX4 docs, "ULog File Format"): a 16-byte header, the flag-bits message
('B', first), formats ('F'), info ('I') and parameters ('P'), then subscriptions ('A') and data ('D'),
dropouts ('O') and parameter changes ('P') in time order. Fields are written packed in the declared order,
as pyulog and PX4's tools read them. Data records are built as numpy structured arrays, not per sample.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from magcal_cli import __version__, so3, units
from magcal_cli.atomic import atomic_path
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.synth.physics import local
from magcal_cli.synth.simulate import T0_ROS, Simulation

#: pyulog's HEADER_BYTES ("ULog" + 0x01 0x12 0x35), then the file version
MAGIC = b"ULog\x01\x12\x35"
FILE_VERSION = 1
#: ULog field type -> little-endian numpy type (pyulog's _UNPACK_TYPES)
NUMPY_TYPES = {"int8_t": "i1", "uint8_t": "u1", "int16_t": "<i2", "uint16_t": "<u2", "int32_t": "<i4",
               "uint32_t": "<u4", "int64_t": "<i8", "uint64_t": "<u8", "float": "<f4", "double": "<f8",
               "bool": "u1", "char": "i1"}
#: the simulated vehicle's clock when logging starts (us since boot); samples follow at their simulation times
START_US = 20_000_000
#: DeviceStructure of the simulated magnetometer: bus type 4 (simulation), bus 0, address 0x0e, devtype 0x06
SIM_MAG_DEVICE_ID = 4 | (0 << 3) | (0x0E << 8) | (0x06 << 16)
#: magnetometer k of a simulation is on bus k (same type and address), so each has a device id of its own
SIM_MAG_BUS_STEP = 1 << 3
#: the temperature the simulated magnetometer reports (degC) when the simulation has no temperature stream
SIM_MAG_TEMPERATURE = 25.0
#: DeviceStructure of the simulated GNSS receiver: bus type 5 (serial), bus 1, devtype 0xa6 (GPS)
SIM_GPS_DEVICE_ID = 5 | (1 << 3) | (0xA6 << 16)
#: vehicle_attitude is logged at most this often (Hz), as PX4's logger rate-limits it
ATTITUDE_RATE_HZ = 50.0


@dataclass(frozen=True, eq=False)
class Topic:
    """One logged topic instance: its ULog fields (type, name), timestamp first, and a column per field.

    Array fields (`float[3] gyro_rad`) take (N, 3) columns; scalar fields (N,) columns.
    """

    name: str
    fields: tuple[tuple[str, str], ...]
    data: Mapping[str, npt.ArrayLike]
    multi_id: int = 0

    def format_text(self) -> str:
        """The 'F' message body: `name:type field;type field;...`."""
        return f"{self.name}:" + "".join(f"{t} {n};" for t, n in self.fields)

    def dtype(self) -> np.dtype[np.void]:
        """A packed record: message header (uint16 size, uint8 'D'), uint16 msg_id, then the fields."""
        cols: list[tuple[str, str] | tuple[str, str, tuple[int]]] = [
            ("size", "<u2"), ("type", "u1"), ("msg_id", "<u2")]
        for type_, name in self.fields:
            base, _, count = type_.partition("[")
            np_type = NUMPY_TYPES[base]
            cols.append((name, np_type, (int(count.rstrip("]")),)) if count else (name, np_type))
        return np.dtype(cols)

    def records(self, msg_id: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
        """(timestamps, (N, record size) bytes) of every data message of this topic."""
        dt = self.dtype()
        n = len(np.asarray(self.data["timestamp"]))
        rec = np.zeros(n, dtype=dt)
        rec["size"], rec["type"], rec["msg_id"] = dt.itemsize - 3, ord("D"), msg_id
        for _, name in self.fields:
            rec[name] = np.asarray(self.data[name])
        return np.asarray(self.data["timestamp"], dtype=np.int64), rec.view(np.uint8).reshape(n, dt.itemsize)


@dataclass(frozen=True, eq=False)
class UlogContent:
    """Everything a written ULog holds: topics, info, initial parameters, later changes and dropouts."""

    topics: Sequence[Topic]
    params: Mapping[str, int | float] = field(default_factory=dict)
    info: Mapping[str, str] = field(default_factory=dict)
    start_us: int = START_US
    changed_params: Sequence[tuple[int, str, int | float]] = ()
    dropouts: Sequence[tuple[int, int]] = ()          # (time us, duration ms)


def _message(kind: str, payload: bytes) -> bytes:
    """One message: uint16 payload size, uint8 type, payload."""
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _key_value(type_: str, name: str, value: bytes) -> bytes:
    """An info or parameter body: uint8 key length, key `type name`, value bytes."""
    key = f"{type_} {name}".encode()
    return bytes([len(key)]) + key + value


def _param(name: str, value: int | float) -> bytes:
    """A parameter body: int32_t for integers, float otherwise (the two types PX4 has)."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return _key_value("int32_t", name, struct.pack("<i", int(value)))
    return _key_value("float", name, struct.pack("<f", float(value)))


def ulog_bytes(content: UlogContent) -> bytes:
    """The complete file."""
    head = [MAGIC + bytes([FILE_VERSION]) + struct.pack("<Q", content.start_us),
            _message("B", bytes(16) + struct.pack("<3Q", 0, 0, 0))]     # no flags set, nothing appended
    formats = {t.name: t.format_text() for t in content.topics}
    head += [_message("F", text.encode()) for text in formats.values()]
    head += [_message("I", _key_value(f"char[{len(v.encode())}]", k, v.encode()))
             for k, v in content.info.items()]
    head += [_message("P", _param(k, v)) for k, v in content.params.items()]
    head += [_message("A", struct.pack("<BH", t.multi_id, i) + t.name.encode())
             for i, t in enumerate(content.topics)]
    chunks = [t.records(i) for i, t in enumerate(content.topics)]
    for t_us, name, value in content.changed_params:
        chunks.append(_single(t_us, _message("P", _param(name, value))))
    for t_us, duration_ms in content.dropouts:
        chunks.append(_single(t_us, _message("O", struct.pack("<H", duration_ms))))
    return b"".join(head) + _merge(chunks).tobytes()


def _single(t_us: int, message: bytes) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
    """One message as a chunk of one record."""
    return np.array([t_us], dtype=np.int64), np.frombuffer(message, dtype=np.uint8)[None, :]


def _merge(chunks: list[tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]]) -> npt.NDArray[np.uint8]:
    """Interleave the fixed-size records of several chunks by time stamp (earlier chunks first at a tie)."""
    if not chunks:
        return np.zeros(0, dtype=np.uint8)
    times = np.concatenate([t for t, _ in chunks])
    sizes = np.concatenate([np.full(len(t), rows.shape[1], dtype=np.int64) for t, rows in chunks])
    order = np.argsort(times, kind="stable")
    start = np.empty_like(sizes)
    start[order] = np.cumsum(sizes[order]) - sizes[order]          # where each record lands in the output
    out = np.empty(int(sizes.sum()), dtype=np.uint8)
    first = 0
    for t, rows in chunks:
        dest = start[first:first + len(t), None] + np.arange(rows.shape[1])
        out[dest] = rows
        first += len(t)
    return out


def write_content(content: UlogContent, path: Path) -> None:
    """Write a ULog atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(ulog_bytes(content))


def _us(t: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Simulation seconds -> the vehicle clock in integer microseconds."""
    return START_US + np.round(np.asarray(t, dtype=np.float64) * 1e6).astype(np.int64)


def sim_content(sim: Simulation) -> UlogContent:
    """The simulation as PX4 logs it: sensor_combined (means over gyro/accelerometer_integral_dt, the IMU period,
    ending at the stamp), sensor_mag instance k per magnetometer (gauss, stamped where it was sampled, with the
    simulated temperature; CAL_MAGk_ID its device id), vehicle_attitude, parameters, and battery_status, vehicle_thrust_setpoint and vehicle_gps_position when the
    simulation has battery, throttle or position streams."""
    rec = sim.recording
    acc, gyr = rec.select(Kind.ACCELEROMETER), rec.select(Kind.GYROSCOPE)
    t_imu, n = _us(gyr.t), len(gyr)
    # sensor_combined's samples are means over the integration period ending at their stamp (Sampling.PRECEDING)
    window = gyr.window_s or (1.0 / gyr.rate_hz if gyr.rate_hz > 0 else 0.0)
    period = int(round(window * 1e6))
    zeros = np.zeros(n)
    comb = Topic("sensor_combined", (
        ("uint64_t", "timestamp"), ("float[3]", "gyro_rad"), ("uint32_t", "gyro_integral_dt"),
        ("int32_t", "accelerometer_timestamp_relative"), ("float[3]", "accelerometer_m_s2"),
        ("uint32_t", "accelerometer_integral_dt"), ("uint8_t", "accelerometer_clipping"),
        ("uint8_t", "gyro_clipping"), ("uint8_t", "accel_calibration_count"),
        ("uint8_t", "gyro_calibration_count")),
        {"timestamp": t_imu, "gyro_rad": gyr.values, "gyro_integral_dt": np.full(n, period),
         "accelerometer_timestamp_relative": _us(acc.t) - t_imu, "accelerometer_m_s2": acc.values,
         "accelerometer_integral_dt": np.full(n, period), "accelerometer_clipping": zeros,
         "gyro_clipping": zeros, "accel_calibration_count": zeros, "gyro_calibration_count": zeros})
    mags = [_sensor_mag(rec, s, k) for k, s in enumerate(rec.of_kind(Kind.MAGNETOMETER))]
    step = max(1, int(round(gyr.rate_hz / ATTITUDE_RATE_HZ)))
    att_t = t_imu[::step]
    att = Topic("vehicle_attitude", (
        ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[4]", "q"),
        ("float[4]", "delta_q_reset"), ("uint8_t", "quat_reset_counter")),
        {"timestamp": att_t + 300, "timestamp_sample": att_t, "q": so3.as_quat(sim.rotations[::step]),
         "delta_q_reset": np.zeros((len(att_t), 4)), "quat_reset_counter": np.zeros(len(att_t))})
    params: dict[str, int | float] = {"CAL_MAG0_ID": SIM_MAG_DEVICE_ID, "CAL_MAG0_PRIO": 50,
                                      "CAL_MAG0_ROT": 0, "CAL_MAG_COMP_TYP": 0, "SENS_BOARD_ROT": 0,
                                      "SDLOG_PROFILE": 1 | 64}
    params |= {f"CAL_MAG0_{ax}": 0.0 for ax in ("ROLL", "PITCH", "YAW")}   # a release with custom Euler angles
    for axis in "XYZ":
        params |= {f"CAL_MAG0_{axis}OFF": 0.0, f"CAL_MAG0_{axis}SCALE": 1.0, f"CAL_MAG0_{axis}ODIAG": 0.0,
                   f"CAL_MAG0_{axis}COMP": 0.0, f"SENS_BOARD_{axis}_OFF": 0.0}
    for k in range(1, len(mags)):
        params |= {f"CAL_MAG{k}_ID": SIM_MAG_DEVICE_ID + k * SIM_MAG_BUS_STEP, f"CAL_MAG{k}_PRIO": 50,
                   f"CAL_MAG{k}_ROT": 0} | {f"CAL_MAG{k}_{ax}": 0.0 for ax in ("ROLL", "PITCH", "YAW")}
        for axis in "XYZ":
            params |= {f"CAL_MAG{k}_{axis}OFF": 0.0, f"CAL_MAG{k}_{axis}SCALE": 1.0, f"CAL_MAG{k}_{axis}ODIAG": 0.0,
                       f"CAL_MAG{k}_{axis}COMP": 0.0}
    info = {"sys_name": "PX4", "ver_hw": "MAGCAL_SIM", "ver_sw": f"magcal {__version__} simulate",
            "magcal_simulation": f"{sim.scenario} seed={sim.seed}"}
    return UlogContent((comb, *mags, att, *_aux_topics(rec)), params, info)


def _sensor_mag(rec: Recording, mag: Stream, k: int) -> Topic:
    """sensor_mag instance k (multi_id k, its own device id): the raw field in gauss, stamped where it was
    sampled, published 150 us later, with the simulated temperature."""
    t_mag, m = _us(mag.t), len(mag)
    field_g = mag.xyz * units.from_si("gauss")
    return Topic("sensor_mag", (
        ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
        ("float", "x"), ("float", "y"), ("float", "z"), ("float", "temperature"), ("uint32_t", "error_count"),
        ("bool", "is_external")),
        {"timestamp": t_mag + 150, "timestamp_sample": t_mag,
         "device_id": np.full(m, SIM_MAG_DEVICE_ID + k * SIM_MAG_BUS_STEP),
         "x": field_g[:, 0], "y": field_g[:, 1], "z": field_g[:, 2],
         "temperature": _series(rec, Kind.TEMPERATURE, mag.t, np.full(m, SIM_MAG_TEMPERATURE)),
         "error_count": np.zeros(m),
         "is_external": np.ones(m)}, multi_id=k)


def _series(rec: Recording, kind: Kind, t: npt.NDArray[np.float64],
            default: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The recording's stream of `kind` at t (held at its ends), else `default`."""
    found = rec.of_kind(kind)
    if not found or len(found[0]) < 2:
        return default
    out: npt.NDArray[np.float64] = np.interp(t, found[0].t, found[0].values[:, 0])      # held at its ends
    return out


def _aux_topics(rec: Recording) -> list[Topic]:
    """battery_status, vehicle_thrust_setpoint and vehicle_gps_position for the auxiliary streams present."""
    out = []
    cur, volt = rec.of_kind(Kind.BATTERY_CURRENT), rec.of_kind(Kind.BATTERY_VOLTAGE)
    if cur:
        t, amps = cur[0].t, cur[0].values[:, 0]
        volts = _series(rec, Kind.BATTERY_VOLTAGE, t, np.full(t.size, np.nan)) if volt else np.full(t.size, 0.0)
        used = np.concatenate([[0.0], np.cumsum(0.5 * (amps[1:] + amps[:-1]) * np.diff(t))]) / 3.6   # mAh
        n = t.size
        out.append(Topic("battery_status", (
            ("uint64_t", "timestamp"), ("float", "voltage_v"), ("float", "current_a"),
            ("float", "current_average_a"), ("float", "discharged_mah"), ("float", "remaining"),
            ("float", "temperature"), ("uint8_t", "cell_count"), ("bool", "connected"), ("uint8_t", "id")),
            {"timestamp": _us(t), "voltage_v": volts, "current_a": amps, "current_average_a": amps,
             "discharged_mah": used, "remaining": 1.0 - used / 5000.0, "temperature": np.full(n, np.nan),
             "cell_count": np.full(n, 4), "connected": np.ones(n), "id": np.ones(n)}))
    thr = rec.of_kind(Kind.THROTTLE)
    if thr:              # PX4 >= 1.14: multicopter thrust along -z (FRD), normalised 0..1
        t, n = thr[0].t, len(thr[0])
        xyz = np.column_stack([np.zeros(n), np.zeros(n), -thr[0].values[:, 0]])
        out.append(Topic("vehicle_thrust_setpoint", (
            ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[3]", "xyz")),
            {"timestamp": _us(t) + 50, "timestamp_sample": _us(t), "xyz": xyz}))
    pos = rec.of_kind(Kind.POSITION)
    if pos:
        t, lla, n = pos[0].t, pos[0].values, len(pos[0])
        vel = np.gradient(local(lla), t, axis=0) if n > 1 else np.zeros((n, 3))
        out.append(Topic("vehicle_gps_position", (
            ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
            ("double", "latitude_deg"), ("double", "longitude_deg"), ("double", "altitude_msl_m"),
            ("float", "eph"), ("float", "epv"), ("float", "vel_m_s"), ("float", "vel_n_m_s"),
            ("float", "vel_e_m_s"), ("float", "vel_d_m_s"), ("bool", "vel_ned_valid"), ("uint8_t", "fix_type"),
            ("uint8_t", "satellites_used"), ("uint64_t", "time_utc_usec")),
            {"timestamp": _us(t) + 80_000, "timestamp_sample": _us(t), "device_id": np.full(n, SIM_GPS_DEVICE_ID),
             "latitude_deg": lla[:, 0], "longitude_deg": lla[:, 1], "altitude_msl_m": lla[:, 2],
             "eph": np.full(n, 0.8), "epv": np.full(n, 1.2), "vel_m_s": np.linalg.norm(vel[:, :2], axis=1),
             "vel_n_m_s": vel[:, 0], "vel_e_m_s": vel[:, 1], "vel_d_m_s": vel[:, 2], "vel_ned_valid": np.ones(n),
             "fix_type": np.full(n, 3), "satellites_used": np.full(n, 14),
             # the receiver's UTC at the fix (simulation time 0 is T0_ROS), which dates the log for the WMM
             "time_utc_usec": np.round((T0_ROS + np.asarray(t, dtype=np.float64)) * 1e6).astype(np.int64)}))
    return out


def write_ulg(sim: Simulation, path: Path) -> None:
    """Write the simulation as a PX4 ULog: raw field in sensor_mag (gauss), IMU in sensor_combined."""
    write_content(sim_content(sim), path)
