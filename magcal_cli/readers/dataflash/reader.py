"""DataFlash reader: ArduPilot binary `.bin` and text `.log`, and legacy PX4 sdlog2 `.px4log`.

ArduPilot logs the corrected magnetometer field; the MAGNETOMETER streams carry the raw reading rebuilt by
undoing the parameters in force at each sample (`dataflash_mag`). Everything stays in the body frame the
firmware logs (COMPASS_ORIENTn / AHRS_ORIENTATION already applied). See docs/readers-ardupilot.md.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from magcal_cli.errors import LogReadError, MagcalError, StreamError, UnsupportedFormatError
from magcal_cli.progress import active, current, within
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.cut import mark_cut, refuse_if_strict
from magcal_cli.readers.dataflash.binary import parse_binary
from magcal_cli.readers.dataflash.compass import (
    ROUNDED_EVIDENCE,
    Correction,
    ParamHistory,
    compass_correction,
    motor_cast_evidence,
    motor_product,
    offset_cast_evidence,
    offsets_in_force,
    param_suffix,
    truncation_evidence,
    undo_correction,
)
from magcal_cli.readers.dataflash.format import MessageFormat, RawLog, Table
from magcal_cli.readers.dataflash.streams import (
    Clock,
    Pending,
    clock_from,
    euler_quat,
    finish,
    instances,
    time_of,
)
from magcal_cli.readers.dataflash.text import looks_like_text, parse_text
from magcal_cli.streams import Cut, FloatArray, Kind, Recording
from magcal_cli.units import GPS_EPOCH_UNIX, GPS_LEAP_S, GPS_WEEK_S

MAG_NAMES = ("MAG", "MAG2", "MAG3")
IMU_NAMES = ("IMU", "IMU2", "IMU3")
#: the record types magcal uses (the parsers decode only these, plus units)
WANTED = frozenset({*MAG_NAMES, *IMU_NAMES, "PARM", "MSG", "VER", "ATT", "AHR2", "BAT", "BAT2", "CURR",
                    "CTUN", "RCOU", "GPS", "GPS2", "TIME", "IMU1", "BATT", "ATTC"})
MG_TO_T = 1e-7
#: above this share of unreadable bytes a log is an error with --strict, or when what is left is unusable
MOSTLY_CORRUPT = 0.5
#: the share of a read that parsing takes, by text log or not; building the streams takes the rest (measured:
#: 0.26-0.47 on binary logs of 3-55 MB, where rebuilding the raw field and checking the streams is vectorised
#: but touches every sample, 0.93 on a 2.7 MB text log, whose parse splits every line in Python)
PARSE_SHARE = {False: 0.3, True: 0.9}
#: where each step of build_ardupilot ends in its share of the read: IMU streams, raw field, the other streams
#: (then finish() checks every stream); measured on a 55 MB simulated .bin
BUILD_STEPS = (0.15, 0.45, 0.55)
Series = tuple[FloatArray, FloatArray]


def load(path: Path) -> RawLog:
    """Parse a binary or text DataFlash file, translating parser failures into one-line LogReadErrors."""
    try:
        with path.open("rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
        raise LogReadError(msg) from None
    hook = current()
    try:
        if b"\xa3\x95" in head[:512]:
            with active(within(hook, 0.0, PARSE_SHARE[False])):
                raw = parse_binary(path, WANTED)
        elif looks_like_text(head):
            with active(within(hook, 0.0, PARSE_SHARE[True])):
                raw = parse_text(path, WANTED)
        else:
            msg = (f"{path}: not a DataFlash log (no A3 95 record header and no FMT text lines at the "
                   "start). Check the file, or pass --format for another log type")
            raise UnsupportedFormatError(msg)
    except MagcalError:
        raise
    except (ValueError, IndexError, KeyError, TypeError, OverflowError) as exc:
        msg = (f"{path}: the DataFlash log is corrupt ({type(exc).__name__}: {exc}). "
               "Re-copy the log from the vehicle")
        raise LogReadError(msg) from None
    if not any(v for k, v in raw.counts.items() if k != "FMT"):
        msg = (f"{path}: the DataFlash log holds no data records (only {raw.counts.get('FMT', 0)} FMT). "
               "Re-copy the log")
        raise LogReadError(msg)
    return raw


def is_px4log(raw: RawLog) -> bool:
    """Legacy PX4 sdlog2 logs carry TIME.StartTime and the field inside IMU (MagX..); ArduPilot never does."""
    imu = raw.formats.get("IMU")
    time = raw.formats.get("TIME")
    return (time is not None and time.has("StartTime")) or (imu is not None and imu.has("MagX"))


class DataflashReader:
    """Reads ArduPilot DataFlash (`.bin`, text `.log`) and PX4 `.px4log` logs into SI streams."""

    name: ClassVar[str] = "dataflash"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Every stream magcal uses; a cut log up to its last complete message (--strict refuses it). The
        fraction read is reported as the "reading" stage of `progress.current()`: bytes parsed, then streams."""
        hook = current()
        raw = load(path)
        mostly_corrupt = raw.skipped_bytes > MOSTLY_CORRUPT * raw.size
        if mostly_corrupt and not options.allow_truncated:
            raise LogReadError(_mostly_corrupt(path, raw, "Re-copy the log, or leave out --strict to use them"))
        cut = Cut(raw.size - raw.truncated_bytes, raw.size, raw.cut_lost) if raw.truncated_bytes else None
        refuse_if_strict(path, options, cut)
        try:
            with active(within(hook, PARSE_SHARE[raw.text], 1.0)):
                if is_px4log(raw):
                    from magcal_cli.readers.dataflash.px4log import build_px4log

                    return mark_cut(build_px4log(path, raw), cut)
                return mark_cut(build_ardupilot(path, raw), cut)
        except StreamError:
            if mostly_corrupt:          # what is missing was lost to the damage: say that, not "never logged"
                why = "They are not enough to calibrate; re-copy the log from the vehicle"
                raise LogReadError(_mostly_corrupt(path, raw, why)) from None
            raise


def _mostly_corrupt(path: Path, raw: RawLog, then: str) -> str:
    """The message for a log more than half unreadable; `then` ends it."""
    kept = sum(v for k, v in raw.counts.items() if k != "FMT")
    return (f"{path}: {raw.skipped_bytes} of {raw.size} bytes are not complete records (the log is mostly "
            f"corrupt, or its FMT records are damaged); {kept} messages could be read. {then}")


def firmware_version(raw: RawLog) -> tuple[int, int] | None:
    """(major, minor) from the VER record or a MSG banner such as 'APM:Copter V3.3-dev'."""
    ver = raw.table("VER")
    if ver is not None and ver.fmt.has("Maj", "Min"):
        return int(ver.num("Maj")[0]), int(ver.num("Min")[0])
    msgs = raw.table("MSG")
    for text in msgs.text("Message") if msgs is not None and msgs.fmt.has("Message") else []:
        m = re.search(r"\bV(\d+)\.(\d+)", text)
        if m:
            return int(m.group(1)), int(m.group(2))
    return None


def param_history(raw: RawLog, clock: Clock) -> ParamHistory:
    """Every PARM record with its time (its own TimeUS, else that of the message before it)."""
    parm = raw.table("PARM")
    if parm is None or not parm.fmt.has("Name", "Value"):
        return ParamHistory([], np.zeros(0), np.zeros(0))
    t = time_of(parm, clock)
    return ParamHistory(parm.text("Name"), np.nan_to_num(t, nan=-np.inf), parm.num("Value"))


def _inst(fmt: MessageFormat, inst: int) -> str:
    """`[I=n]` for instanced record types (4.x), else nothing."""
    return f"[I={inst}]" if fmt.has("I") else ""


def _cols(table: Table, names: tuple[str, ...], factor: float = 1.0) -> FloatArray:
    """(N, len(names)) float columns times a factor."""
    return np.stack([table.num(c) * factor for c in names], axis=1)


def _int_factor(table: Table, column: str, integer_default: float) -> float:
    """Factor to the base unit: an FMTU multiplier for integer fields, else the firmware convention."""
    char = table.fmt.char(column)
    if char in "bBhHiIqQ":
        return table.fmt.mults.get(column, integer_default)
    return 1.0


def _raw_resolution(corr: Correction, count: float) -> FloatArray | None:
    """Quantisation std per raw axis (mG): one count's uniform error (count/sqrt 12) through the undone matrix."""
    if not len(corr.scale):
        return None
    i = len(corr.scale) // 2
    inv = np.linalg.inv(corr.matrix[i]) / corr.scale[i]
    out: FloatArray = count / np.sqrt(12.0) * np.sqrt(np.sum(inv**2, axis=1))
    return out


def _mag_factor(table: Table) -> float:
    """Logged field to milligauss: FMTU says Gauss times 1e-3; old logs mean mGauss by convention."""
    unit, mult = table.fmt.units.get("MagX", ""), table.fmt.mults.get("MagX")
    if unit in ("G", "Gauss") and mult:
        return mult * 1000.0
    return 1.0


def _interp(t: FloatArray, series: Series | None) -> FloatArray | None:
    """A (t, v) series linearly interpolated at t (held at the ends), or None."""
    if series is None or series[0].size == 0:
        return None
    order = np.argsort(series[0], kind="stable")
    return np.interp(t, series[0][order], series[1][order])


def _sample_time(time_us: FloatArray, s_us: FloatArray) -> FloatArray:
    """Seconds of MAG.S, unwrapped against TimeUS; TimeUS where S is unset or more than 1 s older."""
    delay = np.mod(time_us - s_us, 2.0**32)
    return np.where((s_us > 0) & (delay < 1e6), time_us - delay, time_us) * 1e-6


@dataclass(frozen=True, eq=False)
class MagReconstruction:
    """One compass: times (s, boot clock), logged and reconstructed raw field (N, 3) mG, the correction."""

    instance: int
    source: str
    t: FloatArray
    logged: FloatArray
    raw: FloatArray
    correction: Correction
    notes: tuple[str, ...]
    resolution: FloatArray | None = None      # per-axis quantisation std of `raw` (mG), integer fields only


def _reconstruct(path: Path, raw: RawLog, clock: Clock, hist: ParamHistory,
                 throttle: Series | None, current: Series | None) -> list[MagReconstruction]:
    """Every logged compass with the firmware correction in force at each sample undone."""
    version = firmware_version(raw)
    after = version is None or version >= (3, 6)
    params = hist.last()
    out: list[MagReconstruction] = []
    bad_instances: list[str] = []
    found = [(i, tb) for i, tb in instances(raw, MAG_NAMES, notes=bad_instances, limit=3)
             if tb.fmt.has("MagX", "MagY", "MagZ")]
    compasses = [_compass(inst, table, clock) for inst, table in found]
    truncated, cast = _int16_cast(compasses, hist, throttle, current)
    for c in compasses:
        inst, table, t, notes = c.inst, c.table, c.t, list(c.notes)
        f, k, logged = table.fmt, c.factor, c.logged
        field = logged
        if c.integer and truncated:
            # AP_Compass logs (int16_t)field: the cast truncates toward zero, so the field was on average half
            # a count further out; left in, it shrinks D by ~0.5 count / |field| (0.2 % at 270 mG)
            field = logged + 0.5 * k * np.sign(logged)
            notes.append(f"MAG[{inst}]: added back half a count ({0.5 * k:g} mG) lost to the firmware's int16 "
                         "truncation toward zero")
        elif c.integer:
            notes.append(f"MAG[{inst}]: the logged integers were rounded, not truncated as AP_Compass's cast does "
                         f"({cast}); no half count added back")
        suffix, slot_note = param_suffix(inst, params)
        corr, desc = compass_correction(hist, suffix, t, c.ofs, c.motor, after, _interp(t, throttle),
                                        _interp(t, current))
        ext = {"": "COMPASS_EXTERNAL", "2": "COMPASS_EXTERN2", "3": "COMPASS_EXTERN3"}[suffix]
        frame = (f"COMPASS_ORIENT{suffix}={params.get(f'COMPASS_ORIENT{suffix}', 0):.0f}" if params.get(ext)
                 else f"AHRS_ORIENTATION={params.get('AHRS_ORIENTATION', 0):.0f}")
        notes += [slot_note] if slot_note else []
        notes.append(f"MAG[{inst}]: undid the firmware correction of the logged field ({desc}); the raw "
                     f"field stays in the body frame ({frame} already applied by the firmware)")
        if not after and np.any(corr.motor != 0):
            notes.append(f"MAG[{inst}]: motor offsets undone before the iron matrix, where firmware "
                         f"{version[0]}.{version[1]} added them" if version else "")
        if version is None and np.any(corr.motor != 0):
            notes.append(f"MAG[{inst}]: firmware version unknown; motor offsets taken as added after the "
                         "iron matrix")
        src = f"{path.name}#{f.name}{_inst(f, inst)}.MagX/MagY/MagZ (raw, reconstructed)"
        out.append(MagReconstruction(inst, src, t, logged, undo_correction(field, corr), corr,
                                     tuple(bad_instances * (not out) + notes),
                                     _raw_resolution(corr, k) if c.integer else None))
    return out


@dataclass(frozen=True, eq=False)
class _Compass:
    """One compass's healthy MAG records before the correction is undone: times (s), field and motor offsets (mG)."""

    inst: int
    table: Table
    t: FloatArray
    factor: float
    logged: FloatArray
    motor: FloatArray | None
    integer: bool
    notes: tuple[str, ...]
    ofs: FloatArray | None = None


def _compass(inst: int, table: Table, clock: Clock) -> _Compass:
    """The healthy records of one compass (all of them, with a note, when the firmware marked none healthy)."""
    f = table.fmt
    notes: list[str] = []
    t = time_of(table, clock)
    if f.has("S", "TimeUS"):          # 4.x: S (uint32 us, wraps) is when the sample was taken
        t = _sample_time(table.num("TimeUS"), table.num("S"))
    keep = table.num("Health") != 0 if f.has("Health") else np.ones(len(table), dtype=bool)
    if not keep.any():          # a compass that never worked (e.g. all fields zero): the dead-sensor check
        notes.append(f"MAG[{inst}]: the firmware marked all {len(keep)} samples unhealthy")   # judges it
        keep[:] = True
    elif not keep.all():
        notes.append(f"MAG[{inst}]: dropped {int((~keep).sum())} samples the firmware marked unhealthy")
    table, t = table.where(keep), t[keep]
    k = _mag_factor(table)
    mo_cols = next((c for c in (("MOfsX", "MOfsY", "MOfsZ"), ("MOX", "MOY", "MOZ")) if f.has(*c)), None)
    return _Compass(inst, table, t, k, _cols(table, ("MagX", "MagY", "MagZ"), k),
                    _cols(table, mo_cols, k) if mo_cols else None, f.char("MagX") in "bBhHiIqQ", tuple(notes),
                    _cols(table, ("OfsX", "OfsY", "OfsZ"), k) if f.has("OfsX", "OfsY", "OfsZ") else None)


def _int16_cast(compasses: list[_Compass], hist: ParamHistory, throttle: Series | None,
                current: Series | None) -> tuple[bool, str]:
    """Whether the log's integer fields were truncated toward zero (AP_Compass's cast) or rounded, and the evidence:
    the logged motor offsets against the COMPASS_MOT product they were cast from, and the field's zero bin."""
    params = hist.last()
    ints = [c for c in compasses if c.integer]
    zero_bin = truncation_evidence([c.logged / c.factor for c in ints], [c.t for c in ints]) if ints else 0.0
    motor = offset = 0.0
    for c in ints:
        suffix = param_suffix(c.inst, params)[0]
        if c.motor is not None:
            product = motor_product(hist, suffix, c.t, _interp(c.t, throttle), _interp(c.t, current))[0]
            motor += motor_cast_evidence(c.motor / c.factor, product / c.factor)
        in_force = offsets_in_force(hist, suffix, c.t)
        if c.ofs is not None and in_force is not None:
            offset += offset_cast_evidence(c.ofs / c.factor, in_force / c.factor)
    evidence = zero_bin + motor + offset
    decades = -evidence / np.log(10.0)
    ratio = f"1e{decades:.0f}" if decades > 6 else f"{10.0 ** decades:.3g}"
    why = f"likelihood ratio {ratio} from the zero bin" + (", the offsets against COMPASS_OFS" if offset else "") + (
        ", the motor offsets against COMPASS_MOT" if motor else "")
    return evidence > -np.log(ROUNDED_EVIDENCE), why


def reconstruct_mags(path: Path) -> list[MagReconstruction]:
    """The raw field of every compass of an ArduPilot log and what was undone (diagnostics, tests)."""
    raw = load(path)
    clock = clock_from(raw)
    hist = param_history(raw, clock)
    thr, cur = _motor_signals(_throttle(path, raw, clock, hist.last()), _battery(path, raw, clock))
    return _reconstruct(path, raw, clock, hist, thr, cur)


def _motor_signals(throttle: list[Pending], battery: list[Pending]) -> tuple[Series | None, Series | None]:
    """(t, throttle) and (t, current) series for motor compensation, when the log has them."""
    thr = (throttle[0].t, throttle[0].values[:, 0]) if throttle else None
    cur = next(((p.t, p.values[:, 0]) for p in battery if p.kinds[0] is Kind.BATTERY_CURRENT), None)
    return thr, cur


def _imu_streams(path: Path, raw: RawLog, clock: Clock, notes: list[str]) -> list[Pending]:
    """IMU[i]: accelerometer (m/s^2) and gyroscope (rad/s) sharing one id, and the IMU temperature (degC)."""
    out = []
    for inst, table in instances(raw, IMU_NAMES, notes=notes, limit=3):
        f = table.fmt
        if not f.has("GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ"):
            continue
        t = time_of(table, clock)
        src = f"{path.name}#{f.name}{_inst(f, inst)}"
        values = np.concatenate([_cols(table, ("AccX", "AccY", "AccZ")),
                                 _cols(table, ("GyrX", "GyrY", "GyrZ"))], axis=1)
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
                    k = _int_factor(table, col, 0.01)
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
    pwm = _cols(rcou, chans).mean(axis=1)
    thr = np.clip((pwm - lo) / (hi - lo), 0.0, 1.0)
    return [Pending((Kind.THROTTLE,), "RCOU", time_of(rcou, clock), thr[:, None],
                    f"{path.name}#RCOU.{'/'.join(chans)} (mean PWM, MOT_PWM_MIN..MAX)", ("1",))]


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
        pos = np.stack([table.num(c) * _int_factor(table, c, k) for c, k in (("Lat", 1e-7), ("Lng", 1e-7),
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
    hook("reading", BUILD_STEPS[0], 1.0)
    for m in _reconstruct(path, raw, clock, hist, *_motor_signals(throttle, battery)):
        notes += m.notes
        pending.append(Pending((Kind.MAGNETOMETER,), f"MAG[{m.instance}]", m.t, m.raw * MG_TO_T, m.source,
                               ("milligauss",), None if m.resolution is None else m.resolution * MG_TO_T))
    hook("reading", BUILD_STEPS[1], 1.0)
    pending += _attitude(path, raw, clock) + battery + throttle + _gps(path, raw, clock, notes)
    hook("reading", BUILD_STEPS[2], 1.0)
    with active(within(hook, BUILD_STEPS[2], 1.0)):
        rec = finish(path, "dataflash", pending, params, notes)
    boot = _utc_of_boot(raw, clock)
    return rec if boot is None else replace(rec, utc0=boot + rec.t0)
