"""Kok et al. 2012, Algorithm 1: ellipsoid fit, ellipsoid rotation from verticals, initial orientations,
then maximum likelihood over {D, o, dip, R_k} with the noise covariances (methods.md section 2).

Input pairs (y_k, v_k) are magnetometer readings with unit verticals taken at the same orientation: the
means of still segments (each a sufficient statistic for its pose) or quasi-static samples. Work is done
in units of the fitted field scale so that D ~ I; results are returned in tesla.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal_cli import so3
from magcal_cli.align import interpolate
from magcal_cli.config import Config
from magcal_cli.detect import window_means
from magcal_cli.ellipsoid import Ellipsoid, fit_ellipsoid
from magcal_cli.errors import ConvergenceError, InsufficientDataError
from magcal_cli.models.accel import UP_N, G, vertical_factor
from magcal_cli.models.factor import Factor, Linearize
from magcal_cli.models.mag import MagLayout, field_nav, mag_factor
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import ImuFit, MagFit, MethodResult
from magcal_cli.models.sandwich import cluster_robust_cov, time_clusters
from magcal_cli.models.solve import Options, Solution, solve
from magcal_cli.params import MAG
from magcal_cli.streams import FloatArray, Stream

#: theta = (vec D column-major, o, dip): `params.MAG`, the calibration document's covariance order
LAYOUT = MagLayout(*(MAG.slice(n).start for n in MAG.names))
#: verticals all within this angle (deg, 95th percentile) of their mean: level or yaw-only motion, refused
MIN_TILT_SPREAD_DEG = 10.0


@dataclass(frozen=True, eq=False)
class KokData:
    """The ellipsoid fitted to all readings, and K pairs of readings y (K, 3) and unit verticals v (K, 3)."""

    mag_id: str
    ellipsoid: Ellipsoid
    y: FloatArray
    v: FloatArray
    source: str
    t: FloatArray | None = None       # times of quasi-static pairs: their errors are clustered in time

    @classmethod
    def from_samples(cls, mag_id: str, mag_all: FloatArray, y: FloatArray, v: FloatArray, source: str,
                     where: str = "kok2012") -> KokData:
        """Fit the ellipsoid (Sec. IV-A) to at most ~5000 evenly spaced readings and pair it with (y, v)."""
        ell = fit_ellipsoid(mag_all[:: max(1, len(mag_all) // 5000)], where)
        return cls(mag_id, ell, y, v, source)


def rotate_ellipsoid(h: FloatArray, v: FloatArray) -> tuple[FloatArray, float]:
    """R, d minimising 1/2 sum (d - v_k^T R^T h_k)^2 over SO(3) x R (Kok 2012, eq. 25).

    Started from the linear solution of v_k^T M h_k = d (M = R^T up to scale) when K >= 10, else R = I.
    """
    k = len(h)
    rot0, d0 = np.eye(3), float(np.mean(np.sum(v * h, axis=1)))
    if k >= 10:
        rows = np.concatenate([np.einsum("ki,kj->kij", v, h).reshape(k, 9), -np.ones((k, 1))], axis=1)
        eta = np.linalg.svd(rows, full_matrices=False)[2][-1]
        m = eta[:9].reshape(3, 3)
        alpha = float(np.cbrt(np.linalg.det(m)))
        if abs(alpha) > 1e-12:
            rot0, d0 = so3.project(m / alpha).T, float(eta[9] / alpha)
    idx = np.zeros(k, dtype=np.int64)

    def linearize(states: FloatArray, theta: FloatArray, jac: bool) -> list[Factor]:
        mb = h @ states[0]                                    # rows of (R^T h_k)^T
        r = (theta[0] - np.sum(v * mb, axis=1))[:, None]
        if not jac:
            return [Factor("dip", r)]
        jx = -np.einsum("ki,kij->kj", v, so3.hat(mb))[:, None, :]
        return [Factor("dip", r, idx, jx, None, np.ones((k, 1, 1)))]

    sol = solve(linearize, rot0[None], np.array([d0]), Options(max_iterations=50))
    return sol.states[0], float(sol.theta[0])


def initial_orientations(d0: FloatArray, o0: FloatArray, dip0: float, y: FloatArray, v: FloatArray) -> FloatArray:
    """R_k (K, 3, 3) aligning (m_n0, up) with (D0^-1 (y_k - o0), v_k) (Kok 2012, Sec. IV-C; Wahba's problem)."""
    h = (y - o0) @ np.linalg.inv(d0).T
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    body = np.stack([h, v], axis=1)
    return so3.wahba(body, np.stack([field_nav(dip0), UP_N]))


def _sigma_update(sol: Solution, sig_m: float, sig_v: float, where: str = "kok2012") -> tuple[float, float]:
    """ML noise levels per residual group with leverage-corrected degrees of freedom (REML-like).

    A vertical residual has 2 informative directions per pair (the one along v_k is second order).
    """
    fm, fv = sol.factors
    h_m, h_v = sol.leverage(fm).sum(), sol.leverage(fv).sum()
    k = fm.r.shape[0]
    dof_m, dof_v = 3 * k - h_m, 2 * k - h_v
    if dof_m <= 1.0 or dof_v <= 1.0:
        msg = (f"{where}: too few distinct measurement pairs to estimate the noise levels; hold the sensor still "
               "in more orientations (on each side and upside down) for 2-4 s each")
        raise InsufficientDataError(msg)
    ss_m = float(np.sum(fm.r**2)) * sig_m**2
    ss_v = float(np.sum(fv.r**2)) * sig_v**2
    return float(np.sqrt(ss_m / dof_m)), float(np.sqrt(ss_v / dof_v))


def fit_kok2012(data: KokData, sigma_rounds: int = 3, where: str = "kok2012") -> MagFit:
    """Algorithm 1 of Kok et al. 2012 on `data`; covariance of (vec D, o, dip) from the ML information."""
    k = len(data.y)
    if k < 8:
        msg = (f"{where}: only {k} vertical measurements; Kok 2012 needs at least 8 "
               "(hold the sensor still in more orientations)")
        raise InsufficientDataError(msg)
    ell = data.ellipsoid
    scale = float(np.cbrt(np.linalg.det(ell.D0)))
    dt0, o0 = ell.D0 / scale, ell.o0 / scale
    y = data.y / scale
    h = (y - o0) @ np.linalg.inv(dt0).T
    rot, d = rotate_ellipsoid(h, data.v)
    d0 = dt0 @ rot                                                   # eq. 24
    dip0 = float(-np.arcsin(np.clip(d, -1.0, 1.0)))                  # d = up . m_n = -sin(dip)
    states0 = initial_orientations(d0, o0, dip0, y, data.v)
    theta0 = MAG.zeros()
    MAG.put(theta0, "D", d0.ravel(order="F"))
    MAG.put(theta0, "o", o0)
    MAG.put(theta0, "dip", dip0)
    idx = np.arange(k)
    sig_m, sig_v = 1e-3, 1e-2                                        # replaced by the ML estimate below

    def make(sm: float, sv: float) -> Linearize:
        lm, lv = np.eye(3) / sm, np.eye(3) / sv

        def linearize(states: FloatArray, theta: FloatArray, jac: bool) -> list[Factor]:
            return [mag_factor(states, y, lm, theta, LAYOUT, idx, jac),
                    vertical_factor(states, data.v, lv, idx, jac)]
        return linearize

    states, theta, iters = states0, theta0, 0
    log: list[str] = []
    sol = None
    for _ in range(max(1, sigma_rounds)):
        sol = solve(make(sig_m, sig_v), states, theta)
        states, theta, iters = sol.states, sol.theta, iters + sol.iterations
        log.extend(sol.log)
        sig_m, sig_v = _sigma_update(sol, sig_m, sig_v, where)
    sol = solve(make(sig_m, sig_v), states, theta)
    log.extend(sol.log)
    if not np.all(np.isfinite(sol.cov_theta)):
        msg = f"{where}: the ML problem is singular at the optimum; record more distinct orientations"
        raise ConvergenceError(msg, tuple(log))
    cov_w = sol.cov_theta
    if data.t is not None:
        # per-sample verticals share the tilt of any accelerometer bias, which drifts with the orientation:
        # errors correlate over tens of seconds, so use time clusters with Newey-West lags (docs/methods.md)
        ids = time_clusters(data.t)
        cov_w = cluster_robust_cov(sol, [ids, ids], lags=4)
    scale_vec = MAG.si_factors(scale)
    cov = cov_w * np.outer(scale_vec, scale_vec)
    dmat, o, dip = LAYOUT.unpack(sol.theta)
    resid = sol.factors[0].r * sig_m * scale
    return MagFit(data.mag_id, dmat * scale, o * scale, dip, cov,
                  float(np.sqrt(np.mean(resid**2))), k, iters + sol.iterations, sol.converged, tuple(log))


def distinct_poses(v: FloatArray, m: FloatArray, separation_deg: float) -> int:
    """Number of poses whose vertical or field direction differs by >= separation from every earlier kept pose."""
    cos_sep = np.cos(np.deg2rad(separation_deg))
    mh = m / np.linalg.norm(m, axis=1, keepdims=True)
    kept: list[int] = []
    for i in range(len(v)):                          # poses, not samples: a few dozen at most
        if any(v[i] @ v[j] > cos_sep and mh[i] @ mh[j] > cos_sep for j in kept):
            continue
        kept.append(i)
    return len(kept)


def kok_data(problem: Problem, mag: Stream, min_poses: int, separation_deg: float,
             gravity_tolerance: float) -> KokData:
    """Vertical measurements for one magnetometer: still-segment means, else quasi-static samples."""
    segs = problem.still.segments
    ell = fit_ellipsoid(mag.xyz[:: max(1, len(mag) // 5000)], f"{problem.where}: {mag.id}")
    if segs:
        y, counts = window_means(mag, segs)
        keep = counts > 0
        v = np.array([s.vertical for s in segs])[keep]
        y = y[keep]
        if len(y) >= 8 and distinct_poses(v, y - ell.o0, separation_deg) >= min_poses:
            return KokData(mag.id, ell, y, v, f"{len(y)} still segments")
    t = mag.t
    inside = (t >= problem.acc.t[0]) & (t <= problem.acc.t[-1])
    a = interpolate(problem.acc, t[inside])
    norm = np.linalg.norm(a, axis=1)
    quasi = np.abs(norm / G - 1.0) <= gravity_tolerance
    y, v, tq = mag.xyz[inside][quasi], a[quasi] / norm[quasi, None], t[inside][quasi]
    step = max(1, len(y) // 20000)
    return KokData(mag.id, ell, y[::step], v[::step], f"{len(y[::step])} quasi-static samples", tq[::step])


def distinct_directions(v: FloatArray, separation_deg: float, enough: int = 64, cells: int = 2000) -> int:
    """Number (up to `enough`) of directions among the vectors v (K, 3) at least `separation_deg` apart, counted
    greedily over the cells of a Fibonacci sphere lattice they fall in (thousands of samples: one product)."""
    if len(v) == 0:
        return 0
    k = np.arange(cells) + 0.5
    z = 1.0 - 2.0 * k / cells
    phi = np.pi * (1.0 + np.sqrt(5.0)) * k
    centres = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    cos_sep = np.cos(np.deg2rad(separation_deg))
    kept = np.zeros((0, 3))
    for c in centres[np.unique(np.argmax(u @ centres.T, axis=1))]:     # cells, not samples: at most `cells`
        if kept.shape[0] and np.max(kept @ c) > cos_sep:
            continue
        kept = np.vstack([kept, c])
        if kept.shape[0] >= enough:
            break
    return int(kept.shape[0])


def vertical_spread_deg(v: FloatArray) -> float:
    """95th percentile of the angle (deg) between the unit verticals (K, 3) and their mean direction."""
    mean = v.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    if len(v) == 0 or norm < 1e-6:
        return 180.0
    return float(np.percentile(np.degrees(np.arccos(np.clip(v @ (mean / norm), -1.0, 1.0))), 95))


def gyro_bias_from_still(problem: Problem) -> ImuFit:
    """Gyro bias = mean rate over the still samples (std = noise / sqrt(n)); Kok 2012 has no accelerometer bias."""
    segs = problem.still.segments
    if not segs:
        return ImuFit(problem.imu_id)
    n = sum(s.n for s in segs)
    return ImuFit(problem.imu_id, None, problem.still.gyr_bias, None, problem.still.gyr_noise / np.sqrt(n))


def run(problem: Problem, cfg: Config) -> MethodResult:
    """Kok 2012 for every magnetometer of the problem."""
    fits, notes = [], []
    for mag in problem.mags:
        data = kok_data(problem, mag, cfg.min_poses, cfg.min_pose_separation_deg, cfg.still.gravity_tolerance)
        if len(data.y) < 8:
            n_seg = len(problem.still.segments)
            msg = (f"{problem.where}: only {n_seg} stationary segments and too few quasi-static samples for "
                   f"{mag.id}; hold the sensor still in >= {cfg.min_poses} distinct orientations for 2-4 s each")
            raise InsufficientDataError(msg)
        spread = vertical_spread_deg(data.v)
        if spread < MIN_TILT_SPREAD_DEG:
            msg = (f"{problem.where}: {mag.id}: every vertical measurement ({data.source}) lies within {spread:.0f} deg "
                   "of the same direction (level or yaw-only motion), which cannot determine the calibration; hold "
                   f"the sensor still in >= {cfg.min_poses} orientations that differ in tilt -- on each side and upside "
                   "down -- for 2-4 s each")
            raise InsufficientDataError(msg)
        poses = distinct_directions(data.v, cfg.min_pose_separation_deg)
        if poses < cfg.min_poses:
            msg = (f"{problem.where}: {mag.id}: the vertical measurements ({data.source}) show only {poses} distinct "
                   f"orientations ({cfg.min_pose_separation_deg:g} deg apart); Kok 2012 needs >= {cfg.min_poses}: hold "
                   "the sensor still in more orientations -- on each side and upside down -- for 2-4 s each")
            raise InsufficientDataError(msg)
        notes.append(f"{mag.id}: vertical measurements from {data.source}")
        fits.append(fit_kok2012(data, cfg.kok_sigma_rounds, f"{problem.where}: {mag.id}"))
    return MethodResult("kok2012", tuple(fits), gyro_bias_from_still(problem), {}, tuple(notes))
