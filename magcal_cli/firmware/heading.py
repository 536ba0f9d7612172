"""Never silently worse (issue 38 item 6): heading against the vehicle's own attitude, magcal's vs the flown.

Where a log has the vehicle's attitude (ArduPilot ATT, PX4 vehicle_attitude), each calibrated compass's field is
corrected twice, with magcal's document and with the calibration the vehicle flew with (`firmware.flown`),
levelled with the attitude's roll and pitch, and its heading compared with the attitude's yaw (plus the WMM's
declination when the log's position is known). One constant offset per calibration is removed (the compass's yaw
mounting against the IMU, and the declination when unknown), and what is left is the heading error.

Protocol (docs/decisions.md, 2026-11-29): magcal's fit never sees the attitude's yaw, so the yaw is an independent
reference for both calibrations; the flown calibration was made before the log (out of sample by construction).
magcal's calibration is NOT refitted per fold (that would cost a fit per fold): instead the samples are cut into
`FOLDS` contiguous time blocks, the RMS error of each calibration is taken in each block, and the comparison is
the mean of the paired block differences (magcal - flown) with their block-to-block standard error as its own
uncertainty. A compass is "worse" when that mean exceeds max(1.96 x its standard error, `FLOOR_DEG`), "better"
when it is below minus that, else "same". A calibration whose dip is more than `DIP_OFF_DEG` off the WMM while the
log's motion determines little (uncertainty widened `WIDENED`x or more, or less than `MIN_COVERAGE_DEG` of yaw
seen) is not passed on either. Either way it is left out of the firmware parameter file unless `export_worse`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from magcal_cli import so3
from magcal_cli.align import onto
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.errors import MagcalError
from magcal_cli.findings import Finding, Severity
from magcal_cli.firmware.flown import Flown, flown_fields, heading_gap_deg, headings, slow
from magcal_cli.streams import FloatArray, Kind, Recording, Stream
from magcal_cli.wmm import ReferenceField

FOLDS = 5
#: samples taken while turning faster than this are left out (as firmware.check's MAX_RATE_DPS: attitude latency)
MAX_RATE_DPS = 30.0
#: fewest samples per fold; with fewer, two folds; with fewer still, no check
MIN_PER_FOLD = 30
#: a difference below this (deg) is "same" however small its standard error: heading references are not that exact
FLOOR_DEG = 0.5
DIP_OFF_DEG, WIDENED, MIN_COVERAGE_DEG = 10.0, 10.0, 180.0
PROTOCOL = (f"paired time folds: heading RMS against the attitude's yaw per contiguous fold, one constant offset "
            f"removed per calibration; difference (magcal - flown) = mean over folds, its uncertainty the folds' "
            f"standard error; worse/better beyond max(1.96 x that, {FLOOR_DEG} deg); magcal not refitted per fold "
            "(its fit never sees the yaw), the flown calibration out of sample by construction")


def _wrap(a: FloatArray) -> FloatArray:
    """Angles (rad) wrapped to (-pi, pi]."""
    out: FloatArray = np.angle(np.exp(1j * a))
    return out


def _errors(field: FloatArray, lev: FloatArray, yaw: FloatArray, declination: float) -> tuple[FloatArray, float]:
    """Heading error (rad) with its circular mean removed, and that mean (deg)."""
    e = _wrap(headings(field, lev) + declination - yaw)
    mean = float(np.angle(np.mean(np.exp(1j * e))))
    return _wrap(e - mean), float(np.rad2deg(mean))


def _folds(n: int) -> list[FloatArray] | None:
    """Index blocks of the contiguous time folds (FOLDS, else 2), None when too few samples."""
    for k in (FOLDS, 2):
        if n >= k * MIN_PER_FOLD:
            return [np.asarray(b) for b in np.array_split(np.arange(n), k)]
    return None


def _rms(e: FloatArray) -> float:
    """RMS in degrees."""
    return float(np.rad2deg(np.sqrt(np.mean(e**2))))


@dataclass(frozen=True, eq=False)
class Series:
    """Both calibrations' heading errors (rad, mean removed) at the samples kept, their times and the yaw seen."""

    t: FloatArray
    flown: FloatArray
    magcal: FloatArray
    offsets_deg: tuple[float, float]            # (flown, magcal): the constant removed from each
    yaw: FloatArray


def series(flown: Flown, mine: Flown, att: Stream, rec: Recording, declination: float) -> Series | None:
    """Heading errors of the flown and magcal's field against the attitude's yaw (None: too few samples)."""
    mask, q = onto(att, flown.t, max_gap_s=1.0)
    if mask.sum() < 2 * MIN_PER_FOLD:
        return None
    rpy = so3.as_rpy(so3.from_quat(q))
    yaw = rpy[:, 2].copy()
    rpy[:, 2] = 0.0
    if rec.format == "dataflash":           # ATT is the vehicle's attitude, the board's plus AHRS_TRIM (as magfit_WMM)
        rpy[:, 0] += rec.params.get("AHRS_TRIM_X", 0.0)
        rpy[:, 1] += rec.params.get("AHRS_TRIM_Y", 0.0)
    lev = so3.from_rpy(rpy)
    g = np.einsum("nij,nj->ni", lev, flown.field[mask])
    h = np.hypot(g[:, 0], g[:, 1])
    # fast turns put the compass and the attitude's latency apart; near-vertical fields have no heading
    finite = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(flown.field[mask] + mine.field[mask]), axis=1)
    keep = slow(rec, flown.t[mask], MAX_RATE_DPS) & (h > 0.5 * np.nanmedian(h)) & finite
    if keep.sum() < 2 * MIN_PER_FOLD:
        return None
    e_f, off_f = _errors(flown.field[mask][keep], lev[keep], yaw[keep], declination)
    e_m, off_m = _errors(mine.field[mask][keep], lev[keep], yaw[keep], declination)
    return Series(flown.t[mask][keep], e_f, e_m, (off_f, off_m), yaw[keep])


def compare(flown: Flown, mine: Flown, att: Stream, rec: Recording, declination: float) -> dict[str, Any] | None:
    """The heading_check block's numbers for one compass (None when too few samples line up with the attitude)."""
    s = series(flown, mine, att, rec, declination)
    folds = None if s is None else _folds(s.t.size)
    if s is None or folds is None:
        return None
    per_f = [_rms(s.flown[b]) for b in folds]
    per_m = [_rms(s.magcal[b]) for b in folds]
    d = np.subtract(per_m, per_f)
    se = float(np.std(d, ddof=1) / np.sqrt(d.size))
    diff = float(np.mean(d))
    bound = max(1.96 * se, FLOOR_DEG)
    verdict = "worse" if diff > bound else "better" if diff < -bound else "same"
    return {"verdict": verdict, "rms_deg": {"magcal": _rms(s.magcal), "flown": _rms(s.flown)},
            "difference_deg": diff, "difference_std_deg": se, "reference": att.id, "samples": int(s.t.size),
            "folds": len(folds), "fold_rms_deg": {"magcal": per_m, "flown": per_f},
            "offset_deg": {"magcal": s.offsets_deg[1], "flown": s.offsets_deg[0]},
            "heading_coverage_deg": 360.0 - heading_gap_deg(s.yaw),
            "flown_slot": flown.slot, "flown_used": flown.used, "protocol": PROTOCOL}


def error_series(rec: Recording, cal: Calibration, mag_id: str) -> Series | None:
    """The heading errors behind a compass's heading_check, for the report's plot (None: not measurable)."""
    att = [s for s in rec.of_kind(Kind.ATTITUDE) if len(s) >= 2]
    try:
        flown = flown_fields(rec, [mag_id], None, None)[0]
        mine = flown_fields(rec, [mag_id], None, cal)[0]
    except MagcalError:
        return None
    return series(flown[0], mine[0], att[0], rec, 0.0) if att and flown and mine else None


def _dip_suspect(mag: MagCalibration, block: dict[str, Any], ref: ReferenceField | None,
                 widened: float | None) -> str | None:
    """Why the dip says the motion determined too little (None when it does not)."""
    if ref is None:
        return None
    off = mag.dip_deg - ref.dip_deg
    block["dip_off_wmm_deg"] = off
    weak = (widened or 1.0) >= WIDENED or block["heading_coverage_deg"] < MIN_COVERAGE_DEG
    if abs(off) <= DIP_OFF_DEG or not weak:
        return None
    return (f"its dip is {off:+.1f} deg off the World Magnetic Model's while the log's motion determines little "
            f"(uncertainty widened {widened or 1.0:.1f}x, {block['heading_coverage_deg']:.0f} deg of heading seen)")


def _finding(mag: MagCalibration, block: dict[str, Any], why: str, export_worse: bool) -> Finding:
    """The warning that the flown calibration is better for heading, and what happens to the firmware file."""
    r = block["rms_deg"]
    fate = ("written to the firmware parameter file anyway (--export-worse)" if export_worse else
            "left out of the firmware parameter file, so the vehicle keeps its own calibration for it "
            "(--export-worse writes it anyway)")
    head = ("the calibration the vehicle flew with is better for heading" if block["verdict"] == "worse" else
            "magcal's calibration is not passed on as an improvement over the one the vehicle flew with")
    msg = (f"{mag.id}: {head}: against the vehicle's attitude "
           f"({block['reference']} yaw) it errs {r['flown']:.1f} deg RMS, magcal's {r['magcal']:.1f} deg "
           f"(difference {block['difference_deg']:+.1f} +- {block['difference_std_deg']:.1f} deg over "
           f"{block['folds']} time folds); {why}. {mag.id} is {fate}")
    return Finding(Severity.WARNING, "flown_calibration_better", msg,
                   {"sensor": mag.id, "rms_magcal_deg": r["magcal"], "rms_flown_deg": r["flown"],
                    "difference_deg": block["difference_deg"], "difference_std_deg": block["difference_std_deg"]})


def heading_checks(rec: Recording, cal: Calibration, findings: Sequence[Finding], ref: ReferenceField | None,
                   export_worse: bool = False) -> tuple[Calibration, list[Finding]]:
    """Each calibrated compass with its heading_check block (where the log has attitude and a flown
    calibration), and the warnings for those not passed on as an improvement."""
    att = [s for s in rec.of_kind(Kind.ATTITUDE) if len(s) >= 2]
    if not att or not cal.magnetometers:
        return cal, []
    declination = ref.declination if ref is not None else 0.0
    widened: dict[str, float] = {}
    for f in findings:
        if f.code == "correlated_residuals" and "max_factor" in f.evidence:
            s = str(f.evidence.get("sensor"))
            widened[s] = max(widened.get(s, 1.0), float(f.evidence["max_factor"]))
    mags, out = [], []
    for mag in cal.magnetometers:
        try:
            flown = flown_fields(rec, [mag.id], None, None)[0]
            mine = flown_fields(rec, [mag.id], None, cal)[0]
        except MagcalError:
            mags.append(mag)                # no flown calibration known: nothing to compare with
            continue
        block = compare(flown[0], mine[0], att[0], rec, declination) if flown and mine else None
        if block is None:
            mags.append(mag)
            continue
        # the attitude method fits against this attitude: its side of the comparison is in sample, favoured
        block["reference_in_fit"] = mag.reference != "motion"
        dip = _dip_suspect(mag, block, ref, widened.get(mag.id))
        why = ("magcal's is worse by more than the comparison's uncertainty" if block["verdict"] == "worse"
               else None if block["verdict"] == "better" else dip)
        block["exported"] = why is None or export_worse
        block["left_out_reason"] = None if block["exported"] else why
        if why is not None:
            out.append(_finding(mag, block, why, export_worse))
        mags.append(replace(mag, heading_check=block))
    return replace(cal, magnetometers=tuple(mags)), out


def _left_out_line(mag_id: str, h: dict[str, Any]) -> str:
    """One header line: which compass a firmware file leaves out and why."""
    return (f"left out: {mag_id}: not an improvement on the calibration the vehicle flew with for heading "
            f"({h['rms_deg']['flown']:.1f} vs magcal's {h['rms_deg']['magcal']:.1f} deg RMS against "
            f"{h['reference']}); {h['left_out_reason']}; the vehicle keeps its own values (magcal fit --export-worse "
            "writes it)")


def firmware_selection(cal: Calibration) -> tuple[list[str] | None, list[str]]:
    """The magnetometers a firmware file gets (None: all) and header lines naming those left out and why."""
    left = {m.id: m.heading_check for m in cal.magnetometers
            if m.heading_check is not None and not m.heading_check.get("exported", True)}
    if not left:
        return None, []
    return [m.id for m in cal.magnetometers if m.id not in left], [_left_out_line(i, h) for i, h in left.items()]


def parameter_file(cal: Calibration, firmware: str, params: dict[str, float], style: str) -> str:
    """The firmware parameter file's text: every magnetometer the heading check passes on (or all), the header
    naming those left out; only that header when every one is left out (the vehicle keeps its values)."""
    from magcal_cli.firmware.common import Options
    from magcal_cli.firmware.export import export
    from magcal_cli.firmware.paramfile import render

    ids, left = firmware_selection(cal)
    if ids == []:
        return render({}, style, [f"magcal {firmware} compass parameters from {cal.source.path}", *left,
                                  "no parameters: every compass is left out"])
    exp = export(cal, firmware, params, Options(skip_refused=True), ids)
    return render(exp.params, style, [*exp.header(), *left], exp.integers)
