"""The Summary section: the verdict, the key numbers per magnetometer and what to do next."""

from __future__ import annotations

from html import escape
from pathlib import Path

from magcal_cli import units
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import anchor, badge, num
from magcal_cli.writers.report.text import DISPLAY, methods_line
from magcal_cli.writers.report.verdict import LEVELS, next_steps, overall


def render(ctx: Context) -> str:
    """The verdict, the key numbers per magnetometer (each linked to its section) and what to do next."""
    result, verdicts = ctx.result, ctx.verdicts
    cal = result.calibration
    level = overall(verdicts)
    if cal.refused and level == "good":          # a compass of the log could not be calibrated: not all is well
        level = "check"
    words = {"good": "ready to use", "check": "usable, with caveats", "poor": "not usable; record again"}
    by_level = {lv: [v.mag_id for v in verdicts if v.level == lv] for lv in LEVELS}
    parts = [f"{words[lv]} ({', '.join(ids)})" if len(verdicts) > 1 else words[lv]
             for lv, ids in by_level.items() if ids]
    n = len(verdicts)
    head = (f"{n} magnetometer{'s' if n != 1 else ''} calibrated from {Path(cal.source.path).name} with "
            f"{methods_line(cal)}: {'; '.join(parts)}.")
    if cal.refused:
        head += (f" {len(cal.refused)} refused ({', '.join(r['id'] for r in cal.refused)}): no method could "
                 "calibrate {}.".format("it" if len(cal.refused) == 1 else "them"))
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
            f"<td>{num(v.raw_norm_pct, '{:.2f}')} &rarr; {num(m.get('field_norm_rms_pct'), '{:.3f}')}</td>"
            f"<td>{num(None if rms is None else rms * f, '{:.3g}', unit)}</td>"
            f"<td>{num(m.get('coverage_pct'), '{:.0f}', '%')}</td>"
            f"<td>{num(m.get('misalignment_deg'), '{:.2f}')} &plusmn; {num(m.get('misalignment_std_deg'), '{:.2f}')}"
            f"</td><td>{num(m.get('heading_std_deg'), '{:.2f}')}</td>"
            f"<td>{'; '.join(escape(r) for r in v.reasons) or 'no caveats'}</td></tr>")
    rows += [f"<tr><td>{escape(r['id'])}</td><td>{badge('poor', 'refused')}</td><td colspan='5'>not calibrated"
             f"</td><td>{escape(r['reason'])}; to fix: {escape(r['advice'])}</td></tr>" for r in cal.refused]
    table = ("<table class='grid'><thead><tr><th>magnetometer</th><th>verdict</th><th>field strength error "
             "raw &rarr; calibrated [% RMS]</th><th>residual RMS</th><th>coverage</th><th>misalignment [deg]</th>"
             "<th>heading 1&sigma; [deg]</th><th>why</th></tr></thead><tbody>" + "".join(rows) + "</tbody></table>")
    steps = "".join(f"<li>{escape(s)}</li>" for s in next_steps(result))
    return (f"<section id='{ctx.anchor}' class='card {level}'><h2>Summary {badge(level, LEVELS[level])}</h2>"
            f"<p class='lead'>{escape(head)}</p>{table}<h3>What to do next</h3><ol>{steps}</ol></section>")
