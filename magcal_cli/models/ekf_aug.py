"""Wu et al. 2018: one pass of an EKF whose state is the orientation and the calibration (`--method ekf-aug`).

The error state is (phi, d theta) with R = R_hat Exp(phi) and theta = (b_a, b_g, vec D, o, dip) (`ekf.py`);
theta follows a random walk with tiny process noise. The gyro drives the orientation between magnetometer epochs
(preintegrated: Gamma_k = dR_k Exp(d_bias (b_g - b_bar)), whose bias Jacobian couples phi to b_g); the
accelerometer and magnetometer update both. theta and its covariance are the final mean and covariance block
(methods.md section 4; the authors' EKF/jointCalibration_wu.m). Initial standard deviations are the authors'
(config.json, EKF section), expressed in magcal's parametrisation; see docs/method-ekf.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .. import so3
from ..config import Config
from ..errors import ConvergenceError
from ..progress import Hook, current, noop
from . import ekf
from .ekf import Batch, Prepared
from .params import BASE, Layout, ParamBlock
from .problem import Problem
from .result import MethodResult

FloatArray = npt.NDArray[np.float64]

#: the filter's error state: the orientation error phi (R = R_hat Exp(phi)), then theta in BASE order
STATE = Layout((ParamBlock("orientation_error", 3, labels=("x", "y", "z")), *BASE.blocks))
N = STATE.size
PHI = STATE.slice("orientation_error")
THETA = STATE.span(BASE.names[0], BASE.names[-1])
GYRO_BIAS = STATE.slice("gyroscope_bias")
#: epochs between progress reports inside a filter pass
PROGRESS_EPOCHS = 128
#: the authors' simulated field strength (uT): their absolute magnetometer stds are relative to it
AUTHORS_FIELD_UT = 27.0


@dataclass(frozen=True)
class Settings:
    """Initial stds and random-walk densities: the authors' config.json EKF section, except the calibration walk.

    Field-relative entries are in units of the field strength (the authors' S is D / |m0|, their h and m0 are in
    uT of a 27 uT field). The authors let their nav-frame field vector m0 walk at 0.05 uT/sqrt(s) (1.9e-3 of the
    field) and keep S and h fixed; magcal lets D, o and dip walk at 3e-5 of the field per sqrt(s) (0.8 nT/sqrt(s) at
    27 uT). Without any walk the final covariance keeps the information of early updates linearised at poor
    estimates and was overconfident (|z| up to 14 on `handheld`); 3e-5 made it honest and, by discounting those
    updates, also more accurate (docs/method-ekf.md).
    """

    acc_bias_std: float = 0.5                     # init_acc_bias_std, m/s^2
    gyro_bias_std: float = 0.001                  # init_gyro_bias_std, rad/s
    D_std: float = 0.1                            # init_S_std, field-relative
    o_std: float = 2.0 / AUTHORS_FIELD_UT         # init_h_std 2 uT, field-relative
    dip_std: float = 4.0 / AUTHORS_FIELD_UT       # init_m0_std 4 uT across a 27 uT field, rad
    acc_bias_walk: float = 1e-5                   # acc_bias_noise_std, m/s^2/sqrt(s)
    gyro_bias_walk: float = 1e-5                  # gyro_bias_noise_std, rad/s/sqrt(s)
    calibration_walk: float = 3e-5                # D, o (field-relative) and dip (rad) per sqrt(s)


def initial_covariance(b: int, s: Settings) -> FloatArray:
    """Diagonal start covariance (B, N, N) of (phi, theta) in scaled units (field ~ 1)."""
    sd = STATE.zeros()
    STATE.put(sd, "orientation_error", ekf.ROT0_STD)
    STATE.put(sd, "accelerometer_bias", s.acc_bias_std)
    STATE.put(sd, "gyroscope_bias", s.gyro_bias_std)
    STATE.put(sd, "D", s.D_std)
    STATE.put(sd, "o", s.o_std)
    STATE.put(sd, "dip", s.dip_std)
    return np.repeat(np.diag(sd**2)[None], b, axis=0)


def walk_density(s: Settings) -> FloatArray:
    """Random-walk variance densities (N,) per second of theta's entries (zero for phi: the gyro covers it)."""
    q = STATE.zeros()
    STATE.put(q, "accelerometer_bias", s.acc_bias_walk**2)
    STATE.put(q, "gyroscope_bias", s.gyro_bias_walk**2)
    q[STATE.span("D", "dip")] = s.calibration_walk**2
    return q


@dataclass(frozen=True, eq=False)
class Final:
    """The filters' final theta (B, BASE.size), covariance (B, N, N), magnetometer innovation RMS (B,) and mean normalised
    innovation squared per measurement (B,) (6 when the noise levels fit)."""

    theta: FloatArray
    cov: FloatArray
    mag_rms: FloatArray
    nis: FloatArray


def filter_pass(batch: Batch, theta0: FloatArray, settings: Settings = Settings(), progress: Hook = noop,
                stage: str = "ekf-aug filter pass") -> Final:
    """One augmented-state EKF pass over B filters from theta0 (B, BASE.size)."""
    b, k_all = batch.size
    rot = batch.rot0.copy()
    x = theta0.copy()
    cov = initial_covariance(b, settings)
    walk = walk_density(settings)
    w_all = batch.valid.astype(float)
    ss_mag, nis = np.zeros(b), np.zeros(b)
    eye6 = np.eye(6)
    for k in range(k_all):
        if k % PROGRESS_EPOCHS == 0:
            progress(stage, k, k_all)
        if k > 0:                                                   # predict: R <- R Gamma, P <- F P F^T + Q
            g = (batch.d_bias[:, k - 1] @ (BASE.get(x, "gyroscope_bias") - batch.bias)[:, :, None])[:, :, 0]
            step, jr = so3.exp_and_right_jacobian(g)
            gm = batch.delta[:, k - 1] @ step
            psi = jr @ batch.d_bias[:, k - 1]                       # d phi_k / d b_g (Forster eq. 44)
            rot = rot @ gm
            gt = gm.transpose(0, 2, 1)
            rows = gt @ cov[:, PHI] + psi @ cov[:, GYRO_BIAS]       # F P: phi rows
            cov[:, PHI] = rows
            cols = cov[:, :, PHI] @ gm + cov[:, :, GYRO_BIAS] @ psi.transpose(0, 2, 1)
            cov[:, :, PHI] = cols
            cov[:, PHI, PHI] += batch.cov[:, k - 1]
            cov += (batch.dt[:, k - 1, None] * walk)[:, :, None] * np.eye(N)
        w = w_all[:, k]
        m = ekf.measure(rot, ekf.Calib.of(x))
        big_h = np.concatenate([m.H, m.J], axis=2)                  # (B, 6, N)
        e = batch.y[:, k] - m.h
        pht = cov @ big_h.transpose(0, 2, 1)                        # (B, N, 6)
        s = big_h @ pht + batch.var[:, k, :, None] * eye6
        s_inv = np.linalg.inv(s)
        gain = (pht @ s_inv) * w[:, None, None]
        dx = (gain @ e[:, :, None])[:, :, 0]
        rot = rot @ so3.exp_and_right_jacobian(dx[:, PHI])[0]
        x = x + dx[:, THETA]
        cov = cov - gain @ pht.transpose(0, 2, 1)
        cov = 0.5 * (cov + cov.transpose(0, 2, 1))
        ss_mag += w * np.sum(e[:, 3:] ** 2, axis=1)
        nis += w * np.einsum("bi,bij,bj->b", e, s_inv, e)
    n_valid = batch.valid.sum(axis=1)
    return Final(x, cov, np.sqrt(ss_mag / (3.0 * n_valid)), nis / n_valid)


def fit_batch(preps: Sequence[Prepared], settings: Settings = Settings(), progress: Hook = noop
              ) -> list[ekf.Estimate]:
    """The augmented EKF on several prepared filters at once (one Python loop per epoch for all)."""
    batch = ekf.stack(preps)
    final = filter_pass(batch, np.array([p.theta0 for p in preps]), settings, progress)
    out = []
    for i, p in enumerate(preps):
        cov = final.cov[i, THETA, THETA]
        if not np.all(np.isfinite(cov)) or not np.all(np.isfinite(final.theta[i])):
            msg = f"{p.where}: the augmented EKF diverged; check the time stamps and that the sensor was rotated"
            raise ConvergenceError(msg)
        out.append(ekf.estimate(p, final.theta[i], cov, p.noise, float(final.mag_rms[i]), 1, True, (),
                                (f"{p.mag_id}: one augmented-state EKF pass over {p.t.size} epochs; mean "
                                 f"normalised innovation {final.nis[i]:.2f} (6 when the noise levels fit)",)))
    return out


def run(problem: Problem, cfg: Config, progress: Hook | None = None) -> MethodResult:
    """Wu et al. 2018 for every magnetometer of the problem, each against the IMU (batched in one filter loop);
    progress defaults to the current hook (the pipeline calls every method as run(problem, cfg))."""
    preps = [ekf.prepare(problem, m) for m in problem.mags]    # dip starts from the data (docs/method-ekf.md)
    return ekf.method_result("ekf-aug", problem, fit_batch(preps, progress=progress or current()))
