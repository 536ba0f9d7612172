"""Joint MAP calibration (Huang et al. 2025): Jacobians, truth within the reported covariance, multi-rate
data, observability findings and the errors for motion that cannot determine the calibration.

Modules it covers (the mirrored test file aside): magcal_cli.models.map.fit, magcal_cli.models.map.init,
magcal_cli.models.map.noise, magcal_cli.models.result, magcal_cli.models.spikes.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.epochs import Noise, epochs_for
from magcal_cli.models.gyro import preintegrate
from magcal_cli.models.map import fit as mapm
from magcal_cli.models.map import noise as map_noise
from magcal_cli.models.map.cost import make_linearize
from magcal_cli.models.map.estimate import MapEstimate
from magcal_cli.pipeline import select_problem
from magcal_cli.synth.simulate import paper_trajectory, simulate

from .mapsim import noise_of, record, theta_of

#: NEES of the 19 parameters beyond this happens with probability 1e-3 when the covariance is right
NEES_BOUND = float(stats.chi2.ppf(0.999, 19))


def _nees(est: MapEstimate, truth: np.ndarray) -> float:
    e = est.theta - truth
    return float(e @ np.linalg.solve(est.cov, e))


def test_factor_jacobians_against_finite_differences() -> None:
    """Every block of the MAP factors (accelerometer with interpolation weights, magnetometer, gyro)."""
    rng = np.random.default_rng(0)
    rot = paper_trajectory(rng, 50.0, 12.0)
    problem, truths, r_m = record(rot, 50.0, 0, mag_step=2, mag_offset=0.3)
    scale = truths[0].field_strength
    ep = epochs_for(problem, problem.mags[0], scale)
    assert np.any(ep.acc_factor < 0.99)                         # interpolated: rows are re-weighted
    acc, gyr, mag = noise_of(truths[0])
    noise = Noise(acc, gyr, mag / scale)
    pre = preintegrate(problem.gyr.t, problem.gyr.xyz, ep.t, truths[0].gyro_bias + 0.01, gyr)
    theta = theta_of(truths[0]) / np.concatenate([np.ones(6), np.full(12, scale), [1.0]])
    theta[3:6] = rng.normal(size=3) * 0.01
    states = r_m @ so3.exp(0.02 * rng.normal(size=r_m.shape[:1] + (3,)))
    lin = make_linearize(ep, pre, noise)
    factors = lin(states, theta, True)
    eps = 1e-6
    for k, f in enumerate(factors):
        for a in range(3):
            for parity in (0, 1):
                mask = (np.arange(states.shape[0]) % 2 == parity)[:, None]
                d = np.zeros_like(states[:, 0]) + eps * np.eye(3)[a] * mask
                plus = lin(states @ so3.exp(d), theta, False)[k].r
                fd = (plus - lin(states @ so3.exp(-d), theta, False)[k].r) / (2 * eps)
                rows = mask[: f.r.shape[0], 0]
                np.testing.assert_allclose(fd[rows], f.J_x[rows, :, a], rtol=1e-5, atol=1e-4)
                if f.J_next is not None:
                    nxt = mask[1:, 0]
                    np.testing.assert_allclose(fd[nxt], f.J_next[nxt, :, a], rtol=1e-5, atol=1e-4)
        for c, col in enumerate(f.theta_cols):
            e = np.zeros(theta.size)
            e[col] = eps
            fd = (lin(states, theta + e, False)[k].r - lin(states, theta - e, False)[k].r) / (2 * eps)
            np.testing.assert_allclose(fd, f.J_theta[:, :, c], rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_paper_protocol_truth_within_reported_covariance(seed: int) -> None:
    """Huang et al. 2025 protocol (shortened to 60 s): NEES of all 19 parameters within the 99.9 % bound, and
    the re-estimated noise levels within 10 % of the simulated ones."""
    sim = simulate("paper", seed, duration=60.0)
    problem = select_problem(sim.recording, Config())
    est = mapm.fit_map(problem, problem.mags[0])
    assert est.converged
    assert _nees(est, sim.truth.theta) < NEES_BOUND
    sd = sim.truth.noise_std
    np.testing.assert_allclose(est.noise.acc, sd["accelerometer"], rtol=0.1)
    np.testing.assert_allclose(est.noise.mag, sd["magnetometer"], rtol=0.1)
    np.testing.assert_allclose(est.noise.gyr, sd["gyroscope"], rtol=0.1)


@pytest.mark.parametrize(("step", "offset"), [(3, 0.0), (4, 0.37)])
def test_multi_rate_and_epochs_between_imu_samples(step: int, offset: float) -> None:
    """Magnetometer every L IMU samples (eq. 16), and at times that fall between IMU samples (partial pieces
    and an interpolated accelerometer): truth within the reported covariance."""
    rng = np.random.default_rng(10 + step)
    rot = paper_trajectory(rng, 100.0, 90.0)
    problem, truths, _ = record(rot, 100.0, 10 + step, mag_step=step, mag_offset=offset)
    est = mapm.fit_map(problem, problem.mags[0])
    assert est.epochs.size == problem.mags[0].t.size
    assert _nees(est, theta_of(truths[0])) < NEES_BOUND


def test_flat_yaw_mostly_log_reports_what_it_leaves_poorly_determined() -> None:
    """Yaw turns with only +-10 deg of tilt: the vertical hard-iron/soft-iron column are confounded; the
    findings name them and the manoeuvre (rotate about all axes), and the estimate is still honest."""
    rate = 100.0
    t = np.arange(int(120 * rate) + 1) / rate
    tilt = np.deg2rad(10.0)
    rot = so3.exp(np.stack([0 * t, 0 * t, 0.6 * t], 1)) @ so3.exp(
        np.stack([tilt * np.sin(0.7 * t), tilt * np.cos(0.43 * t), 0 * t], 1))
    problem, truths, _ = record(rot, rate, 1, mag_step=2)
    est = mapm.fit_map(problem, problem.mags[0])
    codes = {f.code: f for f in est.findings}
    assert "fisher_condition" in codes and codes["fisher_condition"].evidence["condition_number"] > 1e4
    warned = [f for f in est.findings if f.code == "poorly_observable"]
    assert any("hard-iron offset" in f.message and "rotate the vehicle about all three axes" in f.message
               for f in warned)
    assert _nees(est, theta_of(truths[0])) < NEES_BOUND


def test_nearly_flat_yaw_log_is_calibrated_within_its_uncertainty() -> None:
    """Yaw turns within +-3 deg of level defeat the ellipsoid start values (magcal used to refuse the log): the
    partial-calibration path starts from a sphere fit instead, holds what the motion cannot determine (here the
    tilt suffices for everything) and every entry's error stays within the reported covariance."""
    rate = 100.0
    t = np.arange(int(60 * rate) + 1) / rate
    tilt = np.deg2rad(3.0)
    rot = so3.exp(np.stack([0 * t, 0 * t, 0.6 * t], 1)) @ so3.exp(
        np.stack([tilt * np.sin(0.7 * t), tilt * np.cos(0.43 * t), 0 * t], 1))
    problem, truths, _ = record(rot, rate, 2, mag_step=2)
    est = mapm.fit_map(problem, problem.mags[0])
    assert est.held is not None                                   # the partial path ran
    assert _nees(est, theta_of(truths[0])) < NEES_BOUND


def test_no_rotation_is_an_insufficient_data_error() -> None:
    """A log that never rotates: a clear error naming the motion to add, not a crash or a silent result."""
    rot = np.broadcast_to(so3.exp([0.1, -0.2, 0.3]), (3001, 3, 3)).copy()
    problem, _, _ = record(rot, 100.0, 3, mag_step=2)
    with pytest.raises(InsufficientDataError, match="rotat"):
        mapm.fit_map(problem, problem.mags[0])


def test_robust_loss_resists_magnetometer_outliers() -> None:
    """2 % of the magnetometer readings replaced by spikes: Huber keeps the hard-iron error near the noise
    where the plain least-squares estimate moves by many standard deviations."""
    rng = np.random.default_rng(5)
    rot = paper_trajectory(rng, 50.0, 60.0)
    problem, truths, _ = record(rot, 50.0, 5)
    mag = problem.mags[0]
    y = mag.xyz.copy()
    bad = rng.choice(len(y), len(y) // 50, replace=False)
    y[bad] += rng.normal(size=(bad.size, 3)) * 5e-6 + 3e-6
    spiked = type(mag)(mag.kind, mag.id, mag.t, y, mag.source, mag.native_unit)
    problem = type(problem)(problem.where, problem.imu_id, problem.acc, problem.gyr, (spiked,), problem.still)
    o_true = truths[0].o
    plain = mapm.fit_map(problem, spiked)
    robust = mapm.fit_map(problem, spiked, loss="huber")
    err_plain = np.abs(plain.theta[15:18] - o_true) / robust.std[15:18]
    err_robust = np.abs(robust.theta[15:18] - o_true) / robust.std[15:18]
    assert err_robust.max() < 5.0
    assert err_plain.max() > 3.0 * err_robust.max()


def test_start_noise_is_the_residuals_white_part_not_a_slow_disturbance() -> None:
    """A slow offset drift (current, temperature) inflates the ellipsoid residual but not the start noise."""
    from magcal_cli.models.map.init import white_rms

    rng = np.random.default_rng(3)
    k = 6000
    u = rng.normal(size=(k, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    noise = 0.002
    white = u * (1.0 + noise * rng.normal(size=(k, 1)))
    drift = u * (1.0 + 0.02 * np.sin(np.linspace(0, 6, k))[:, None] + noise * rng.normal(size=(k, 1)))
    assert white_rms(white) == pytest.approx(noise, rel=0.05)
    assert white_rms(drift) == pytest.approx(noise, rel=0.05)       # the full residual RMS is ~7x that
    assert np.isnan(white_rms(u[:2]))


@pytest.mark.parametrize(("history", "expected"), [
    ([], -0.5 / map_noise.FIRST_GYRO_SLOPE),            # first step: the paper protocol's slope
    ([(0.0, 1.0)], 1.0),                           # measured slope (0.5 - 1) / (1 - 0) = -0.5: step 0.5 / 0.5
    ([(0.0, 0.2)], -0.5 / map_noise.FIRST_GYRO_SLOPE),  # the factor grew (+0.3): coupling, not a fixed-point slope
])
def test_gyro_noise_secant_falls_back_when_the_slope_is_not_a_fixed_points(
        history: list[tuple[float, float]], expected: float) -> None:
    """The secant's slope comes from the last two rounds; a positive one (the magnetometer level moved the gyro's
    factor) would have sent the level 10x too far, as it did on an effects fit with a low magnetometer start."""
    assert map_noise.secant(history, 1.0, 0.5) == pytest.approx(expected)
