"""Does an effect matter in practice: the heading, field, tilt or attitude change its fitted term makes, and how far
leaving it out would move the calibration (mismatch.md section 3.8, the fourth acceptance rule of select.py)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from magcal_cli.effects.base import Target
from magcal_cli.models.map.cost import point_at
from magcal_cli.models.map.estimate import MapEstimate
from magcal_cli.streams import FloatArray

RELEVANT_DEG = 0.25
RELEVANT_FIELD = 0.01
#: the calibration shift (in its own stds) that makes an effect matter: the simulated warm-ups the heading rule
#: rejected (0.23 deg) had moved the offsets 5.7-6.4 std
RELEVANT_SIGMAS = 2.0
#: the quantile over the log that stands for an effect's largest change
TOP_QUANTILE = 0.99


def relevance(est: MapEstimate, eid: str) -> dict[str, float]:
    """The largest (99th percentile) and RMS heading change (deg) an effect's fitted term makes and its largest
    field change (%) (magnetometer effects), or tilt change (deg, accelerometer), or 10-s attitude change (deg,
    gyro)."""
    ctx = est.context
    assert ctx is not None
    b = next(x for x in ctx.bound if x.effect.id == eid)
    beta = ctx.theta[ctx.layout.cols(*b.names())]
    if not beta.size:
        return {}
    at = point_at(ctx.states, ctx.theta, ctx.layout, ctx.pre)
    value = b.effect.term(b.inputs, beta, at).value
    out = {"calibration_shift_sigma": calibration_shift(est, b.names())}
    if b.effect.target is Target.MAG:
        dh = value @ np.linalg.inv(at.D).T                      # fraction of the field, body frame
        east = np.einsum("kij,kj->ki", ctx.states, dh)[:, 1]
        dip = float(ctx.layout.get(ctx.theta, "dip")[0])
        head = np.rad2deg(np.abs(east) / max(abs(np.cos(dip)), 0.05))
        return out | {"heading_max_deg": _top(head), "heading_rms_deg": float(np.sqrt(np.mean(head**2))),
                      "field_max_pct": _top(100.0 * np.linalg.norm(dh, axis=1))}
    if b.effect.target is Target.ACCEL:
        tilt = np.rad2deg(np.linalg.norm(value, axis=1) / 9.80665)
        return out | {"tilt_max_deg": _top(tilt), "tilt_rms_deg": float(np.sqrt(np.mean(tilt**2)))}
    dt = float(np.median(np.diff(ctx.ep.t)))
    k = max(1, int(round(10.0 / dt)))
    acc = np.cumsum(value, axis=0)
    drift = np.linalg.norm(acc[k:] - acc[:-k], axis=1) if acc.shape[0] > k else np.linalg.norm(acc, axis=1)
    return out | {"attitude_10s_max_deg": _top(np.rad2deg(drift))}


def calibration_shift(est: MapEstimate, names: Sequence[str]) -> float:
    """How far (in their own stds) leaving the effect out would move the calibration (D, o, dip), to first order:
    the posterior regression of those on the effect's parameters at beta = 0, against their std with beta held."""
    cal, eff = est.layout.cols("D", "o", "dip"), est.layout.cols(*names)
    c = est.cov
    c_ce, c_ee = c[np.ix_(cal, eff)], c[np.ix_(eff, eff)]
    try:
        gain = np.linalg.solve(c_ee, c_ce.T).T                  # C_ce C_ee^-1
    except np.linalg.LinAlgError:
        return 0.0
    shift = gain @ est.theta[eff]
    held = np.clip(np.diag(c[np.ix_(cal, cal)] - gain @ c_ce.T), 1e-300, None)
    return float(np.max(np.abs(shift) / np.sqrt(held)))


def _top(x: FloatArray) -> float:
    """The "largest" change: the TOP_QUANTILE of |x| (a single vibration spike is not the operating envelope)."""
    return float(np.quantile(np.abs(x), TOP_QUANTILE))


def relevant(rel: dict[str, float]) -> bool:
    """Does the effect matter in practice: for the heading, the field or the tilt, or for the calibration's own
    honesty (left out, it would move D, o or the dip by more than RELEVANT_SIGMAS of their stds)?"""
    return any(v >= RELEVANT_DEG for k, v in rel.items() if k.endswith("max_deg")) or \
        rel.get("field_max_pct", 0.0) >= 100.0 * RELEVANT_FIELD or \
        rel.get("calibration_shift_sigma", 0.0) >= RELEVANT_SIGMAS
