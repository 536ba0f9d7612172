"""The Diagnosis section: the simulation check per magnetometer, before and after, and what it located."""

from __future__ import annotations

from html import escape

from magcal_cli.diagnose.summary import p_text
from magcal_cli.writers.report.sections.base import Context


def render(ctx: Context) -> str:
    """The mismatch diagnosis per magnetometer: simulation check before and after, where and what it located."""
    diag = ctx.result.calibration.diagnosis
    if not diag:
        return (f"<section id='{ctx.anchor}'><h2>Diagnosis</h2><p>Not run (it runs with <code>--effects auto</code> "
                "and the joint MAP method).</p></section>")
    rows = []
    for b in diag.get("sensors", [diag]):
        loc = b.get("located") or {}
        before, after = (b.get("ppc") or {}).get("global_p"), (b.get("ppc_after") or {}).get("global_p")
        top = ", ".join(f"{t.get('statistic')} (z {t.get('z')})" for t in (b.get("ppc") or {}).get("top", []))
        where = "; ".join(f"{a:g}–{z:g} s" for a, z in loc.get("time_windows_s", [])) or "none"
        band = loc.get("band_hz")
        rows.append(f"<tr><td>{escape(str(b.get('sensor')))}</td><td>{escape(p_text(before))} &rarr; "
                    f"{escape(p_text(after))}</td><td>{escape(', '.join(loc.get('axes', [])) or '–')}</td>"
                    f"<td>{escape(where)}</td><td>{escape('–' if not band else f'{band[0]:g}–{band[1]:g} Hz')}</td>"
                    f"<td>{escape(top)}</td></tr>")
    return (f"<section id='{ctx.anchor}'><h2>Diagnosis</h2><p>A simulation check compares the recording with "
            "replicates simulated from the fitted model; a small p says the model leaves something out, and the "
            "located axes, time windows, frequency band and channels say where.</p><table class='grid'><thead><tr>"
            "<th>sensor</th><th>p before &rarr; after</th><th>axes</th><th>time windows</th><th>band</th>"
            "<th>largest statistics</th></tr></thead><tbody>" + "".join(rows) + "</tbody></table></section>")
