"""Vehicle topics of a ULog: attitude, battery, throttle, GPS position and the UTC time of the clock's zero."""

from __future__ import annotations

import numpy as np

from magcal_cli.readers.ulog.topics import Piece, Topics
from magcal_cli.streams import Kind

#: a GPS UTC time (us since 1970) before this (2001-09) is a receiver that has no time yet, not a date
MIN_UTC_US = 1_000_000_000_000_000


def other_pieces(tp: Topics) -> list[Piece]:
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


def _throttle_piece(tp: Topics) -> Piece | None:
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


#: the most motors read (ArduPilot's per-motor compensation uses 4; the effect uses motors 1-4)
MAX_MOTORS = 8


def motor_pieces(tp: Topics, params: dict[str, float]) -> list[Piece]:
    """motor[k]: each motor's output 0..1 (issue 28): actuator_motors.control[k-1] (PX4 >= 1.14; NaN while disarmed
    -> 0), else actuator_outputs[0].output[k-1] as a fraction of PWM_MAIN_MIN..MAX (default 1000..2000 us). Only
    outputs that change (std > 1 % of the range) are motors; none: no stream."""
    ds = tp.get("actuator_motors")
    name, fields, lo, hi = "actuator_motors", "control[{}]", 0.0, 1.0
    if ds is None:
        ds, name, fields = tp.get("actuator_outputs"), "actuator_outputs", "output[{}]"
        lo, hi = params.get("PWM_MAIN_MIN", 1000.0), params.get("PWM_MAIN_MAX", 2000.0)
    if ds is None:
        return []
    t = tp.stamps(ds, name)
    out = []
    for k in range(MAX_MOTORS):
        col = tp.columns(ds, [fields.format(k)])
        if col is None:
            break
        u = np.clip((np.nan_to_num(col[:, 0], nan=lo) - lo) / (hi - lo), 0.0, 1.0)
        if float(np.std(u)) < 0.01:
            break
        out.append(Piece(Kind.MOTOR_OUTPUT, f"motor[{k + 1}]", t, u[:, None], tp.source(name, fields.format(k)), "1"))
    return out


def _gps_piece(tp: Topics) -> Piece | None:
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


def utc_of_boot(tp: Topics) -> float | None:
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
