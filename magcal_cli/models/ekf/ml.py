"""Kok & Schoen 2016: calibration by maximising the EKF's innovation likelihood (`--method ekf-ml`).

An orientation-only EKF (gyro input, accelerometer and magnetometer updates; `core.py`) gives the innovations e_k
and their covariances S_k; the negative log-likelihood sum_k 1/2 (log det S_k + e_k^T S_k^-1 e_k) is minimised
over theta = (b_a, b_g, vec D, o, dip) and three log variance factors (accelerometer, gyro, magnetometer) that
scale the start noise levels (methods.md section 4; the authors' ML/calneglkh.m).

Instead of the paper's quasi-Newton method with numerical gradients (one filter pass per parameter), one pass
carries the forward-mode sensitivities of the filter recursion -- d R_hat (as a tangent Psi, R_hat(theta + d) =
R_hat Exp(Psi d)), d P, d e_k, d S_k -- and accumulates the exact gradient and the Fisher information
sum_k de^T S^-1 de + 1/2 tr(S^-1 dS_i S^-1 dS_j) (Gupta & Mehra 1974). Fisher scoring then converges in a few
passes (from one augmented-EKF pass as the start), and the inverse Fisher information at the optimum is the
reported covariance. Additive magnetometer effects (current, throttle, temperature; `ekf/effects.py`) append
their parameters beta after the noise factors: the innovation loses the plug-in's term, e_k = y_k - h_k - t_k(beta),
and its sensitivity gains d e_k / d beta = -d t_k / d beta; a plug-in's prior (the throttle exponent's) adds its
Gaussian term to the likelihood. See docs/method-ekf.md.
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
from magcal_cli.models.epochs import Noise
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MethodResult
from magcal_cli.params import BASE, ParamBlock
from magcal_cli.progress import Hook, current, noop
from magcal_cli.streams import FloatArray

#: log variance factors of the accelerometer, gyro and magnetometer noise follow theta; effect parameters follow
#: them (from column P on)
LOG_VARS = (ParamBlock("log_var_acc", 1), ParamBlock("log_var_gyr", 1), ParamBlock("log_var_mag", 1))
LAYOUT = BASE.extended(LOG_VARS)
P = LAYOUT.size
NA, NG, NM = (LAYOUT.slice(b.name).start for b in LOG_VARS)
#: theta's columns: `extended` appends, so the base parameters come first
THETA = LAYOUT.span(BASE.names[0], BASE.names[-1])
NOISE = LAYOUT.span(LOG_VARS[0].name, LOG_VARS[-1].name)
EFFECTS = slice(P, None)
GYRO_BIAS = LAYOUT.slice("gyroscope_bias")
DIP = LAYOUT.slice("dip").start
#: Fisher scoring stops when the Newton decrement g^T F^-1 g (twice the predicted decrease of the negative
#: log-likelihood) falls below this: the last step moved theta by ~0.03 standard deviations
DECREMENT_TOL = 1e-3
MAX_ITERATIONS = 30
#: epochs between progress reports inside a filter pass (a pass over a 20-minute log has ~10^5)
PROGRESS_EPOCHS = 128
#: largest change of a log variance factor per step (a factor e^2 ~ 7 in variance)
MAX_LOG_VAR_STEP = 2.0
#: the warm start is used unless it moved D or o by more than this (field units) from the start values
WARM_START_LIMIT = 0.2


@dataclass(frozen=True, eq=False)
class Pass:
    """One filter pass over B filters: negative log-likelihood (B,), gradient (B, P + p), Fisher information
    (B, P + p, P + p) (zero without derivatives) and the magnetometer innovation RMS (B,) in scaled units."""

    nll: FloatArray
    grad: FloatArray
    fisher: FloatArray
    mag_rms: FloatArray


#: dH_m/dvec(D)_c = E_ij [v]x: entry (column c = 3j + i of vec D, row 3 + i of H) takes row j of [v]x
_D_COLS = LAYOUT.cols("D")
_D_ROWS = np.array([3 + i for j in range(3) for i in range(3)])
_D_SRC = np.array([j for j in range(3) for i in range(3)])


def _kron(a: FloatArray, b: FloatArray) -> FloatArray:
    """Batched Kronecker products (B, n p, m q) of a (B, n, m) and b (B, p, q).

    With row-major vec, vec(A X B) = vec(X) kron(A^T, B): the sensitivity recursions below apply one congruence to
    all P parameter columns as a single (P x nm) @ (nm x n'm') product per filter, instead of P tiny products.
    """
    n, m = a.shape[1:]
    p, q = b.shape[1:]
    return (a[:, :, None, :, None] * b[:, None, :, None, :]).reshape(a.shape[0], n * p, m * q)


def _d_measurement_jacobian(m: ekf.Measured, d_basis: FloatArray, psi: FloatArray) -> FloatArray:
    """dH/dtheta (B, n, 6, 3), n = P (+ effect parameters): how the orientation Jacobian H = [-[u]x; D [v]x] changes
    with each parameter, directly (D, dip) and through R_hat's sensitivity psi (B, 3, n): du = [u]x psi,
    dv = [v]x psi + R^T dm_n. d_basis (B, 3, 9) holds vec(D [e_k]x), so that D [dv]x = dv^T d_basis."""
    b, n = psi.shape[0], psi.shape[2]
    hv = so3.hat(m.v)
    du = so3.hat(m.u) @ psi
    dv = hv @ psi
    dv[:, :, DIP] += m.dv
    out = np.empty((b, n, 6, 3))
    out[:, :, :3] = -so3.hat(du.transpose(0, 2, 1))
    out[:, :, 3:] = (dv.transpose(0, 2, 1) @ d_basis).reshape(b, n, 3, 3)
    out[:, _D_COLS, _D_ROWS] += hv[:, _D_SRC]
    return out


def filter_pass(batch: Batch, theta: FloatArray, derivatives: bool = True, progress: Hook = noop,
                stage: str = "ekf-ml filter pass") -> Pass:
    """Run B orientation EKFs at parameters theta (B, P + p; p the effect parameters of `batch.terms`); with
    `derivatives`, also the exact gradient and Fisher information of the negative log-likelihood (forward-mode
    sensitivities of the recursion).

    Prediction over interval k: R <- R Gamma_k, P <- Gamma^T P Gamma + s_g Q_k (preintegrated); update with the
    stacked accelerometer and magnetometer residual e = y - h(R), S = H P H^T + diag(s_a var_a, s_m var_m),
    K = P H^T S^-1, R <- R Exp(K e), P <- P - K S K^T (the authors' calneglkh.m, without the reset Jacobian).
    Sensitivities: psi (B, 3, P) with R_hat(theta + d) = R_hat Exp(psi d), dP (B, P, 3, 3), and per update
    de = -(H psi + J), dS, dK (B, P, ...), all symmetric products formed as dS_c S^-1 and vec-Kronecker products.
    """
    b, k_all = batch.size
    n = theta.shape[1]                                              # P and the effect parameters
    terms = batch.terms
    cal = ekf.Calib.of(theta)
    d_basis = (cal.D[:, None] @ so3.hat(np.eye(3))[None]).reshape(b, 3, 9)     # [e_k]x stacked over k
    gamma, psi_b = ekf.bias_steps(batch, theta[:, GYRO_BIAS])
    gamma_t = gamma.transpose(0, 1, 3, 2)
    hat_psi_b = so3.hat(psi_b.transpose(0, 1, 3, 2))                  # (B, K-1, 3, 3, 3): [a_c]x per bias column
    s_a, s_g, s_m = (np.exp(theta[:, c]) for c in (NA, NG, NM))
    var = batch.var * np.repeat(np.stack([s_a, s_m], axis=1), 3, axis=1)[:, None]
    q = batch.cov * s_g[:, None, None, None]
    weight = batch.valid.astype(float)
    rot = batch.rot0.copy()
    cov = np.broadcast_to(ekf.ROT0_STD**2 * np.eye(3), (b, 3, 3)).copy()
    psi = np.zeros((b, 3, n))
    d_cov = np.zeros((b, n, 3, 3))
    nll, grad, fisher = np.zeros(b), np.zeros((b, n)), np.zeros((b, n, n))
    ss_mag = np.zeros(b)
    eye6 = np.eye(6)
    acc_diag, mag_diag = (np.arange(3), np.arange(3)), (np.arange(3, 6), np.arange(3, 6))
    if terms is not None:                                           # additive magnetometer terms: y += t(beta)
        t_value, t_beta = terms.table(theta[:, EFFECTS], k_all)
    for k in range(k_all):
        if k % PROGRESS_EPOCHS == 0:
            progress(stage, k, k_all)
        if k > 0:                                                   # predict over the interval k-1 -> k
            gm, gt = gamma[:, k - 1], gamma_t[:, k - 1]
            rot = rot @ gm
            mid = gt @ cov @ gm
            cov = mid + q[:, k - 1]
            if derivatives:
                psi = gt @ psi
                psi[:, :, GYRO_BIAS] += psi_b[:, k - 1]
                d_cov = (d_cov.reshape(b, n, 9) @ _kron(gm, gm)).reshape(b, n, 3, 3)     # Gamma^T dP Gamma
                a = hat_psi_b[:, k - 1]                             # dGamma/db_c = Gamma [a_c]x
                d_cov[:, GYRO_BIAS] += mid[:, None] @ a - a @ mid[:, None]
                d_cov[:, NG] += q[:, k - 1]
        w = weight[:, k]
        m = ekf.measure(rot, cal)
        big_h, big_ht = m.H, m.H.transpose(0, 2, 1)
        e = batch.y[:, k] - m.h
        if terms is not None:
            e[:, 3:] -= t_value[:, k]
        r_k = var[:, k]
        pht = cov @ big_ht                                              # (B, 3, 6)
        s = big_h @ pht + r_k[:, :, None] * eye6
        s_inv = np.linalg.inv(s)
        alpha = (s_inv @ e[:, :, None])[:, :, 0]
        nll += w * 0.5 * (np.linalg.slogdet(s)[1] + np.sum(e * alpha, axis=1))
        ss_mag += w * np.sum(e[:, 3:] ** 2, axis=1)
        gain = (pht @ s_inv) * w[:, None, None]                         # (B, 3, 6)
        dphi = (gain @ e[:, :, None])[:, :, 0]
        step, jr = so3.exp_and_right_jacobian(dphi)
        if derivatives:
            de = -(big_h @ psi)                                         # (B, 6, P)
            de[:, :, THETA] -= m.J
            if terms is not None:
                de[:, 3:, EFFECTS] -= t_beta[:, k]
            dh = _d_measurement_jacobian(m, d_basis, psi).reshape(b, n * 6, 3)
            a6 = (dh @ pht).reshape(b, n, 6, 6)
            ds = a6 + a6.transpose(0, 1, 3, 2) + (d_cov.reshape(b, n, 9) @ _kron(big_ht, big_ht)).reshape(b, n, 6, 6)
            ds[:, NA, acc_diag[0], acc_diag[1]] += r_k[:, :3]
            ds[:, NM, mag_diag[0], mag_diag[1]] += r_k[:, 3:]
            ds_rows = ds.reshape(b, n * 6, 6)
            v = (ds_rows @ s_inv).reshape(b, n, 6, 6)                   # dS_c S^-1 (trace-equivalent to S^-1 dS_c)
            ds_alpha = (ds_rows @ alpha[:, :, None]).reshape(b, n, 6)
            v_flat = v.reshape(b, n, 36)
            grad += w[:, None] * (0.5 * v_flat[:, :, ::7].sum(axis=2) + (alpha[:, None] @ de)[:, 0]
                                  - 0.5 * np.sum(ds_alpha * alpha[:, None], axis=2))
            fisher += w[:, None, None] * (de.transpose(0, 2, 1) @ (s_inv @ de)
                                          + 0.5 * (v_flat @ v.transpose(0, 3, 2, 1).reshape(b, 36, n)))
            # dK_c = (dP_c H^T + P dh_c^T - K dS_c) S^-1, with P dh^T = (dh P)^T and K dS = (dS K^T)^T
            t1 = (d_cov.reshape(b, n * 3, 3) @ big_ht).reshape(b, n, 3, 6)
            t2 = (dh @ cov).reshape(b, n, 6, 3).transpose(0, 1, 3, 2)
            t3 = (ds_rows @ gain.transpose(0, 2, 1)).reshape(b, n, 6, 3).transpose(0, 1, 3, 2)
            d_gain = ((t1 + t2 - t3).reshape(b, n * 3, 6) @ s_inv) * w[:, None, None]      # (B, P*3, 6)
            d_dphi = (d_gain @ e[:, :, None]).reshape(b, n, 3).transpose(0, 2, 1) + gain @ de   # (B, 3, P)
            psi = step.transpose(0, 2, 1) @ psi + jr @ d_dphi
            kp = (d_gain @ pht.transpose(0, 2, 1)).reshape(b, n, 3, 3)
            gt6 = gain.transpose(0, 2, 1)
            kk = (ds.reshape(b, n, 36) @ _kron(gt6, gt6)).reshape(b, n, 3, 3)              # K dS_c K^T
            d_cov = d_cov - kp - kp.transpose(0, 1, 3, 2) - kk
        rot = rot @ step
        cov = cov - gain @ pht.transpose(0, 2, 1)
        cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    if terms is not None:                                           # the plug-ins' priors (throttle exponent)
        has = np.isfinite(terms.std)
        z = np.where(has, (theta[:, EFFECTS] - terms.mean) / np.where(has, terms.std, 1.0), 0.0)
        info = np.where(has, 1.0 / np.where(has, terms.std, 1.0) ** 2, 0.0)
        nll += 0.5 * np.sum(z**2, axis=1)
        if derivatives:
            grad[:, EFFECTS] += z * np.sqrt(info)
            fisher[:, EFFECTS, EFFECTS] += info[:, :, None] * np.eye(terms.size)
    n_valid = batch.valid.sum(axis=1)
    return Pass(nll, grad, fisher, np.sqrt(ss_mag / (3.0 * n_valid)))


def start_theta(preps: Sequence[Prepared]) -> FloatArray:
    """Start parameters (B, P + p): the joint MAP initialisation, unit noise factors, effects at the base model
    (the filters must carry the same effects)."""
    terms = ekf.stack(preps).terms if any(p.effects for p in preps) else None
    theta = np.zeros((len(preps), LAYOUT.size + (0 if terms is None else terms.size)))
    theta[:, THETA] = [p.theta0 for p in preps]
    if terms is not None:
        theta[:, EFFECTS] = terms.start()
    return theta


def warm_start(batch: Batch, theta: FloatArray, progress: Hook = noop) -> FloatArray:
    """theta (B, P) moved to one augmented-EKF pass's estimate (`ekf_aug`), where that pass stayed near the start.

    The pass costs less than one likelihood pass and halves the Fisher-scoring passes (7 -> 3 on `handheld` and
    the paper protocol, same optimum); a filter whose D or o moved by more than 0.2 of the field keeps its start.
    """
    from magcal_cli.models.ekf import aug as ekf_aug

    aug = ekf_aug.filter_pass(batch, theta[:, THETA], progress=progress,
                              stage="ekf-ml warm start (augmented EKF)").theta
    moved = np.abs(aug[:, BASE.span("D", "o")] - theta[:, LAYOUT.span("D", "o")]).max(axis=1)
    ok = np.all(np.isfinite(aug), axis=1) & (moved < WARM_START_LIMIT)
    out = theta.copy()
    out[np.ix_(ok, np.arange(THETA.start, THETA.stop))] = aug[ok, :BASE.size]
    out[ok, EFFECTS] = aug[ok, BASE.size:]                       # the effect parameters the pass also estimated
    return out


def _step(pas: Pass, active: npt.NDArray[np.bool_]) -> tuple[FloatArray, FloatArray]:
    """Fisher-scoring steps F^-1 (-g) (B, P + p) and Newton decrements g^T F^-1 g (B,)."""
    steps, dec = np.zeros(pas.grad.shape), np.zeros(pas.grad.shape[0])
    for i in np.flatnonzero(active):
        f = pas.fisher[i]
        d = np.sqrt(np.clip(np.diag(f), 1e-300, None))
        x = np.linalg.lstsq(f / np.outer(d, d), -pas.grad[i] / d, rcond=1e-12)[0] / d
        steps[i] = x
        dec[i] = -float(pas.grad[i] @ x)
    lv = steps[:, NOISE]
    steps[:, NOISE] = np.clip(lv, -MAX_LOG_VAR_STEP, MAX_LOG_VAR_STEP)
    return steps, dec


@dataclass(frozen=True, eq=False)
class Fit:
    """Fisher-scoring outcome for B filters: parameters (B, P + p), the last accepted pass there, iterations, flags."""

    theta: FloatArray
    last: Pass
    iterations: int
    converged: npt.NDArray[np.bool_]
    log: tuple[str, ...]


def fisher_scoring(batch: Batch, theta0: FloatArray, max_iterations: int = MAX_ITERATIONS, progress: Hook = noop
                   ) -> Fit:
    """Minimise the negative log-likelihood of B filters at once: Fisher-scoring steps, halved when they raise it."""

    def stage(n: int) -> str:          # the number of passes is known only at the end: each is shown on its own
        return f"ekf-ml likelihood pass {n} (at most {max_iterations + 1})"

    b = theta0.shape[0]
    acc_theta = theta0.copy()
    acc = filter_pass(batch, acc_theta, progress=progress, stage=stage(1))
    full, dec = _step(acc, np.ones(b, dtype=bool))
    converged = dec < DECREMENT_TOL
    done = converged.copy()
    fraction = np.ones(b)
    log = [f"start: -log L {np.array2string(acc.nll, precision=2)}"]
    it = 0
    while not np.all(done) and it < max_iterations:
        it += 1
        new = filter_pass(batch, acc_theta + fraction[:, None] * full, progress=progress, stage=stage(it + 1))
        # a step may not raise -log L beyond its rounding (~1e-16 of each of ~1e4 terms)
        tol = 1e-12 * np.abs(acc.nll) + 1e-9
        better = (new.nll <= acc.nll + tol) & ~done & np.all(np.isfinite(new.grad), axis=1)
        acc_theta = np.where(better[:, None], acc_theta + fraction[:, None] * full, acc_theta)
        acc = Pass(np.where(better, new.nll, acc.nll), np.where(better[:, None], new.grad, acc.grad),
                   np.where(better[:, None, None], new.fisher, acc.fisher), np.where(better, new.mag_rms, acc.mag_rms))
        steps, dec_new = _step(acc, better)
        full = np.where(better[:, None], steps, full)
        dec = np.where(better, dec_new, dec)
        fraction = np.where(better, 1.0, 0.5 * fraction)
        converged |= better & (dec < DECREMENT_TOL)
        stuck = fraction < 1e-3                     # ten halvings failed: at the optimum to rounding, or lost
        converged |= stuck & (dec < 1.0)
        done |= converged | stuck
        log.append(f"iteration {it}: -log L {np.array2string(acc.nll, precision=2)}, accepted "
                   f"{int(better.sum())}/{b}, decrement {np.array2string(dec, precision=3)}")
    return Fit(acc_theta, acc, it, converged, tuple(log))


def fit_batch(preps: Sequence[Prepared], progress: Hook = noop) -> list[ekf.Estimate]:
    """Maximum-likelihood calibration of several prepared filters at once (one Python loop per epoch for all
    filters that carry the same effects)."""
    out: list[ekf.Estimate | None] = [None] * len(preps)
    for group in ekf.groups(preps):
        for i, est in zip(group, _fit_group([preps[i] for i in group], progress), strict=True):
            out[i] = est
    return [e for e in out if e is not None]


def _fit_group(preps: Sequence[Prepared], progress: Hook) -> list[ekf.Estimate]:
    """`fit_batch` for filters that carry the same effects."""
    preps = list(preps)
    theta = warm_start(ekf.stack(preps), start_theta(preps), progress)
    fit = None
    iterations = 0
    for _ in range(3):                              # re-preintegrate when the gyro bias moved far (rarely needed)
        batch = ekf.stack(preps)
        fit = fisher_scoring(batch, theta, progress=progress)
        iterations += fit.iterations + 1                   # filter passes: the start and one per trial
        theta = fit.theta
        redo = ekf.needs_repreintegration(batch, theta[:, GYRO_BIAS])
        if not np.any(redo):
            break
        preps = [p.repreintegrated(theta[i, GYRO_BIAS]) if redo[i] else p for i, p in enumerate(preps)]
    assert fit is not None
    out = []
    for i, p in enumerate(preps):
        info = fit.last.fisher[i]
        cov = np.linalg.inv(info) if np.all(np.isfinite(info)) else np.full(info.shape, np.nan)
        if not np.all(np.isfinite(cov)):
            msg = f"{p.where}: the EKF likelihood is flat in some parameter; rotate the sensor about all three axes"
            raise ConvergenceError(msg, fit.log)
        f = np.exp(0.5 * theta[i, NOISE])
        noise = Noise(p.noise.acc * f[0], p.noise.gyr * f[1], p.noise.mag * f[2])
        keep = np.r_[np.arange(THETA.start, THETA.stop), np.arange(P, theta.shape[1])]    # calibration, effects
        out.append(ekf.estimate(p, theta[i, keep], cov[np.ix_(keep, keep)], noise, float(fit.last.mag_rms[i]),
                                iterations, bool(fit.converged[i]), fit.log,
                                (f"{p.mag_id}: EKF likelihood maximised by Fisher scoring in {iterations} passes "
                                 "with analytic sensitivities, from one augmented-EKF pass",)))
    return out


def run(problem: Problem, cfg: Config, progress: Hook | None = None) -> MethodResult:
    """Kok & Schoen 2016 for every magnetometer of the problem, each against the IMU (batched in one filter loop);
    progress defaults to the current hook (the pipeline calls every method as run(problem, cfg))."""
    preps = ekf.prepare_all(problem, cfg, "ekf-ml")
    return ekf.method_result("ekf-ml", problem, fit_batch(preps, progress or current()))

