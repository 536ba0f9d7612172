"""`magcal check`: judge the calibration a vehicle flew with, for post-flight CI.

For each compass: the raw field the reader rebuilt, corrected as flown (`firmware.flown`); its field-norm
consistency; the residual iron and interference left, fitted against the log's roll and pitch
(`firmware.residual`), with the level heading error they cause; and, when a new magcal calibration of the
same log succeeds, the heading change that calibration would bring as the firmware would hold it.

A gate whose metric the log cannot measure (too few headings, no current) is "not measured": reported, and a
failure only with `require_measured` (--require-measured). The field-norm consistency is always measured, and
its default gate (`DEFAULT_MAX_FIELD_NORM_RMS_PCT`) fails a compass whose flown field strength varies far beyond
what any calibration should leave, whatever else could not be measured (issue 30: 01_07_59.px4log's MAG[1], 13.6 %,
PASSED with its heading gate not measured).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli import units
from magcal_cli.calibration.types import Calibration
from magcal_cli.errors import MagcalError
from magcal_cli.firmware import FirmwareError, gates
from magcal_cli.firmware.common import Options
from magcal_cli.firmware.export import export
from magcal_cli.firmware.flown import Flown, flown_fields, heading_gap_deg, levelling, signal_at, slow
from magcal_cli.firmware.flown import headings as _headings
from magcal_cli.firmware.residual import MIN_SAMPLES, fit_residual
from magcal_cli.streams import FloatArray, Kind, Recording

#: metric -> meaning, for --fail-on and the documentation
METRICS = {
    "field_norm_rms_pct": "RMS deviation of the flown field's magnitude from its median, in %",
    "heading_error_deg": "worst level heading error the flown calibration leaves (residual iron and interference)",
    "heading_error_std_deg": "standard deviation of heading_error_deg",
    "interference_pct": "residual interference at the log's peak current (or throttle), % of the field",
    "residual_offset_pct": "residual hard iron left by the flown calibration, % of the field",
    "heading_change_deg": "largest heading change over the flight a new magcal calibration would bring",
}
DEFAULT_MAX_HEADING_ERROR_DEG = 5.0
#: the default gate on field_norm_rms_pct. Residual iron that spreads the flown field's magnitude by p (RMS, relative)
#: over a level turn at dip d leaves a worst heading error of about sqrt(2) p / cos(d)^2 rad (an offset e on the
#: horizontal field H spreads |field| by H e / (sqrt(2) F^2) and turns the heading by up to e / H; a scale error
#: likewise): at 10 % that is 8 deg at the magnetic equator and 42 deg at dip 60 deg, beyond the default heading gate
#: anywhere. Compasses that fly well keep 0.2-2.5 % in flight (the real logs of docs/firmware-export.md), poorly
#: calibrated ones 4-6.5 %; ArduPilot's own calibration accepts at most COMPASS_CAL_FIT = 16 mG of misfit (about 3 %
#: of a 500 mG field)
DEFAULT_MAX_FIELD_NORM_RMS_PCT = 10.0
#: samples taken while turning faster than this are left out of the residual fit (flown.slow)
MAX_RATE_DPS = 30.0
#: the heading error needs the flight's headings to leave no gap wider than this (deg): a circle seen over
#: less than half its length does not fix its centre
MAX_HEADING_GAP_DEG = 180.0
SCHEMA = "magcal.check/1"


@dataclass
class CompassCheck:
    """One compass: metrics, what could not be measured and why, details, the gates failed and not measured."""

    id: str
    unit: str
    slot: str
    used: bool | None
    samples: int
    metrics: dict[str, float | None] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    unmeasured: list[str] = field(default_factory=list)

    @property
    def gated(self) -> bool:
        """Gates apply unless the parameters say the compass is not used for yaw."""
        return self.used is not False

    @property
    def verdict(self) -> str:
        """pass, fail or not measured, with '(not used for yaw: not gated)' for a compass not used."""
        word = "fail" if self.failed else "not measured" if self.unmeasured else "pass"
        return word if self.gated else f"{word} (not used for yaw: not gated)"


@dataclass
class CheckReport:
    """The whole check: the log, where the flown calibration came from, the gates, every compass."""

    log: str
    calibration_source: str
    levelling: str
    conditions: tuple[gates.Condition, ...]
    compasses: list[CompassCheck]
    notes: list[str] = field(default_factory=list)
    require_measured: bool = False

    @property
    def passed(self) -> bool:
        """True when no gated compass fails (a gate not measured does not fail unless require_measured)."""
        return not any(c.failed and c.gated for c in self.compasses)

    @property
    def unmeasured(self) -> int:
        """How many gates of gated compasses could not be measured (and do not fail)."""
        return sum(len(c.unmeasured) for c in self.compasses if c.gated)

    def verdict(self) -> str:
        """The last line: PASSED or FAILED, with the gates not measured."""
        if not self.passed:
            return "FAILED"
        n = self.unmeasured
        return "PASSED" if not n else (f"PASSED, but {n} gate{'s' if n > 1 else ''} not measured "
                                       "(--require-measured fails on them)")

    def to_json(self) -> str:
        """The report as one JSON document (`magcal.check/1`)."""
        doc = {"schema": SCHEMA, "log": self.log, "calibration_source": self.calibration_source,
               "levelling": self.levelling, "gates": [str(c) for c in self.conditions], "passed": self.passed,
               "require_measured": self.require_measured,
               "compasses": [{"id": c.id, "unit": c.unit, "slot": c.slot, "used": c.used, "samples": c.samples,
                              "verdict": c.verdict, "failed": c.failed, "gates_not_measured": c.unmeasured,
                              "metrics": c.metrics,
                              "not_measured": c.missing, "details": c.details, "notes": c.notes}
                             for c in self.compasses],
               "notes": self.notes}
        return json.dumps(doc, indent=2, default=float) + "\n"

    def to_text(self) -> str:
        """The report for people: one block per compass, the overall verdict last."""
        lines = [f"{self.log}: calibration from {self.calibration_source}; levelled with {self.levelling}",
                 f"gates: {', '.join(str(c) for c in self.conditions) or 'none'}"]
        for c in self.compasses:
            lines.append(f"{c.id} ({c.slot}{'' if c.used is None else ', used' if c.used else ', not used'}): "
                         f"{c.verdict.upper()}")
            lines += [f"  {line}" for line in _describe(c)]
            lines += [f"  failed: {f}" for f in c.failed]
            lines += [f"  gate not measured: {f}" for f in c.unmeasured]
        lines += [f"note: {n}" for n in self.notes]
        lines.append(self.verdict())
        return "\n".join(lines) + "\n"


def _fmt(value: float | None, std: float | None = None, digits: int = 2) -> str:
    """A number with its standard deviation, or 'n/a'."""
    if value is None:
        return "n/a"
    return f"{value:.{digits}f}" + (f" +- {std:.{digits}f}" if std is not None else "")


def _typical(c: CompassCheck) -> str:
    """' (x at the median current)' when interference was fitted, else nothing."""
    at = c.details.get("interference_at")
    if at is None:
        return ""
    what = "current" if at.endswith(" A") else "throttle"
    return f" ({c.details['heading_error_at_median_signal_deg']:.2f} at the median {what})"


def _describe(c: CompassCheck) -> list[str]:
    """Human lines for one compass's numbers."""
    m, d = c.metrics, c.details
    out = [f"field-norm consistency {_fmt(m.get('field_norm_rms_pct'))} % RMS over {c.samples} samples"]
    if m.get("heading_error_deg") is not None:
        out.append(f"heading error (level, worst heading) {_fmt(m['heading_error_deg'], m['heading_error_std_deg'])}"
                   f" deg{_typical(c)}; residual offset {_fmt(m.get('residual_offset_pct'))} % of the field "
                   f"{d.get('field_strength', float('nan')):.4g} {c.unit}, dip {d.get('dip_deg', float('nan')):.1f}"
                   " deg")
    else:
        out.append(f"heading error n/a ({c.missing.get('heading_error_deg', '')})")
    if m.get("interference_pct") is not None:
        out.append(f"interference {_fmt(m['interference_pct'], d.get('interference_std_pct'))} % of the field "
                   f"at {d.get('interference_at', '')}")
    if m.get("heading_change_deg") is not None:
        out.append(f"a new calibration would change the heading by up to {m['heading_change_deg']:.2f} deg "
                   f"(RMS {d.get('heading_change_rms_deg', float('nan')):.2f}); its field-norm consistency "
                   f"{d.get('new_field_norm_rms_pct', float('nan')):.2f} % RMS")
    else:
        out.append(f"no new calibration ({c.missing.get('heading_change_deg', '')})")
    return out + [f"note: {n}" for n in c.notes]


def _residual_metrics(c: CompassCheck, f: Flown, rec: Recording, mask: npt.NDArray[np.bool_], lev: FloatArray
                      ) -> None:
    """Heading error, residual offset and interference from the attitude-constrained fit."""
    current = signal_at(rec, Kind.BATTERY_CURRENT, f.t)
    throttle = signal_at(rec, Kind.THROTTLE, f.t)
    signal, what = (current, "A") if current is not None else (throttle, "throttle")
    keep = slow(rec, f.t[mask], MAX_RATE_DPS)
    c.details["residual_fit_samples"] = int(keep.sum())
    gap = heading_gap_deg(_headings(f.field[mask][keep], lev[keep]))
    c.details["largest_heading_gap_deg"] = gap
    if gap > MAX_HEADING_GAP_DEG and keep.sum() >= MIN_SAMPLES:
        why = (f"the vehicle's headings leave a {gap:.0f} deg gap (turning slower than {MAX_RATE_DPS:g} deg/s); "
               "fly a slow full turn")
        for k in ("heading_error_deg", "heading_error_std_deg", "residual_offset_pct", "interference_pct"):
            c.missing[k] = why
        return
    try:
        r = fit_residual(f.field[mask][keep], lev[keep], None if signal is None else signal[mask][keep],
                         f.t[mask][keep])
    except MagcalError as exc:
        for k in ("heading_error_deg", "heading_error_std_deg", "residual_offset_pct", "interference_pct"):
            c.missing[k] = str(exc)
        return
    c.metrics |= {"heading_error_deg": r.heading_error_deg, "heading_error_std_deg": r.heading_error_std_deg,
                  "residual_offset_pct": float(100.0 * np.linalg.norm(r.c0) / r.field_strength),
                  "interference_pct": r.interference_pct}
    c.details |= {"heading_error_at_median_signal_deg": r.heading_error_median_deg, "residual_tilt_deg": r.tilt_deg,
                  "field_strength": r.field_strength, "dip_deg": r.dip_deg, "residual_offset": r.c0.tolist(),
                  "residual_soft_iron": r.S.tolist(), "residual_fit_rms_pct": r.rms_pct}
    peak = max(abs(v) for v in r.signal_range)
    if r.interference_pct is None:
        c.missing["interference_pct"] = "no battery current or throttle that varies in the log"
    else:
        c.details |= {"interference_std_pct": r.interference_std_pct,
                      "interference_per_unit": None if r.k is None else r.k.tolist(),
                      "interference_at": (f"{peak:.1f} A" if what == "A" else f"throttle {peak:.2f}")}


def _change(c: CompassCheck, f: Flown, cal: Calibration, vehicle: dict[str, float], mask: npt.NDArray[np.bool_],
            lev: FloatArray, keep: npt.NDArray[np.bool_]) -> None:
    """Heading change a new calibration brings, as the firmware would hold it (its export split)."""
    new = cal.magnetometer(f.id)
    to_flown = units.to_si(new.unit) * units.from_si(f.unit)
    if f.firmware is not None:
        m = export(cal, f.firmware, vehicle, Options(), [new.id]).mags[0]
        field_new = (f.raw - new.o * to_flown) @ m.split.held.T       # held = F D^-1 as the firmware holds it
        c.details |= {"new_parameters": m.params, "new_export_lost": m.lost()}
    else:
        field_new = new.field_strength * to_flown * new.apply(f.raw / to_flown)
    # slow samples whose levelled field keeps a horizontal part: elsewhere a heading is not defined well
    g = np.einsum("nij,nj->ni", lev, f.field[mask])
    h = np.hypot(g[:, 0], g[:, 1])
    use = keep & (h > 0.5 * np.median(h))
    if not use.any():
        c.missing["heading_change_deg"] = f"no samples turning slower than {MAX_RATE_DPS:g} deg/s"
        return
    d = np.angle(np.exp(1j * (_headings(field_new[mask][use], lev[use]) - _headings(f.field[mask][use], lev[use]))))
    norm = np.linalg.norm(field_new, axis=1)
    c.metrics["heading_change_deg"] = float(np.rad2deg(np.max(np.abs(d))))
    c.details |= {"heading_change_rms_deg": float(np.rad2deg(np.sqrt(np.mean(d**2)))),
                  "new_field_norm_rms_pct": float(100 * np.sqrt(np.mean((norm / np.median(norm) - 1) ** 2))),
                  "new_method": cal.method}


def flown_or_refuse(rec: Recording, mags: list[str] | None, params: dict[str, float] | None,
                    calibration: Calibration | None) -> tuple[list[Flown], str]:
    """The compasses as flown and where their calibration came from; FirmwareError when none is known."""
    flown, source = flown_fields(rec, mags, params, calibration)
    if not flown:
        msg = f"{rec.path.name}: none of the selected magnetometers is in the calibration; check --mag"
        raise FirmwareError(msg)
    return flown, source


@dataclass(frozen=True)
class CheckOptions:
    """How to judge: require every gate measured; how to name the calibration source in the header; the default
    field-norm gate (inf: none; a --fail-on condition on field_norm_rms_pct replaces it)."""

    require_measured: bool = False
    source: str | None = None           # e.g. "the calibration document /abs/cal.json" [default: flown_fields's]
    max_field_norm_rms_pct: float = DEFAULT_MAX_FIELD_NORM_RMS_PCT


def default_gates(conditions: tuple[gates.Condition, ...], options: CheckOptions) -> tuple[gates.Condition, ...]:
    """The conditions with the default field-norm gate added, unless turned off (inf) or the caller gave its own
    condition on field_norm_rms_pct: the one metric every compass measures, so a compass whose field strength
    varies far beyond a calibration's never passes on what could not be measured."""
    limit = options.max_field_norm_rms_pct
    if not np.isfinite(limit) or any(c.metric == "field_norm_rms_pct" for c in conditions):
        return conditions
    return (*conditions, gates.Condition("field_norm_rms_pct", ">", limit))


def check_recording(rec: Recording, conditions: tuple[gates.Condition, ...], *,
                    params: dict[str, float] | None = None, calibration: Calibration | None = None,
                    mags: list[str] | None = None, new: Calibration | None = None,
                    why_no_new: str = "no new calibration", options: CheckOptions | None = None,
                    flown: tuple[list[Flown], str] | None = None) -> CheckReport:
    """Check every selected compass of a recording against the calibration flown and, if given, a new one."""
    options = options or CheckOptions()
    conditions = default_gates(conditions, options)
    compasses, source = flown or flown_or_refuse(rec, mags, params, calibration)
    vehicle = dict(rec.params) if params is None else params
    report = CheckReport(str(rec.path), options.source or source, "", conditions, [],
                         require_measured=options.require_measured)
    if params is None and calibration is None and any("changed during the log" in n for n in rec.notes):
        report.notes.append("compass parameters changed during the log; the check applies their last values to "
                            "every sample (cut the log with the reader's notes in mind)")
    for f in compasses:
        c = CompassCheck(f.id, f.unit, f.slot, f.used, len(f.t))
        norm = np.linalg.norm(f.field, axis=1)
        c.metrics["field_norm_rms_pct"] = float(100 * np.sqrt(np.mean((norm / np.median(norm) - 1) ** 2)))
        c.details["field_norm_median"] = float(np.median(norm))
        mask, lev, report.levelling = levelling(rec, f.t)
        _residual_metrics(c, f, rec, mask, lev)
        if new is not None and any(m.id == f.id for m in new.magnetometers):
            try:
                _change(c, f, new, vehicle, mask, lev, slow(rec, f.t[mask], MAX_RATE_DPS))
            except FirmwareError as exc:
                c.missing["heading_change_deg"] = str(exc)
        else:
            c.missing["heading_change_deg"] = why_no_new if new is None else "the new calibration lacks it"
        c.failed, c.unmeasured = gates.judge(conditions, c.metrics, c.missing)
        if options.require_measured:
            c.failed, c.unmeasured = gates.failures(conditions, c.metrics, c.missing), []
        report.compasses.append(c)
    return report
