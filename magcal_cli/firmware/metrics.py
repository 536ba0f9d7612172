"""Per-magnetometer quality figures of a new calibration, for `fit --fail-on` (names shared with `check`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.errors import MagcalError
from magcal_cli.firmware.effects import carried, tested
from magcal_cli.firmware.split import HEADINGS_DEG
from magcal_cli.params import MAG
from magcal_cli.streams import FloatArray, Kind

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult


#: the heading depends on D and o (not the dip): their joint covariance, in this order
_D_O = MAG.sub(("D", "o"))

#: metric -> meaning, for --fail-on and the documentation
METRICS = {
    "field_norm_rms_pct": "RMS deviation of the calibrated field's magnitude from 1, in %",
    "residual_rms": "RMS model residual, in the magnetometer's unit",
    "coverage_pct": "share of field directions the log visited, in %",
    "misalignment_deg": "rotation between magnetometer and IMU axes",
    "misalignment_std_deg": "standard deviation of that rotation",
    "heading_std_deg": "1-sigma heading uncertainty of a level vehicle, worst heading",
    "heading_error_deg": "worst level heading error of what the log's firmware can hold (0 without firmware)",
    "residual_misalignment_deg": "misalignment the log's firmware cannot represent (0 without firmware)",
    "interference_pct": "current/throttle interference the calibration carries at the log's peak, % of the field",
}
#: the firmware whose parameters a log's vehicle takes (fit writes them for these formats)
FIRMWARE_OF_FORMAT = {"dataflash": "ardupilot", "ulog": "px4"}


def heading_std_deg(mag: MagCalibration) -> float | None:
    """Worst 1-sigma heading error (deg) of a level vehicle from the covariance of D and o (first order)."""
    curve = heading_std_curve_deg(mag)
    return None if curve is None else float(curve.max())


def heading_std_curve_deg(mag: MagCalibration, headings_deg: FloatArray = HEADINGS_DEG) -> FloatArray | None:
    """1-sigma heading error (deg) of a level vehicle at each heading, from the covariance of D and o.

    With m = A (y - o) and y = D m_b + o: dm = -A (dD m_b + do); the heading atan2(-m_y, m_x) moves by
    (m_y dm_x - m_x dm_y) / (m_x^2 + m_y^2).
    """
    cov = mag.cov_of(*_D_O.names)
    if not np.all(np.isfinite(cov)):
        return None
    psi = np.deg2rad(headings_deg)
    dip = np.arctan2(np.sin(np.deg2rad(mag.dip_deg)), abs(np.cos(np.deg2rad(mag.dip_deg))))
    mb = np.stack([np.cos(dip) * np.cos(psi), -np.cos(dip) * np.sin(psi), np.full_like(psi, np.sin(dip))], axis=1)
    A = mag.A
    jac = np.zeros((psi.size, 3, _D_O.size))
    d_at = _D_O.slice("D").start
    for j in range(3):                        # vec(D) is column-major: D[i, j] at index i + 3 j
        for i in range(3):
            jac[:, :, d_at + i + 3 * j] = -A[:, i][None, :] * mb[:, j][:, None]
    jac[:, :, _D_O.slice("o")] = -A[None, :, :]
    h2 = mb[:, 0] ** 2 + mb[:, 1] ** 2
    g = (mb[:, 1, None] * jac[:, 0, :] - mb[:, 0, None] * jac[:, 1, :]) / h2[:, None]
    var = np.einsum("ni,ij,nj->n", g, cov, g)
    out: FloatArray = np.rad2deg(np.sqrt(np.clip(var, 0.0, None)))
    return out


def _interference(cal: Calibration, mag: MagCalibration, peak_current: float | None) -> tuple[float | None, str]:
    """% of the field at the peak signal of the interference the calibration carries; 0 when tested, not carried."""
    inter, _ = carried(cal, mag)
    if inter is not None:
        peak = 1.0 if inter.kind == "throttle" else peak_current
        if peak is None:
            return None, "the log has no battery current"
        return float(100.0 * np.linalg.norm(mag.A @ inter.c) * peak), ""
    if tested(cal, mag.id, "current") or tested(cal, mag.id, "throttle"):
        return 0.0, ""
    return None, "the diagnosis did not test current or throttle interference"


def fit_metrics(result: RunResult) -> dict[str, tuple[dict[str, float | None], dict[str, str]]]:
    """mag id -> (metrics, reasons for the ones that are None)."""
    from magcal_cli.firmware.common import Options
    from magcal_cli.firmware.export import export

    cal = result.calibration
    rec = result.recording
    currents = [np.abs(s.values[:, 0]) for s in rec.of_kind(Kind.BATTERY_CURRENT) if len(s)]
    peak = float(max(c.max() for c in currents)) if currents else None
    firmware = FIRMWARE_OF_FORMAT.get(rec.format)
    out: dict[str, tuple[dict[str, float | None], dict[str, str]]] = {}
    for mag in cal.magnetometers:
        q = mag.quality
        w = mag.misalignment_cov()
        m: dict[str, float | None] = {
            "field_norm_rms_pct": None if q is None else q.field_norm_rms_pct,
            "residual_rms": None if q is None else q.residual_rms,
            "coverage_pct": None if q is None else q.coverage_pct,
            "misalignment_deg": float(np.rad2deg(so3.angle(mag.misalignment))),
            "misalignment_std_deg": float(np.rad2deg(np.sqrt(np.trace(w)))) if np.all(np.isfinite(w)) else None,
            "heading_std_deg": heading_std_deg(mag),
            "heading_error_deg": 0.0, "residual_misalignment_deg": 0.0,
        }
        why: dict[str, str] = {}
        if firmware is not None:
            try:
                lost = export(cal, firmware, dict(rec.params), Options(), [mag.id]).mags[0].lost()
                m["heading_error_deg"] = lost["heading_error_deg"]
                m["residual_misalignment_deg"] = lost["residual_misalignment_deg"]
            except MagcalError as exc:
                m["heading_error_deg"] = m["residual_misalignment_deg"] = None
                why["heading_error_deg"] = why["residual_misalignment_deg"] = str(exc)
        m["interference_pct"], reason = _interference(cal, mag, peak)
        if reason:
            why["interference_pct"] = reason
        why |= {k: "the method does not estimate it" for k, v in m.items() if v is None and k not in why}
        out[mag.id] = (m, why)
    return out
