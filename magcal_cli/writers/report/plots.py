"""What the report's figures share (drawn as SVG by `svg`, no matplotlib): size, colours, margins, embedding,
the effect grid."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from magcal_cli.progress import current
from magcal_cli.streams import FloatArray
from magcal_cli.writers.report.data import EffectView, thin
from magcal_cli.writers.report.svg import DPI, Axes, Figure, Handle

WIDTH_IN = 8.4
RAW, CAL, REF, WINDOW, DIP = "#d62728", "#1f77b4", "#595959", "#ff7f0e", "#2ca02c"
STILL, EXCLUDED = "#e6e6e6", "#999999"


def margins(height_in: float, wspace: float = 0.35, hspace: float = 0.3, left_in: float = 0.75,
            right_in: float = 0.12, top_in: float = 0.3) -> dict[str, float]:
    """Fixed margins in inches as figure fractions (matplotlib's GridSpec convention)."""
    return {"left": left_in / WIDTH_IN, "right": 1 - right_in / WIDTH_IN, "bottom": 0.5 / height_in,
            "top": 1 - top_in / height_in, "wspace": wspace, "hspace": hspace}


class Plot(NamedTuple):
    """One embedded figure: a short title, a caption saying how to read it, and its data URI."""

    title: str
    caption: str
    uri: str


def figure(height_in: float) -> Figure:
    """An empty figure of the report's width and `height_in` inches (96 px per inch)."""
    return Figure(WIDTH_IN * DPI, height_in * DPI)


def embed(fig: Figure) -> str:
    """A figure as an SVG data URI; one step of the report's progress per figure (html.py)."""
    uri = fig.uri()
    current()("drawing the report's figures", 0)
    return uri


def legend_above(ax: Axes, ncols: int) -> None:
    """A legend right-aligned above the axes, where it hides no data."""
    ax.legend("above", ncols)


def robust_ylim(ax: Axes, *series: FloatArray) -> None:
    """Y limits from the 0.5 and 99.5 percentiles: a few spikes must not flatten what the rest shows."""
    x = np.concatenate([np.ravel(a)[np.isfinite(np.ravel(a))] for a in series])
    if x.size:
        lo, hi = np.percentile(x, [0.5, 99.5])
        pad = 0.1 * max(hi - lo, 1e-9)
        ax.ylim = (float(lo - pad), float(hi + pad))


def binned_medians(x: FloatArray, y: FloatArray, bins: int = 20) -> tuple[FloatArray, FloatArray]:
    """Medians of y in `bins` bins of equal count along x, at the bins' midpoints."""
    edges = np.unique(np.percentile(x, np.linspace(0, 100, bins + 1)))
    mid, idx = 0.5 * (edges[1:] + edges[:-1]), np.clip(np.digitize(x, edges) - 1, 0, edges.size - 2)
    med = np.array([np.median(y[idx == k]) if np.any(idx == k) else np.nan for k in range(mid.size)])
    return mid, med


def effect_grid(views: list[EffectView], max_cols: int, title: str, caption: str) -> Plot | None:
    """Views in rows of up to `max_cols` panels: residual against channel before (red) and after (blue)."""
    if not views:
        return None
    cols = min(len(views), max_cols)
    rows = -(-len(views) // cols)
    height = 2.9 * rows + 0.3
    fig = figure(height)
    axes = [a for row in fig.grid(rows, cols, margins(height, wspace=0.3, hspace=0.45, top_in=0.6)) for a in row]
    for k, (ax, e) in enumerate(zip(axes, views, strict=False)):
        ok = np.isfinite(e.x) & np.isfinite(e.before) & np.isfinite(e.after)
        x, before, after = e.x[ok], e.before[ok], e.after[ok]
        s = thin(x.size, 2000)
        ms, alpha = (2.0, 0.35) if x.size > 200 else (5.3, 0.7)      # a few points (still poses) must show
        ax.dots(x[s], before[s], RAW, ms, alpha)
        ax.dots(x[s], after[s], CAL, ms, alpha)
        if x.size > 40:
            for y, c in ((before, RAW), (after, CAL)):
                ax.line(*binned_medians(x, y), color=c, width=2.1)
        left = views[k - k % cols]                  # a row's panels that plot the same residual label it once
        ax.xlabel, ax.ylabel = e.xlabel, e.ylabel if k % cols == 0 or e.ylabel != left.ylabel else ""
        ax.title = f"{e.effect_id}{', ' + e.part if e.part else ''} ({e.status})"
        robust_ylim(ax, before, after)
    for ax in axes[len(views):]:
        ax.off = True
    fig.legend([Handle("dot", RAW, "without the effect"), Handle("dot", CAL, "with the effect removed")], 2,
               markerscale=7.5 / 3.5)
    return Plot(title, caption, embed(fig))
