"""report.html: the text report with plots of the field before and after calibration (PNG, embedded)."""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ..atomic import write_text
from .report import render

if TYPE_CHECKING:
    from ..pipeline import MagSeries, RunResult


def _png(fig: Any) -> str:
    """A figure as a base64 PNG data URI (and close it)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _figures(mag_id: str, series: MagSeries, still: list[tuple[float, float]]) -> list[tuple[str, str]]:
    """(caption, data URI) pairs for one magnetometer."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r_raw = np.linalg.norm(series.raw, axis=1)
    r_cal = np.linalg.norm(series.calibrated, axis=1)
    fig, ax = plt.subplots(figsize=(9, 3.2))
    for t0, t1 in still:
        ax.axvspan(t0, t1, color="0.92", lw=0)
    ax.plot(series.t, 100 * (r_raw / np.mean(r_raw) - 1), lw=0.7, label="raw |y| (relative to its mean)")
    ax.plot(series.t, 100 * (r_cal - 1), lw=0.7, label="calibrated |A (y - b)|")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("field strength error [%]")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    out = [(f"{mag_id}: field strength over time; a good calibration is flat at 0 (grey: still segments)",
            _png(fig))]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.4), gridspec_kw={"width_ratios": [1.6, 1]})
    u = series.calibrated / np.maximum(r_cal[:, None], 1e-12)
    step = max(1, len(u) // 5000)
    az = np.degrees(np.arctan2(u[::step, 1], u[::step, 0]))
    el = np.degrees(np.arcsin(np.clip(u[::step, 2], -1, 1)))
    ax1.scatter(az, el, s=2, alpha=0.5)
    ax1.set_xlim(-180, 180)
    ax1.set_ylim(-90, 90)
    ax1.set_xticks(range(-180, 181, 60))
    ax1.set_yticks(range(-90, 91, 30))
    ax1.grid(alpha=0.3)
    ax1.set_xlabel("azimuth in the body frame [deg]")
    ax1.set_ylabel("elevation [deg]")
    ax1.set_title("field directions seen (coverage)", fontsize=9)
    ax2.hist(100 * (r_cal - 1), bins=60, color="tab:orange")
    ax2.set_xlabel("calibrated field strength error [%]")
    ax2.set_ylabel("readings")
    ax2.set_title("residual field strength error", fontsize=9)
    fig.tight_layout()
    out.append((f"{mag_id}: where the field pointed in the body frame (empty areas are orientations the "
                "recording never visited) and the spread of the calibrated field strength", _png(fig)))
    return out


class HtmlReport:
    """report.html: the report text and its plots in one self-contained file."""

    name: ClassVar[str] = "plots"
    files: ClassVar[tuple[str, ...]] = ("report.html",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Render the plots and write the HTML report."""
        still = [(s.start, s.end) for s in result.still.segments]
        parts = ["<!doctype html><html><head><meta charset='utf-8'><title>magcal report</title>",
                 "<style>body{font-family:sans-serif;max-width:960px;margin:2em auto}"
                 "pre{background:#f6f6f6;padding:1em;overflow-x:auto}</style></head><body>",
                 "<h1>magcal calibration report</h1>"]
        diag = result.calibration.diagnosis
        if diag:                                  # the paragraph a pilot reads first
            parts += [f"<p>{html.escape(str(b.get('summary', '')))}</p>" for b in diag.get("sensors", [diag])]
        parts.append(f"<pre style='white-space:pre-wrap'>{html.escape(render(result))}</pre>")
        for mag_id, series in result.series.items():
            for caption, uri in _figures(mag_id, series, still):
                parts.append(f"<figure><img src='{uri}' alt='{html.escape(caption)}' style='max-width:100%'>"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        parts.append("</body></html>")
        return [write_text(outdir / self.files[0], "\n".join(parts) + "\n")]
