"""ArduPilot DataFlash `.bin` writer for simulations: a 4.x record set with the field logged *corrected*.

The simulated firmware flies with an earlier onboard calibration (COMPASS_OFS/DIA/ODI, optionally SCALE and
motor compensation; `Simulation.previous`, synth/firmware.py) and logs MAG the way AP_Compass does: corrected,
in the body frame, truncated to int16 mGauss, with OfsX.. and MOX.. beside it. Every magnetometer of the
simulation (up to three) is a compass: MAG instance I = k with the parameters COMPASS_*, *2, *3.
Metadata records (FMT, UNIT, MULT, FMTU, PARM, VER, MSG) are packed with struct; sensor records are built as
numpy structured arrays and interleaved by time in one pass.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import as_strided

from magcal_cli import so3
from magcal_cli.atomic import atomic_path
from magcal_cli.errors import MagcalError
from magcal_cli.readers.dataflash.compass import Correction, apply_correction, effective_scale, iron_matrix
from magcal_cli.readers.dataflash.format import FMT_ID, FMT_LENGTH, FORMAT_CHARS, HEAD1, HEAD2, MessageFormat
from magcal_cli.streams import FloatArray, Kind, Recording, Stream
from magcal_cli.synth.firmware import MAX_COMPASSES, CompassParams
from magcal_cli.synth.firmware import (
    PreviousCalibration as PreviousCalibration,  # re-exported: its home before the move
)
from magcal_cli.synth.physics import local
from magcal_cli.synth.simulate import Simulation
from magcal_cli.units import GPS_EPOCH_UNIX, GPS_LEAP_S, GPS_WEEK_S

BOOT_S = 30.0                    # the simulated log starts 30 s after boot, as real logs do
UNITS = {"s": "s", "#": "instance", "G": "Gauss", "E": "rad/s", "o": "m/s/s", "O": "degC", "z": "Hz",
         "d": "deg", "h": "degheading", "v": "V", "A": "A", "a": "Ah", "X": "W.h", "w": "Ohm", "%": "%",
         "m": "m", "n": "m/s", "S": "satellites", "D": "deglatitude", "U": "deglongitude", "-": ""}
MULTS = {"-": 0.0, "?": 1.0, "0": 1.0, "B": 1e-2, "C": 1e-3, "F": 1e-6, "G": 1e-7}
#: (type id, name, format, columns, unit ids, multiplier ids) as ArduCopter 4.6 logs them (LogStructure.h)
RECORDS = [
    (32, "PARM", "QNff", "TimeUS,Name,Value,Default", "s---", "F---"),
    (0, "CTUN", "Qffffffefffhh", "TimeUS,ThI,ABst,ThO,ThH,DAlt,Alt,BAlt,DSAlt,SAlt,TAlt,DCRt,CRt",
     "s----mmmmmmnn", "F----00B000BB"),
    (72, "ATT", "QffffffB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,AEKF", "sddddhh-", "F000000-"),
    (88, "BAT", "QBfffffcfBBB", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct,H,SH",
     "s#vvAaXOw%-%", "F-000C0?0000"),
    (94, "GPS", "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
     "s#-s-S-DUmnhnh-", "F--C-0BGGB000--"),
    (113, "MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",
     "s#GGGGGGGGG-s", "F-CCCCCCCCC-F"),
    (118, "FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds", "s---", "F---"),
    (119, "UNIT", "QbZ", "TimeUS,Id,Label", "s--", "F--"),
    (120, "MULT", "Qbd", "TimeUS,Id,Mult", "s--", "F--"),
    (163, "IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
     "s#EEEooo--O--zz", "F-000000-----00"),
    (177, "MSG", "QZ", "TimeUS,Message", "s-", "F-"),
    (178, "VER", "QBHBBBBIZ", "TimeUS,BT,BST,Maj,Min,Pat,FWT,GH,FWS", "s--------", "F--------"),
]


#: COMPASS_DEV_ID, DEV_ID2, DEV_ID3 (and PRIOn_ID) of the simulated compasses: ArduPilot SITL's three
DEV_IDS = (97539, 131874, 263178)
#: what an earlier calibration's offsets missed the negated true hard iron by, per compass (mG)
OFFSET_MISS = ((6.0, -4.0, 5.0), (-5.0, 7.0, -3.0), (4.0, 5.0, -6.0))
#: MAG records of instance k are logged this much (us) after instance k - 1's, as one update loop writes them
INSTANCE_STAGGER_US = 30


#: format character -> struct code
STRUCT = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d", "n": "4s",
          "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "M": "B", "q": "q",
          "Q": "Q", "g": "e"}


#: RCOU (motor PWM of channels 1-4, as ArduCopter logs C1..C14): written, with its FMT/FMTU, MOT_PWM_MIN/MAX and
#: SERVOn_FUNCTION, only when the simulation has per-motor outputs, so other simulated logs keep their bytes
RCOU = (60, "RCOU", "QHHHH", "TimeUS,C1,C2,C3,C4", "s----", "F----")
#: the PWM range the simulated motors' outputs 0..1 span (MOT_PWM_MIN, MOT_PWM_MAX)
PWM_RANGE = (1000.0, 2000.0)


def _formats() -> dict[str, MessageFormat]:
    """The MessageFormat of every record type written."""
    return {name: MessageFormat(tid, name, 3 + MessageFormat(tid, name, 0, fmt, ()).payload_size, fmt,
                                tuple(cols.split(","))) for tid, name, fmt, cols, _, _ in (*RECORDS, RCOU)}


FORMATS = _formats()


def _pack(name: str, *values: object) -> bytes:
    """One record packed with struct (metadata: a few hundred records)."""
    f = FORMATS[name]
    return bytes([HEAD1, HEAD2, f.type_id]) + struct.pack("<" + "".join(STRUCT[c] for c in f.format), *values)


def f32(v: npt.ArrayLike) -> FloatArray:
    """Values rounded to float32, as PARM records store them."""
    return np.asarray(v, dtype=np.float32).astype(np.float64)


def _us(t: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Boot time in integer microseconds of simulation times (s)."""
    return np.round((np.asarray(t, dtype=np.float64) + BOOT_S) * 1e6).astype(np.int64)


def _records(name: str, n: int) -> np.ndarray:
    """A zeroed structured array of n records of `name`, header bytes filled in."""
    f = FORMATS[name]
    fields = [(c, FORMAT_CHARS[ch][0]) for c, ch in zip(f.columns, f.format, strict=True)]
    dt = np.dtype([("h1", "u1"), ("h2", "u1"), ("id", "u1"), *fields])
    out = np.zeros(n, dtype=dt)
    out["h1"], out["h2"], out["id"] = HEAD1, HEAD2, f.type_id
    return out


def interleave(parts: list[tuple[npt.NDArray[np.int64], np.ndarray]]) -> npt.NDArray[np.uint8]:
    """Records of several types merged in time order (stable: equal times keep the part order)."""
    times = np.concatenate([t for t, _ in parts])
    lens = np.concatenate([np.full(len(r), r.dtype.itemsize, dtype=np.int64) for _, r in parts])
    order = np.argsort(times, kind="stable")
    start = np.empty_like(lens)
    start[order] = np.concatenate([[0], np.cumsum(lens[order])[:-1]])
    out = np.zeros(int(lens.sum()), dtype=np.uint8)
    at = 0
    for _, recs in parts:
        width = recs.dtype.itemsize
        window = as_strided(out, shape=(out.size - width + 1, width), strides=(1, 1), writeable=True)
        window[start[at:at + len(recs)]] = recs.view(np.uint8).reshape(len(recs), width)
        at += len(recs)
    return out


def _metadata(params: dict[str, float], t_us: int, banner: str, rcou: bool = False,
              messages: tuple[str, ...] = (), version: tuple[int, int, int] = (4, 6, 2)) -> bytes:
    """FMT for every type (RCOU only with `rcou`), UNIT, MULT, FMTU, the PARM dump, VER (firmware 4.0 on, as
    ArduPilot logs it), MSG and `messages`."""
    records = [*RECORDS, RCOU] if rcou else RECORDS
    fmt_code = "<BB4s16s64s"
    out = [bytes([HEAD1, HEAD2, FMT_ID]) + struct.pack(fmt_code, FMT_ID, FMT_LENGTH, b"FMT", b"BBnNZ",
                                                          b"Type,Length,Name,Format,Columns")]
    out += [bytes([HEAD1, HEAD2, FMT_ID]) + struct.pack(fmt_code, f.type_id, f.length, f.name.encode(),
                                                           f.format.encode(), ",".join(f.columns).encode())
            for f in FORMATS.values() if rcou or f.name != "RCOU"]
    out += [_pack("UNIT", t_us, ord(k), v.encode()) for k, v in UNITS.items()]
    out += [_pack("MULT", t_us, ord(k), v) for k, v in MULTS.items()]
    out += [_pack("FMTU", t_us, tid, u.encode(), m.encode()) for tid, _, _, _, u, m in records]
    out += [_pack("PARM", t_us, k.encode(), v, v) for k, v in params.items()]
    out += [_pack("VER", t_us, 3, 0, *version, 255, 0, banner.encode())] if version >= (4, 0, 0) else []
    out += [_pack("MSG", t_us, banner.encode())]
    out += [_pack("MSG", t_us, m.encode()) for m in messages]
    return b"".join(out)


def compass_params(prev: PreviousCalibration, ofs: FloatArray,
                   more_ofs: tuple[FloatArray, ...] = ()) -> dict[str, float]:
    """The PARM dump: compass 1 calibration, the globals the reader and exporters look at, and compasses 2, 3
    (their offsets `more_ofs`)."""
    p = {f"COMPASS_OFS_{a}": float(v) for a, v in zip("XYZ", ofs, strict=True)}
    p |= {f"COMPASS_DIA_{a}": v for a, v in zip("XYZ", prev.dia, strict=True)}
    p |= {f"COMPASS_ODI_{a}": v for a, v in zip("XYZ", prev.odi, strict=True)}
    p |= {f"COMPASS_MOT_{a}": v for a, v in zip("XYZ", prev.mot, strict=True)}
    p |= {"COMPASS_SCALE": prev.scale, "COMPASS_MOTCT": float(prev.motct), "COMPASS_ORIENT": 0.0,
          "COMPASS_EXTERNAL": 1.0, "COMPASS_USE": 1.0, "COMPASS_DEV_ID": 97539.0, "COMPASS_PRIO1_ID": 97539.0,
          "COMPASS_LEARN": 0.0, "COMPASS_AUTODEC": 1.0, "AHRS_ORIENTATION": 0.0, "INS_GYRO_RATE": 0.0}
    # what a 4.6 vehicle with a GPS/compass module logs besides: custom rotations (4.3+), the EKF in use and
    # the level trim the attitude estimate includes
    p |= {"CUST_ROT_ENABLE": 0.0, "AHRS_EKF_TYPE": 3.0} | {f"AHRS_TRIM_{a}": 0.0 for a in "XYZ"}
    p |= {f"CUST_ROT{n}_{ax}": 0.0 for n in (1, 2) for ax in ("ROLL", "PITCH", "YAW")}
    for k, ofs_k in enumerate(more_ofs, start=1):
        cp, n = prev.compass(k), str(k + 1)
        for stem, vec in (("OFS", ofs_k), ("DIA", cp.dia), ("ODI", cp.odi), ("MOT", cp.mot)):
            p |= {f"COMPASS_{stem}{n}_{a}": float(v) for a, v in zip("XYZ", vec, strict=True)}
        p |= {f"COMPASS_SCALE{n}": cp.scale, f"COMPASS_ORIENT{n}": 0.0, f"COMPASS_EXTERN{n}": 0.0,
              f"COMPASS_USE{n}": 1.0, f"COMPASS_DEV_ID{n}": float(DEV_IDS[k]),
              f"COMPASS_PRIO{n}_ID": float(DEV_IDS[k])}
    return p | prev.extra_params


def default_offsets(sim: Simulation, k: int = 0) -> FloatArray:
    """COMPASS_OFS (k = 0) or OFS{k+1} of an earlier calibration: the negated true hard iron of magnetometer k
    (mGauss) missed by a few mGauss."""
    out: FloatArray = np.round(-sim.truths[k].o * 1e7 + np.array(OFFSET_MISS[k]), 2)
    return out


def build(sim: Simulation, prev: PreviousCalibration | None = None) -> npt.NDArray[np.uint8]:
    """The bytes of a `.bin` log of the simulation flown with `prev` (default: `sim.previous`, else an earlier
    calibration without motor compensation)."""
    prev = prev or sim.previous or PreviousCalibration()
    rec = sim.recording
    acc, gyr, mags = rec.select(Kind.ACCELEROMETER), rec.select(Kind.GYROSCOPE), rec.of_kind(Kind.MAGNETOMETER)
    if len(mags) > MAX_COMPASSES:
        msg = (f"an ArduPilot log holds at most {MAX_COMPASSES} calibrated compasses, the simulation has "
               f"{len(mags)} magnetometers; simulate with n_mags <= {MAX_COMPASSES} or write another format")
        raise MagcalError(msg)
    ofs0 = f32(prev.ofs if prev.ofs is not None else default_offsets(sim))

    imu = _records("IMU", len(acc))
    imu["TimeUS"] = _us(acc.t)
    for i, a in enumerate("XYZ"):
        imu[f"Gyr{a}"], imu[f"Acc{a}"] = gyr.values[:, i], acc.values[:, i]
    imu["T"] = _series(rec, Kind.TEMPERATURE, acc.t, 38.0 + 4.0 * (1.0 - np.exp(-acc.t / 600.0)))
    imu["GH"], imu["AH"], imu["GHz"], imu["AHz"] = 1, 1, round(acc.rate_hz), round(acc.rate_hz)

    t10 = np.arange(0.0, float(acc.t[-1]), 0.1)
    swing = 0.5 * (1.0 - np.cos(2.0 * np.pi * t10 / 20.0))
    t_bat, t_thr = _times(rec, Kind.BATTERY_CURRENT, t10), _times(rec, Kind.THROTTLE, t10)
    current = _series(rec, Kind.BATTERY_CURRENT, t_bat, 0.8 + prev.current_swing_a * swing)
    throttle = _series(rec, Kind.THROTTLE, t_thr, 0.2 + 0.5 * swing if prev.motct == 1 else np.zeros_like(t10))
    motor = (t_thr, throttle) if prev.motct == 1 else (t_bat, current) if prev.motct == 2 else None

    parts = [(imu["TimeUS"], imu)]
    more_ofs = []
    for k, mag in enumerate(mags):
        cp = prev.compass(k)
        ofs_k = ofs0 if k == 0 else f32(cp.ofs if cp.ofs is not None else default_offsets(sim, k))
        ofs = np.tile(ofs_k, (len(mag), 1))
        if k == 0 and prev.change_at_s is not None and prev.ofs_after is not None:
            ofs[mag.t >= prev.change_at_s] = f32(prev.ofs_after)
        more_ofs += [ofs_k] if k else []
        m = _mag_records(mag, k, cp, ofs, motor, prev.motor_after_matrix)
        parts.append((m["TimeUS"], m))
    parts += _slow_records(sim, t10, (t_bat, current), (t_thr, throttle))
    if prev.change_at_s is not None and prev.ofs_after is not None:
        change = _records("PARM", 3)
        change["TimeUS"] = _us(prev.change_at_s)
        change["Name"] = [f"COMPASS_OFS_{a}".encode() for a in "XYZ"]
        change["Value"] = change["Default"] = f32(prev.ofs_after)
        parts.append((change["TimeUS"], change))
    name = "ArduCopter" if prev.firmware >= (3, 6, 0) else "APM:Copter"        # renamed with 3.6
    banner = f"{name} V{'.'.join(map(str, prev.firmware))} (magcal simulate {sim.scenario} seed={sim.seed})"
    params = compass_params(prev, ofs0, tuple(more_ofs))
    motors = rec.of_kind(Kind.MOTOR_OUTPUT)
    if motors:
        parts.append(_rcou(motors))
        params |= {"MOT_PWM_MIN": PWM_RANGE[0], "MOT_PWM_MAX": PWM_RANGE[1]}
        params |= {f"SERVO{k}_FUNCTION": 32.0 + k for k in range(1, len(motors) + 1)}     # 33 = motor 1 [S7]
        params |= {"COMPASS_PMOT_EN": 0.0, "COMPASS_PMOT_EXP": 0.65}         # a 4.6 vehicle has them, off
    meta = _metadata(params, int(_us(0.0)) - 50_000, banner, rcou=bool(motors), messages=prev.messages,
                     version=prev.firmware)
    head = np.frombuffer(meta, dtype=np.uint8)
    return np.concatenate([head, interleave(parts)])


def _rcou(motors: list[Stream]) -> tuple[npt.NDArray[np.int64], np.ndarray]:
    """RCOU records at the first motor's stamps: each motor's output 0..1 as PWM over PWM_RANGE (channels 1-4)."""
    t = motors[0].t
    out = _records("RCOU", len(t))
    out["TimeUS"] = _us(t) + 600
    for k, m in enumerate(motors[:4], start=1):
        u = np.interp(t, m.t, m.values[:, 0])
        out[f"C{k}"] = np.round(PWM_RANGE[0] + np.clip(u, 0.0, 1.0) * (PWM_RANGE[1] - PWM_RANGE[0]))
    return out["TimeUS"], out


def _mag_records(mag: Stream, k: int, cp: CompassParams, ofs: FloatArray,
                 motor: tuple[FloatArray, FloatArray] | None, motor_after_matrix: bool = True) -> np.ndarray:
    """MAG records of instance k: the raw field (tesla) corrected with the offsets `ofs` (N, 3) mG and `cp`, plus
    MOT times the motor signal (t, throttle or current) at the readings' stamps (after the iron matrix, or before
    it as firmware 3.5 and older did), as AP_Compass logs it."""
    n = len(mag)
    signal = np.zeros(n) if motor is None else np.interp(mag.t, *motor)
    corr = Correction(ofs, iron_matrix(np.tile(f32(cp.dia), (n, 1)), np.tile(f32(cp.odi), (n, 1))),
                      effective_scale(np.full(n, f32(cp.scale))), signal[:, None] * f32(cp.mot), motor_after_matrix)
    logged = apply_correction(mag.values * 1e7, corr)
    m = _records("MAG", n)
    m["I"] = k
    m["S"] = _us(mag.t) % (1 << 32)                     # uint32 us: wraps after 71.6 min, as in firmware
    m["TimeUS"] = _us(mag.t) + 150 + INSTANCE_STAGGER_US * k     # logged a little after the sample was taken
    for i, a in enumerate("XYZ"):                       # int16 casts truncate toward zero, as (int16_t) does
        m[f"Mag{a}"] = np.trunc(np.clip(logged[:, i], -32768, 32767))
        m[f"Ofs{a}"] = np.trunc(ofs[:, i])
        m[f"MO{a}"] = np.trunc(corr.motor[:, i])
    m["Health"] = 1
    return m


def _series(rec: Recording, kind: Kind, t: FloatArray, default: FloatArray) -> FloatArray:
    """The simulation's own stream of `kind` at t when it has one, else the default profile."""
    found = rec.of_kind(kind)
    if not found:
        return np.asarray(default, dtype=np.float64)
    out: FloatArray = np.interp(t, found[0].t, found[0].values[:, 0])      # held at its ends
    return out


def _times(rec: Recording, kind: Kind, default: FloatArray) -> FloatArray:
    """The times of the simulation's stream of `kind`, else `default`."""
    found = rec.of_kind(kind)
    return found[0].t if found and len(found[0]) > 1 else default


def _slow_records(sim: Simulation, t10: FloatArray, current: tuple[FloatArray, FloatArray],
                  throttle: tuple[FloatArray, FloatArray]) -> list[tuple[npt.NDArray[np.int64], np.ndarray]]:
    """ATT at 10 Hz; BAT and CTUN at the times of the simulation's current and throttle (else 10 Hz); GPS at the
    simulated position's times, else at 5 Hz at a fixed position (the base scenarios do not travel)."""
    rec = sim.recording
    acc_t = rec.select(Kind.ACCELEROMETER).t
    idx = np.clip(np.searchsorted(acc_t, t10), 0, len(sim.rotations) - 1)
    rpy = np.rad2deg(so3.as_rpy(sim.rotations[idx]))        # gimbal-locked poses: all the turn in yaw
    att = _records("ATT", len(t10))
    att["TimeUS"] = _us(t10) + 300
    att["Roll"] = att["DesRoll"] = rpy[:, 0]
    att["Pitch"] = att["DesPitch"] = rpy[:, 1]
    att["Yaw"] = att["DesYaw"] = np.mod(rpy[:, 2], 360.0)
    att["AEKF"] = 3
    t_bat, amps = current
    bat = _records("BAT", len(t_bat))
    bat["TimeUS"] = _us(t_bat) + 500
    bat["Volt"] = bat["VoltR"] = _series(rec, Kind.BATTERY_VOLTAGE, t_bat, 16.4 - 0.0002 * t_bat)
    bat["Curr"] = amps
    bat["CurrTot"] = np.concatenate([[0.0], np.cumsum(0.5 * (amps[1:] + amps[:-1]) * np.diff(t_bat))]) / 3.6
    bat["RemPct"], bat["H"] = 99, 1
    t_thr, thr = throttle
    ctun = _records("CTUN", len(t_thr))
    ctun["TimeUS"] = _us(t_thr) + 700
    ctun["ThO"] = ctun["ThI"] = thr
    return [(att["TimeUS"], att), (bat["TimeUS"], bat), (ctun["TimeUS"], ctun), _gps(rec, t10[::2])]


def _gps(rec: Recording, t5: FloatArray) -> tuple[npt.NDArray[np.int64], np.ndarray]:
    """GPS records: the simulated position (Lat/Lng 1e-7 deg, Alt cm, Spd, GCrs, VZ down), else a fixed fix."""
    pos = rec.of_kind(Kind.POSITION)
    t = pos[0].t if pos else t5
    gps = _records("GPS", len(t))
    gps["TimeUS"] = _us(t) + 900
    gps["Status"], gps["NSats"], gps["HDop"] = 3, 14, 70
    gps_s = rec.t0 + t - GPS_EPOCH_UNIX + GPS_LEAP_S             # the simulation's own date (T0_ROS), GPS time
    gps["GWk"] = np.floor(gps_s / GPS_WEEK_S)
    gps["GMS"] = np.round((gps_s % GPS_WEEK_S) * 1000.0)
    if not pos:
        gps["Lat"], gps["Lng"], gps["Alt"] = 473_977_420, 85_455_940, 48_800        # 1e-7 deg, 1e-7 deg, cm
        return gps["TimeUS"], gps
    lla = pos[0].values
    gps["Lat"], gps["Lng"] = np.round(lla[:, 0] * 1e7), np.round(lla[:, 1] * 1e7)
    gps["Alt"] = np.round(lla[:, 2] * 100.0)
    if len(t) > 1:
        vel = np.gradient(local(lla), t, axis=0)
        gps["Spd"] = np.linalg.norm(vel[:, :2], axis=1)
        gps["GCrs"] = np.mod(np.rad2deg(np.arctan2(vel[:, 1], vel[:, 0])), 360.0)
        gps["VZ"] = vel[:, 2]
    return gps["TimeUS"], gps


def write_bin(sim: Simulation, path: Path) -> None:
    """Write the simulation as an ArduPilot `.bin` log (atomically)."""
    data = build(sim)
    with atomic_path(path) as tmp:
        data.tofile(tmp)
