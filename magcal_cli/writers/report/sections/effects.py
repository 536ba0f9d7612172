"""The Effects section: every effect the run considered, and the figure of the IMU's modelled effects."""

from __future__ import annotations

from html import escape

from magcal_cli.diagnose.summary import p_text, unit_suffix
from magcal_cli.writers.report.data import EffectView
from magcal_cli.writers.report.imu import imu_effect_views
from magcal_cli.writers.report.plots import Plot, effect_grid
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import badge, figures
from magcal_cli.writers.report.text import by_effect, fmt_param, physics

#: effect status -> the badge's CSS class
STATUS_CLASS = {"accepted": "good", "ambiguous": "check", "rejected": "muted", "not_testable": "muted"}


def imu_figure(views: list[EffectView]) -> Plot | None:
    """For each modelled IMU effect, one row: per axis, the residual against its channel, before and after."""
    return effect_grid(views, 3, "Modelled IMU effects", "One row per modelled effect of the IMU, one panel per "
                       "axis: the residual without that axis's term (red) and with it removed (blue); lines are "
                       "binned medians. accel_scale: at each still pose, the specific force's magnitude less g "
                       "against the force on the axis (a scale s bends it into s f²/g). lever_arm: the same at every "
                       "sample against the rotation's term for that component of the arm, along the force (slope: "
                       "the arm in m). gyro_scale: between consecutive still poses, the gyro's rotation less the one "
                       "the accelerometer and the calibrated magnetometer see, against the rotation about the axis "
                       "(slope: the scale). A trend that flattens is the effect the model now explains.")


def render(ctx: Context) -> str:
    """Every effect the run considered: status, parameters with std and units, test and why; then the figure of the
    IMU's effects (the magnetometers' are beside each magnetometer)."""
    imu = imu_figure(imu_effect_views(ctx.result))
    plots = [imu] if imu is not None else []
    rows = []
    for eid, entries in by_effect(ctx.result.calibration.effects).items():
        for i, e in enumerate(entries):      # what the effect is: once, on its first sensor's row
            params, std, unit_of = e.get("params") or {}, e.get("std") or {}, e.get("units") or {}
            values = "<br>".join(escape(f"{k} = {fmt_param(v, std.get(k))}{unit_suffix(unit_of.get(k))}")
                                 for k, v in params.items())
            p = (e.get("test") or {}).get("p_value")
            status = str(e.get("status"))
            about = "" if i else f"<br><span class='muted'>{escape(physics(eid, entries))}</span>"
            rows.append(f"<tr><td>{escape(eid)}</td><td>{escape(str(e.get('sensor')))}</td>"
                        f"<td>{badge(STATUS_CLASS.get(status, 'muted'), status.replace('_', ' '))}</td>"
                        f"<td>{values or '&ndash;'}</td><td>{escape(p_text(p if isinstance(p, float) else None))}"
                        f"</td><td>{escape(str(e.get('reason') or ''))}{about}</td></tr>")
    if not rows:
        return (f"<section id='{ctx.anchor}'><h2>Effects</h2><p>The base model only: no effect was tested "
                "(<code>--effects none</code> or a method without effect terms).</p></section>")
    return (f"<section id='{ctx.anchor}'><h2>Effects beyond the base model</h2><table class='grid'><thead><tr><th>"
            "effect</th><th>sensor</th><th>status</th><th>estimate</th><th>p</th><th>test and physics</th></tr>"
            "</thead><tbody>" + "".join(rows) + "</tbody></table>" + (figures(plots, "IMU") if plots else "")
            + "</section>")
