"""What a reader sees first: a verdict per magnetometer, the key numbers, next steps and grouped warnings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.types import MagCalibration
from magcal_cli.findings import Finding, Severity
from magcal_cli.firmware.metrics import fit_metrics
from magcal_cli.writers.report.text import advice

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult

#: verdict level -> the words a reader sees (ordered best first)
LEVELS = {"good": "Good", "check": "Usable, with caveats", "poor": "Not usable"}
#: finding code -> the heading of its group
TITLES = {
    "poorly_observable": "Parameters the log determines poorly",
    "correlated_residuals": "Residuals correlated in time (uncertainty widened)",
    "dip_disagrees_with_wmm": "Dip differs from the World Magnetic Model",
    "flown_calibration_better": "The calibration the vehicle flew with is better for heading",
    "fisher_condition": "Confounded parameters",
    "not_calibrated": "Magnetometers not calibrated",
    "disturbance_modelled": "Calibrated with a disturbance modelled",
    "reader_note": "Reading the log",
    "method_note": "Solver",
}
#: the thresholds behind the verdict (the same scale the text report's advice uses)
NORM_CHECK_PCT, NORM_POOR_PCT = 1.0, 5.0
COVERAGE_CHECK_PCT, COVERAGE_POOR_PCT = 30.0, 15.0
HEADING_CHECK_DEG = 2.0
#: low coverage alone makes a calibration unusable only when the heading it gives is this uncertain (1 sigma):
#: accuracy is judged by heading (docs/results/heading.md), and a flight that yawed through full turns within
#: +-20 deg of level covers 11-15 % of the sphere yet determines the heading to a degree
HEADING_POOR_DEG = 5.0
APPLY = "Apply m_b = A (y - b) to raw readings"


@dataclass(frozen=True)
class Verdict:
    """One magnetometer's verdict: a level of LEVELS, the reasons and its key numbers."""

    mag_id: str
    level: str
    reasons: tuple[str, ...]
    metrics: dict[str, float | None]
    raw_norm_pct: float

    @property
    def label(self) -> str:
        """The verdict in words."""
        return LEVELS[self.level]


@dataclass(frozen=True)
class Group:
    """Findings that share a code: a heading, the sensors they name and every message in full."""

    code: str
    title: str
    severity: Severity
    sensors: tuple[str, ...]
    messages: tuple[str, ...]


def mentions(message: str, mag_id: str) -> bool:
    """True when a finding's message is about `mag_id` (messages name their sensor as 'ID: ...')."""
    return f"{mag_id}:" in message or f"{mag_id} " in message


def _raw_norm_pct(result: RunResult, mag: MagCalibration) -> float:
    """RMS spread of the raw field strength around its mean, in %."""
    series = result.series.get(mag.id)
    if series is None:
        return float("nan")
    r = np.linalg.norm(series.raw, axis=1)
    return float(100.0 * np.std(r) / np.mean(r))


def verdicts(result: RunResult) -> list[Verdict]:
    """A verdict per calibrated magnetometer, from its quality figures and the warnings that name it."""
    metrics = fit_metrics(result)
    warnings = [f for f in result.findings if f.severity is Severity.WARNING]
    out = []
    for mag in result.calibration.magnetometers:
        m = metrics[mag.id][0]
        q = mag.quality
        poor: list[str] = []
        check: list[str] = []
        if q is not None and not q.converged:
            poor.append("the solver did not converge")
        norm, cover, heading = m.get("field_norm_rms_pct"), m.get("coverage_pct"), m.get("heading_std_deg")
        fw = m.get("heading_error_deg")
        if norm is not None:
            (poor if norm > NORM_POOR_PCT else check if norm > NORM_CHECK_PCT else []).append(  # [] drops it
                f"the calibrated field strength still varies by {norm:.2f} % RMS")
        if cover is not None and cover < COVERAGE_CHECK_PCT:
            unsure = heading is None or heading > HEADING_POOR_DEG
            (poor if cover < COVERAGE_POOR_PCT and unsure else check).append(
                f"the log covers only {cover:.0f} % of the field directions")
        if heading is not None and heading > HEADING_CHECK_DEG:
            check.append(f"the heading is uncertain by up to {heading:.1f} deg (1 sigma)")
        if fw is not None and fw > HEADING_CHECK_DEG:
            check.append(f"the firmware parameters leave a level heading error up to {fw:.1f} deg")
        mine = [w for w in warnings if mentions(w.message, mag.id)]
        if mine:
            check.append(f"{len(mine)} warning{'s' if len(mine) > 1 else ''} (see Warnings)")
        level = "poor" if poor else "check" if check else "good"
        out.append(Verdict(mag.id, level, tuple(poor + check), m, _raw_norm_pct(result, mag)))
    return out


def overall(vs: list[Verdict]) -> str:
    """The worst level among the verdicts."""
    order = list(LEVELS)
    return max((v.level for v in vs), key=order.index, default="poor")


def next_steps(result: RunResult) -> list[str]:
    """What to do next, each step once (naming the magnetometers it concerns when not all)."""
    mags = result.calibration.magnetometers
    steps: dict[str, list[str]] = {}
    for mag in mags:
        misalign = float(np.rad2deg(so3.angle(mag.misalignment)))
        for step in advice(mag, misalign, _raw_norm_pct(result, mag)):
            if not step.startswith(APPLY):
                steps.setdefault(step, []).append(mag.id)
    out = [s if len(ids) == len(mags) or len(mags) == 1 else f"{', '.join(ids)}: {s}" for s, ids in steps.items()]
    out.append("Use the calibration: apply m_b = A (y - b) to raw readings (calibration.json, magnetometers[].A "
               "and .b), or `magcal apply`; `magcal export` writes ArduPilot or PX4 parameters.")
    return out


def groups(findings: tuple[Finding, ...], mag_ids: list[str]) -> list[Group]:
    """Findings grouped by code, warnings first, each group with the sensors its messages name."""
    by_code: dict[str, list[Finding]] = {}
    for f in findings:
        by_code.setdefault(f.code, []).append(f)
    out = []
    for code, fs in by_code.items():
        severity = Severity.WARNING if any(f.severity is Severity.WARNING for f in fs) else Severity.INFO
        sensors = tuple(m for m in mag_ids if any(mentions(f.message, m) for f in fs))
        title = TITLES.get(code, code.replace("_", " ").capitalize())
        out.append(Group(code, title, severity, sensors, tuple(f.message for f in fs)))
    return sorted(out, key=lambda g: g.severity is not Severity.WARNING)
