"""report.html: one self-contained page (no scripts, no external resources) people can share and open offline."""

from __future__ import annotations

from html import escape
from itertools import accumulate
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from magcal_cli.atomic import write_text
from magcal_cli.progress import active, current, steps
from magcal_cli.writers.report.sections import (
    diagnosis,
    effects,
    heading,
    magnetometer,
    method,
    notes,
    provenance,
    summary,
)
from magcal_cli.writers.report.sections.base import Context, Section
from magcal_cli.writers.report.verdict import groups, verdicts

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult

CSS = """
:root{--fg:#1d2330;--muted:#6b7280;--line:#e3e6ea;--bg:#f7f8fa;--good:#1e7d32;--check:#a15c00;--poor:#b3261e}
*{box-sizing:border-box}
body{font:14px/1.5 system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;color:var(--fg);
 margin:0;background:#fff;overflow-wrap:break-word}
p,li,pre,figcaption,code{overflow-wrap:anywhere}
main{max-width:1260px;margin:0 auto;padding:24px 28px 60px}
header h1{font-size:24px;margin:0 0 4px}
header p{margin:0;color:var(--muted)}
nav{margin:14px 0 18px;font-size:13px}
nav a{margin-right:14px;color:#1f5fa8;text-decoration:none}
h2{font-size:19px;margin:34px 0 10px;padding-bottom:4px;border-bottom:1px solid var(--line)}
h2 small{font-weight:normal;color:var(--muted);font-size:13px}
h3{font-size:15px;margin:16px 0 6px}
h4{font-size:14px;margin:14px 0 4px}
p,li{max-width:75ch}
.card{border:1px solid var(--line);border-left:6px solid var(--muted);border-radius:6px;padding:4px 18px 10px;
 background:var(--bg)}
.card.good{border-left-color:var(--good)}.card.check{border-left-color:var(--check)}
.card.poor{border-left-color:var(--poor)}
.card h2{border:0}
.lead{font-size:16px}
.badge{display:inline-block;white-space:nowrap;padding:1px 9px;border-radius:10px;font-size:12px;font-weight:600;color:#fff;
 background:var(--muted);vertical-align:middle}
.badge.good{background:var(--good)}.badge.check{background:var(--check)}.badge.poor{background:var(--poor)}
.badge.muted{background:#9aa1ab}
.muted{color:var(--muted)}
table{border-collapse:collapse;font-variant-numeric:tabular-nums}
table.grid{width:100%;font-size:13px;margin:8px 0}
table.grid th,table.grid td{border-bottom:1px solid var(--line);padding:5px 8px;text-align:left;vertical-align:top}
table.grid thead th{background:#eef0f3;font-weight:600;overflow-wrap:normal}
table.kv th{font-weight:600;text-align:left;padding:4px 12px 4px 0;vertical-align:top;white-space:nowrap;
 color:#374151}
table.kv td{padding:4px 0;vertical-align:top}
table.matrix td{padding:0 10px 0 0;white-space:nowrap;font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12.5px}
.pair{display:grid;grid-template-columns:minmax(360px,1fr) minmax(0,2fr);gap:24px;align-items:start}
.plots figure{margin:0 0 18px}
.plots img{width:100%;height:auto;border:1px solid var(--line);border-radius:4px}
figcaption{font-size:12.5px;color:#374151;margin-bottom:4px}
.note{background:#fff7e6;border-left:3px solid var(--check);padding:6px 10px}
pre{white-space:pre-wrap;overflow-wrap:anywhere;background:var(--bg);border:1px solid var(--line);padding:12px;
 font-size:12px}
code{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12.5px}
details summary{cursor:pointer;color:#1f5fa8;margin:10px 0}
@media (max-width:900px){.pair{grid-template-columns:1fr}}
@media print{nav{display:none}.pair{grid-template-columns:1fr}}
"""


#: the progress line's stage while the page is rendered (one step per figure)
STAGE = "writing report.html"


#: the page's sections in order: its navigation links and its body both come from here, so a new section is its
#: module under sections/ and one line
SECTIONS: tuple[Section, ...] = (
    Section("summary", "Summary", summary.render),
    Section("method", "Method", method.render),
    Section("mag", "Magnetometer", magnetometer.render, per_magnetometer=True),
    Section("heading", "Heading check", heading.render),
    Section("effects", "Effects", effects.render),
    Section("diagnosis", "Diagnosis", diagnosis.render),
    Section("warnings", "Warnings", notes.render),
    Section("provenance", "Provenance", provenance.render),
)


def render_html(result: RunResult) -> str:
    """The whole page: a link per section, then the sections, in the order of SECTIONS."""
    cal = result.calibration
    page = Context(result, verdicts(result), groups(result.findings, [m.id for m in cal.magnetometers]))
    todo = [(s, c) for s in SECTIONS for c in s.contexts(page)]
    # the progress line's share of each section: a magnetometer's draws four figures, the others one at most
    share = list(accumulate((1.0 if s.per_magnetometer else 0.25 for s, _ in todo), initial=0.0))
    hook, shown = current(), []
    for k, (s, c) in enumerate(todo):          # each figure drawn moves the progress line (plots.png)
        with active(steps(hook, STAGE, share[k] / share[-1], share[k + 1] / share[-1])):
            body = s.render(c)
        if body is not None:
            shown.append((c, body))
    hook(STAGE, 1.0, 1.0)
    nav = "".join(f"<a href='#{escape(c.anchor)}'>{escape(c.title)}</a>" for c, _ in shown)
    name = Path(cal.source.path).name
    return ("<!doctype html>\n<html lang='en'><head><meta charset='utf-8'>"
            "<meta name='viewport' content='width=device-width,initial-scale=1'>"
            f"<title>magcal report: {escape(name)}</title><style>{CSS}</style></head><body><main>"
            f"<header><h1>Magnetometer calibration: {escape(name)}</h1><p>magcal {escape(cal.magcal_version)}, "
            f"{escape(cal.created_utc)}, method {escape(cal.method)}</p></header><nav>{nav}</nav>"
            + "\n".join(body for _, body in shown) + "</main></body></html>\n")


class HtmlReport:
    """report.html: the report with its plots in one self-contained file."""

    name: ClassVar[str] = "html"
    files: ClassVar[tuple[str, ...]] = ("report.html",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Render the plots and write the HTML report."""
        return [write_text(outdir / self.files[0], render_html(result))]
