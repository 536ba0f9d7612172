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

    raw = series.raw
    centre = np.median(raw, axis=0)
    r_raw = np.linalg.norm(raw - centre, axis=1)
    r_cal = np.linalg.norm(series.calibrated, axis=1)
    fig, ax = plt.subplots(figsize=(9, 3.2))
    for t0, t1 in still:
        ax.axvspan(t0, t1, color="0.92", lw=0)
    ax.plot(series.t, 100 * (r_raw / np.mean(r_raw) - 1), lw=0.7, label="raw (about the median centre)")
    ax.plot(series.t, 100 * (r_cal - 1), lw=0.7, label="calibrated")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("field strength error [%]")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    out = [(f"{mag_id}: field strength over time (grey: still segments)", _png(fig))]
    fig, axes = plt.subplots(1, 3, figsize=(9, 3.2))
    step = max(1, len(raw) // 4000)
    unit_raw = (raw - centre) / np.mean(r_raw)
    circle = np.linspace(0, 2 * np.pi, 200)
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        ax.plot(np.cos(circle), np.sin(circle), color="0.6", lw=0.8)
        ax.scatter(unit_raw[::step, i], unit_raw[::step, j], s=1, alpha=0.4, label="raw, scaled")
        ax.scatter(series.calibrated[::step, i], series.calibrated[::step, j], s=1, alpha=0.4, label="calibrated")
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
    axes[0].legend(loc="lower left", fontsize=7, markerscale=6)
    out.append((f"{mag_id}: readings projected on the body axes (calibrated ones lie on the unit circle "
                "only where the field lies in that plane)", _png(fig)))
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
                 "<h1>magcal calibration report</h1>", f"<pre>{html.escape(render(result))}</pre>"]
        for mag_id, series in result.series.items():
            for caption, uri in _figures(mag_id, series, still):
                parts.append(f"<figure><img src='{uri}' alt='{html.escape(caption)}' style='max-width:100%'>"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        parts.append("</body></html>")
        return [write_text(outdir / self.files[0], "\n".join(parts) + "\n")]
