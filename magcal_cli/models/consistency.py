"""How far several calibrated magnetometers on one vehicle disagree: the "compasses inconsistent" check (issue 14).

Each magnetometer's calibration, its misalignment to the IMU included (the model y = D R^T m_n + o, so
m_b = D^-1 (y - o) is the unit field in the IMU body frame), turns its readings into the field in the body frame.
On one rigid vehicle every calibrated magnetometer should then show the same direction and strength at the same
time; ArduPilot (COMPASS_CONSISTENT: XY angle, 3-D angle, length) and PX4 (COM_ARM_MAG_ANG) refuse to arm when
they do not. Here the per-epoch angle between every pair of calibrated directions and the difference of their
strengths (relative to each one's calibrated field, 1 = nominal) are summarised as RMS over the log's common
span, and a magnetometer that agrees with none of the others becomes a WARNING finding (data, not an exception).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from magcal_cli.align import columns
from magcal_cli.findings import Finding, Severity
from magcal_cli.models.result import MagFit
from magcal_cli.streams import FloatArray, Stream

#: a magnetometer is the outlier when even its closest partner disagrees by more than this (deg / % RMS) ...
OUTLIER_MIN_DEG = 2.0
OUTLIER_MIN_PCT = 2.0
#: ... and by more than this factor times the typical closest-partner disagreement of the others
OUTLIER_RATIO = 3.0
#: at least this many common epochs to judge; at most about MAX_EPOCHS of them, evenly spaced (RMS over 30 x 30
#: pairs: a few thousand epochs pin it to a few per cent)
MIN_EPOCHS = 20
MAX_EPOCHS = 2000


@dataclass(frozen=True, eq=False)
class Consistency:
    """Pairwise RMS angle (M, M) deg and strength difference (M, M) % between calibrated magnetometers over
    `epochs` common epochs, each one's closest-partner disagreement and the outliers (indices into `ids`)."""

    ids: tuple[str, ...]
    angle_deg: FloatArray
    norm_pct: FloatArray
    epochs: int
    outliers: tuple[int, ...]

    def closest(self) -> tuple[FloatArray, FloatArray]:
        """Per magnetometer: RMS angle (deg) and strength difference (%) to the partner that agrees best."""
        eye = np.eye(len(self.ids), dtype=bool)
        return (np.where(eye, np.inf, self.angle_deg).min(axis=1), np.where(eye, np.inf, self.norm_pct).min(axis=1))

    def evidence(self) -> dict[str, Any]:
        """Numbers for a finding's evidence (and the report)."""
        ang, norm = self.closest()
        return {"epochs": self.epochs, "sensors": {
            i: {"closest_angle_rms_deg": float(a), "closest_norm_rms_pct": float(n),
                "median_angle_rms_deg": float(np.median(np.delete(self.angle_deg[k], k))),
                "median_norm_rms_pct": float(np.median(np.delete(self.norm_pct[k], k)))}
            for k, (i, a, n) in enumerate(zip(self.ids, ang, norm, strict=True))}}


def calibrated(fit: MagFit, stream: Stream, t: FloatArray) -> FloatArray:
    """m_b = D^-1 (y - o) of a stream at times t (linear interpolation of the readings), (K, 3), unit nominal."""
    y = columns(t, stream.t, stream.xyz)
    return np.asarray((y - fit.o) @ np.linalg.inv(fit.D).T, dtype=np.float64)


def measure(fits: Sequence[MagFit], streams: Sequence[Stream]) -> Consistency | None:
    """The disagreement of the calibrated magnetometers on the times of the one with most readings inside their
    common span; None with fewer than two or too short an overlap."""
    if len(fits) < 2:
        return None
    start, end = max(float(s.t[0]) for s in streams), min(float(s.t[-1]) for s in streams)
    ref = max(streams, key=lambda s: int(np.count_nonzero((s.t >= start) & (s.t <= end))))
    t = ref.t[(ref.t >= start) & (ref.t <= end)]
    if t.size < MIN_EPOCHS:
        return None
    t = t[:: max(1, t.size // MAX_EPOCHS)]
    m = np.stack([calibrated(f, s, t) for f, s in zip(fits, streams, strict=True)])     # (M, K, 3)
    norm = np.linalg.norm(m, axis=2)
    u = m / np.maximum(norm, 1e-300)[:, :, None]
    cos = np.clip(np.einsum("ikc,jkc->ijk", u, u), -1.0, 1.0)
    angle = np.degrees(np.sqrt(np.mean(np.arccos(cos) ** 2, axis=2)))
    diff = 100.0 * np.sqrt(np.mean((norm[:, None, :] - norm[None, :, :]) ** 2, axis=2))
    out = Consistency(tuple(f.id for f in fits), angle, diff, int(t.size), ())
    return Consistency(out.ids, angle, diff, out.epochs, outliers(out))


def outliers(c: Consistency) -> tuple[int, ...]:
    """The magnetometers (three or more) whose closest partner disagrees by more than OUTLIER_MIN_DEG (or _PCT)
    and OUTLIER_RATIO times the others' median closest-partner disagreement."""
    if len(c.ids) < 3:
        return ()
    ang, norm = c.closest()
    out = []
    for k in range(len(c.ids)):
        others = np.delete(np.arange(len(c.ids)), k)
        if ang[k] > max(OUTLIER_MIN_DEG, OUTLIER_RATIO * float(np.median(ang[others]))) or \
                norm[k] > max(OUTLIER_MIN_PCT, OUTLIER_RATIO * float(np.median(norm[others]))):
            out.append(k)
    return tuple(out)


def typical(c: Consistency) -> tuple[float, float]:
    """The median over the magnetometers that are not outliers of the closest-partner disagreement (deg, %)."""
    ang, norm = c.closest()
    ok = [k for k in range(len(c.ids)) if k not in c.outliers]
    return float(np.median(ang[ok])), float(np.median(norm[ok]))


def agree(c: Consistency) -> bool:
    """The magnetometers that are not outliers agree to within OUTLIER_MIN_DEG and OUTLIER_MIN_PCT (typically)."""
    ang, norm = typical(c)
    return ang <= OUTLIER_MIN_DEG and norm <= OUTLIER_MIN_PCT


def findings(c: Consistency | None, where: str) -> list[Finding]:
    """An INFO finding with the numbers, and a WARNING per outlier (or for a pair that disagrees)."""
    if c is None:
        return []
    ang, norm = c.closest()
    ok = [k for k in range(len(c.ids)) if k not in c.outliers]
    out = [Finding(Severity.INFO, "magnetometer_consistency",
                   f"{where}: after calibration the {len(c.ids)} magnetometers' fields in the body frame differ in "
                   f"direction by {float(np.median(ang[ok])):.2f} deg RMS and in strength by "
                   f"{float(np.median(norm[ok])):.2f} % RMS (median over the magnetometers of the difference to the "
                   f"closest other one, over {c.epochs} epochs of their common span)", c.evidence())]
    for k in c.outliers:
        out.append(Finding(
            Severity.WARNING, "magnetometer_inconsistent",
            f"{where}: {c.ids[k]} disagrees with the other magnetometers after calibration: its field points "
            f"{ang[k]:.1f} deg RMS away from the closest other one and its strength differs by {norm[k]:.1f} % RMS "
            f"(the others: {float(np.median(ang[ok])):.2f} deg, {float(np.median(norm[ok])):.2f} %). This is what an "
            "autopilot reports as 'compasses inconsistent': a disturbance near it (power wiring, motors, steel) or a "
            "calibration that does not hold; do not use it for heading until the cause is found",
            {"sensor": c.ids[k], "angle_rms_deg": float(ang[k]), "norm_rms_pct": float(norm[k])}))
    if len(c.ids) >= 3 and not agree(c):
        a, n = typical(c)
        out.append(Finding(
            Severity.WARNING, "magnetometer_inconsistent",
            f"{where}: after calibration the magnetometers disagree with each other by {a:.1f} deg and {n:.1f} % RMS "
            "(each with the closest other one) and no single one is the outlier: each sees its own disturbance, or "
            "the log's motion left parts of the calibrations uncertain; what an autopilot reports as 'compasses "
            "inconsistent' once it exceeds its limit", {"angle_rms_deg": a, "norm_rms_pct": n}))
    if len(c.ids) == 2 and (ang[0] > OUTLIER_MIN_DEG or norm[0] > OUTLIER_MIN_PCT):
        out.append(Finding(
            Severity.WARNING, "magnetometer_inconsistent",
            f"{where}: {c.ids[0]} and {c.ids[1]} disagree after calibration by {ang[0]:.1f} deg RMS in direction and "
            f"{norm[0]:.1f} % RMS in strength; two cannot tell which one is disturbed (a third magnetometer, or "
            "--method attitude against the World Magnetic Model, can)",
            {"angle_rms_deg": float(ang[0]), "norm_rms_pct": float(norm[0])}))
    return out
