"""The Method section: method, model, data used, IMU, noise and modelled effects."""

from __future__ import annotations

from html import escape
from pathlib import Path

import numpy as np

from magcal_cli.methods.table import title
from magcal_cli.writers.report.sections.base import Context
from magcal_cli.writers.report.sections.markup import pm, rows
from magcal_cli.writers.report.text import vec


def render(ctx: Context) -> str:
    """How the calibration was computed: method, model, data used, IMU, noise and modelled effects."""
    result = ctx.result
    cal = result.calibration
    still = result.still
    modelled = [f"{e.get('id')} ({e.get('sensor')}, {e.get('status')})" for e in cal.effects
                if e.get("status") in ("accepted", "ambiguous") and e.get("params")]
    imu = cal.imu
    pairs = [("method", escape(title(cal.method))),
             ("model", "y = D R<sup>T</sup> m<sub>n</sub>(dip) + o + e; calibrated unit field "
                       "m<sub>b</sub> = A (y &minus; b), A = D<sup>&minus;1</sup>, b = o (IMU body frame)"),
             ("data", escape(f"{cal.source.end_s - cal.source.start_s:.1f} s of {Path(cal.source.path).name} "
                             f"({cal.source.format}); {len(still.segments)} still segments "
                             f"({sum(s.end - s.start for s in still.segments):.1f} s)")),
             ("IMU", escape(imu.id)),
             ("noise per sample", escape(f"accelerometer {vec(still.acc_noise, '{:.3g}')} m/s^2, "
                                         f"gyroscope {vec(still.gyr_noise, '{:.3g}')} rad/s")),
             ("modelled effects", escape(", ".join(modelled) or "none beyond the base model"))]
    if imu.gyroscope_bias is not None:
        std = imu.gyroscope_bias_std if imu.gyroscope_bias_std is not None else np.full(3, np.nan)
        pairs.append(("gyroscope bias [rad/s]", pm(imu.gyroscope_bias, std, "{:+.5f}", "{:.5f}")))
    if imu.accelerometer_bias is not None:
        std = imu.accelerometer_bias_std if imu.accelerometer_bias_std is not None else np.full(3, np.nan)
        pairs.append(("accelerometer bias [m/s^2]", pm(imu.accelerometer_bias, std)))
    return f"<section id='{ctx.anchor}'><h2>Method</h2>{rows(pairs)}</section>"
