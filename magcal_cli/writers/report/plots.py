"""What the report's figures share (matplotlib, Agg): size, colours, margins, PNG embedding, the effect grid."""

from __future__ import annotations

import base64
import io
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from magcal_cli.progress import current
from magcal_cli.streams import FloatArray
from magcal_cli.writers.report.data import EffectView, thin

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: a modest resolution: sharp on screen, small files, fast to render
DPI = 96
WIDTH_IN = 8.4
RAW, CAL, REF, WINDOW, DIP = "#d62728", "#1f77b4", "0.35", "#ff7f0e", "#2ca02c"


def margins(height_in: float, wspace: float = 0.35, hspace: float = 0.3, left_in: float = 0.75,
             right_in: float = 0.12, top_in: float = 0.3) -> dict[str, float]:
    """Fixed margins in inches as figure fractions: constrained layout would measure every label, drawing twice."""
    return {"left": left_in / WIDTH_IN, "right": 1 - right_in / WIDTH_IN, "bottom": 0.5 / height_in,
            "top": 1 - top_in / height_in, "wspace": wspace, "hspace": hspace}


class Plot(NamedTuple):
    """One embedded figure: a short title, a caption saying how to read it, and its data URI."""

    title: str
    caption: str
    uri: str


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (imported on use: `magcal --help` must start fast)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 8, "axes.titlesize": 9, "axes.labelsize": 8, "legend.fontsize": 7,
                         "axes.spines.top": False, "axes.spines.right": False, "axes.grid": True,
                         "grid.alpha": 0.3, "lines.linewidth": 0.8})
    return plt


def png(fig: Figure) -> str:
    """A figure as a base64 PNG data URI (and close it)."""
    plt = pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    current()("drawing the report's figures", 0)      # one step of the report's progress per figure (html.py)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def legend_above(ax: Axes, ncols: int) -> None:
    """A legend right-aligned above the axes, where it hides no data (and needs no 'best' search)."""
    ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), ncols=ncols, frameon=False, borderaxespad=0.1)


def robust_ylim(ax: Axes, *series: FloatArray) -> None:
    """Y limits from the 0.5 and 99.5 percentiles: a few spikes must not flatten what the rest shows."""
    x = np.concatenate([np.ravel(a)[np.isfinite(np.ravel(a))] for a in series])
    if x.size:
        lo, hi = np.percentile(x, [0.5, 99.5])
        pad = 0.1 * max(hi - lo, 1e-9)
        ax.set_ylim(lo - pad, hi + pad)


def effect_grid(views: list[EffectView], max_cols: int, title: str, caption: str) -> Plot | None:
    """Views in rows of up to `max_cols` panels: residual against channel before (red) and after (blue)."""
    if not views:
        return None
    plt = pyplot()
    cols = min(len(views), max_cols)
    rows = -(-len(views) // cols)
    height = 2.9 * rows + 0.3
    fig, axes = plt.subplots(rows, cols, figsize=(WIDTH_IN, height), squeeze=False,
                             gridspec_kw=margins(height, wspace=0.3, hspace=0.45, top_in=0.6))
    scale = 5.0
    for k, (ax, e) in enumerate(zip(axes.ravel(), views, strict=False)):
        ok = np.isfinite(e.x) & np.isfinite(e.before) & np.isfinite(e.after)
        x, before, after = e.x[ok], e.before[ok], e.after[ok]
        s = thin(x.size, 2000)
        ms, alpha = (1.5, 0.35) if x.size > 200 else (4.0, 0.7)       # a few points (still poses) must show
        scale = scale if ax is not axes[0, 0] else 7.5 / ms
        ax.plot(x[s], before[s], ".", ms=ms, color=RAW, alpha=alpha, label="without the effect")
        ax.plot(x[s], after[s], ".", ms=ms, color=CAL, alpha=alpha, label="with the effect removed")
        if x.size > 40:
            edges = np.unique(np.percentile(x, np.linspace(0, 100, 21)))
            mid, idx = 0.5 * (edges[1:] + edges[:-1]), np.clip(np.digitize(x, edges) - 1, 0, edges.size - 2)
            for y, c in ((before, RAW), (after, CAL)):
                med = np.array([np.median(y[idx == k]) if np.any(idx == k) else np.nan for k in range(mid.size)])
                ax.plot(mid, med, "-", color=c, lw=1.6)
        left = views[k - k % cols]                  # a row's panels that plot the same residual label it once
        ax.set(xlabel=e.xlabel, ylabel=e.ylabel if k % cols == 0 or e.ylabel != left.ylabel else "",
               title=f"{e.effect_id}{', ' + e.part if e.part else ''} ({e.status})")
        robust_ylim(ax, before, after)
    for ax in axes.ravel()[len(views):]:
        ax.set_axis_off()
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="upper center", ncols=2, markerscale=scale,
               frameon=False)
    return Plot(title, caption, png(fig))
