"""The Heading check section: each compass's heading against the vehicle's attitude, magcal's vs the flown one."""

from __future__ import annotations

from html import escape
from typing import TYPE_CHECKING

import numpy as np

from magcal_cli.firmware.heading import error_series
from magcal_cli.writers.report.plots import CAL, REF, Plot, embed, figure, legend_above, margins, robust_ylim
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import badge, figures, num

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult
    from magcal_cli.calibration.types import MagCalibration

#: verdict -> badge colour
LEVEL = {"better": "good", "same": "muted", "worse": "poor"}


def render(ctx: Context) -> str:
    """A table of the compasses the heading check measured, or why none was."""
    mags = [m for m in ctx.result.calibration.magnetometers if m.heading_check is not None]
    if not mags:
        return (f"<section id='{ctx.anchor}'><h2>Heading against the vehicle's attitude</h2><p>Not measured: the "
                "log has no attitude estimate of the vehicle (ATT, vehicle_attitude) or no calibration it flew "
                "with, or too few samples line up with it.</p></section>")
    body = []
    for m in mags:
        h = m.heading_check or {}
        left = "written" if h.get("exported", True) else "left out (the vehicle keeps its own)"
        body.append(f"<tr><td>{escape(m.id)}</td><td>{num(h['rms_deg']['flown'], '{:.2f}', 'deg')}</td>"
                    f"<td>{num(h['rms_deg']['magcal'], '{:.2f}', 'deg')}</td>"
                    f"<td>{num(h['difference_deg'], '{:+.2f}')} &plusmn; {num(h['difference_std_deg'], '{:.2f}')} deg"
                    f"</td><td>{badge(LEVEL.get(h['verdict'], 'muted'), h['verdict'])}</td>"
                    f"<td>{escape(left)}</td></tr>")
    h0 = mags[0].heading_check or {}
    return (f"<section id='{ctx.anchor}'><h2>Heading against the vehicle's attitude</h2>"
            f"<p>Heading error RMS of each compass, corrected with the calibration the vehicle flew with and with "
            f"magcal's, against the yaw of {escape(str(h0.get('reference', '')))} (levelled with its roll and "
            f"pitch, one constant offset removed per calibration). Difference: magcal &minus; flown, mean over "
            f"{h0.get('folds', '')} contiguous time folds &plusmn; its standard error. A compass worse than the "
            "flown calibration is left out of the firmware parameter file unless <code>--export-worse</code>. "
            "Where the attitude is steered by that compass (the primary), it leans towards the flown "
            "calibration.</p><table><tr><th>compass</th><th>flown</th><th>magcal</th><th>difference</th>"
            "<th>verdict</th><th>firmware file</th></tr>" + "".join(body) + "</table>"
            + figures(_plots(ctx.result, mags), "heading check") + "</section>")


def _plots(result: RunResult, mags: list[MagCalibration]) -> list[Plot]:
    """One figure: each compass's heading error over time, flown and magcal's (mean removed)."""
    panels = [(m, s) for m in mags if (s := error_series(result.recording, result.calibration, m.id)) is not None]
    if not panels:
        return []
    height = 0.6 + 1.7 * len(panels)
    fig = figure(height)
    for (m, s), (ax,) in zip(panels, fig.grid(len(panels), 1, margins(height, hspace=0.75)), strict=True):
        flown, mine = np.rad2deg(s.flown), np.rad2deg(s.magcal)
        # a NaN after each gap of over a second (fast turns left out) breaks the lines there
        cut = np.flatnonzero(np.diff(s.t) > 1.0) + 1
        t = np.insert(s.t, cut, 0.5 * (s.t[cut - 1] + s.t[cut]))       # x stays finite: the envelope bins by it
        ax.line(t, np.insert(flown, cut, np.nan), REF, label="flown")
        ax.line(t, np.insert(mine, cut, np.nan), CAL, label="magcal")
        robust_ylim(ax, flown, mine)
        ax.title, ax.ylabel, ax.xlabel = m.id, "error (deg)", "time (s)"
        legend_above(ax, 2)
    return [Plot("Heading error against the vehicle's attitude",
                 "The heading of each compass, corrected as flown (grey) and with magcal's calibration (blue), "
                 "minus the attitude's yaw, each with its mean removed; fast turns left out.", embed(fig))]
