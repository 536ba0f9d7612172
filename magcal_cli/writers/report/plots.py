"""The report's figures (matplotlib, Agg): one row of panels per question, embedded as base64 PNG."""

from __future__ import annotations

import base64
import io
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from magcal_cli.streams import FloatArray
from magcal_cli.writers.report.data import EffectView, HeadingView, MagView, thin

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: a modest resolution: sharp on screen, small files, fast to render
DPI = 96
WIDTH_IN = 8.4
RAW, CAL, REF, WINDOW, DIP = "#d62728", "#1f77b4", "0.35", "#ff7f0e", "#2ca02c"



def _margins(height_in: float, wspace: float = 0.35, hspace: float = 0.3, left_in: float = 0.75,
             right_in: float = 0.12, top_in: float = 0.3) -> dict[str, float]:
    """Fixed margins in inches as figure fractions: constrained layout would measure every label, drawing twice."""
    return {"left": left_in / WIDTH_IN, "right": 1 - right_in / WIDTH_IN, "bottom": 0.5 / height_in,
            "top": 1 - top_in / height_in, "wspace": wspace, "hspace": hspace}


class Plot(NamedTuple):
    """One embedded figure: a short title, a caption saying how to read it, and its data URI."""

    title: str
    caption: str
    uri: str


def _pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (imported on use: `magcal --help` must start fast)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 8, "axes.titlesize": 9, "axes.labelsize": 8, "legend.fontsize": 7,
                         "axes.spines.top": False, "axes.spines.right": False, "axes.grid": True,
                         "grid.alpha": 0.3, "lines.linewidth": 0.8})
    return plt


def _png(fig: Figure) -> str:
    """A figure as a base64 PNG data URI (and close it)."""
    plt = _pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _shade(ax: Axes, still: tuple[tuple[float, float], ...], windows: tuple[tuple[float, float], ...]) -> None:
    """Still segments in grey, the diagnosis' windows in orange."""
    for a, b in still:
        ax.axvspan(a, b, color="0.9", lw=0, zorder=0)
    for a, b in windows:
        ax.axvspan(a, b, color=WINDOW, alpha=0.25, lw=0, zorder=0)


def sphere(v: MagView) -> Plot:
    """Raw and calibrated field on the unit sphere, three projections (Kok et al. 2012, Fig. 1)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(WIDTH_IN, 3.1), gridspec_kw=_margins(3.1, wspace=0.4, left_in=0.5, top_in=0.6))
    s = thin(len(v.t), 2500)
    circle = np.linspace(0, 2 * np.pi, 181)
    for ax, (i, j) in zip(axes, [(0, 1), (0, 2), (1, 2)], strict=True):
        ax.plot(v.raw[s, i], v.raw[s, j], ".", ms=1.2, color=RAW, alpha=0.5, label="raw / field strength")
        ax.plot(v.cal[s, i], v.cal[s, j], ".", ms=1.2, color=CAL, alpha=0.5, label="calibrated")
        ax.plot(np.cos(circle), np.sin(circle), "-", color=REF, lw=0.8, label="unit circle")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
        ax.set_title(f"{'xyz'[i]}{'xyz'[j]} projection")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="upper center", ncols=3, markerscale=6, frameon=False)
    return Plot("Field on the sphere", "Raw readings (red, scaled by the field strength) form an offset, tilted "
                "ellipsoid; calibrated readings (blue) should lie on the unit circle in every projection.",
                _png(fig))


def over_time(v: MagView) -> Plot:
    """Field strength, dip and the residuals over time, with still segments and the diagnosis' windows."""
    plt = _pyplot()
    rows = 3 if v.dip_cal is not None else 2
    height = 1.75 * rows + 0.4
    fig, axes = plt.subplots(rows, 1, figsize=(WIDTH_IN, height), sharex=True,
                             gridspec_kw=_margins(height, hspace=0.3, right_in=0.6))
    s = thin(len(v.t))
    t = v.t[s]
    ax = axes[0]
    _shade(ax, v.still, v.windows)
    ax.plot(t, v.norm_raw_pct[s], color=RAW, label="raw |y| relative to its mean")
    ax.plot(t, v.norm_cal_pct[s], color=CAL, label="calibrated |m|")
    ax.set_ylabel("field strength\nerror [%]")
    _robust_ylim(ax, v.norm_raw_pct, v.norm_cal_pct)
    _legend_above(ax, 2)
    if v.dip_raw is not None and v.dip_cal is not None:
        ax = axes[1]
        _shade(ax, v.still, v.windows)
        ax.plot(t, v.dip_raw[s], color=RAW, alpha=0.8, label="raw")
        ax.plot(t, v.dip_cal[s], color=CAL, alpha=0.8, label="calibrated")
        ax.axhline(v.dip_deg, color=REF, ls="--", lw=0.8, label=f"fitted dip {v.dip_deg:.1f} deg")
        ax.set_ylabel("dip [deg]")
        _robust_ylim(ax, v.dip_raw, v.dip_cal)
        _legend_above(ax, 3)
    ax = axes[-1]
    _shade(ax, v.still, v.windows)
    for a, b in v.excluded:
        ax.axvspan(a, b, color="0.6", alpha=0.4, lw=0, zorder=0)
    ax.plot(t, v.norm_cal_pct[s], color=CAL, label="field strength [%]")
    ax.axhline(0.0, color=REF, lw=0.6)
    ax.set_ylabel("field strength\nresidual [%]", color=CAL)
    _robust_ylim(ax, v.norm_cal_pct)
    ax.set_xlabel("time [s]")
    if v.dip_cal is not None:           # a second scale: degrees of dip and % of field strength do not compare
        ax2 = ax.twinx()
        ax2.plot(t, (v.dip_cal - v.dip_deg)[s], color=DIP, alpha=0.55, lw=0.6)
        ax2.set_ylabel("dip residual [deg]", color=DIP)
        _robust_ylim(ax2, v.dip_cal - v.dip_deg)
        ax2.grid(False)
        ax2.spines["right"].set_visible(True)
        ax.set_zorder(ax2.get_zorder() + 1)
        ax.patch.set_visible(False)
    where = " Orange bands: windows where the diagnosis located a mismatch." if v.windows else ""
    return Plot("Over time", "Top: the field strength, flat at 0 when calibrated. Middle: the field's dip below "
                "the accelerometer's horizontal (noisy while the vehicle accelerates). Bottom: what the calibration "
                f"leaves: field strength (blue, left scale) and dip (green, right scale). Grey: still segments.{where}", _png(fig))


def _unwrapped(err: FloatArray) -> FloatArray:
    """A heading error with NaN where it wraps through +-180 deg, so no vertical line joins the two ends."""
    out = np.array(err, dtype=np.float64)
    out[1:][np.abs(np.diff(out)) > 180.0] = np.nan
    return out


def _legend_above(ax: Axes, ncols: int) -> None:
    """A legend right-aligned above the axes, where it hides no data (and needs no 'best' search)."""
    ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), ncols=ncols, frameon=False, borderaxespad=0.1)


def _robust_ylim(ax: Axes, *series: FloatArray) -> None:
    """Y limits from the 0.5 and 99.5 percentiles: a few spikes must not flatten what the rest shows."""
    x = np.concatenate([np.ravel(a)[np.isfinite(np.ravel(a))] for a in series])
    if x.size:
        lo, hi = np.percentile(x, [0.5, 99.5])
        pad = 0.1 * max(hi - lo, 1e-9)
        ax.set_ylim(lo - pad, hi + pad)


def _hist(ax: Axes, x: FloatArray, label: str, color: str) -> None:
    """A histogram of the finite values of x, with its RMS and 95 % range in the title."""
    x = x[np.isfinite(x)]
    if x.size == 0:
        ax.set_axis_off()
        return
    lo, hi = np.percentile(x, [0.5, 99.5])
    counts, edges = np.histogram(x, bins=60, range=(lo, hi + 1e-12))
    ax.stairs(counts, edges, fill=True, color=color, alpha=0.85)      # one patch, not 60 (ax.hist)
    q = np.percentile(x, [2.5, 97.5])
    ax.set_title(f"RMS {np.sqrt(np.mean(x ** 2)):.3g}; 95 % in [{q[0]:.2g}, {q[1]:.2g}]")
    ax.set_xlabel(label)
    ax.set_ylabel("readings")


def quality(v: MagView, h: HeadingView) -> Plot:
    """Residual histograms, orientation coverage and heading error against heading."""
    plt = _pyplot()
    fig = plt.figure(figsize=(WIDTH_IN, 5.4))
    top, bottom = fig.add_gridspec(2, 2, **_margins(5.4, hspace=0.55)), fig.add_gridspec(2, 3, **_margins(5.4, 0.55, 0.55))
    axes = np.array([[fig.add_subplot(top[0, 0]), fig.add_subplot(top[0, 1]), None],
                     [fig.add_subplot(bottom[1, 0]), fig.add_subplot(bottom[1, 1]), fig.add_subplot(bottom[1, 2])]])
    _hist(axes[0, 0], v.norm_cal_pct, "field strength error [%]", CAL)
    if v.dip_cal is not None:
        _hist(axes[0, 1], v.dip_cal - v.dip_deg, "dip error [deg]", DIP)
    else:
        axes[0, 1].set_axis_off()
    ax = axes[1, 0]
    u = v.cal[thin(len(v.t), 3000)]
    u = u[np.all(np.isfinite(u), axis=1)]
    u = u / np.linalg.norm(u, axis=1)[:, None]
    ax.plot(np.degrees(np.arctan2(u[:, 1], u[:, 0])), np.degrees(np.arcsin(np.clip(u[:, 2], -1, 1))), ".",
            ms=1.5, color=CAL, alpha=0.4)
    ax.set(xlim=(-180, 180), ylim=(-90, 90), xticks=range(-180, 181, 90), yticks=range(-90, 91, 45),
           xlabel="azimuth in the sensor frame [deg]", ylabel="elevation [deg]", title="orientation coverage")
    ax = axes[1, 1]
    ax.plot(h.headings, _unwrapped(h.raw), color=RAW, label="raw readings")
    if h.firmware is not None:
        ax.plot(h.headings, _unwrapped(h.firmware), color="#9467bd", label=f"{h.firmware_name} parameters")
    ax.axhline(0.0, color=REF, lw=0.6)
    ax.set(xlim=(0, 360), xticks=range(0, 361, 90), xlabel="heading [deg]", ylabel="heading error [deg]",
           title="level heading error")
    ax.legend(loc="best", frameon=False)
    ax = axes[1, 2]
    if h.std is not None:               # its own axis: the band is often 100 times narrower than the raw error
        ax.fill_between(h.headings, -2 * h.std, 2 * h.std, color=CAL, alpha=0.2, lw=0, label="2 sigma")
        ax.fill_between(h.headings, -h.std, h.std, color=CAL, alpha=0.45, lw=0, label="1 sigma")
        ax.set(xlim=(0, 360), xticks=range(0, 361, 90), xlabel="heading [deg]", ylabel="uncertainty [deg]",
               title="calibrated heading, uncertainty")
        ax.legend(loc="upper right", frameon=False)
    else:
        ax.set_axis_off()
    return Plot("Residuals, coverage and heading", "Top: the spread of what the calibration leaves, in field "
                "strength and in dip. Bottom left: the field directions the log visited in the sensor frame "
                "(empty areas are orientations never seen). Bottom middle: the heading error of a level vehicle "
                "using the raw readings (and what the firmware parameters leave, for a flight log). Bottom right: "
                "the calibrated heading's uncertainty band, 1 and 2 sigma, on its own scale.", _png(fig))


def effects(views: list[EffectView]) -> Plot | None:
    """For each modelled magnetometer effect, the residual against its channel, before and after its removal."""
    return _effect_grid(views, 2, "Modelled effects", "Each modelled effect's residual against its channel, without "
                        "the effect (red) and with it removed (blue); lines are binned medians. A slope that flattens "
                        "is the effect the model now explains.")


def imu_effects(views: list[EffectView]) -> Plot | None:
    """For each modelled IMU effect, one row: per axis, the residual against its channel, before and after."""
    return _effect_grid(views, 3, "Modelled IMU effects", "One row per modelled effect of the IMU, one panel per "
                        "axis: the residual without that axis's term (red) and with it removed (blue); lines are "
                        "binned medians. accel_scale: at each still pose, the specific force's magnitude less g "
                        "against the force on the axis (a scale s bends it into s f²/g). lever_arm: the same at every "
                        "sample against the rotation's term for that component of the arm, along the force (slope: "
                        "the arm in m). gyro_scale: between consecutive still poses, the gyro's rotation less the one "
                        "the accelerometer and the calibrated magnetometer see, against the rotation about the axis "
                        "(slope: the scale). A trend that flattens is the effect the model now explains.")


def _effect_grid(views: list[EffectView], max_cols: int, title: str, caption: str) -> Plot | None:
    """Views in rows of up to `max_cols` panels: residual against channel before (red) and after (blue)."""
    if not views:
        return None
    plt = _pyplot()
    cols = min(len(views), max_cols)
    rows = -(-len(views) // cols)
    height = 2.9 * rows + 0.3
    fig, axes = plt.subplots(rows, cols, figsize=(WIDTH_IN, height), squeeze=False,
                             gridspec_kw=_margins(height, wspace=0.3, hspace=0.45, top_in=0.6))
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
        _robust_ylim(ax, before, after)
    for ax in axes.ravel()[len(views):]:
        ax.set_axis_off()
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="upper center", ncols=2, markerscale=scale,
               frameon=False)
    return Plot(title, caption, _png(fig))
