"""Initial values for the joint MAP calibration (Huang et al. 2025, Sec. III-D; methods.md section 3).

Intrinsic magnetometer fit (Kok's ellipsoid fit, defined up to a rotation), the gyro-magnetometer misalignment
of Wu & Luo 2016 (which also gives a gyro bias when the log has no still segment), the dip angle, and the
trajectory: the gyro-integrated one the paper uses, aligned to the per-epoch accelerometer/magnetometer
attitudes, or those attitudes themselves -- whichever explains the data better.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.ellipsoid import fit_ellipsoid
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.accel import UP_N
from magcal_cli.models.mag import field_nav
from magcal_cli.streams import FloatArray

#: Wu & Luo integrate the kinematics over short windows (the authors' `alignment_interval`, s)
ALIGNMENT_WINDOW_S = 0.5
#: the magnetometer's start noise is at least the ellipsoid residual / this (`Intrinsic.noise_rms`)
WHITE_FLOOR = 10.0


@dataclass(frozen=True, eq=False)
class Intrinsic:
    """Ellipsoid fit in units of its scale (T): |D0^-1 (y/scale - o0)| ~ 1, D0 known up to a rotation."""

    D0: FloatArray
    o0: FloatArray
    scale: float
    residual_rms: float
    white_rms: float

    @property
    def noise_rms(self) -> float:
        """The magnetometer noise to start from: the residual's white part when it is smaller (a slow disturbance
        the model may take up is not noise), but not below a tenth of the whole residual (a coarse sensor's
        successive readings are often equal, which zeroes the differences' spread)."""
        if not np.isfinite(self.white_rms):
            return self.residual_rms
        return float(np.clip(self.white_rms, self.residual_rms / WHITE_FLOOR, self.residual_rms))


def white_rms(m_b: FloatArray) -> float:
    """The white part of the field-strength residual |m_b| - 1: robust RMS of successive differences / sqrt 2.

    Slow disturbances (current, temperature, a drifting offset) cancel in the differences, so this is the
    sensor's noise even when the ellipsoid residual is not; NaN with fewer than 3 readings."""
    d = np.diff(np.linalg.norm(m_b, axis=1))
    if d.size < 2:
        return float("nan")
    return 1.4826 * float(np.median(np.abs(d - np.median(d)))) / float(np.sqrt(2.0))


def intrinsic_fit(y: FloatArray, where: str) -> Intrinsic:
    """Kok 2012 ellipsoid fit on at most ~2000 evenly spaced readings, normalised so that det(D0) = 1 (the
    authors' ml_estimate uses 200; this is only a start value)."""
    ell = fit_ellipsoid(y[:: max(1, len(y) // 2000)], where)
    scale = float(np.cbrt(np.linalg.det(ell.D0)))
    m_b = (y - ell.o0) @ np.linalg.inv(ell.D0).T
    return Intrinsic(ell.D0 / scale, ell.o0 / scale, scale, ell.residual_rms, white_rms(m_b))


def from_prior(y: FloatArray, d: FloatArray, o: FloatArray) -> Intrinsic:
    """Start values from a prior calibration y = D m_b + o (tesla) instead of an ellipsoid fit (partial
    calibration: the readings may not determine an ellipsoid)."""
    scale = float(np.cbrt(abs(np.linalg.det(d))))
    m_b = (y / scale - o / scale) @ np.linalg.inv(d / scale).T
    rms = float(np.sqrt(np.mean((np.linalg.norm(m_b, axis=1) - 1.0) ** 2)))
    return Intrinsic(d / scale, o / scale, scale, rms, white_rms(m_b))


def wu_luo(h: FloatArray, phi: FloatArray, duration: FloatArray, window: int
           ) -> tuple[FloatArray, FloatArray]:
    """Misalignment R_D (h = R_D m_b, possibly improper) and gyro bias correction from the field kinematics.

    In a homogeneous field the body-frame field obeys dm_b/dt = -w x m_b, so h = R_D m_b changes by
    h_k+1 - h_k ~ [h_mid]x R_D (phi_k - db dt_k) over an interval with integrated rate phi_k (Wu & Luo 2016,
    eqs. 12-13). Summed over windows this is linear in (vec R_D, R_D db); R_D is the nearest orthogonal matrix
    of the least-squares solution (its determinant sign is kept, so a left-handed magnetometer works too).
    """
    k = phi.shape[0]
    mid = so3.hat(0.5 * (h[:-1] + h[1:]))                                 # (K-1, 3, 3)
    rows = np.empty((k, 3, 12))
    rows[:, :, :9] = np.einsum("kj,kab->kajb", phi, mid).reshape(k, 3, 9)  # (phi^T kron [h]x) vec(R_D)
    rows[:, :, 9:] = -mid * duration[:, None, None]
    starts = np.arange(0, k, max(1, window))
    a = np.add.reduceat(rows, starts, axis=0).reshape(-1, 12)
    ends = np.minimum(starts + max(1, window), k)
    b = (h[ends] - h[starts]).reshape(-1)
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    m = x[:9].reshape(3, 3, order="F")
    det = np.linalg.det(m)
    if not np.isfinite(det) or abs(det) < 1e-6:
        msg = ("map: the gyro and magnetometer do not determine their relative orientation (too little "
               "rotation); rotate the sensor about at least two different axes")
        raise InsufficientDataError(msg)
    sign = float(np.sign(det))
    r_d = sign * so3.project(sign * m)
    return r_d, r_d.T @ x[9:]


def dip_from_data(m_b: FloatArray, up_b: FloatArray) -> float:
    """Dip (rad) from the mean angle between calibrated field and vertical: up . m_b = -sin(dip)."""
    m = m_b / np.linalg.norm(m_b, axis=1, keepdims=True)
    u = up_b / np.linalg.norm(up_b, axis=1, keepdims=True)
    return float(np.arcsin(np.clip(-np.mean(np.sum(m * u, axis=1)), -1.0, 1.0)))


def attitudes(m_b: FloatArray, up_b: FloatArray, dip: float) -> FloatArray:
    """Per-epoch body->NED rotations from the vertical and the field (TRIAD: the vertical exactly, the field's
    horizontal direction for heading) -- closed form, no per-epoch SVD."""

    def triad(first: FloatArray, second: FloatArray) -> FloatArray:
        a = first / np.linalg.norm(first, axis=-1, keepdims=True)
        b = np.cross(a, second)
        b /= np.linalg.norm(b, axis=-1, keepdims=True)
        return np.stack([a, b, np.cross(a, b)], axis=-1)              # columns: orthonormal frame

    body = triad(up_b, m_b)
    nav = triad(UP_N, field_nav(dip))
    return nav @ body.transpose(0, 2, 1)


def integrated(delta: FloatArray, anchor: FloatArray, broken: npt.NDArray[np.bool_] | None = None) -> FloatArray:
    """Gyro-integrated trajectory R_k = R_0 dR_0 ... dR_k-1, with R_0 chosen to best match `anchor` (K, 3, 3).

    The paper starts from a fixed attitude; aligning the whole integrated trajectory to the per-epoch
    attitudes (one Wahba problem over all epochs) starts it from the data instead. Across a `broken` interval
    (K-1,) the gyro says nothing: each unbroken piece is integrated and aligned on its own.
    """
    cuts = [0, *(np.flatnonzero(broken) + 1 if broken is not None else []), delta.shape[0] + 1]
    out = np.empty_like(anchor)
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        rel = np.concatenate([np.eye(3)[None], so3.cumulative_product(delta[a:b - 1], reproject=False)])
        r0 = so3.project(np.einsum("kij,klj->il", anchor[a:b], rel))   # argmin sum |anchor_k - R_0 rel_k|
        out[a:b] = r0 @ rel
    return np.asarray(out, dtype=np.float64)
