"""Shared core of the two EKF baselines (methods.md section 4): inputs, start values, measurement model, results.

Both filters (`ml`, `aug`) run an error-state EKF over the orientation R (body -> NED, right perturbation
R = R_hat Exp(phi)) at the magnetometer epochs, with the gyro as input and the accelerometer (interpolated onto the
epochs, as the joint MAP does) and the magnetometer as measurements. The gyro samples between two epochs enter
through Forster preintegration (`gyro.preintegrate`): composing the per-sample predictions R <- R Exp(w dt),
P <- F P F^T + Q of the authors' filters over an interval gives exactly the preintegrated rotation and covariance,
so the sequential loop runs once per magnetometer epoch instead of once per IMU sample.

Every array carries a leading batch axis B: several independent filters (the magnetometers of a log, or the
datasets of a study) advance together, so the Python loop runs once per epoch for all of them. Shorter filters are
padded at the end (`valid` is False there: no update, identity prediction). Internally the magnetometer is in units
of its ellipsoid-fit scale (field ~ 1), as in the joint MAP; results are converted to SI.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from magcal_cli import so3, units
from magcal_cli.detect import BlockScale
from magcal_cli.errors import MagcalError
from magcal_cli.findings import Finding
from magcal_cli.models.accel import G
from magcal_cli.models.ekf.effects import Terms, fitted, layout_of, not_carried
from magcal_cli.models.epochs import BIAS_SCALE, GYRO_START_DIVISOR, Noise, epochs_for, initial_noise
from magcal_cli.models.gyro import Preintegrated, preintegrate, preintegrate_epochs
from magcal_cli.models.map import init as map_init
from magcal_cli.models.map.effects import Bound, bind
from magcal_cli.models.observability import check_observability
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit, ImuFit, MagFit, MethodResult
from magcal_cli.params import BASE, MAG
from magcal_cli.streams import FloatArray, Stream

BoolArray = npt.NDArray[np.bool_]

#: calibration parameters theta = (b_a, b_g, vec D column-major, o, dip) in `params.BASE` order, total gyro bias
ACC_BIAS, GYRO_BIAS = BASE.slice("accelerometer_bias"), BASE.slice("gyroscope_bias")
D_COLS, O_COLS = BASE.slice("D"), BASE.slice("o")
DIP = BASE.slice("dip").start
#: std (rad) of the start orientation from the first epoch's accelerometer and magnetometer: an accelerometer bias
#: b tilts the vertical by |b|/g, and a steep field turns that into a heading error of about |b|/(g cos dip) --
#: 8.8 deg for 0.45 m/s^2 at 72 deg dip on the paper protocol. The first updates then fix it.
ROT0_STD = 0.2
#: when the still-segment gyro bias and Wu & Luo's estimate from the field kinematics differ by more than this
#: (rad/s), the still segments are not still (seen at 10 Hz on the paper protocol): start from Wu & Luo's
BIAS_DISAGREEMENT = 5e-3
#: re-preintegrate when the first-order bias correction rotates an interval by more than this (rad), as the MAP does
REPREINTEGRATE_RAD = 0.01


@dataclass(frozen=True, eq=False)
class Prepared:
    """One magnetometer's filter inputs: epochs t (K,) s, measurements y (K, 6) = [acc m/s^2, mag / scale],
    the accelerometer's interpolation std factor (K,), gyro preintegration between epochs, the gyro samples (for
    re-preintegration), start noise levels, start theta (BASE) and orientation (3, 3); the additive effects bound to
    its epochs and those the log cannot test (`bind_prepared`)."""

    where: str
    mag_id: str
    t: FloatArray
    y: FloatArray
    acc_factor: FloatArray
    pre: Preintegrated
    gyr_t: FloatArray
    gyr: FloatArray
    noise: Noise
    scale: float
    theta0: FloatArray
    rot0: FloatArray
    notes: tuple[str, ...] = ()
    breaks: tuple[tuple[float, float], ...] = ()      # Problem.unmeasured
    gyr_scale: BlockScale | None = None               # Problem.gyr_scale
    effects: tuple[Bound, ...] = ()
    untestable: tuple[EffectFit, ...] = ()

    def repreintegrated(self, bias: FloatArray) -> Prepared:
        """The same inputs with the gyro preintegrated at `bias` (rad/s)."""
        pre = preintegrate(self.gyr_t, self.gyr, self.t, bias, self.noise.gyr, self.where, breaks=self.breaks,
                           scale=self.gyr_scale)
        return replace(self, pre=pre)

    @property
    def effect_ids(self) -> tuple[str, ...]:
        """The ids of the effects it carries (filters batch together only with the same ones)."""
        return tuple(e.effect.id for e in self.effects)


@dataclass(frozen=True, eq=False)
class Batch:
    """B prepared filters stacked over K epochs (padded at the end where `valid` (B, K) is False).

    y (B, K, 6); var (B, K, 6): per-epoch measurement variances at the start noise levels; delta, d_bias, cov
    (B, K-1, 3, 3): preintegrated rotation, its bias Jacobian and noise covariance; dt (B, K-1) s; bias (B, 3)
    the gyro bias the preintegration used; rot0 (B, 3, 3); the filters' additive effect terms (None: base model).
    """

    y: FloatArray
    var: FloatArray
    valid: BoolArray
    delta: FloatArray
    d_bias: FloatArray
    cov: FloatArray
    dt: FloatArray
    bias: FloatArray
    rot0: FloatArray
    terms: Terms | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(B, K)."""
        return self.valid.shape


def prepare(problem: Problem, mag: Stream, dip_prior: float | None = None) -> Prepared:
    """Epochs, preintegration and start values for one magnetometer: the joint MAP's initialisation.

    Gyro bias from the still segments (else Wu & Luo's alignment), Kok's ellipsoid fit for the intrinsic part,
    Wu & Luo's misalignment, dip from the World Magnetic Model or the data (Huang et al. 2025, Sec. III-D), and the
    start orientation from the first epoch's accelerometer and magnetometer (Wahba's problem). Noise levels: gyro
    as the joint MAP starts (still segments, else the quietest windows / 10), accelerometer and magnetometer from
    consecutive epochs (`kinematic_noise`).
    """
    where = f"{problem.where}: {mag.id}"
    intr = map_init.intrinsic_fit(mag.xyz, where)
    ep = epochs_for(problem, mag, intr.scale)
    noise = initial_noise(problem, mag, intr.scale, intr.residual_rms)
    gyr = problem.gyr
    still = bool(problem.still.segments)
    bias = problem.still.gyr_bias if still else np.zeros(3)
    pre = preintegrate_epochs(problem, ep, bias, noise.gyr, where)
    h = (ep.mag - intr.o0) @ np.linalg.inv(intr.D0).T
    window = max(1, int(round(map_init.ALIGNMENT_WINDOW_S / float(np.median(pre.duration)))))
    r_d, db = map_init.wu_luo(h, so3.log(pre.delta), pre.duration, window)
    notes = list(ep.notes)
    if not still or float(np.linalg.norm(db)) > BIAS_DISAGREEMENT:
        if still:                                      # not still after all: their gyro level is an upper bound
            noise = Noise(noise.acc, noise.gyr / GYRO_START_DIVISOR, noise.mag)
        bias = bias + db
        pre = preintegrate_epochs(problem, ep, bias, noise.gyr, where)
        why = "no still segment" if not still else (f"the still segments' gyro bias is {np.linalg.norm(db):.4f} "
                                                    "rad/s away from the field kinematics'")
        notes.append(f"{mag.id}: {why}; gyro bias started from the Wu & Luo alignment and the gyro noise from "
                     f"the quietest windows / {GYRO_START_DIVISOR:g}")
    d0 = intr.D0 @ r_d
    noise = kinematic_noise(ep.acc, ep.acc_factor, ep.mag, intr.o0, d0, pre.delta, noise)
    m_b = (ep.mag - intr.o0) @ np.linalg.inv(d0).T
    dip = dip_prior if dip_prior is not None else map_init.dip_from_data(m_b, ep.acc)
    theta = BASE.zeros()
    BASE.put(theta, "gyroscope_bias", bias)
    BASE.put(theta, "D", d0.ravel(order="F"))
    BASE.put(theta, "o", intr.o0)
    BASE.put(theta, "dip", dip)
    rot0 = map_init.attitudes(m_b[:1], ep.acc[:1], dip)[0]
    y = np.concatenate([ep.acc, ep.mag], axis=1)
    return Prepared(where, mag.id, ep.t, y, ep.acc_factor, pre, gyr.t, gyr.xyz, noise, intr.scale, theta, rot0,
                    tuple(notes), problem.unmeasured, problem.gyr_scale)


def prepare_all(problem: Problem, cfg: object, method: str) -> list[Prepared]:
    """Every magnetometer prepared for `method`, with the effects of cfg.effects bound to its epochs. The dip starts
    from the data (docs/method-ekf.md); the WMM declination (where the log's position is known) turns true-north
    effect inputs into the model's frame."""
    from magcal_cli.wmm import reference_for

    ids = tuple(getattr(cfg, "effects", ()))
    ref = reference_for(cfg) if ids else None
    declination = 0.0 if ref is None else ref.declination
    return [bind_prepared(problem, prepare(problem, m), ids, method, declination) for m in problem.mags]


def bind_prepared(problem: Problem, prep: Prepared, ids: Sequence[str], method: str, declination: float = 0.0
                  ) -> Prepared:
    """One prepared filter of `method` with the requested effects bound to its epochs (the plug-ins' `inputs`);
    effects this log cannot test are kept as `not_testable` results."""
    if not ids:
        return prep
    refused = not_carried(ids, method)
    if refused:
        msg = f"{prep.where}: the {method} method cannot carry {', '.join(refused)}; use --method map"
        raise MagcalError(msg)
    mag = next(m for m in problem.mags if m.id == prep.mag_id)
    bound, untestable = bind(problem, mag, prep.t, BASE.get(prep.theta0, "gyroscope_bias"), ids, declination)
    return replace(prep, effects=tuple(bound), untestable=tuple(untestable))


#: share of the smallest squared residuals kept by `kinematic_noise`, and E[z^2 | |z| < q] for the Gaussian
#: quantile q = 1.645 of that share: 1 - 2 q phi(q) / 0.9
KEEP = 0.9
TRUNCATED_VARIANCE = 1.0 - 2.0 * 1.6449 * 0.10314 / 0.9


def kinematic_noise(acc: FloatArray, acc_factor: FloatArray, mag: FloatArray, o: FloatArray, d: FloatArray,
                    delta: FloatArray, start: Noise) -> Noise:
    """Accelerometer and magnetometer noise std from consecutive epochs; the gyro level is kept from `start`.

    Between epochs the gyro predicts how a body-frame vector turns: x_k+1 = dR_k^T x_k for the calibrated field
    D^-1 (y - o) and for the specific force (bias and rotation errors enter only through the small rotation dR).
    Along x_k+1 the gyro's own error has no first-order effect, so the residual there is the sensors' noise alone:
    var = sigma^2 (|D^-T u|^2 + |D^-T dR u|^2) for the magnetometer, sigma^2 (f_k+1^2 + f_k^2) for the
    (interpolated) accelerometer. The mean square omits the largest 10 % (spikes, bursts of motion) and is
    corrected for that truncation of a Gaussian; a median would read 0 on quantised logs, where most differences
    are exactly zero. Unlike still segments this sees quantisation and needs no still period (the detector finds
    false ones at 10 Hz).
    """
    def along(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        u = x[1:] / np.linalg.norm(x[1:], axis=1, keepdims=True)
        r = x[1:] - np.einsum("kji,kj->ki", delta, x[:-1])
        return np.sum(r * u, axis=1), u

    def robust_var(res: FloatArray, factor: FloatArray) -> float:
        z2 = np.sort(res**2 / factor)
        return float(np.mean(z2[: max(1, int(KEEP * z2.size))]) / TRUNCATED_VARIANCE)

    d_inv = np.linalg.inv(d)
    r_m, u = along((mag - o) @ d_inv.T)
    c_m = np.sum((u @ d_inv) ** 2, axis=1) + np.sum((np.einsum("kij,kj->ki", delta, u) @ d_inv) ** 2, axis=1)
    r_a, _ = along(acc)
    c_a = acc_factor[1:] ** 2 + acc_factor[:-1] ** 2
    sig_m = np.sqrt(robust_var(r_m, c_m))
    sig_a = np.sqrt(robust_var(r_a, c_a))
    return Noise(np.full(3, max(sig_a, 1e-4)), start.gyr, np.full(3, max(sig_m, 1e-6)))


def stack(preps: Sequence[Prepared]) -> Batch:
    """Stack prepared filters along a batch axis, padding shorter ones at the end."""
    b = len(preps)
    k = max(p.t.size for p in preps)
    y = np.zeros((b, k, 6))
    var = np.ones((b, k, 6))
    valid = np.zeros((b, k), dtype=bool)
    delta = np.broadcast_to(np.eye(3), (b, k - 1, 3, 3)).copy()
    d_bias, cov = np.zeros((b, k - 1, 3, 3)), np.zeros((b, k - 1, 3, 3))
    dt = np.zeros((b, k - 1))
    for i, p in enumerate(preps):
        n = p.t.size
        y[i, :n] = p.y
        var[i, :n, :3] = p.noise.acc**2 * p.acc_factor[:, None] ** 2
        var[i, :n, 3:] = p.noise.mag**2
        valid[i, :n] = True
        delta[i, :n - 1], d_bias[i, :n - 1], cov[i, :n - 1] = p.pre.delta, p.pre.d_bias, p.pre.cov
        dt[i, :n - 1] = p.pre.duration
    return Batch(y, var, valid, delta, d_bias, cov, dt, np.array([p.pre.bias for p in preps]),
                 np.array([p.rot0 for p in preps]), Terms.of([p.effects for p in preps], [p.scale for p in preps]))


def groups(preps: Sequence[Prepared]) -> list[list[int]]:
    """Indices of the filters that can share a batch: those carrying the same effects."""
    out: dict[tuple[str, ...], list[int]] = {}
    for i, p in enumerate(preps):
        out.setdefault(p.effect_ids, []).append(i)
    return list(out.values())


@dataclass(frozen=True, eq=False)
class Calib:
    """theta's measurement-model pieces for B filters: D (B, 3, 3), the NED field m_n and dm_n/ddip stacked as
    fields (B, 2, 3), b_a and o (B, 3)."""

    D: FloatArray
    fields: FloatArray
    b_a: FloatArray
    o: FloatArray

    @classmethod
    def of(cls, theta: FloatArray) -> Calib:
        """Unpack theta (B, >= BASE.size), BASE first (D column-major, methods.md section 1)."""
        b = theta.shape[0]
        dip = theta[:, DIP]
        c, s, z = np.cos(dip), np.sin(dip), np.zeros(b)
        fields = np.stack([np.stack([c, z, s], axis=1), np.stack([-s, z, c], axis=1)], axis=1)
        return cls(BASE.value(theta, "D"), fields, theta[:, ACC_BIAS], theta[:, O_COLS])


@dataclass(frozen=True, eq=False)
class Measured:
    """The measurement model at B orientations: h (B, 6) = [-R^T g_n + b_a, D R^T m_n + o], H = dh/dphi (B, 6, 3)
    for R = R_hat Exp(phi), J = dh/dtheta (B, 6, BASE.size), and u = R^T g_n, v = R^T m_n, dv = R^T dm_n/ddip (B, 3)."""

    h: FloatArray
    H: FloatArray
    J: FloatArray
    u: FloatArray
    v: FloatArray
    dv: FloatArray


#: the constant part of J: identity blocks for b_a (accelerometer rows) and o (magnetometer rows)
_J_CONST = np.zeros((6, BASE.size))
_J_CONST[:3, ACC_BIAS] = _J_CONST[3:, O_COLS] = np.eye(3)


def measure(rot: FloatArray, cal: Calib) -> Measured:
    """Predicted accelerometer and magnetometer readings and their Jacobians (methods.md sections 1 and 3).

    H and J are the negatives of the residual Jacobians of `accel_factor` and `mag_factor` with L = I (a test pins
    them), batched over filters that each have their own theta.
    """
    b = rot.shape[0]
    u = G * rot[:, 2, :]                                                         # R^T g_n, g_n = [0, 0, g]
    vd = cal.fields @ rot                                                         # rows (R^T m_n)^T, (R^T dm_n)^T
    dvd = vd @ cal.D.transpose(0, 2, 1)                                           # rows (D R^T m_n)^T, (D R^T dm_n)^T
    h = np.empty((b, 6))
    h[:, :3] = cal.b_a - u
    h[:, 3:] = dvd[:, 0] + cal.o
    big_h = np.empty((b, 6, 3))
    big_h[:, :3] = -so3.hat(u)
    big_h[:, 3:] = cal.D @ so3.hat(vd[:, 0])
    jac = np.repeat(_J_CONST[None], b, axis=0)
    jac[:, 3:, D_COLS] = (vd[:, 0, None, :, None] * np.eye(3)[None, :, None, :]).reshape(b, 3, 9)  # v^T kron I
    jac[:, 3:, DIP] = dvd[:, 1]
    return Measured(h, big_h, jac, u, vd[:, 0], vd[:, 1])


def measurement(rot: FloatArray, theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """h (B, 6), H (B, 6, 3) and J (B, 6, BASE.size) at orientations rot (B, 3, 3) and parameters theta
    (B, >= BASE.size)."""
    m = measure(rot, Calib.of(theta))
    return m.h, m.H, m.J


def bias_steps(batch: Batch, bias: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Interval rotations Gamma = dR Exp(d_bias (b - b_bar)) (B, K-1, 3, 3) at gyro biases `bias` (B, 3), and their
    bias Jacobians psi = J_r(d_bias db) d_bias, so that Gamma(b + e) = Gamma Exp(psi e) (Forster et al. 2017, eq. 44)."""
    g = np.einsum("bkij,bj->bki", batch.d_bias, bias - batch.bias)
    return batch.delta @ so3.exp(g), so3.right_jacobian(g) @ batch.d_bias


def needs_repreintegration(batch: Batch, bias: FloatArray) -> BoolArray:
    """Filters (B,) whose bias moved so far from the preintegration's that the first-order correction is inexact."""
    out: BoolArray = np.linalg.norm(bias - batch.bias, axis=1) * batch.dt.max(axis=1) > REPREINTEGRATE_RAD
    return out


def si_jacobian(scale: float) -> FloatArray:
    """Diagonal of d theta_SI / d theta_scaled (BASE.size,): the field blocks (D, o) scale with the field unit."""
    return BASE.si_factors(scale)


@dataclass(frozen=True, eq=False)
class Estimate:
    """One filter's outcome in SI: theta and its covariance in BASE order, noise levels used, magnetometer innovation
    RMS (T), the optimiser's record and remarks, and the effects fitted (or not testable)."""

    prep: Prepared
    theta: FloatArray
    cov: FloatArray
    noise: Noise
    mag_rms: float
    iterations: int
    converged: bool
    log: tuple[str, ...]
    notes: tuple[str, ...] = ()
    findings: tuple[Finding, ...] = ()
    effects: tuple[EffectFit, ...] = ()

    @property
    def std(self) -> FloatArray:
        """Marginal standard deviations of theta (SI)."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))


def estimate(prep: Prepared, theta: FloatArray, cov: FloatArray, noise: Noise, mag_rms: float, iterations: int,
             converged: bool, log: Sequence[str], notes: Sequence[str] = ()) -> Estimate:
    """Convert a scaled-unit theta and covariance (BASE, then the effect blocks of `prep.effects`) to SI, check what
    the log determines (observability) and test the effects."""
    jac = BASE.extended(layout_of(prep.effects).blocks).si_factors(prep.scale)
    theta_si, cov_si = theta * jac, cov * np.outer(jac, jac)
    base = slice(0, BASE.size)
    _, findings = check_observability(cov_si[base, base], prep.scale, prep.y[:, :3], prep.where)
    noise_si = Noise(noise.acc, noise.gyr, noise.mag * prep.scale)
    effects = fitted(prep.effects, theta_si, cov_si, prep.mag_id, "") if prep.effects else []
    return Estimate(prep, theta_si[base], cov_si[base, base], noise_si, mag_rms * prep.scale, iterations, converged,
                    tuple(log), tuple(prep.notes) + tuple(notes), tuple(findings),
                    (*effects, *prep.untestable))


def method_result(method: str, problem: Problem, ests: Sequence[Estimate], notes: Sequence[str] = ()) -> MethodResult:
    """The estimates as a MethodResult; IMU biases from the magnetometer fit with the smallest bias uncertainty."""
    biases = BASE.cols("accelerometer_bias", "gyroscope_bias")
    best = min(ests, key=lambda e: float(np.sum(e.std[biases] / BIAS_SCALE)))
    imu = ImuFit(problem.imu_id, best.theta[ACC_BIAS], best.theta[GYRO_BIAS], best.std[ACC_BIAS],
                 best.std[GYRO_BIAS])
    noise: dict[str, list[float]] = {"accelerometer_std": best.noise.acc.tolist(),
                                     "gyroscope_std": best.noise.gyr.tolist()}
    fits: list[MagFit] = []
    findings: list[Finding] = []
    all_notes = list(notes)
    mag_cols = BASE.cols(*MAG.names)
    for est, stream in zip(ests, problem.mags, strict=True):
        d, o, dip = (BASE.value(est.theta, n) for n in MAG.names)
        fits.append(MagFit(est.prep.mag_id, d, o, float(dip), est.cov[np.ix_(mag_cols, mag_cols)], est.mag_rms,
                           int(est.prep.t.size), est.iterations, est.converged, est.log))
        noise[f"magnetometer_std[{est.prep.mag_id}]"] = (est.noise.mag * units.from_si(stream.native_unit)).tolist()
        all_notes.extend(est.notes)
        findings.extend(est.findings)
    if len(ests) > 1:
        all_notes.append(f"IMU biases from the fit against {best.prep.mag_id} (smallest bias uncertainty of "
                         f"{len(ests)} magnetometers)")
    effects = tuple(f for e in ests for f in e.effects)
    return MethodResult(method, tuple(fits), imu, noise, tuple(all_notes), tuple(findings), effects)
