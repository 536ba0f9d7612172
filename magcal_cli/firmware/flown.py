"""The calibration a vehicle flew with, applied to the raw field a reader rebuilt, and the signals it needs.

Sources: the log's own parameters (ArduPilot PARM, PX4 ULog parameters), a parameter file (`--params`, any
style `paramfile` reads) or a magcal document (`--calibration`). The result is the body-frame field the
firmware computed, in the firmware's unit (mGauss for ArduPilot, gauss for PX4, the document's unit).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from magcal_cli import so3, units
from magcal_cli.align import columns, onto
from magcal_cli.calibration.types import Calibration
from magcal_cli.firmware import FirmwareError, ardupilot, px4
from magcal_cli.firmware.effects import carried
from magcal_cli.readers.dataflash.compass import param_suffix
from magcal_cli.streams import FloatArray, Kind, Recording, Stream

BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class Flown:
    """One compass corrected as flown: times (s), raw and corrected field (N, 3) in `unit`, slot, in use."""

    id: str
    unit: str
    t: FloatArray
    raw: FloatArray
    field: FloatArray
    slot: str
    used: bool | None
    firmware: str | None


def firmware_of(params: Mapping[str, float]) -> str | None:
    """"ardupilot" or "px4" from the parameter names, None when neither kind is there."""
    if any(k.startswith("COMPASS_") for k in params):
        return "ardupilot"
    if any(re.match(r"CAL_MAG\d_", k) for k in params):
        return "px4"
    return None


def signal_at(rec: Recording, kind: Kind, t: FloatArray) -> FloatArray | None:
    """The first stream of `kind` (current A, throttle 0..1) at times t, held at the ends; None if absent."""
    streams = [s for s in rec.of_kind(kind) if len(s) >= 2]
    if not streams:
        return None
    s = streams[0]
    return np.interp(t, s.t, s.values[:, 0])


def _ardupilot(rec: Recording, mag: Stream, index: int, params: Mapping[str, float]) -> Flown:
    """A MAG[i] stream corrected with the COMPASS_* parameters of its slot (log instance -> priority)."""
    m = re.fullmatch(r"MAG\[(\d)\]", mag.id)
    suffix, _ = param_suffix(int(m.group(1)) if m else index, dict(params))
    raw = mag.xyz * units.from_si(ardupilot.UNIT)
    motct = int(params.get("COMPASS_MOTCT", 0))
    signal = signal_at(rec, Kind.THROTTLE if motct == 1 else Kind.BATTERY_CURRENT, mag.t) if motct else None
    use = params.get(f"COMPASS_USE{suffix}")
    return Flown(mag.id, ardupilot.UNIT, mag.t, raw, ardupilot.correct(raw, params, suffix, signal),
                 f"COMPASS_*{suffix}", None if use is None else use >= 1, "ardupilot")


def _px4(rec: Recording, mag: Stream, index: int, params: Mapping[str, float]) -> Flown:
    """A sensor_mag[i] stream corrected with the CAL_MAGn_* slot whose ID is its device id.

    Other streams (sensor_combined, vehicle_magnetometer, legacy px4log IMU.Mag) hold the field the firmware
    already corrected (docs/readers-px4.md, readers-ardupilot.md): they are taken as flown.
    """
    raw = mag.xyz * units.from_si(px4.UNIT)
    if rec.format == "px4log" or not re.fullmatch(r"sensor_mag\[\d\]", mag.id):
        return Flown(mag.id, px4.UNIT, mag.t, raw, raw, "the firmware's correction", None, None)
    n, dev, _ = px4.slot_of(mag.id, index, params, None)
    typ = int(params.get("CAL_MAG_COMP_TYP", 0))
    signal = signal_at(rec, Kind.THROTTLE if typ == 1 else Kind.BATTERY_CURRENT, mag.t) if typ else None
    prio = params.get(f"CAL_MAG{n}_PRIO")
    return Flown(mag.id, px4.UNIT, mag.t, raw, px4.correct(raw, params, n, signal), f"CAL_MAG{n}_*",
                 None if prio is None else prio > 0, "px4")


def _document(rec: Recording, mag: Stream, cal: Calibration) -> Flown:
    """A stream corrected with a magcal document: F A (y - o - c s) in the document's unit."""
    doc = cal.magnetometer(mag.id)
    raw = mag.xyz * units.from_si(doc.unit)
    y = raw
    inter, _ = carried(cal, doc)
    if inter is not None:
        s = signal_at(rec, Kind.BATTERY_CURRENT if inter.kind == "current" else Kind.THROTTLE, mag.t)
        if s is not None:
            y = raw - (np.abs(s) ** inter.exponent if inter.kind == "throttle" else s)[:, None] * inter.c
    field = doc.field_strength * doc.apply(y)
    return Flown(mag.id, doc.unit, mag.t, raw, field, "document", None, None)


def flown_fields(rec: Recording, mag_ids: list[str] | None, params: Mapping[str, float] | None,
                 cal: Calibration | None) -> tuple[list[Flown], str]:
    """Every selected compass corrected as flown, and a description of where the calibration came from."""
    mags = rec.of_kind(Kind.MAGNETOMETER)
    if mag_ids:
        mags = [rec.select(Kind.MAGNETOMETER, m, "--mag") for m in mag_ids]
    if cal is not None:
        return [_document(rec, m, cal) for m in mags if m.id in {d.id for d in cal.magnetometers}], \
            f"the calibration document {cal.source.path}"
    source = "the parameter file" if params is not None else f"the log's parameters ({rec.format})"
    params = dict(rec.params) if params is None else dict(params)
    firmware = firmware_of(params)
    if firmware == "ardupilot":
        return [_ardupilot(rec, m, i, params) for i, m in enumerate(mags)], source
    if firmware == "px4":
        return [_px4(rec, m, i, params) for i, m in enumerate(mags)], source
    msg = (f"{rec.path.name}: no compass calibration known ({source} hold no COMPASS_* or CAL_MAGn_* parameters). "
           "Pass --params with the vehicle's parameter file or --calibration with the calibration it used")
    raise FirmwareError(msg)


def levelling(rec: Recording, t: FloatArray) -> tuple[BoolArray, FloatArray, str]:
    """(usable mask, Ry(pitch) Rx(roll) at the usable times, source): from an attitude stream, else gravity.

    The log's yaw is never used: a compass error steers it.
    """
    att = [s for s in rec.of_kind(Kind.ATTITUDE) if len(s) >= 2]
    if att:
        mask, q = onto(att[0], t, max_gap_s=1.0)
        rpy = so3.as_rpy(so3.from_quat(q))       # at pitch +-90 deg roll and yaw merge; yaw is dropped anyway
        rpy[:, 2] = 0.0
        return mask, so3.from_rpy(rpy), f"roll and pitch of {att[0].id}"
    acc = [s for s in rec.of_kind(Kind.ACCELEROMETER) if len(s) >= 2]
    if not acc:
        msg = (f"{rec.path.name}: no attitude and no accelerometer stream, so the field cannot be levelled. "
               "Log the attitude (ATT / vehicle_attitude) or the IMU")
        raise FirmwareError(msg)
    a = acc[0]
    win = max(1, int(round(0.2 * a.rate_hz)))               # 0.2 s mean: vibration out, manoeuvres stay
    kernel = np.ones(win) / win
    smooth = np.stack([np.convolve(a.values[:, i], kernel, mode="same") for i in range(3)], axis=1)
    mask = (t >= a.t[0]) & (t <= a.t[-1])
    f = columns(t[mask], a.t, smooth)
    roll = np.arctan2(-f[:, 1], -f[:, 2])
    pitch = np.arctan2(f[:, 0], np.hypot(f[:, 1], f[:, 2]))
    rpy = np.stack([roll, pitch, np.zeros_like(roll)], axis=1)
    return mask, so3.from_rpy(rpy), f"gravity from {a.id} (no attitude stream; accelerations tilt it)"


def slow(rec: Recording, t: FloatArray, max_rate_dps: float) -> BoolArray:
    """True where the first gyroscope turns slower than `max_rate_dps` (all True without a gyroscope).

    In fast turns a few tens of milliseconds between the compass and the attitude tilt the levelled field.
    """
    gyr = [s for s in rec.of_kind(Kind.GYROSCOPE) if len(s) >= 2]
    if not gyr:
        return np.ones(t.size, dtype=bool)
    g = gyr[0]
    rate = np.linalg.norm(columns(t, g.t, g.values), axis=1)
    out: BoolArray = np.rad2deg(rate) <= max_rate_dps
    return out


def headings(v: FloatArray, lev: FloatArray) -> FloatArray:
    """Heading (rad) of body-frame field vectors after levelling: atan2(-g_y, g_x)."""
    g = np.einsum("nij,nj->ni", lev, v)
    out: FloatArray = np.arctan2(-g[:, 1], g[:, 0])
    return out


def heading_gap_deg(headings: FloatArray, bin_deg: float = 10.0, min_count: int = 3) -> float:
    """The widest run of heading bins (deg) with fewer than `min_count` samples, around the circle."""
    bins = int(round(360.0 / bin_deg))
    counts = np.bincount((np.mod(np.rad2deg(headings), 360.0) // bin_deg).astype(int) % bins, minlength=bins)
    empty = np.concatenate([counts, counts]) < min_count
    run = best = 0
    for e in empty:
        run = run + 1 if e else 0
        best = max(best, run)
    return float(min(best, bins) * bin_deg)


def load_params(path: Path) -> dict[str, float]:
    """A parameter file, or the parameters of a log (any format the readers open)."""
    from magcal_cli.firmware import paramfile

    if path.suffix.lower() in (".param", ".parm", ".params", ".txt", ".sh"):
        return paramfile.load(path)
    from magcal_cli.readers import open_recording

    params = dict(open_recording(path).params)
    if not params:
        msg = f"{path}: the log holds no parameters. Pass the vehicle's parameter file instead"
        raise FirmwareError(msg)
    return params
