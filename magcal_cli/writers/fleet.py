"""The fleet report: one HTML page with a table of every vehicle's compasses and their state, and a trend plot
per compass (each watched parameter over the flights, its uncertainty band and the changes found), drawn with
the report's inline-SVG plotter (writers/report/svg.py): one file, no script."""

from __future__ import annotations

from html import escape

import numpy as np

from magcal_cli.history.entry import utc_text
from magcal_cli.history.fleet import WATCHED, Compass, Fleet, category
from magcal_cli.writers.report.svg import DPI, Axes, Figure

COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")
STATE_COLORS = {"changed": "#f8d0d0", "settled": "#fdf0c8", "new": "#e6e6e6", "steady": "#d8f0d8"}
TITLES = {"hard_iron": "hard iron o [{unit}]", "soft_iron": "soft iron (unitless)",
          "orientation": "orientation [deg]", "interference": "interference [{unit}/A]"}
#: what the panels show: each parameter's change since the compass's first flight, so that series of different
#: size share a panel and a step stands out against the bands
#: the band drawn around each series, in (inflated) standard deviations
BAND_SIGMAS = 2.0
CSS = """body{font-family:DejaVu Sans,Helvetica,Arial,sans-serif;margin:24px;color:#222;max-width:1250px}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}
th{background:#f0f0f0}td.num{text-align:right}h2{margin-top:32px;font-size:17px}p.note{font-size:13px;color:#444}
img{display:block;margin:6px 0 18px 0}"""


def _panel(ax: Axes, c: Compass, group: str, factors: dict[str, float]) -> None:
    """One group's series of a compass: lines with BAND_SIGMAS bands, the changes as red spans."""
    names = [n for n in sorted(c.series) if category(n) == group]
    x = np.arange(1, len(c.flights) + 1, dtype=np.float64)
    for k, n in enumerate(names):
        v, s = c.series[n]
        finite = v[np.isfinite(v)]
        v = v - (finite[0] if finite.size else 0.0)
        s = s * factors.get(n, 1.0)
        color = COLORS[k % len(COLORS)]
        ax.band(x, v - BAND_SIGMAS * s, v + BAND_SIGMAS * s, color, 0.18)
        ax.line(x, v, color, label=n.rsplit(".", 1)[-1])
        ax.dots(x, v, color, 3.0)
    for ch in c.changes:
        if ch.category == group:
            ax.vspan(ch.start + 0.5, ch.start + 1.5, "#d62728", 0.12)
    ax.title = "change of " + TITLES[group].format(unit=c.unit) + " since flight 1"
    ax.xlabel = "flight"
    ax.xlim = (0.5, len(c.flights) + 0.5)
    ax.legend_at, ax.legend_cols = "upper left", min(len(names), 6)


def trend_figure(c: Compass, factors: dict[str, float]) -> Figure | None:
    """A row of panels, one per watched group the compass has."""
    groups = [g for g in WATCHED if any(category(n) == g for n in c.series)]
    if not groups or not c.flights:
        return None
    width, height = 12.5 * DPI, 2.6 * DPI
    fig = Figure(width, height)
    spec = {"left": 0.05, "right": 0.99, "top": 0.88, "bottom": 0.17, "wspace": 0.28, "hspace": 0.0}
    for ax, g in zip(fig.grid(1, len(groups), spec)[0], groups, strict=True):
        _panel(ax, c, g, factors)
    return fig


def _row(c: Compass, k: int) -> str:
    """The table row of a compass."""
    last = c.flights[-1]
    q = last.get("quality") or {}
    groups = c.change_groups()
    change = ""
    if groups:
        at, start, cs = groups[-1]
        change = (f"{', '.join(sorted({x.category for x in cs}))} at flight {start + 1} "
                  f"({escape(c.flights[start]['path'].rsplit('/', 1)[-1])}), alarm at {at + 1}")
    norm, heading = q.get("field_norm_rms_pct"), q.get("heading_std_deg")
    cells = [escape(c.vehicle), escape(c.sensor), str(len(c.flights)),
             f"<b>{c.state}</b>", utc_text(last.get("log_utc")),
             "-" if norm is None else f"{norm:.2f}", "-" if heading is None else f"{heading:.2f}", change]
    style = f" style='background:{STATE_COLORS[c.state]}'"
    anchor = f"<a href='#c{k}'>{cells[0]}</a>"
    return (f"<tr{style}><td>{anchor}</td>" + "".join(f"<td>{x}</td>" for x in cells[1:4])
            + f"<td>{cells[4]}</td><td class='num'>{cells[5]}</td><td class='num'>{cells[6]}</td>"
            f"<td>{cells[7]}</td></tr>")


def html(fleet: Fleet, title: str = "magcal fleet report") -> str:
    """The whole page."""
    order = {"changed": 0, "settled": 1, "new": 2, "steady": 3}
    compasses = sorted(fleet.compasses, key=lambda c: (order[c.state], c.vehicle, c.sensor))
    counts = fleet.counts()
    head = ["VEHICLE", "COMPASS", "FLIGHTS", "STATE", "LAST FLIGHT (UTC)", "FIELD-NORM %", "HEADING STD deg",
            "LAST CHANGE"]
    out = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{escape(title)}</title>"
           f"<style>{CSS}</style></head><body><h1>{escape(title)}</h1>",
           f"<p>{len(fleet.compasses)} compasses on {len({c.vehicle for c in fleet.compasses})} vehicles: "
           + ", ".join(f"{counts[s]} {s}" for s in counts) + ".</p>",
           f"<p class='note'>Change detection: two-sided CUSUM (slack {fleet.slack:g}, threshold "
           f"{fleet.threshold:g}) on each watched parameter, standardised by the flight's reported std times the "
           "fleet's observed flight-to-flight inflation. Plots: each parameter's change since the compass's first "
           "flight; bands are ±2 inflated std; red spans mark the first flight after a change. See docs/fleet.md.</p>",
           "<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>",
           *(_row(c, k) for k, c in enumerate(compasses)), "</table>"]
    out += [f"<p class='note'>Warning: {escape(v)} is identified by SYSID_THISMAV only: vehicles sharing it merge "
            "into one series, and a compass change may be another vehicle's compass.</p>"
            for v in sorted({c.vehicle for c in compasses if c.sysid_only})]
    for k, c in enumerate(compasses):
        fig = trend_figure(c, fleet.inflation)
        out.append(f"<h2 id='c{k}'>{escape(c.vehicle)} · {escape(c.sensor)} · {c.state}</h2>")
        out.append(f"<p class='note'>Vehicle identified by {escape(c.identified_by)}.</p>")
        if fig is not None:
            out.append(f"<img alt='{escape(c.vehicle)} {escape(c.sensor)} trends' width='{fig.width:.0f}' "
                       f"height='{fig.height:.0f}' src='{fig.uri()}'>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"
