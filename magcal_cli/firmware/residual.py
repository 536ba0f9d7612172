"""What a flown calibration leaves, measured without a new calibration: residual iron and interference.

The field the firmware computed, c (body frame), is modelled as c = Q (I + S) b + c0 + k s(t): b the true Earth
field, Q = Exp([qx, qy, 0]) a residual tilt of the compass against the IMU, S symmetric and traceless
(residual soft iron), c0 a residual offset, k the interference per unit of the signal s (battery current or
throttle) the flown compensation left. Rolled and pitched back to level with the
log's roll and pitch, b must have a constant horizontal magnitude H and vertical Z; the heading is free, so the
log's yaw, which the same compass steered, is never used. Heading error and interference follow from the fit;
their standard deviations from its covariance (the delta method), so a flight with little rotation reports a
large uncertainty instead of a wrong number. On a level vehicle a tilt qy acts like an offset qy Z along x,
so tilt, iron and offset separate only through the flight's tilts; the level heading error needs only their
sum, which level flight determines. A yaw misalignment between compass and IMU (a constant heading offset)
is invisible without a heading reference and is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from magcal_cli import so3
from magcal_cli.errors import InsufficientDataError
from magcal_cli.firmware.split import heading_error_deg
from magcal_cli.models.sandwich import newey_west, std_factors, time_clusters
from magcal_cli.params import XYZ, Layout, ParamBlock
from magcal_cli.streams import FloatArray

#: weak priors (field-strength units, rad) that keep directions the flight leaves unobserved finite
PRIOR_S, PRIOR_C0, PRIOR_Q = 0.3, 1.0, 0.2
MIN_SAMPLES = 50
MAX_SAMPLES = 3000
#: neighbouring time blocks allowed to correlate, and the false-alarm rate of the widening (as models/sandwich.py)
LAGS, FALSE_ALARM = 4, 1e-3

#: the residual fit's parameters (field quantities in units of the median field strength, tilt in rad): S's five
#: free entries, the tilt (qx, qy), c0, k (only with a signal), then the levelled field's H and Z
_S = ParamBlock("S", 5, labels=("11", "22", "12", "13", "23"))
_TILT = ParamBlock("tilt", 2, labels=("x", "y"))
_C0 = ParamBlock("c0", 3, labels=XYZ)
_K = ParamBlock("k", 3, labels=XYZ)
_H, _Z = ParamBlock("H", 1), ParamBlock("Z", 1)
LAYOUTS = {False: Layout((_S, _TILT, _C0, _H, _Z)), True: Layout((_S, _TILT, _C0, _K, _H, _Z))}


@dataclass(frozen=True, eq=False)
class Residual:
    """The fitted residual (field quantities in the stream's unit) and the figures derived from it."""

    S: FloatArray
    tilt_deg: tuple[float, float]
    c0: FloatArray
    k: FloatArray | None
    H: float
    Z: float
    signal_range: tuple[float, float]
    samples: int
    rms_pct: float
    heading_error_deg: float
    heading_error_std_deg: float
    heading_error_median_deg: float             # at the median current or throttle of the samples
    interference_pct: float | None
    interference_std_pct: float | None

    @property
    def field_strength(self) -> float:
        """|b| = sqrt(H^2 + Z^2)."""
        return float(np.hypot(self.H, self.Z))

    @property
    def dip_deg(self) -> float:
        """Dip angle of the fitted field (positive down)."""
        return float(np.rad2deg(np.arctan2(self.Z, self.H)))


def _unpack(theta: FloatArray, with_k: bool) -> tuple[FloatArray, FloatArray, FloatArray, float, float]:
    """(Q (I + S), c0, k, H, Z) from the parameter vector (LAYOUTS[with_k])."""
    lay = LAYOUTS[with_k]
    s11, s22, s12, s13, s23 = lay.get(theta, "S")
    S = np.array([[s11, s12, s13], [s12, s22, s23], [s13, s23, -s11 - s22]])
    qx, qy = lay.get(theta, "tilt")
    E = so3.exp([qx, qy, 0.0]) @ (np.eye(3) + S)
    k = lay.get(theta, "k") if with_k else np.zeros(3)
    return E, lay.get(theta, "c0"), k, float(lay.value(theta, "H")), float(lay.value(theta, "Z"))


def _residuals(theta: FloatArray, c: FloatArray, lev: FloatArray, s: FloatArray, with_k: bool,
               sigma: float) -> FloatArray:
    """Whitened |g_xy| - H and g_z - Z for every sample, then the prior rows."""
    E, c0, k, H, Z = _unpack(theta, with_k)
    b = np.linalg.solve(E, (c - c0 - s[:, None] * k).T).T
    g = np.einsum("nij,nj->ni", lev, b)
    data = np.concatenate([np.hypot(g[:, 0], g[:, 1]) - H, g[:, 2] - Z]) / sigma
    lay = LAYOUTS[with_k]
    prior = np.concatenate([lay.get(theta, "S") / PRIOR_S, lay.get(theta, "tilt") / PRIOR_Q, c0 / PRIOR_C0])
    return np.concatenate([data, prior])


def sandwich(jac: FloatArray, r: FloatArray, cov: FloatArray, t: FloatArray) -> tuple[FloatArray, int]:
    """Cluster-robust covariance of the parameters from time blocks of samples (models/sandwich.py): each
    sample's two data rows (|g_xy| - H, g_z - Z) score its block, the prior rows none; and the block count."""
    n = t.size
    ids = time_clusters(t)
    rows = np.concatenate([ids, ids])                             # data rows are [horizontal (n), vertical (n)]
    score = jac[: 2 * n] * r[: 2 * n, None]
    scores = np.zeros((int(ids.max()) + 1, jac.shape[1]))
    np.add.at(scores, rows, score)
    return cov @ newey_west(scores, LAGS) @ cov, scores.shape[0]


def widening(grad: FloatArray, cov: FloatArray, sand: tuple[FloatArray, int] | None) -> float:
    """Factor >= 1 for the std of a derived figure with gradient `grad`: sqrt(sandwich / model variance) where
    that ratio exceeds what a correct white-noise model gives by chance (chi2(nu)/nu at 1 - FALSE_ALARM)."""
    if sand is None:
        return 1.0
    model, robust = np.array([grad @ cov @ grad]), np.array([grad @ sand[0] @ grad])
    return float(std_factors(model, robust, sand[1], LAGS, FALSE_ALARM)[0])


def _heading(theta: FloatArray, with_k: bool, lo: float, hi: float) -> float:
    """Worst level heading error over all headings and the signal's range."""
    E, c0, k, H, Z = _unpack(theta, with_k)
    f = float(np.hypot(H, Z))
    dip = float(np.rad2deg(np.arctan2(Z, H)))
    return max(heading_error_deg(E, (c0 + s * k) / f, dip) for s in {lo, hi})


def fit_residual(c: npt.ArrayLike, level: npt.ArrayLike, signal: npt.ArrayLike | None = None,
                 t: npt.ArrayLike | None = None) -> Residual:
    """Fit the residual model to the flown field c (N, 3) with levelling rotations (N, 3, 3) = Ry(pitch) Rx(roll).

    `signal` (N,) is battery current (A) or throttle (0..1) at the samples; None leaves interference out. `t`
    (N,) s: the samples' times; with them the standard deviations are widened where the residuals are
    correlated in time beyond the fit's white-noise model (`widening`).
    """
    c = np.asarray(c, dtype=np.float64)
    lev = np.asarray(level, dtype=np.float64)
    step = max(1, c.shape[0] // MAX_SAMPLES)          # long logs: every step-th sample keeps the fit fast
    c, lev = c[::step], lev[::step]
    times = None if t is None else np.asarray(t, dtype=np.float64)[::step]
    if signal is not None:
        signal = np.asarray(signal, dtype=np.float64)[::step]
    if c.shape[0] < MIN_SAMPLES:
        msg = (f"{c.shape[0]} usable samples (with attitude, turning slowly); the residual fit needs at least "
               f"{MIN_SAMPLES}")
        raise InsufficientDataError(msg)
    f0 = float(np.median(np.linalg.norm(c, axis=1)))
    cn = c / f0
    with_k = signal is not None and float(np.ptp(np.asarray(signal))) > 0.0
    s = np.asarray(signal, dtype=np.float64) if with_k else np.zeros(c.shape[0])
    s_scale = float(np.max(np.abs(s))) or 1.0
    sn = s / s_scale
    g0 = np.einsum("nij,nj->ni", lev, cn)
    lay = LAYOUTS[with_k]
    theta0 = lay.zeros()
    lay.put(theta0, "H", np.median(np.hypot(g0[:, 0], g0[:, 1])))
    lay.put(theta0, "Z", np.median(g0[:, 2]))
    args = (cn, lev, sn, with_k)
    first = least_squares(_residuals, theta0, args=(*args, 0.01), loss="soft_l1", f_scale=3.0, x_scale="jac",
                          tr_solver="lsmr", max_nfev=200)
    n = c.shape[0]
    sigma = float(np.sqrt(np.mean(first.fun[: 2 * n] ** 2))) * 0.01 or 1e-6
    fit = least_squares(_residuals, first.x, args=(*args, sigma), loss="soft_l1", f_scale=3.0, x_scale="jac",
                          tr_solver="lsmr", max_nfev=200)
    jac = fit.jac
    cov = np.linalg.pinv(jac.T @ jac)
    lo, hi = float(sn.min()), float(sn.max())
    he = _heading(fit.x, with_k, lo, hi)
    grad = np.zeros(fit.x.size)
    for i in range(fit.x.size):
        step = 1e-6 * max(1.0, abs(fit.x[i]))
        d = np.zeros_like(fit.x)
        d[i] = step
        grad[i] = (_heading(fit.x + d, with_k, lo, hi) - _heading(fit.x - d, with_k, lo, hi)) / (2 * step)
    sand = None if times is None else sandwich(jac, fit.fun, cov, times)
    he_std = float(np.sqrt(max(float(grad @ cov @ grad), 0.0))) * widening(grad, cov, sand)
    E, c0, k, H, Z = _unpack(fit.x, with_k)
    F = float(np.hypot(H, Z))
    inter = inter_std = None
    if with_k:
        peak = max(abs(lo), abs(hi))
        inter = float(100.0 * np.linalg.norm(k) * peak / F)
        gk = np.zeros(fit.x.size)
        gk[lay.slice("k")] = 100.0 * peak / F * k / max(float(np.linalg.norm(k)), 1e-12)
        inter_std = float(np.sqrt(max(float(gk @ cov @ gk), 0.0))) * widening(gk, cov, sand)
    rms = float(100.0 * np.sqrt(np.mean((fit.fun[: 2 * n] * sigma) ** 2)) / F)
    S = so3.polar(E)[1] - np.eye(3)
    qx, qy = lay.get(fit.x, "tilt")
    tilt = (float(np.rad2deg(qx)), float(np.rad2deg(qy)))
    typical = float(np.median(sn))
    return Residual(S, tilt, c0 * f0, k * f0 / s_scale if with_k else None, H * f0, Z * f0,
                    (lo * s_scale, hi * s_scale), n, rms, he, he_std, _heading(fit.x, with_k, typical, typical),
                    inter, inter_std)
