"""The Provenance section: where the numbers came from, and the whole text report."""

from __future__ import annotations

from html import escape

from magcal_cli.timing import sentence
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import rows
from magcal_cli.writers.report.text import render as render_text


def render(ctx: Context) -> str:
    """Where the numbers came from, and the whole text report."""
    cal = ctx.result.calibration
    src = cal.source
    pairs = [("log", escape(src.path)), ("format", escape(src.format)), ("sha256", f"<code>{escape(src.sha256)}</code>"),
             ("time span used", escape(f"{src.start_s:.2f} – {src.end_s:.2f} s")),
             *([("sample timing", escape(sentence(src.timing)))] if src.timing else []),
             ("magcal", escape(f"{cal.magcal_version}, {cal.created_utc}")),
             ("files written", escape(", ".join(ctx.result.outputs) or "report.html")),
             ("schema", "calibration.json and calibration.yaml: <code>magcal.calibration/1</code>")]
    return (f"<section id='{ctx.anchor}'><h2>Provenance</h2>{rows(pairs)}<details><summary>The text report "
            f"(report.txt)</summary><pre>{escape(render_text(ctx.result))}</pre></details></section>")
