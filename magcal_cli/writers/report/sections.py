"""The HTML report's sections, each a function of the run returning escaped HTML."""

from __future__ import annotations

from html import escape
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from magcal_cli import so3, units
from magcal_cli.calibration.types import MagCalibration
from magcal_cli.findings import Severity
from magcal_cli.timing import sentence
from magcal_cli.writers.report.plots import Plot
from magcal_cli.writers.report.summary import LEVELS, Group, Verdict, next_steps, overall
from magcal_cli.writers.report.text import DISPLAY, METHOD_NAMES, fmt_param, held_sentence, vec

if TYPE_CHECKING:
    from magcal_cli.pipeline import RunResult

#: effect status -> the badge's CSS class
STATUS_CLASS = {"accepted": "good", "ambiguous": "check", "rejected": "muted", "not_testable": "muted"}


def _num(x: float | None, fmt: str = "{:.3g}", unit: str = "") -> str:
    """A number for a table cell ('n/a' when missing)."""
    if x is None or not np.isfinite(x):
        return "<span class='muted'>n/a</span>"
    return escape(fmt.format(x) + (f" {unit}" if unit else ""))


def _pm(v: npt.ArrayLike, s: npt.ArrayLike, fmt: str = "{:+.3f}", sfmt: str = "{:.3f}") -> str:
    """'v ± s' per component, one per line."""
    pairs = zip(np.ravel(v), np.ravel(s), strict=True)
    return "<br>".join(escape(fmt.format(a)) + " &plusmn; " + escape(sfmt.format(b)) for a, b in pairs)


def _matrix(m: npt.ArrayLike, fmt: str) -> str:
    """A 3x3 matrix as a small borderless table."""
    rows = "".join("<tr>" + "".join(f"<td>{escape(fmt.format(x))}</td>" for x in r) + "</tr>" for r in np.asarray(m))
    return f"<table class='matrix'>{rows}</table>"


def _rows(pairs: list[tuple[str, str]]) -> str:
    """A two-column table of (escaped label, HTML value) rows."""
    body = "".join(f"<tr><th>{escape(k)}</th><td>{v}</td></tr>" for k, v in pairs)
    return f"<table class='kv'>{body}</table>"


def badge(level: str, text: str) -> str:
    """A coloured status word."""
    return f"<span class='badge {escape(level)}'>{escape(text)}</span>"


def summary(result: RunResult, verdicts: list[Verdict]) -> str:
    """The verdict, the key numbers per magnetometer and what to do next."""
    cal = result.calibration
    level = overall(verdicts)
    words = {"good": "ready to use", "check": "usable, with caveats", "poor": "not usable; record again"}
    by_level = {lv: [v.mag_id for v in verdicts if v.level == lv] for lv in LEVELS}
    parts = [f"{words[lv]} ({', '.join(ids)})" if len(verdicts) > 1 else words[lv]
             for lv, ids in by_level.items() if ids]
    n = len(verdicts)
    head = (f"{n} magnetometer{'s' if n != 1 else ''} calibrated from {Path(cal.source.path).name} with "
            f"{cal.method}: {'; '.join(parts)}.")
    rows = []
    for v in verdicts:
        m = v.metrics
        unit = DISPLAY.get(cal.magnetometer(v.mag_id).unit, ("", ""))[1]
        f = units.to_si(cal.magnetometer(v.mag_id).unit) * units.from_si(DISPLAY.get(
            cal.magnetometer(v.mag_id).unit, ("tesla", ""))[0])
        rms = m.get("residual_rms")
        rows.append(
            f"<tr><td><a href='#mag-{anchor(v.mag_id)}'>{escape(v.mag_id)}</a></td>"
            f"<td>{badge(v.level, v.label)}</td>"
            f"<td>{_num(v.raw_norm_pct, '{:.2f}')} &rarr; {_num(m.get('field_norm_rms_pct'), '{:.3f}')}</td>"
            f"<td>{_num(None if rms is None else rms * f, '{:.3g}', unit)}</td>"
            f"<td>{_num(m.get('coverage_pct'), '{:.0f}', '%')}</td>"
            f"<td>{_num(m.get('misalignment_deg'), '{:.2f}')} &plusmn; {_num(m.get('misalignment_std_deg'), '{:.2f}')}"
            f"</td><td>{_num(m.get('heading_std_deg'), '{:.2f}')}</td>"
            f"<td>{'; '.join(escape(r) for r in v.reasons) or 'no caveats'}</td></tr>")
    table = ("<table class='grid'><thead><tr><th>magnetometer</th><th>verdict</th><th>field strength error "
             "raw &rarr; calibrated [% RMS]</th><th>residual RMS</th><th>coverage</th><th>misalignment [deg]</th>"
             "<th>heading 1&sigma; [deg]</th><th>why</th></tr></thead><tbody>" + "".join(rows) + "</tbody></table>")
    steps = "".join(f"<li>{escape(s)}</li>" for s in next_steps(result))
    return (f"<section id='summary' class='card {level}'><h2>Summary {badge(level, LEVELS[level])}</h2>"
            f"<p class='lead'>{escape(head)}</p>{table}<h3>What to do next</h3><ol>{steps}</ol></section>")


def anchor(mag_id: str) -> str:
    """An id attribute for a magnetometer's section."""
    return "".join(c if c.isalnum() else "-" for c in mag_id).strip("-") or "mag"


def method(result: RunResult) -> str:
    """How the calibration was computed: method, model, data used, IMU, noise and modelled effects."""
    cal = result.calibration
    still = result.still
    modelled = [f"{e.get('id')} ({e.get('sensor')}, {e.get('status')})" for e in cal.effects
                if e.get("status") in ("accepted", "ambiguous") and e.get("params")]
    imu = cal.imu
    pairs = [("method", escape(METHOD_NAMES.get(cal.method, cal.method))),
             ("model", "y = D R<sup>T</sup> m<sub>n</sub>(dip) + o + e; calibrated unit field "
                       "m<sub>b</sub> = A (y &minus; b), A = D<sup>&minus;1</sup>, b = o (IMU body frame)"),
             ("data", escape(f"{cal.source.end_s - cal.source.start_s:.1f} s of {Path(cal.source.path).name} "
                             f"({cal.source.format}); {len(still.segments)} still segments "
                             f"({sum(s.end - s.start for s in still.segments):.1f} s)")),
             ("IMU", escape(imu.id)),
             ("noise per sample", escape(f"accelerometer {vec(still.acc_noise, '{:.3g}')} m/s^2, "
                                         f"gyroscope {vec(still.gyr_noise, '{:.3g}')} rad/s")),
             ("modelled effects", escape(", ".join(modelled) or "none beyond the base model"))]
    if imu.gyroscope_bias is not None:
        std = imu.gyroscope_bias_std if imu.gyroscope_bias_std is not None else np.full(3, np.nan)
        pairs.append(("gyroscope bias [rad/s]", _pm(imu.gyroscope_bias, std, "{:+.5f}", "{:.5f}")))
    if imu.accelerometer_bias is not None:
        std = imu.accelerometer_bias_std if imu.accelerometer_bias_std is not None else np.full(3, np.nan)
        pairs.append(("accelerometer bias [m/s^2]", _pm(imu.accelerometer_bias, std)))
    return f"<section id='method'><h2>Method</h2>{_rows(pairs)}</section>"


def _diagnosis_block(result: RunResult, mag_id: str) -> dict[str, Any] | None:
    """The diagnosis entry of one magnetometer, if the run diagnosed it."""
    diag = result.calibration.diagnosis or {}
    return next((b for b in diag.get("sensors", [diag]) if b.get("sensor") == mag_id), None)


def magnetometer(result: RunResult, mag: MagCalibration, verdict: Verdict, plots: list[Plot],
                 groups: list[Group]) -> str:
    """One magnetometer: its parameters, quality, diagnosis and advice beside its plots."""
    unit, sym = DISPLAY.get(mag.unit, (mag.unit, mag.unit))
    f = units.to_si(mag.unit) * units.from_si(unit)
    misalign = float(np.rad2deg(so3.angle(mag.misalignment)))
    w_sd = float(np.rad2deg(np.sqrt(max(np.trace(mag.misalignment_cov()), 0.0))))
    rpy = np.rad2deg(so3.as_rpy(mag.misalignment))
    pairs = [("hard iron b [" + sym + "]", _pm(mag.o * f, mag.std_of("o") * f)),
             ("field strength", escape(f"{mag.field_strength * f:.3f} {sym} ({mag.field_strength_source})")),
             ("dip", escape(f"{mag.dip_deg:.2f} ± {float(mag.std_of('dip')):.2f} deg")),
             ("misalignment", escape(f"{misalign:.2f} ± {w_sd:.2f} deg (roll, pitch, yaw "
                                     f"{vec(rpy, '{:+.2f}')} deg)")),
             ("soft iron P/|F|", _matrix(mag.soft_iron, "{:+.4f}")),
             (f"A = D^-1 [1/{sym}]", _matrix(mag.A / f, "{:+.6f}"))]
    q = mag.quality
    if q is not None:
        pairs += [("field strength spread", escape(f"raw {verdict.raw_norm_pct:.2f} % → calibrated "
                                                   f"{q.field_norm_rms_pct:.3f} % RMS ({q.samples} readings)")),
                  ("model residual", escape(f"{q.residual_rms * f:.4g} {sym} RMS")),
                  ("coverage", escape(f"{q.coverage_pct:.0f} % of the field directions")),
                  ("solver", escape(f"{'converged' if q.converged else 'NOT converged'} after {q.iterations} "
                                    "iterations"))]
    text = [f"<h3>{badge(verdict.level, verdict.label)}</h3>", _rows(pairs)]
    if mag.held:
        text.append(f"<p class='note'>{escape(held_sentence(mag))}</p>")
    block = _diagnosis_block(result, mag.id)
    if block is not None:
        text.append(f"<h4>What the recording says</h4><p>{escape(str(block.get('summary', '')))}</p>")
    mine = [m for g in groups if g.severity is Severity.WARNING for m in g.messages if mag.id in m]
    if mine:
        text.append("<h4>Warnings</h4><ul>" + "".join(f"<li>{escape(m)}</li>" for m in mine) + "</ul>")
    return (f"<section id='mag-{anchor(mag.id)}' class='mag'><h2>Magnetometer {escape(mag.id)} "
            f"<small>(log unit: {escape(mag.unit)})</small></h2><div class='pair'><div class='text'>{''.join(text)}"
            f"</div>{_figures(plots, mag.id)}</div></section>")


def _figures(plots: list[Plot], who: str) -> str:
    """The plots, each with its caption, in a `plots` block."""
    figs = "".join(f"<figure><figcaption><b>{escape(p.title)}.</b> {escape(p.caption)}</figcaption>"
                   f"<img src='{p.uri}' alt='{escape(who)}: {escape(p.title)}'></figure>" for p in plots)
    return f"<div class='plots'>{figs}</div>"


def effects(result: RunResult, plots: list[Plot]) -> str:
    """Every effect the run considered: status, parameters with std and units, test and why; then `plots` (those of
    the IMU's effects: the magnetometers' are beside each magnetometer)."""
    rows = []
    for e in result.calibration.effects:
        params, std, unit_of = e.get("params") or {}, e.get("std") or {}, e.get("units") or {}
        values = "<br>".join(escape(f"{k} = {fmt_param(v, std.get(k))} {unit_of.get(k, '')}".rstrip())
                             for k, v in params.items())
        p = (e.get("test") or {}).get("p_value")
        status = str(e.get("status"))
        rows.append(f"<tr><td>{escape(str(e.get('id')))}</td><td>{escape(str(e.get('sensor')))}</td>"
                    f"<td>{badge(STATUS_CLASS.get(status, 'muted'), status)}</td><td>{values or '&ndash;'}</td>"
                    f"<td>{_num(p if isinstance(p, float) else None, '{:.2g}')}</td>"
                    f"<td>{escape(str(e.get('reason') or ''))}<br><span class='muted'>"
                    f"{escape(str(e.get('physics_left_out') or ''))}</span></td></tr>")
    if not rows:
        return ("<section id='effects'><h2>Effects</h2><p>The base model only: no effect was tested "
                "(<code>--effects none</code> or a method without effect terms).</p></section>")
    return ("<section id='effects'><h2>Effects beyond the base model</h2><table class='grid'><thead><tr><th>effect"
            "</th><th>sensor</th><th>status</th><th>estimate</th><th>p</th><th>test and physics</th></tr></thead>"
            "<tbody>" + "".join(rows) + "</tbody></table>" + (_figures(plots, "IMU") if plots else "") + "</section>")


def diagnosis(result: RunResult) -> str:
    """The mismatch diagnosis per magnetometer: simulation check before and after, where and what it located."""
    diag = result.calibration.diagnosis
    if not diag:
        return ("<section id='diagnosis'><h2>Diagnosis</h2><p>Not run (it runs with <code>--effects auto</code> "
                "and the joint MAP method).</p></section>")
    rows = []
    for b in diag.get("sensors", [diag]):
        loc = b.get("located") or {}
        before, after = (b.get("ppc") or {}).get("global_p"), (b.get("ppc_after") or {}).get("global_p")
        top = ", ".join(f"{t.get('statistic')} (z {t.get('z')})" for t in (b.get("ppc") or {}).get("top", []))
        where = "; ".join(f"{a:g}–{z:g} s" for a, z in loc.get("time_windows_s", [])) or "none"
        band = loc.get("band_hz")
        rows.append(f"<tr><td>{escape(str(b.get('sensor')))}</td><td>{_num(before, '{:.3g}')} &rarr; "
                    f"{_num(after, '{:.3g}')}</td><td>{escape(', '.join(loc.get('axes', [])) or '–')}</td>"
                    f"<td>{escape(where)}</td><td>{escape('–' if not band else f'{band[0]:g}–{band[1]:g} Hz')}</td>"
                    f"<td>{escape(top)}</td></tr>")
    return ("<section id='diagnosis'><h2>Diagnosis</h2><p>A simulation check compares the recording with "
            "replicates simulated from the fitted model; a small p says the model leaves something out, and the "
            "located axes, time windows, frequency band and channels say where.</p><table class='grid'><thead><tr>"
            "<th>sensor</th><th>p before &rarr; after</th><th>axes</th><th>time windows</th><th>band</th>"
            "<th>largest statistics</th></tr></thead><tbody>" + "".join(rows) + "</tbody></table></section>")


def warnings(groups: list[Group]) -> str:
    """Every warning and note in full, grouped by kind (the terminal prints a short list)."""
    if not groups:
        return "<section id='warnings'><h2>Warnings and notes</h2><p>None.</p></section>"
    parts = []
    for g in groups:
        who = f" <small>({escape(', '.join(g.sensors))})</small>" if g.sensors else ""
        level = "check" if g.severity is Severity.WARNING else "muted"
        items = "".join(f"<li>{escape(m)}</li>" for m in g.messages)
        parts.append(f"<h3>{badge(level, g.severity.value)} {escape(g.title)} &times; {len(g.messages)}{who}</h3>"
                     f"<ul>{items}</ul>")
    return "<section id='warnings'><h2>Warnings and notes</h2>" + "".join(parts) + "</section>"


def provenance(result: RunResult, text_report: str) -> str:
    """Where the numbers came from, and the whole text report."""
    cal = result.calibration
    src = cal.source
    pairs = [("log", escape(src.path)), ("format", escape(src.format)), ("sha256", f"<code>{escape(src.sha256)}</code>"),
             ("time span used", escape(f"{src.start_s:.2f} – {src.end_s:.2f} s")),
             *([("sample timing", escape(sentence(src.timing)))] if src.timing else []),
             ("magcal", escape(f"{cal.magcal_version}, {cal.created_utc}")),
             ("files", "calibration.json / calibration.yaml (<code>magcal.calibration/1</code>), report.txt")]
    return (f"<section id='provenance'><h2>Provenance</h2>{_rows(pairs)}<details><summary>The text report "
            f"(report.txt)</summary><pre>{escape(text_report)}</pre></details></section>")
