"""The Warnings and notes section: every finding in full, grouped by kind."""

from __future__ import annotations

from html import escape

from magcal_cli.findings import Severity
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import badge


def render(ctx: Context) -> str:
    """Every warning and note in full, grouped by kind (the terminal prints a short list)."""
    if not ctx.groups:
        return f"<section id='{ctx.anchor}'><h2>Warnings and notes</h2><p>None.</p></section>"
    parts = []
    for g in ctx.groups:
        who = f" <small>({escape(', '.join(g.sensors))})</small>" if g.sensors else ""
        level = "check" if g.severity is Severity.WARNING else "muted"
        items = "".join(f"<li>{escape(m)}</li>" for m in g.messages)
        parts.append(f"<h3>{badge(level, g.severity.value)} {escape(g.title)} &times; {len(g.messages)}{who}</h3>"
                     f"<ul>{items}</ul>")
    return f"<section id='{ctx.anchor}'><h2>Warnings and notes</h2>" + "".join(parts) + "</section>"
