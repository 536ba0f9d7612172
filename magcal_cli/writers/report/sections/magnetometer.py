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
    EXCLUDED,
    RAW,
    REF,
    STILL,
    WINDOW,
    Plot,
    effect_grid,
    embed,
    figure,
    legend_above,
    margins,
    robust_ylim,
)
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import badge, figures, matrix, pm, rows
from magcal_cli.writers.report.svg import Axes, Handle
from magcal_cli.writers.report.text import DISPLAY, held_sentence, vec, widening, widening_sentence

if TYPE_CHECKING:
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
        ax.vspan(a, b, STILL)
    for a, b in windows:
        ax.vspan(a, b, WINDOW, alpha=0.25)


def sphere(v: MagView) -> Plot:
    """Raw and calibrated field on the unit sphere, three projections (Kok et al. 2012, Fig. 1)."""
    fig = figure(3.1)
    (axes,) = fig.grid(1, 3, margins(3.1, wspace=0.4, left_in=0.5, top_in=0.6))
    s = thin(len(v.t), 2500)
    circle = np.linspace(0, 2 * np.pi, 181)
    for ax, (i, j) in zip(axes, [(0, 1), (0, 2), (1, 2)], strict=True):
        ax.dots(v.raw[s, i], v.raw[s, j], RAW, 1.6, 0.5)
        ax.dots(v.cal[s, i], v.cal[s, j], CAL, 1.6, 0.5)
        ax.line(np.cos(circle), np.sin(circle), REF, width=1.07)
        ax.equal = True
        ax.xlabel, ax.ylabel, ax.title = "xyz"[i], "xyz"[j], f"{'xyz'[i]}{'xyz'[j]} projection"
    fig.legend([Handle("dot", RAW, "raw / field strength"), Handle("dot", CAL, "calibrated"),
                Handle("line", REF, "unit circle")], 3, markerscale=2.0)
    return Plot("Field on the sphere", "Raw readings (red, scaled by the field strength) form an offset, tilted "
                "ellipsoid; calibrated readings (blue) should lie on the unit circle in every projection.",
                embed(fig))


def over_time(v: MagView) -> Plot:
    """Field strength, dip and the residuals over time, with still segments and the diagnosis' windows."""
    n_rows = 3 if v.dip_cal is not None else 2
    height = 1.75 * n_rows + 0.4
    fig = figure(height)
    axes = [row[0] for row in fig.grid(n_rows, 1, margins(height, hspace=0.3, right_in=0.6))]
    t = v.t
    span = (float(t[0]), float(t[-1])) if t.size else (0.0, 1.0)
    ax = axes[0]
    _shade(ax, v.still, v.windows)
    ax.line(t, v.norm_raw_pct, RAW, label="raw |y| relative to its mean")
    ax.line(t, v.norm_cal_pct, CAL, label="calibrated |m|")
    ax.ylabel = "field strength\nerror [%]"
    robust_ylim(ax, v.norm_raw_pct, v.norm_cal_pct)
    legend_above(ax, 2)
    if v.dip_raw is not None and v.dip_cal is not None:
        ax = axes[1]
        _shade(ax, v.still, v.windows)
        ax.line(t, v.dip_raw, RAW, alpha=0.8, label="raw")
        ax.line(t, v.dip_cal, CAL, alpha=0.8, label="calibrated")
        ax.hline(v.dip_deg, REF, width=1.07, dash="4 2", label=f"fitted dip {v.dip_deg:.1f} deg")
        ax.ylabel = "dip [deg]"
        robust_ylim(ax, v.dip_raw, v.dip_cal)
        legend_above(ax, 3)
    ax = axes[-1]
    _shade(ax, v.still, v.windows)
    for a, b in v.excluded:
        ax.vspan(a, b, EXCLUDED, alpha=0.4)
    if v.dip_cal is not None:           # a second scale: degrees of dip and % of field strength do not compare
        ax2 = ax.twin()
        ax2.line(t, v.dip_cal - v.dip_deg, DIP, width=0.8, alpha=0.55)
        ax2.ylabel, ax2.ylabel_color = "dip residual [deg]", DIP
        robust_ylim(ax2, v.dip_cal - v.dip_deg)
    ax.hline(0.0, REF, width=0.8)
    ax.line(t, v.norm_cal_pct, CAL, label="field strength [%]")
    ax.ylabel, ax.ylabel_color = "field strength\nresidual [%]", CAL
    robust_ylim(ax, v.norm_cal_pct)
    ax.xlabel = "time [s]"
    for panel in axes:                  # one time axis for every panel; its numbers under the last one only
        panel.xlim = span
        panel.xticklabels = panel is axes[-1]
    where = " Orange bands: windows where the diagnosis located a mismatch." if v.windows else ""
    return Plot("Over time", "Top: the field strength, flat at 0 when calibrated. Middle: the field's dip below "
                "the accelerometer's horizontal (noisy while the vehicle accelerates). Bottom: what the calibration "
                f"leaves: field strength (blue, left scale) and dip (green, right scale). Grey: still segments.{where}",
                embed(fig))


def _unwrapped(err: FloatArray) -> FloatArray:
    """A heading error with NaN where it wraps through +-180 deg, so no vertical line joins the two ends."""
    out = np.array(err, dtype=np.float64)
    out[1:][np.abs(np.diff(out)) > 180.0] = np.nan
    return out


def _hist(ax: Axes, x: FloatArray, label: str, color: str) -> None:
    """A histogram of the finite values of x, with its RMS and 95 % range in the title."""
    x = x[np.isfinite(x)]
    if x.size == 0:
        ax.off = True
        return
    lo, hi = np.percentile(x, [0.5, 99.5])
    counts, edges = np.histogram(x, bins=60, range=(lo, hi + 1e-12))
    ax.stairs(counts.astype(np.float64), edges, color, alpha=0.85)
    ax.ylim = (0.0, 1.05 * float(counts.max()))
    q = np.percentile(x, [2.5, 97.5])
    ax.title = f"RMS {np.sqrt(np.mean(x ** 2)):.3g}; 95 % in [{q[0]:.2g}, {q[1]:.2g}]"
    ax.xlabel, ax.ylabel = label, "readings"


def quality(v: MagView, h: HeadingView) -> Plot:
    """Residual histograms, orientation coverage and heading error against heading."""
    fig = figure(5.4)
    top = fig.grid(2, 2, margins(5.4, hspace=0.55))
    bottom = fig.grid(2, 3, margins(5.4, 0.55, 0.55))
    for ax in [*top[1], *bottom[0]]:     # the grids' unused halves
        fig.axes.remove(ax)
    _hist(top[0][0], v.norm_cal_pct, "field strength error [%]", CAL)
    if v.dip_cal is not None:
        _hist(top[0][1], v.dip_cal - v.dip_deg, "dip error [deg]", DIP)
    else:
        top[0][1].off = True
    ax = bottom[1][0]
    u = v.cal[thin(len(v.t), 3000)]
    u = u[np.all(np.isfinite(u), axis=1)]
    u = u / np.linalg.norm(u, axis=1)[:, None]
    ax.dots(np.degrees(np.arctan2(u[:, 1], u[:, 0])), np.degrees(np.arcsin(np.clip(u[:, 2], -1, 1))), CAL, 2.0, 0.4)
    ax.xlim, ax.ylim, ax.xticks, ax.yticks = (-180, 180), (-90, 90), range(-180, 181, 90), range(-90, 91, 45)
    ax.xlabel, ax.ylabel, ax.title = "azimuth in the sensor frame [deg]", "elevation [deg]", "orientation coverage"
    ax = bottom[1][1]
    ax.line(h.headings, _unwrapped(h.raw), RAW, label="raw readings")
    if h.firmware is not None:
        ax.line(h.headings, _unwrapped(h.firmware), "#9467bd", label=f"{h.firmware_name} parameters")
    ax.hline(0.0, REF, width=0.8)
    ax.xlim, ax.xticks = (0, 360), range(0, 361, 90)
    ax.xlabel, ax.ylabel, ax.title = "heading [deg]", "heading error [deg]", "level heading error"
    ax.legend("best")
    ax = bottom[1][2]
    if h.std is not None:               # its own axis: the band is often 100 times narrower than the raw error
        ax.band(h.headings, -2 * h.std, 2 * h.std, CAL, 0.2, label="2 sigma")
        ax.band(h.headings, -h.std, h.std, CAL, 0.45, label="1 sigma")
        ax.xlim, ax.xticks = (0, 360), range(0, 361, 90)
        ax.xlabel, ax.ylabel, ax.title = "heading [deg]", "uncertainty [deg]", "calibrated heading, uncertainty"
        ax.legend("upper right")
    else:
        ax.off = True
    return Plot("Residuals, coverage and heading", "Top: the spread of what the calibration leaves, in field "
                "strength and in dip. Bottom left: the field directions the log visited in the sensor frame "
                "(empty areas are orientations never seen). Bottom middle: the heading error of a level vehicle "
                "using the raw readings (and what the firmware parameters leave, for a flight log). Bottom right: "
                "the calibrated heading's uncertainty band, 1 and 2 sigma, on its own scale.", embed(fig))


def effects_figure(views: list[EffectView]) -> Plot | None:
    """For each modelled magnetometer effect, the residual against its channel, before and after its removal."""
    return effect_grid(views, 2, "Modelled effects", "Each modelled effect's residual against its channel, without "
                        "the effect (red) and with it removed (blue); lines are binned medians. A slope that flattens "
                        "is the effect the model now explains.")
