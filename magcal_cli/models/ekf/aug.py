"""Wu et al. 2018: one pass of an EKF whose state is the orientation and the calibration (`--method ekf-aug`).

The error state is (phi, d theta) with R = R_hat Exp(phi) and theta = (b_a, b_g, vec D, o, dip) (`core.py`);
theta follows a random walk with tiny process noise. The gyro drives the orientation between magnetometer epochs
(preintegrated: Gamma_k = dR_k Exp(d_bias (b_g - b_bar)), whose bias Jacobian couples phi to b_g); the
accelerometer and magnetometer update both. theta and its covariance are the final mean and covariance block
(methods.md section 4; the authors' EKF/jointCalibration_wu.m). Initial standard deviations are the authors'
(config.json, EKF section), expressed in magcal's parametrisation; see docs/method-ekf.md. Additive magnetometer
effects (current, throttle, temperature; `ekf/effects.py`) append their parameters to the state, starting at the
base model with the plug-in's prior (else its plausibility limit) as the std.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.errors import ConvergenceError
from magcal_cli.models.ekf import core as ekf
from magcal_cli.models.ekf.core import Batch, Prepared
from magcal_cli.models.ekf.effects import Terms
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MethodResult
from magcal_cli.params import BASE, Layout, ParamBlock
from magcal_cli.progress import Hook, current, noop
from magcal_cli.streams import FloatArray

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
    effect_walk: float = 3e-5                     # effect terms (field-relative) per sqrt(s), see effect_walk()


def initial_covariance(b: int, s: Settings, effect_std: FloatArray | None = None) -> FloatArray:
    """Diagonal start covariance (B, N + p, N + p) of (phi, theta, effect parameters) in scaled units (field ~ 1);
    effect_std (B, p)."""
    sd = STATE.zeros()
    STATE.put(sd, "orientation_error", ekf.ROT0_STD)
    STATE.put(sd, "accelerometer_bias", s.acc_bias_std)
    STATE.put(sd, "gyroscope_bias", s.gyro_bias_std)
    STATE.put(sd, "D", s.D_std)
    STATE.put(sd, "o", s.o_std)
    STATE.put(sd, "dip", s.dip_std)
    sd_all = np.repeat(sd[None], b, axis=0)
    if effect_std is not None:
        sd_all = np.concatenate([sd_all, effect_std], axis=1)
    return sd_all[:, :, None] ** 2 * np.eye(sd_all.shape[1])


def walk_density(s: Settings, n_effect: int = 0) -> FloatArray:
    """Random-walk variance densities (N + n_effect,) per second of theta's entries (zero for phi: the gyro covers
    it; zero for the effect parameters, whose walk `effect_walk` sets per filter)."""
    q = np.zeros(N + n_effect)
    STATE.put(q, "accelerometer_bias", s.acc_bias_walk**2)
    STATE.put(q, "gyroscope_bias", s.gyro_bias_walk**2)
    q[STATE.span("D", "dip")] = s.calibration_walk**2
    return q


def effect_walk(terms: Terms, k_all: int, s: Settings) -> FloatArray:
    """Random-walk variance densities (B, p) per second of the effect parameters: each entry walks so that its term
    walks by s.effect_walk of the field per sqrt(s) at the RMS of its regressor d t / d beta over the log, as o does.

    A slow effect (a warm-up's temperature) is otherwise aliased with the calibration's own walk and with the
    linearisation errors of the first updates: without a walk `temperature_drift` covered its truth in 73 % of 60
    entries over 20 handheld seeds (z mean -1.8 and std 2.3 on one axis), with 3e-5 in 100 % (z std 0.55-0.76);
    `current_interference` 90 % -> 95 % (docs/method-ekf.md). A parameter without influence at the start (the
    throttle exponent at c = 0, in `ekf-ml`'s warm start) does not walk."""
    rms = np.sqrt(np.mean(terms.table(terms.start(), k_all)[1] ** 2, axis=(1, 2)))
    out: FloatArray = np.where(rms > 0.0, (s.effect_walk / np.where(rms > 0.0, rms, 1.0)) ** 2, 0.0)
    return out


@dataclass(frozen=True, eq=False)
class Final:
    """The filters' final theta (B, BASE.size + p), covariance (B, N + p, N + p) of (phi, theta), magnetometer
    innovation RMS (B,) and mean normalised innovation squared per measurement (B,) (6 when the noise levels fit)."""

    theta: FloatArray
    cov: FloatArray
    mag_rms: FloatArray
    nis: FloatArray


def predict(rot: FloatArray, x: FloatArray, terms: Terms | None = None, k: int = 0,
            valid: npt.NDArray[np.bool_] | None = None) -> tuple[FloatArray, FloatArray]:
    """The predicted measurement h (B, 6) at orientations rot (B, 3, 3) and states x (B, BASE.size + p), and its
    Jacobian (B, 6, N + p) by the error state (phi, theta, effect parameters): `ekf.measure` plus the additive
    magnetometer terms of epoch k (the plug-ins' `term`; its d_beta is their column)."""
    cal = ekf.Calib.of(x)
    m = ekf.measure(rot, cal)
    if terms is None:
        return m.h, np.concatenate([m.H, m.J], axis=2)
    value, d_beta = terms.at(k, x[:, BASE.size:], rot, m.v, m.dv, m.u, cal.D,
                             np.ones(x.shape[0], bool) if valid is None else valid)
    h = m.h.copy()
    h[:, 3:] += value
    big_j = np.zeros((x.shape[0], 6, terms.size))
    big_j[:, 3:] = d_beta
    return h, np.concatenate([m.H, m.J, big_j], axis=2)


def filter_pass(batch: Batch, theta0: FloatArray, settings: Settings = Settings(), progress: Hook = noop,
                stage: str = "ekf-aug filter pass") -> Final:
    """One augmented-state EKF pass over B filters from theta0 (B, BASE.size): the effect parameters of
    `batch.terms` start at the base model."""
    b, k_all = batch.size
    rot = batch.rot0.copy()
    terms = batch.terms
    x = theta0[:, :BASE.size] if terms is None else np.concatenate([theta0[:, :BASE.size], terms.start()], axis=1)
    cov = initial_covariance(b, settings, None if terms is None else terms.std0)
    walk = np.repeat(walk_density(settings, 0 if terms is None else terms.size)[None], b, axis=0)
    if terms is not None:
        walk[:, N:] = effect_walk(terms, k_all, settings)
    n = walk.shape[1]
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
            cov += (batch.dt[:, k - 1, None] * walk)[:, :, None] * np.eye(n)
        w = w_all[:, k]
        h, big_h = predict(rot, x, terms, k, batch.valid[:, k])
        e = batch.y[:, k] - h
        pht = cov @ big_h.transpose(0, 2, 1)                        # (B, N, 6)
        s = big_h @ pht + batch.var[:, k, :, None] * eye6
        s_inv = np.linalg.inv(s)
        gain = (pht @ s_inv) * w[:, None, None]
        dx = (gain @ e[:, :, None])[:, :, 0]
        rot = rot @ so3.exp_and_right_jacobian(dx[:, PHI])[0]
        x = x + dx[:, PHI.stop:]
        cov = cov - gain @ pht.transpose(0, 2, 1)
        cov = 0.5 * (cov + cov.transpose(0, 2, 1))
        ss_mag += w * np.sum(e[:, 3:] ** 2, axis=1)
        nis += w * np.einsum("bi,bij,bj->b", e, s_inv, e)
    n_valid = batch.valid.sum(axis=1)
    return Final(x, cov, np.sqrt(ss_mag / (3.0 * n_valid)), nis / n_valid)


def fit_batch(preps: Sequence[Prepared], settings: Settings = Settings(), progress: Hook = noop
              ) -> list[ekf.Estimate]:
    """The augmented EKF on several prepared filters at once (one Python loop per epoch for all)."""
    out: list[ekf.Estimate | None] = [None] * len(preps)
    for group in ekf.groups(preps):
        for i, est in zip(group, _fit_group([preps[i] for i in group], settings, progress), strict=True):
            out[i] = est
    return [e for e in out if e is not None]


def _fit_group(preps: Sequence[Prepared], settings: Settings, progress: Hook) -> list[ekf.Estimate]:
    """`fit_batch` for filters that carry the same effects."""
    batch = ekf.stack(preps)
    final = filter_pass(batch, np.array([p.theta0 for p in preps]), settings, progress)
    out = []
    for i, p in enumerate(preps):
        cov = final.cov[i, PHI.stop:, PHI.stop:]
        if not np.all(np.isfinite(cov)) or not np.all(np.isfinite(final.theta[i])):
            msg = f"{p.where}: the augmented EKF diverged; check the time stamps and that the sensor was rotated"
            raise ConvergenceError(msg)
        out.append(ekf.estimate(p, final.theta[i], cov, p.noise, float(final.mag_rms[i]), 1, True, (),
                                (f"{p.mag_id}: one augmented-state EKF pass over {p.t.size} epochs; mean "
                                 f"normalised innovation {final.nis[i]:.2f} (6 when the noise levels fit)",)))
    return out


def run(problem: Problem, cfg: Config, progress: Hook | None = None) -> MethodResult:
    """Wu et al. 2018 for every magnetometer of the problem, each against the IMU (batched in one filter loop), with
    the additive effects of cfg.effects; progress defaults to the current hook (the pipeline calls every method as
    run(problem, cfg))."""
    preps = ekf.prepare_all(problem, cfg, "ekf-aug")
    return ekf.method_result("ekf-aug", problem, fit_batch(preps, progress=progress or current()))
