"""report.txt: what was found, how good it is, what to do next — for people."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import numpy.typing as npt

from magcal_cli import effects as registry
from magcal_cli import so3, units
from magcal_cli.atomic import write_text
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.diagnose.summary import fold, p_is, unit_suffix
from magcal_cli.effects.correct import terms
from magcal_cli.findings import Severity
from magcal_cli.methods.table import title
from magcal_cli.timing import sentence

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult

#: the unit a report shows a native unit in (tesla is unreadable at Earth-field scale)
DISPLAY = {"tesla": ("microtesla", "uT"), "millitesla": ("microtesla", "uT"), "microtesla": ("microtesla", "uT"),
           "nanotesla": ("microtesla", "uT"), "gauss": ("milligauss", "mG"), "milligauss": ("milligauss", "mG")}
#: an effect's test kind -> its name in a sentence
TESTS = {"wald": "Wald test", "score": "score test"}


def vec(v: npt.ArrayLike, fmt: str = "{:+.3f}") -> str:
    """A vector as '[a, b, c]' with each component formatted by `fmt`."""
    return "[" + ", ".join(fmt.format(x) for x in np.ravel(v)) + "]"


def _mat(m: npt.ArrayLike, indent: int, fmt: str = "{:+.4f}") -> str:
    """A matrix as one `vec` per row, the rows after the first indented by `indent` spaces."""
    rows = [vec(r, fmt) for r in np.asarray(m)]
    return ("\n" + " " * indent).join(rows)


def advice(mag: MagCalibration, misalign_deg: float, norm_before: float,
           carried: tuple[str, ...] = ()) -> list[str]:
    """Next steps for one magnetometer, from its quality numbers; `carried`: the ids of the magnetometer effects
    its calibration carries (they are removed before A is applied)."""
    q, out = mag.quality, []
    if q is not None and q.coverage_pct < 30.0:
        out.append("Coverage is low: record again, rolling and pitching the vehicle through all orientations.")
    if q is not None and q.field_norm_rms_pct > 1.0:
        out.append("The calibrated field strength still varies by more than 1 %: something the model leaves out "
                   "(motor current, a nearby moving magnet, a time offset) disturbs this magnetometer.")
    if misalign_deg > 10.0:
        out.append(f"The magnetometer is rotated {misalign_deg:.0f} deg from the IMU: check the mounting and the "
                   "orientation parameter of an external compass.")
    if norm_before > 5.0:
        out.append("The raw readings deviate strongly from a sphere; use this calibration (A, b) rather than "
                   "offsets only.")
    then = (f" after correcting the readings for {', '.join(carried)} (calibration.json: effects[] of {mag.id}; "
            "`magcal apply` does both)" if carried else "")
    out.append(f"Apply m_b = A (y - b) to raw readings (calibration.json: magnetometers[].A, .b){then}; the result "
               "is a unit vector in the IMU body frame.")
    return out


def render(result: RunResult) -> str:
    """The whole text report."""
    cal = result.calibration
    src = cal.source
    lines = [f"magcal {cal.magcal_version} calibration report ({cal.created_utc})", "",
             f"Log:     {src.path} ({src.format}, {src.end_s - src.start_s:.1f} s used, sha256 {src.sha256[:12]})",
             f"Method:  {methods_line(cal)}"]
    if src.timing:
        lines.append(f"Timing:  {sentence(src.timing)}")
    if result.outputs:
        lines.append(f"Files:   {', '.join(result.outputs)}")
    if cal.diagnosis:
        lines += ["", "What the recording says"]
        for text in fold([str(b.get("summary", "")) for b in cal.diagnosis.get("sensors", [cal.diagnosis])]):
            lines += textwrap.wrap(text, 100, initial_indent="  ", subsequent_indent="  ")
    still = result.still
    still_s = sum(s.end - s.start for s in still.segments)
    imu = cal.imu
    lines += [f"IMU:     {imu.id}: {len(still.segments)} still segments ({still_s:.1f} s); noise per sample "
              f"accel {vec(still.acc_noise, '{:.3g}')} m/s^2, gyro {vec(still.gyr_noise, '{:.3g}')} rad/s"]
    if imu.gyroscope_bias is not None:
        std = imu.gyroscope_bias_std if imu.gyroscope_bias_std is not None else np.full(3, np.nan)
        lines.append(f"         gyroscope bias {vec(imu.gyroscope_bias, '{:+.5f}')} +- {vec(std, '{:.5f}')} rad/s")
    if imu.accelerometer_bias is not None:
        std = imu.accelerometer_bias_std if imu.accelerometer_bias_std is not None else np.full(3, np.nan)
        lines.append(f"         accelerometer bias {vec(imu.accelerometer_bias)} +- {vec(std)} m/s^2")
    else:
        lines.append(f"         accelerometer bias: not estimated by {cal.method}")
    for mag in cal.magnetometers:
        lines += [""] + _render_mag(mag, result)
    for r in cal.refused:
        lines += ["", f"{r['id']}: refused (not calibrated)",
                  *textwrap.wrap(f"why: {r['reason']}", 100, initial_indent="  ", subsequent_indent="    "),
                  *textwrap.wrap(f"to fix: {r['advice']}", 100, initial_indent="  ", subsequent_indent="    ")]
    if cal.effects:
        lines += ["", "Effects beyond the base model", *render_effects(cal.effects)]
    notes = [f for f in result.findings if f.severity is Severity.WARNING] + \
            [f for f in result.findings if f.severity is Severity.INFO]
    if notes:
        lines += ["", "Notes"] + [f"  - [{f.severity.value}] {f.message}" for f in notes]
    return "\n".join(lines) + "\n"


def methods_line(cal: Calibration) -> str:
    """The method, or each magnetometer's where they differ (each compass gets the strongest its data support)."""
    used = {m.method or cal.method for m in cal.magnetometers} or {cal.method}
    if len(used) == 1:
        return title(used.pop())
    return "; ".join(f"{m.id}: {title(m.method or cal.method)}" for m in cal.magnetometers)


def _render_mag(mag: MagCalibration, result: RunResult) -> list[str]:
    """The section of one magnetometer."""
    unit, sym = DISPLAY.get(mag.unit, (mag.unit, mag.unit))
    f = units.to_si(mag.unit) * units.from_si(unit)
    u = mag.misalignment
    misalign = float(np.rad2deg(so3.angle(u)))
    w_sd = float(np.rad2deg(np.sqrt(max(np.trace(mag.misalignment_cov()), 0.0))))
    series = result.series.get(mag.id)
    before = float("nan")
    if series is not None:
        r = np.linalg.norm(series.raw, axis=1)
        before = float(100.0 * np.std(r) / np.mean(r))
    q = mag.quality
    by = f"; calibrated by {title(mag.method)}" if mag.method not in ("", result.calibration.method) else ""
    lines = [f"Magnetometer {mag.id} (log unit: {mag.unit}{by})", "  What was found",
             f"    hard iron b        {vec(mag.o * f)} +- {vec(mag.std_of('o') * f, '{:.3f}')} {sym}",
             f"    field strength     {mag.field_strength * f:.3f} {sym} (source: {mag.field_strength_source})",
             f"    dip                {mag.dip_deg:.2f} +- {float(mag.std_of('dip')):.2f} deg",
             f"    misalignment       {misalign:.2f} +- {w_sd:.2f} deg to the IMU axes "
             f"(roll, pitch, yaw {vec(np.rad2deg(so3.as_rpy(u)), '{:+.2f}')} deg)",
             f"    soft iron P/|F|    {_mat(mag.soft_iron, 23)}",
             f"    A = D^-1 [1/{sym}]".ljust(23) + _mat(mag.A / f, 23, "{:+.6f}")]
    if mag.held:
        lines += textwrap.wrap(held_sentence(mag), 100, initial_indent="    ", subsequent_indent="    ")
    if q is not None:
        lines += ["  How good",
                  f"    field-norm spread  raw |y| {before:.2f} % RMS -> calibrated "
                  f"{q.field_norm_rms_pct:.3f} % RMS over {q.samples} readings",
                  f"    model residual     {q.residual_rms * units.to_si(mag.unit) * units.from_si(unit):.4f} {sym} RMS",
                  f"    coverage           {q.coverage_pct:.0f} % of the sphere of field directions",
                  *([f"    uncertainty        {widening_sentence(factor)}"] if (factor := widening(result, mag.id)) else []),
                  f"    solver             {'converged' if q.converged else 'NOT converged'} "
                  f"after {q.iterations} iterations"]
    lines += heading_lines(mag)
    carried = tuple(eff.id for _, eff in terms(result.calibration.effects, mag.id))
    lines += ["  What to do next"] + [f"    - {a}" for a in advice(mag, misalign, before, carried)]
    return lines


def heading_lines(mag: MagCalibration) -> list[str]:
    """The heading check (firmware/heading.py): magcal's and the flown calibration against the attitude's yaw."""
    h = mag.heading_check
    if h is None:
        return []
    r = h["rms_deg"]
    out = ["  Heading against the vehicle's attitude",
           f"    {h['reference']} yaw, RMS  flown {r['flown']:.2f} deg, magcal {r['magcal']:.2f} deg; difference "
           f"{h['difference_deg']:+.2f} +- {h['difference_std_deg']:.2f} deg over {h['folds']} time folds: "
           f"{h['verdict']}"]
    if not h.get("exported", True):
        out += textwrap.wrap(f"left out of the firmware parameter file: {h['left_out_reason']} (magcal fit "
                             "--export-worse writes it)", 100, initial_indent="    ", subsequent_indent="    ")
    return out


def widening(result: RunResult, mag_id: str) -> float | None:
    """How far the fit widened this magnetometer's uncertainties for residuals correlated in time (None: not)."""
    factors = [float(f.evidence["max_factor"]) for f in result.findings
               if f.code == "correlated_residuals" and f.evidence.get("sensor") == mag_id and "max_factor" in f.evidence]
    return max(factors) if factors else None


def widening_sentence(factor: float) -> str:
    """The widening as the report's finding: its number, why, and that the stds above include it."""
    return (f"widened up to {factor:.1f}x: the residuals are correlated in time beyond the noise model, and the "
            "stds above include it")


def held_sentence(mag: MagCalibration) -> str:
    """One sentence on a partial calibration: what was held, at what, and why."""
    names = ", ".join(str(h["parameter"]) for h in mag.held)
    sources = "; ".join(sorted({str(h["source"]) for h in mag.held}))
    return (f"Partial calibration: this log's motion cannot determine {names}, so they are held at their prior, "
            "with its doubt as their std, and the rest is estimated from the data; a recording with more tilt in "
            f"every direction would determine them too. Their prior: {sources}.")


class TextReport:
    """report.txt."""

    name: ClassVar[str] = "report"
    files: ClassVar[tuple[str, ...]] = ("report.txt",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Write the text report."""
        return [write_text(outdir / self.files[0], render(result))]


def fmt_param(value: Any, std: Any) -> str:
    """'v +- s' for a number or a vector (std may be missing)."""
    if isinstance(value, list) and value and not isinstance(value[0], list):
        s = std if isinstance(std, list) else [float("nan")] * len(value)
        return "[" + ", ".join(f"{v:.4g} +- {e:.2g}" for v, e in zip(value, s, strict=False)) + "]"
    if isinstance(value, (int, float)):
        return f"{value:.4g}" + (f" +- {std:.2g}" if isinstance(std, (int, float)) else "")
    return str(value)


def by_effect(effects: tuple[dict[str, Any], ...]) -> dict[str, list[dict[str, Any]]]:
    """The document's effects[] grouped by effect id, in the order each id first appears."""
    out: dict[str, list[dict[str, Any]]] = {}
    for e in effects:
        out.setdefault(str(e.get("id")), []).append(e)
    return out


def physics(eid: str, entries: list[dict[str, Any]]) -> str:
    """What an effect is, said once for all its sensors; with the recording that separates it from the rivals a log
    could not tell it apart from."""
    known = eid in registry.EFFECTS
    text = registry.get(eid).physics_left_out if known else str(entries[0].get("physics_left_out", ""))
    rivals = sorted({r for e in entries if e.get("status") == "ambiguous" for r in e.get("confounded_with") or ()})
    if rivals and known:
        text += (f" To tell it apart from {' or '.join(rivals)}, record "
                 f"{registry.get(eid).separating_experiment}.")
    return text


def effect_line(e: dict[str, Any]) -> str:
    """One sensor's verdict on an effect: status and test, then the estimates with std and unit, then why."""
    test = e.get("test") or {}
    p = test.get("p_value")
    kind = str(test.get("kind"))
    head = f"{e.get('sensor')}: {str(e.get('status')).replace('_', ' ')}"
    if isinstance(p, float) and np.isfinite(p):
        head += f", {TESTS.get(kind, kind)} {p_is(p)}"
    std, units_of = e.get("std") or {}, e.get("units") or {}
    parts = [f"{k} = {fmt_param(v, std.get(k))}{unit_suffix(units_of.get(k))}"
             for k, v in (e.get("params") or {}).items()]
    return "; ".join([head, *parts, *([str(e["reason"])] if e.get("reason") else [])])


def render_effects(effects: tuple[dict[str, Any], ...]) -> list[str]:
    """Every effect considered: what it is, once, then one line per sensor it was tested on."""
    lines = []
    for eid, entries in by_effect(effects).items():
        lines += textwrap.wrap(f"{eid}: {physics(eid, entries)}", 100, initial_indent="  ", subsequent_indent="    ")
        lines += [f"    - {effect_line(e)}" for e in entries]
    return lines
