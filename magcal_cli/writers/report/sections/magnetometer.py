"""The section of one magnetometer: parameters, quality, diagnosis and advice beside its figures."""

from __future__ import annotations

from html import escape
from typing import TYPE_CHECKING, Any

import numpy as np

from magcal_cli import so3, units
from magcal_cli.findings import Severity
from magcal_cli.streams import FloatArray
from magcal_cli.writers.report.data import (
    EffectView,
    HeadingView,
    MagView,
    effect_views,
    heading_view,
    mag_view,
    thin,
)
from magcal_cli.writers.report.plots import (
    CAL,
    DIP,
    RAW,
    REF,
    WIDTH_IN,
    WINDOW,
    Plot,
    effect_grid,
    legend_above,
    margins,
    png,
    pyplot,
    robust_ylim,
)
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import badge, figures, matrix, pm, rows
from magcal_cli.writers.report.text import DISPLAY, held_sentence, vec, widening, widening_sentence

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from magcal_cli.calibration.run import RunResult
    from magcal_cli.calibration.types import MagCalibration


def render(ctx: Context) -> str | None:
    """One magnetometer: its parameters, quality, diagnosis and advice beside its figures."""
    mag, verdict, result = ctx.mag, ctx.verdict, ctx.result
    if mag is None or verdict is None:
        return None
    plots = mag_figures(result, mag)
    unit, sym = DISPLAY.get(mag.unit, (mag.unit, mag.unit))
    f = units.to_si(mag.unit) * units.from_si(unit)
    misalign = float(np.rad2deg(so3.angle(mag.misalignment)))
    w_sd = float(np.rad2deg(np.sqrt(max(np.trace(mag.misalignment_cov()), 0.0))))
    rpy = np.rad2deg(so3.as_rpy(mag.misalignment))
    pairs = [("hard iron b [" + sym + "]", pm(mag.o * f, mag.std_of("o") * f)),
             ("field strength", escape(f"{mag.field_strength * f:.3f} {sym} ({mag.field_strength_source})")),
             ("dip", escape(f"{mag.dip_deg:.2f} ± {float(mag.std_of('dip')):.2f} deg")),
             ("misalignment", escape(f"{misalign:.2f} ± {w_sd:.2f} deg (roll, pitch, yaw "
                                     f"{vec(rpy, '{:+.2f}')} deg)")),
             ("soft iron P/|F|", matrix(mag.soft_iron, "{:+.4f}")),
             (f"A = D^-1 [1/{sym}]", matrix(mag.A / f, "{:+.6f}"))]
    q = mag.quality
    if q is not None:
        pairs += [("field strength spread", escape(f"raw {verdict.raw_norm_pct:.2f} % → calibrated "
                                                   f"{q.field_norm_rms_pct:.3f} % RMS ({q.samples} readings)")),
                  ("model residual", escape(f"{q.residual_rms * f:.4g} {sym} RMS")),
                  ("coverage", escape(f"{q.coverage_pct:.0f} % of the field directions")),
                  *([("uncertainty", escape(widening_sentence(factor)))] if (factor := widening(result, mag.id)) else []),
                  ("solver", escape(f"{'converged' if q.converged else 'NOT converged'} after {q.iterations} "
                                    "iterations"))]
    text = [f"<h3>{badge(verdict.level, verdict.label)}</h3>", rows(pairs)]
    if mag.held:
        text.append(f"<p class='note'>{escape(held_sentence(mag))}</p>")
    block = diagnosis_block(result, mag.id)
    if block is not None:
        text.append(f"<h4>What the recording says</h4><p>{escape(str(block.get('summary', '')))}</p>")
    mine = [m for g in ctx.groups if g.severity is Severity.WARNING for m in g.messages if mag.id in m]
    if mine:
        text.append("<h4>Warnings</h4><ul>" + "".join(f"<li>{escape(m)}</li>" for m in mine) + "</ul>")
    return (f"<section id='{ctx.anchor}' class='mag'><h2>Magnetometer {escape(mag.id)} "
            f"<small>(log unit: {escape(mag.unit)})</small></h2><div class='pair'><div class='text'>{''.join(text)}"
            f"</div>{figures(plots, mag.id)}</div></section>")


def diagnosis_block(result: RunResult, mag_id: str) -> dict[str, Any] | None:
    """The diagnosis entry of one magnetometer, if the run diagnosed it."""
    diag = result.calibration.diagnosis or {}
    return next((b for b in diag.get("sensors", [diag]) if b.get("sensor") == mag_id), None)


def mag_figures(result: RunResult, mag: MagCalibration) -> list[Plot]:
    """The figures of one magnetometer: sphere, over time, quality and heading, modelled effects."""
    view = mag_view(result, mag)
    if view is None:
        return []
    out = [sphere(view), over_time(view), quality(view, heading_view(result, mag))]
    eff = effects_figure(effect_views(result, mag))
    return out + ([eff] if eff is not None else [])


def _shade(ax: Axes, still: tuple[tuple[float, float], ...], windows: tuple[tuple[float, float], ...]) -> None:
    """Still segments in grey, the diagnosis' windows in orange."""
    for a, b in still:
        ax.axvspan(a, b, color="0.9", lw=0, zorder=0)
    for a, b in windows:
        ax.axvspan(a, b, color=WINDOW, alpha=0.25, lw=0, zorder=0)


def sphere(v: MagView) -> Plot:
    """Raw and calibrated field on the unit sphere, three projections (Kok et al. 2012, Fig. 1)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(WIDTH_IN, 3.1), gridspec_kw=margins(3.1, wspace=0.4, left_in=0.5, top_in=0.6))
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
                png(fig))


def over_time(v: MagView) -> Plot:
    """Field strength, dip and the residuals over time, with still segments and the diagnosis' windows."""
    plt = pyplot()
    n_rows = 3 if v.dip_cal is not None else 2
    height = 1.75 * n_rows + 0.4
    fig, axes = plt.subplots(n_rows, 1, figsize=(WIDTH_IN, height), sharex=True,
                             gridspec_kw=margins(height, hspace=0.3, right_in=0.6))
    s = thin(len(v.t))
    t = v.t[s]
    ax = axes[0]
    _shade(ax, v.still, v.windows)
    ax.plot(t, v.norm_raw_pct[s], color=RAW, label="raw |y| relative to its mean")
    ax.plot(t, v.norm_cal_pct[s], color=CAL, label="calibrated |m|")
    ax.set_ylabel("field strength\nerror [%]")
    robust_ylim(ax, v.norm_raw_pct, v.norm_cal_pct)
    legend_above(ax, 2)
    if v.dip_raw is not None and v.dip_cal is not None:
        ax = axes[1]
        _shade(ax, v.still, v.windows)
        ax.plot(t, v.dip_raw[s], color=RAW, alpha=0.8, label="raw")
        ax.plot(t, v.dip_cal[s], color=CAL, alpha=0.8, label="calibrated")
        ax.axhline(v.dip_deg, color=REF, ls="--", lw=0.8, label=f"fitted dip {v.dip_deg:.1f} deg")
        ax.set_ylabel("dip [deg]")
        robust_ylim(ax, v.dip_raw, v.dip_cal)
        legend_above(ax, 3)
    ax = axes[-1]
    _shade(ax, v.still, v.windows)
    for a, b in v.excluded:
        ax.axvspan(a, b, color="0.6", alpha=0.4, lw=0, zorder=0)
    ax.plot(t, v.norm_cal_pct[s], color=CAL, label="field strength [%]")
    ax.axhline(0.0, color=REF, lw=0.6)
    ax.set_ylabel("field strength\nresidual [%]", color=CAL)
    robust_ylim(ax, v.norm_cal_pct)
    ax.set_xlabel("time [s]")
    if v.dip_cal is not None:           # a second scale: degrees of dip and % of field strength do not compare
        ax2 = ax.twinx()
        ax2.plot(t, (v.dip_cal - v.dip_deg)[s], color=DIP, alpha=0.55, lw=0.6)
        ax2.set_ylabel("dip residual [deg]", color=DIP)
        robust_ylim(ax2, v.dip_cal - v.dip_deg)
        ax2.grid(False)
        ax2.spines["right"].set_visible(True)
        ax.set_zorder(ax2.get_zorder() + 1)
        ax.patch.set_visible(False)
    where = " Orange bands: windows where the diagnosis located a mismatch." if v.windows else ""
    return Plot("Over time", "Top: the field strength, flat at 0 when calibrated. Middle: the field's dip below "
                "the accelerometer's horizontal (noisy while the vehicle accelerates). Bottom: what the calibration "
                f"leaves: field strength (blue, left scale) and dip (green, right scale). Grey: still segments.{where}", png(fig))


def _unwrapped(err: FloatArray) -> FloatArray:
    """A heading error with NaN where it wraps through +-180 deg, so no vertical line joins the two ends."""
    out = np.array(err, dtype=np.float64)
    out[1:][np.abs(np.diff(out)) > 180.0] = np.nan
    return out


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
    plt = pyplot()
    fig = plt.figure(figsize=(WIDTH_IN, 5.4))
    top, bottom = fig.add_gridspec(2, 2, **margins(5.4, hspace=0.55)), fig.add_gridspec(2, 3, **margins(5.4, 0.55, 0.55))
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
                "the calibrated heading's uncertainty band, 1 and 2 sigma, on its own scale.", png(fig))


def effects_figure(views: list[EffectView]) -> Plot | None:
    """For each modelled magnetometer effect, the residual against its channel, before and after its removal."""
    return effect_grid(views, 2, "Modelled effects", "Each modelled effect's residual against its channel, without "
                        "the effect (red) and with it removed (blue); lines are binned medians. A slope that flattens "
                        "is the effect the model now explains.")
