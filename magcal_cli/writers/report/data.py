"""The numbers the HTML report plots, without matplotlib: field, dip, residuals, heading error, effects."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from magcal_cli import units
from magcal_cli.align import columns
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.effects import EFFECTS, get
from magcal_cli.effects.base import Target
from magcal_cli.effects.correct import MODELLED, remove
from magcal_cli.errors import MagcalError
from magcal_cli.firmware.metrics import FIRMWARE_OF_FORMAT, heading_std_curve_deg
from magcal_cli.firmware.split import HEADINGS_DEG, heading_errors_deg
from magcal_cli.streams import FloatArray, Kind, Recording

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult

Window = tuple[float, float]

#: readings whose specific force is further than this from g do not show the vertical (the vehicle accelerates)
GRAVITY_TOLERANCE = 0.1


@dataclass(frozen=True, eq=False)
class MagView:
    """One magnetometer in plot units: field in units of its strength, dip and residuals in degrees and %."""

    mag_id: str
    t: FloatArray                    # (N,) s
    raw: FloatArray                  # (N, 3) raw readings / field strength
    cal: FloatArray                  # (N, 3) calibrated unit field m_b (NaN where excluded)
    norm_raw_pct: FloatArray         # |y| / mean |y| - 1, in %
    norm_cal_pct: FloatArray         # |m_b| - 1, in %
    dip_raw: FloatArray | None       # angle of the raw field below the accelerometer's horizontal, deg
    dip_cal: FloatArray | None       # the same for m_b
    dip_deg: float                   # the fitted dip
    still: tuple[Window, ...]
    windows: tuple[Window, ...]      # where the diagnosis located a mismatch
    excluded: tuple[Window, ...]     # readings a transient disturbance removed


@dataclass(frozen=True, eq=False)
class HeadingView:
    """Level heading error (deg) against heading: raw compass, 1-sigma of the calibration, firmware residual."""

    headings: FloatArray
    raw: FloatArray
    std: FloatArray | None
    firmware: FloatArray | None
    firmware_name: str | None


@dataclass(frozen=True, eq=False)
class EffectView:
    """One modelled effect: a residual against its channel, with and without the effect removed; `part` names what
    of the effect a view shows when it takes several (an IMU effect's axis)."""

    effect_id: str
    status: str
    xlabel: str
    ylabel: str
    x: FloatArray
    before: FloatArray
    after: FloatArray
    part: str = ""


def thin(n: int, max_points: int = 4000) -> slice:
    """A stride that leaves at most `max_points` of n samples (more cost drawing time, not information)."""
    return slice(None, None, max(1, -(-n // max_points)))


def down_at(rec: Recording, cal: Calibration, t: FloatArray) -> FloatArray | None:
    """Unit vector of gravity (down) in the IMU body frame at times t from the accelerometer, NaN while accelerating."""
    try:
        acc = rec.select(Kind.ACCELEROMETER, cal.imu.id)
    except MagcalError:
        return None
    f = acc.xyz - (cal.imu.accelerometer_bias if cal.imu.accelerometer_bias is not None else 0.0)
    fi = columns(t, acc.t, f, left=np.nan, right=np.nan)   # NaN, not the end value, outside the stream's span
    n = np.linalg.norm(fi, axis=1)
    g = units.to_si("g")
    with np.errstate(invalid="ignore"):
        down: FloatArray = -fi / n[:, None]   # at rest the specific force points up
        down[np.abs(n - g) > GRAVITY_TOLERANCE * g] = np.nan
    return down


def _dip(v: FloatArray, down: FloatArray | None) -> FloatArray | None:
    """Angle (deg) of the vectors v below the horizontal given by `down`."""
    if down is None:
        return None
    with np.errstate(invalid="ignore"):
        s = np.sum(v * down, axis=1) / np.linalg.norm(v, axis=1)
    out: FloatArray = np.rad2deg(np.arcsin(np.clip(s, -1.0, 1.0)))
    return out


def _windows(cal: Calibration, mag_id: str) -> tuple[tuple[Window, ...], tuple[Window, ...]]:
    """(windows the diagnosis located, windows a transient disturbance excluded) for one magnetometer."""
    located: list[Window] = []
    for block in (cal.diagnosis or {}).get("sensors", []):
        if block.get("sensor") == mag_id:
            located += [(float(a), float(b)) for a, b in (block.get("located") or {}).get("time_windows_s", [])]
    excluded = [(float(a), float(b)) for e in cal.effects
                if e.get("sensor") == mag_id and e.get("status") in MODELLED
                for a, b in (e.get("params") or {}).get("windows_s", [])]
    return tuple(located), tuple(excluded)


def mag_view(result: RunResult, mag: MagCalibration) -> MagView | None:
    """The series of `mag` in plot units (None when the run kept no series for it)."""
    series = result.series.get(mag.id)
    if series is None:
        return None
    fs = mag.field_strength
    r_raw = np.linalg.norm(series.raw, axis=1)
    down = down_at(result.recording, result.calibration, series.t)
    located, excluded = _windows(result.calibration, mag.id)
    with np.errstate(invalid="ignore"):
        norm_cal = 100.0 * (np.linalg.norm(series.calibrated, axis=1) - 1.0)
    return MagView(mag.id, series.t, series.raw / fs, series.calibrated, 100.0 * (r_raw / np.mean(r_raw) - 1.0),
                   norm_cal, _dip(series.raw, down), _dip(series.calibrated, down), mag.dip_deg,
                   tuple((s.start, s.end) for s in result.still.segments), located, excluded)


def heading_view(result: RunResult, mag: MagCalibration) -> HeadingView:
    """Heading error of a level vehicle at every heading: raw readings, the calibration's 1-sigma, the firmware."""
    from magcal_cli.firmware.common import Options
    from magcal_cli.firmware.export import export

    fs = mag.field_strength
    raw = heading_errors_deg(mag.D / fs, mag.o / fs, mag.dip_deg)    # the compass reads D m_b + o
    firmware = FIRMWARE_OF_FORMAT.get(result.recording.format)
    held = None
    if firmware is not None:
        try:
            m = export(result.calibration, firmware, dict(result.recording.params), Options(), [mag.id]).mags[0]
            held = heading_errors_deg(m.split.residual, np.zeros(3), m.dip_deg)
        except MagcalError:
            held = None
    return HeadingView(HEADINGS_DEG, raw, heading_std_curve_deg(mag), held, firmware if held is not None else None)


def _channel(rec: Recording, kind: Kind, names: list[str], t: FloatArray) -> FloatArray | None:
    """The effect's channel at times t: the stream the fit named, else the first of its kind (as `remove` does)."""
    found = [s for s in rec.of_kind(kind) if s.id in names and len(s) >= 2] or \
            [s for s in rec.of_kind(kind) if len(s) >= 2]
    if not found:
        return None
    out: FloatArray = np.interp(t, found[0].t, found[0].values[:, 0])
    return out


def _rotation_rate(result: RunResult, m_b: FloatArray, t: FloatArray, down: FloatArray) -> FloatArray | None:
    """How fast rotation turns the field's vertical component, (omega x m_b) . down / cos(dip), in deg/s.

    A reading late by tau shows m_b(t - tau) = m_b + tau (omega x m_b), so its dip error is tau times this rate.
    """
    cal = result.calibration
    try:
        gyr = result.recording.select(Kind.GYROSCOPE, cal.imu.id)
    except MagcalError:
        return None
    w = gyr.xyz - (cal.imu.gyroscope_bias if cal.imu.gyroscope_bias is not None else 0.0)
    rate = np.sum(np.cross(columns(t, gyr.t, w, left=np.nan, right=np.nan), m_b) * down, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        horizontal = np.sqrt(np.clip(1.0 - np.sum(m_b * down, axis=1) ** 2, 0.0, None))
        out: FloatArray = np.rad2deg(rate / horizontal)
    return out


def effect_views(result: RunResult, mag: MagCalibration) -> list[EffectView]:
    """Per modelled magnetometer effect of `mag`: its residual against its channel, before and after removal."""
    cal, rec = result.calibration, result.recording
    series = result.series.get(mag.id)
    mine = [e for e in cal.effects if e.get("sensor") == mag.id and e.get("status") in MODELLED and e.get("params")
            and e.get("id") in EFFECTS and get(str(e["id"])).target is Target.MAG]
    if series is None or not mine:
        return []
    # series.t is re-stamped by a modelled time offset; undo that to start from the log's stamps
    t0 = series.t + sum(float(e["params"]["tau_s"]) for e in mine if e["id"] == "time_offset")
    out = []
    for e in mine:
        others = [x for x in cal.effects if x is not e]
        views = [remove(list(effs), mag.id, rec, t0, series.raw, MODELLED)[:2] for effs in (others, cal.effects)]
        view = _effect_view(result, mag, e, views)
        if view is not None:
            out.append(view)
    return out


def _effect_view(result: RunResult, mag: MagCalibration, e: dict[str, Any],
                 views: list[tuple[FloatArray, FloatArray]]) -> EffectView | None:
    """The plotted pair for one effect: field-strength error against its channel, or dip error against rotation."""
    eff = get(str(e["id"]))
    (t_b, y_b), (t_a, y_a) = views
    m_b, m_a = mag.apply(y_b), mag.apply(y_a)
    if eff.channels:
        kind = eff.channels[0]
        x = _channel(result.recording, kind, [str(c) for c in e.get("channels") or []], t_a)
        if x is None:
            return None
        with np.errstate(invalid="ignore"):
            before = 100.0 * (np.linalg.norm(m_b, axis=1) - 1.0)
            after = 100.0 * (np.linalg.norm(m_a, axis=1) - 1.0)
        label = kind.value.replace("_", " ") + (f" [{kind.si_unit}]" if kind.si_unit != "1" else " (0 to 1)")
        return EffectView(eff.id, str(e.get("status")), label, "field strength error [%]", x, before, after)
    down_b, down_a = down_at(result.recording, result.calibration, t_b), down_at(result.recording,
                                                                                  result.calibration, t_a)
    if down_b is None or down_a is None:
        return None
    x = _rotation_rate(result, m_a, t_a, down_a)
    dip_b, dip_a = _dip(m_b, down_b), _dip(m_a, down_a)
    if x is None or dip_b is None or dip_a is None:
        return None
    return EffectView(eff.id, str(e.get("status")), "rotation rate of the field's dip [deg/s]", "dip error [deg]",
                      x, dip_b - mag.dip_deg, dip_a - mag.dip_deg)
