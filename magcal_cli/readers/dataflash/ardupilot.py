"""The Recording of an ArduPilot DataFlash log: raw field, IMU, attitude, battery, throttle, GPS, parameters.

ArduPilot logs the corrected magnetometer field; the MAGNETOMETER streams carry the raw reading rebuilt by
undoing the parameters in force at each sample (`rawfield`, `compass`). Everything stays in the body frame the
firmware logs (COMPASS_ORIENTn / AHRS_ORIENTATION already applied). See docs/readers-ardupilot.md.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from magcal_cli.errors import LogReadError, StreamError
from magcal_cli.progress import active, current, within
from magcal_cli.readers.checks import rotates
from magcal_cli.readers.dataflash.compass import ParamHistory
from magcal_cli.readers.dataflash.format import RawLog
from magcal_cli.readers.dataflash.load import IMU_NAMES, MAG_NAMES, load
from magcal_cli.readers.dataflash.rawfield import MagReconstruction, Series, reconstruct
from magcal_cli.readers.dataflash.streams import (
    Clock,
    Pending,
    clock_from,
    euler_quat,
    finish,
    instance_tag,
    instances,
    int_factor,
    logged_columns,
    stack_columns,
    time_of,
)
from magcal_cli.streams import Kind, Recording
from magcal_cli.units import GPS_EPOCH_UNIX, GPS_LEAP_S, GPS_WEEK_S

#: milligauss to tesla
MG_TO_T = 1e-7
#: where each step of build_ardupilot ends in its share of the read: IMU streams, raw field, the other streams
#: (then finish() checks every stream); measured on a 55 MB simulated .bin
BUILD_STEPS = (0.15, 0.45, 0.55)
#: a ChibiOS or NuttX board's boot message: its name and its processor's 96-bit unique id as three hex words,
#: e.g. "fmuv3 002F001F 33375111 37353832" (hal.util's system id, logged at every log start)
BOARD_ID = re.compile(r"(\S+) ([0-9A-Fa-f]{8}) ([0-9A-Fa-f]{8}) ([0-9A-Fa-f]{8})")


def board_info(messages: list[str]) -> dict[str, str]:
    """`board` and `board_uid` (24 upper-case hex digits) from the first boot message that names them, else {}."""
    for text in messages:
        m = BOARD_ID.fullmatch(text.strip())
        uid = "".join(m.groups()[1:]).upper() if m else ""
        if m and uid.strip("0") and uid.strip("F"):     # all zero or all one bits: no id read, not a vehicle's
            return {"board": m.group(1), "board_uid": uid}
    return {}


def param_history(raw: RawLog, clock: Clock) -> ParamHistory:
    """Every PARM record with its time (its own TimeUS, else that of the message before it)."""
    parm = raw.table("PARM")
    if parm is None or not parm.fmt.has("Name", "Value"):
        return ParamHistory([], np.zeros(0), np.zeros(0))
    t = time_of(parm, clock)
    return ParamHistory(parm.text("Name"), np.nan_to_num(t, nan=-np.inf), parm.num("Value"))


def reconstruct_mags(path: Path) -> list[MagReconstruction]:
    """The raw field of every compass of an ArduPilot log and what was undone (diagnostics, tests)."""
    raw = load(path)
    clock = clock_from(raw)
    hist = param_history(raw, clock)
    thr, cur = _motor_signals(_throttle(path, raw, clock, hist.last()), _battery(path, raw, clock))
    return reconstruct(path, raw, clock, hist, thr, cur)


def _motor_signals(throttle: list[Pending], battery: list[Pending]) -> tuple[Series | None, Series | None]:
    """(t, throttle) and (t, current) series for motor compensation, when the log has them."""
    thr = (throttle[0].t, throttle[0].blocks()[0][:, 0]) if throttle else None
    cur = next(((p.t, p.blocks()[0][:, 0]) for p in battery if p.kinds[0] is Kind.BATTERY_CURRENT), None)
    return thr, cur


def _imu_streams(path: Path, raw: RawLog, clock: Clock, notes: list[str]) -> list[Pending]:
    """IMU[i]: accelerometer (m/s^2) and gyroscope (rad/s) sharing one id, and the IMU temperature (degC)."""
    out = []
    for inst, table in instances(raw, IMU_NAMES, notes=notes, limit=3):
        f = table.fmt
        if not f.has("GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ"):
            continue
        t = time_of(table, clock)
        src = f"{path.name}#{f.name}{instance_tag(f, inst)}"
        # one array per kind, as the streams hold them: no (N, 6) array to split (issue 39)
        values = (logged_columns(table, ("AccX", "AccY", "AccZ")), logged_columns(table, ("GyrX", "GyrY", "GyrZ")))
        out.append(Pending((Kind.ACCELEROMETER, Kind.GYROSCOPE), f"IMU[{inst}]", t, values, src + ".Acc/Gyr",
                           ("m/s^2", "rad/s")))
        temp = next((c for c in ("Temp", "T") if f.has(c)), None)
        if temp:
            out.append(Pending((Kind.TEMPERATURE,), f"IMU[{inst}]", t, table.num(temp)[:, None],
                               f"{src}.{temp}", ("degC",)))
    return out


def _battery(path: Path, raw: RawLog, clock: Clock) -> list[Pending]:
    """BAT[i] current (A) and voltage (V) from BAT (4.x, amps) or CURR (3.x, centi-amps and centi-volts)."""
    out = []
    for names in (("BAT", "BAT2"), ("CURR",)):
        for inst, table in instances(raw, names):
            f = table.fmt
            t = time_of(table, clock)
            for col, kind, unit in (("Curr", Kind.BATTERY_CURRENT, "A"), ("Volt", Kind.BATTERY_VOLTAGE, "V")):
                if f.has(col):
                    k = int_factor(table, col, 0.01)
                    native = "cA" if k == 0.01 and unit == "A" else unit
                    out.append(Pending((kind,), f"BAT[{inst}]", t, table.num(col)[:, None] * k,
                                       f"{path.name}#{f.name}.{col}", (native,)))
        if out:
            break
    return out


def _throttle(path: Path, raw: RawLog, clock: Clock, params: dict[str, float]) -> list[Pending]:
    """Throttle 0..1 from CTUN.ThO/ThrOut (0..1000 in old logs), else the mean of RCOU channels 1-4."""
    ctun = raw.table("CTUN")
    col = next((c for c in ("ThO", "ThrOut") if ctun is not None and ctun.fmt.has(c)), None)
    if ctun is not None and col is not None:
        out = ctun.num(col)
        k = 1e-3 if np.nanmax(np.abs(out), initial=0.0) > 1.5 else 1.0     # 0..1000 before 3.5, 0..1 since
        return [Pending((Kind.THROTTLE,), "CTUN", time_of(ctun, clock), out[:, None] * k,
                        f"{path.name}#CTUN.{col}", ("1",))]
    rcou = raw.table("RCOU")
    chans = next((c for c in (("C1", "C2", "C3", "C4"), ("Ch1", "Ch2", "Ch3", "Ch4"))
                  if rcou is not None and rcou.fmt.has(*c)), None)
    if rcou is None or chans is None:
        return []
    lo, hi = params.get("MOT_PWM_MIN", 0.0) or 1000.0, params.get("MOT_PWM_MAX", 0.0) or 2000.0
    pwm = stack_columns(rcou, chans).mean(axis=1)
    thr = np.clip((pwm - lo) / (hi - lo), 0.0, 1.0)
    return [Pending((Kind.THROTTLE,), "RCOU", time_of(rcou, clock), thr[:, None],
                    f"{path.name}#RCOU.{'/'.join(chans)} (mean PWM, MOT_PWM_MIN..MAX)", ("1",))]


#: SERVOn_FUNCTION of motor 1 (33 = k_motor1 ... 40 = k_motor8)
MOTOR1_FUNCTION = 33


def _motors(path: Path, raw: RawLog, clock: Clock, params: dict[str, float]) -> list[Pending]:
    """motor[k]: motor k's output 0..1 of its PWM range from RCOU (C1../Ch1..), as ArduPilot's per-motor compass
    compensation reads it (scale_esc_to_unity over MOT_PWM_MIN..MAX, else RC3_MIN..MAX, else 1000..2000 [S7]);
    the channel of motor k is the one whose SERVOn_FUNCTION is 32 + k, else channel k (a quad's default)."""
    rcou = raw.table("RCOU")
    if rcou is None:
        return []
    prefix = next((p for p in ("C", "Ch") if rcou.fmt.has(f"{p}1")), None)
    if prefix is None:
        return []
    lo = params.get("MOT_PWM_MIN", 0.0) or params.get("RC3_MIN", 0.0) or 1000.0
    hi = params.get("MOT_PWM_MAX", 0.0) or params.get("RC3_MAX", 0.0) or 2000.0
    servo = {int(v) - MOTOR1_FUNCTION + 1: int(k[5:-9]) for k, v in params.items()
             if re.fullmatch(r"SERVO\d+_FUNCTION", k) and MOTOR1_FUNCTION <= v < MOTOR1_FUNCTION + 8}
    t = time_of(rcou, clock)
    out = []
    for motor in range(1, 9):
        ch = servo.get(motor, motor if not servo else 0)
        if not ch or not rcou.fmt.has(f"{prefix}{ch}"):
            continue
        u = np.clip((rcou.num(f"{prefix}{ch}") - lo) / (hi - lo), 0.0, 1.0)
        out.append(Pending((Kind.MOTOR_OUTPUT,), f"motor[{motor}]", t, u[:, None],
                           f"{path.name}#RCOU.{prefix}{ch} (PWM over {lo:.0f}..{hi:.0f})", ("1",)))
    return out


def _attitude(path: Path, raw: RawLog, clock: Clock) -> list[Pending]:
    """ATT and AHR2 attitude as quaternions (body to NED) from Roll/Pitch/Yaw in degrees."""
    out = []
    for name in ("ATT", "AHR2"):
        table = raw.table(name)
        if table is not None and table.fmt.has("Roll", "Pitch", "Yaw"):
            q = euler_quat(table.num("Roll"), table.num("Pitch"), table.num("Yaw"))
            out.append(Pending((Kind.ATTITUDE,), name, time_of(table, clock), q,
                               f"{path.name}#{name}.Roll/Pitch/Yaw", ("quaternion wxyz",)))
    return out


def _gps(path: Path, raw: RawLog, clock: Clock, notes: list[str]) -> list[Pending]:
    """GPS[i] position (lat deg, lon deg, alt m) from records with a 3D fix (Status >= 3)."""
    out = []
    for inst, table in instances(raw, ("GPS", "GPS2")):
        f = table.fmt
        if not f.has("Lat", "Lng", "Alt"):
            continue
        fix = table.num("Status") >= 3 if f.has("Status") else np.ones(len(table), dtype=bool)
        t = time_of(table, clock)[fix]
        table = table.where(fix)
        pos = np.stack([table.num(c) * int_factor(table, c, k) for c, k in (("Lat", 1e-7), ("Lng", 1e-7),
                                                                         ("Alt", 0.01))], axis=1)
        if t.size:
            out.append(Pending((Kind.POSITION,), f"GPS[{inst}]", t, pos, f"{path.name}#{f.name}.Lat/Lng/Alt",
                               ("deg, deg, m",)))
    return out


def _utc_of_boot(raw: RawLog, clock: Clock) -> float | None:
    """The Unix time of the log's boot clock zero, from GPS records with a fix (GWk weeks and GMS ms since the GPS
    epoch, minus the leap seconds): the date the World Magnetic Model is evaluated on."""
    for _, table in instances(raw, ("GPS", "GPS2")):
        f = table.fmt
        names = ("GWk", "GMS") if f.has("GWk", "GMS") else ("Week", "TimeMS") if f.has("Week", "TimeMS") else None
        if names is None:                  # 3.x logs name them Week and TimeMS (then T is the boot time)
            continue
        week, ms = table.num(names[0]), table.num(names[1])
        ok = (week > 0) & ((table.num("Status") >= 3) if f.has("Status") else True)
        if ok.any():
            utc = GPS_EPOCH_UNIX + week[ok] * GPS_WEEK_S + ms[ok] / 1000.0 - GPS_LEAP_S
            return float(np.median(utc - time_of(table, clock)[ok]))
    return None


def build_ardupilot(path: Path, raw: RawLog) -> Recording:
    """The Recording of an ArduPilot log: raw field, IMU, attitude, battery, throttle, GPS, parameters."""
    notes = list(raw.notes)
    if not any(raw.table(n) is not None for n in MAG_NAMES):
        defined = [n for n in MAG_NAMES if n in raw.formats]
        why = (f"{'/'.join(defined)} defined by FMT but never written" if defined else "no MAG record format")
        msg = (f"{path}: no magnetometer messages ({why}); nothing to calibrate. Enable compass logging "
               "(LOG_BITMASK) and record the log again")
        raise StreamError(msg)
    clock = clock_from(raw)
    if not clock:
        msg = (f"{path}: the log's records carry no time (no TimeUS/TimeMS fields; firmware before 3.1?); "
               "magcal needs timestamps to pair the magnetometer with the IMU")
        raise LogReadError(msg)
    hist = param_history(raw, clock)
    params = hist.last()
    hook = current()
    throttle = _throttle(path, raw, clock, params)
    battery = _battery(path, raw, clock)
    pending = _imu_streams(path, raw, clock, notes)
    for name in IMU_NAMES:      # the largest decoded records (2 hours at 400 Hz: 0.16 GB), not read again
        raw.tables.pop(name, None)
    hook("reading", BUILD_STEPS[0], 1.0)
    imu = next((p for p in pending if Kind.GYROSCOPE in p.kinds), None)
    turned = imu is not None and rotates(imu.t, imu.blocks()[1])
    dead: dict[str, str] = {}
    for m in reconstruct(path, raw, clock, hist, *_motor_signals(throttle, battery), rotated=turned):
        notes += m.notes
        if m.dead is not None:
            dead[f"MAG[{m.instance}]"] = m.dead
        pending.append(Pending((Kind.MAGNETOMETER,), f"MAG[{m.instance}]", m.t, m.raw * MG_TO_T, m.source,
                               ("milligauss",), None if m.resolution is None else m.resolution * MG_TO_T))
    hook("reading", BUILD_STEPS[1], 1.0)
    pending += (_attitude(path, raw, clock) + battery + throttle + _gps(path, raw, clock, notes)
                + _motors(path, raw, clock, params))
    hook("reading", BUILD_STEPS[2], 1.0)
    with active(within(hook, BUILD_STEPS[2], 1.0)):
        rec = finish(path, "dataflash", pending, params, notes, dead)
    boot = _utc_of_boot(raw, clock)
    msgs = raw.table("MSG")
    info = board_info(msgs.text("Message") if msgs is not None and msgs.fmt.has("Message") else [])
    return replace(rec, utc0=None if boot is None else boot + rec.t0, info=info)
