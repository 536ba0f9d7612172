"""The HTML pieces the sections share: numbers, matrices, key-value tables, badges, anchors and figures."""

from __future__ import annotations

from html import escape

import numpy as np
import numpy.typing as npt

from magcal_cli.writers.report.plots import Plot


def num(x: float | None, fmt: str = "{:.3g}", unit: str = "") -> str:
    """A number for a table cell ('n/a' when missing)."""
    if x is None or not np.isfinite(x):
        return "<span class='muted'>n/a</span>"
    return escape(fmt.format(x) + (f" {unit}" if unit else ""))


def pm(v: npt.ArrayLike, s: npt.ArrayLike, fmt: str = "{:+.3f}", sfmt: str = "{:.3f}") -> str:
    """'v ± s' per component, one per line."""
    pairs = zip(np.ravel(v), np.ravel(s), strict=True)
    return "<br>".join(escape(fmt.format(a)) + " &plusmn; " + escape(sfmt.format(b)) for a, b in pairs)


def matrix(m: npt.ArrayLike, fmt: str) -> str:
    """A 3x3 matrix as a small borderless table."""
    body = "".join("<tr>" + "".join(f"<td>{escape(fmt.format(x))}</td>" for x in r) + "</tr>" for r in np.asarray(m))
    return f"<table class='matrix'>{body}</table>"


def rows(pairs: list[tuple[str, str]]) -> str:
    """A two-column table of (escaped label, HTML value) rows."""
    body = "".join(f"<tr><th>{escape(k)}</th><td>{v}</td></tr>" for k, v in pairs)
    return f"<table class='kv'>{body}</table>"


def badge(level: str, text: str) -> str:
    """A coloured status word."""
    return f"<span class='badge {escape(level)}'>{escape(text)}</span>"


def anchor(mag_id: str) -> str:
    """An id attribute for a magnetometer's section."""
    return "".join(c if c.isalnum() else "-" for c in mag_id).strip("-") or "mag"


def figures(plots: list[Plot], who: str) -> str:
    """The plots, each with its caption, in a `plots` block."""
    figs = "".join(f"<figure><figcaption><b>{escape(p.title)}.</b> {escape(p.caption)}</figcaption>"
                   f"<img src='{p.uri}' alt='{escape(who)}: {escape(p.title)}'></figure>" for p in plots)
    return f"<div class='plots'>{figs}</div>"
