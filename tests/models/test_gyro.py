"""Gyro preintegration (Forster et al. 2017) and its factor: against sequential integration, finite
differences and Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.gyro import gyro_factor, preintegrate

DT = 0.01
SIGMA = np.array([0.01, 0.02, 0.015])


@pytest.fixture
def data() -> tuple[np.ndarray, np.ndarray]:
    """200 IMU samples of a fast random rotation rate."""
    rng = np.random.default_rng(0)
    return np.arange(200) * DT, rng.normal(size=(200, 3))


def _sequential(gyr: np.ndarray, bias: np.ndarray, durations: list[tuple[int, float]]):  # noqa: ANN202
    """Forster's recursions one piece at a time: dR, d dR/d b, covariance (eqs. 35, 44, 63)."""
    d_r, g, c = np.eye(3), np.zeros((3, 3)), np.zeros((3, 3))
    for k, d in durations:
        phi = (gyr[k] - bias) * d
        e, jr = so3.exp(phi), so3.right_jacobian(phi)
        g = e.T @ g - jr * d
        c = e.T @ c @ e + jr @ np.diag(SIGMA**2 * DT * d) @ jr.T
        d_r = d_r @ e
    return d_r, g, c


def test_matches_sequential_recursion_on_aligned_epochs(data: tuple[np.ndarray, np.ndarray]) -> None:
    """Epochs every L = 4 samples (eq. 16): rotation, bias Jacobian and covariance equal the recursion."""
    t, gyr = data
    bias = np.array([0.01, -0.02, 0.03])
    pre = preintegrate(t, gyr, t[::4][:-1], bias, SIGMA)
    for i in (0, 3, 20):
        d_r, g, c = _sequential(gyr, bias, [(4 * i + j, DT) for j in range(4)])
        np.testing.assert_allclose(pre.delta[i], d_r, atol=1e-14)
        np.testing.assert_allclose(pre.d_bias[i], g, atol=1e-14)
        np.testing.assert_allclose(pre.cov[i], c, rtol=1e-10)
    np.testing.assert_allclose(pre.l_inv @ pre.cov @ pre.l_inv.transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), pre.cov.shape), atol=1e-10)


def test_partial_pieces_when_epochs_fall_between_samples(data: tuple[np.ndarray, np.ndarray]) -> None:
    """Unaligned epochs: each interval integrated piecewise (zero-order hold), partial first/last pieces."""
    t, gyr = data
    rng = np.random.default_rng(1)
    epochs = np.sort(rng.uniform(0.05, 1.9, 60))
    bias = np.array([0.01, -0.02, 0.03])
    pre = preintegrate(t, gyr, epochs, bias, SIGMA)
    for i in (0, 10, 58):
        a, b = epochs[i], epochs[i + 1]
        cuts = np.concatenate([[a], t[(t > a) & (t < b)], [b]])
        pieces = [(int(np.searchsorted(t, s, side="right") - 1), e - s)
                  for s, e in zip(cuts[:-1], cuts[1:], strict=True)]
        d_r, g, c = _sequential(gyr, bias, pieces)
        np.testing.assert_allclose(pre.delta[i], d_r, atol=1e-14)
        np.testing.assert_allclose(pre.d_bias[i], g, atol=1e-14)
        np.testing.assert_allclose(pre.cov[i], c, rtol=1e-10)


def test_intervals_compose(data: tuple[np.ndarray, np.ndarray]) -> None:
    """Splitting an interval at an arbitrary time leaves the product of the halves equal to the whole."""
    t, gyr = data
    whole = preintegrate(t, gyr, np.array([0.123, 0.871]), np.zeros(3), SIGMA)
    halves = preintegrate(t, gyr, np.array([0.123, 0.4567, 0.871]), np.zeros(3), SIGMA)
    np.testing.assert_allclose(halves.delta[0] @ halves.delta[1], whole.delta[0], atol=1e-14)


def test_bias_jacobian_against_finite_differences(data: tuple[np.ndarray, np.ndarray]) -> None:
    """dR(b + e) ~ dR(b) Exp(d_bias e) (Forster eq. 44), central differences with step 1e-6."""
    t, gyr = data
    epochs = np.sort(np.random.default_rng(2).uniform(0.0, 1.98, 40))
    bias = np.array([0.01, -0.02, 0.03])
    pre = preintegrate(t, gyr, epochs, bias, SIGMA)
    eps = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = eps
        plus = preintegrate(t, gyr, epochs, bias + e, SIGMA).delta
        minus = preintegrate(t, gyr, epochs, bias - e, SIGMA).delta
        fd = so3.log(minus.transpose(0, 2, 1) @ plus) / (2 * eps)
        np.testing.assert_allclose(fd, pre.d_bias[:, :, j], atol=1e-8)


def test_covariance_matches_monte_carlo() -> None:
    """The propagated covariance of the rotation-vector error matches 4000 noisy repetitions within 10 %."""
    rng = np.random.default_rng(3)
    reps, length = 4000, 10
    omega = rng.normal(size=(length, 3))
    gyr_true = np.tile(omega, (reps, 1))
    gyr = gyr_true + SIGMA * rng.standard_normal(gyr_true.shape)
    t = np.arange(reps * length + 1) * DT
    gyr = np.concatenate([gyr, gyr[-1:]])
    epochs = t[::length]
    noisy = preintegrate(t, gyr, epochs, np.zeros(3), SIGMA)
    exact = preintegrate(t, np.concatenate([gyr_true, gyr_true[-1:]]), epochs, np.zeros(3), SIGMA)
    err = so3.log(exact.delta.transpose(0, 2, 1) @ noisy.delta)
    np.testing.assert_allclose(np.cov(err.T), exact.cov[0], rtol=0.1, atol=0.1 * np.abs(exact.cov[0]).max())


def test_factor_jacobians_against_finite_differences(data: tuple[np.ndarray, np.ndarray]) -> None:
    """dr/dphi_i, dr/dphi_j (right perturbations) and dr/d db of the gyro factor, central differences."""
    t, gyr = data
    rng = np.random.default_rng(4)
    epochs = t[::5][:-1]
    pre = preintegrate(t, gyr, epochs, np.zeros(3), SIGMA)
    states = so3.cumulative_product(pre.delta)
    states = np.concatenate([np.eye(3)[None], states]) @ so3.exp(0.05 * rng.normal(size=(epochs.size, 3)))
    theta = np.concatenate([rng.normal(size=2), 0.3 * rng.normal(size=3)])    # db = theta[2:5]
    f = gyro_factor(states, theta, pre, 2)
    eps = 1e-6
    for a in range(3):
        d = np.zeros((epochs.size, 3))
        d[:, a] = eps
        even = np.arange(epochs.size) % 2 == 0
        for jac, mask in ((f.J_x, even), (f.J_next, ~even)):
            # perturb every other state so that each factor row sees only one perturbed state
            dd = d * mask[:, None]
            plus = gyro_factor(states @ so3.exp(dd), theta, pre, 2, False).r
            minus = gyro_factor(states @ so3.exp(-dd), theta, pre, 2, False).r
            rows = mask[:-1] if jac is f.J_x else mask[1:]
            fd = (plus - minus)[rows] / (2 * eps)
            np.testing.assert_allclose(fd, jac[rows, :, a], rtol=1e-5, atol=1e-4)
    assert f.theta_cols is not None
    np.testing.assert_array_equal(f.theta_cols, [2, 3, 4])
    for c in range(3):
        e = np.zeros(theta.size)
        e[2 + c] = eps
        fd = gyro_factor(states, theta + e, pre, 2, False).r - gyro_factor(states, theta - e, pre, 2, False).r
        np.testing.assert_allclose(fd / (2 * eps), f.J_theta[:, :, c], rtol=1e-5, atol=1e-4)


def test_too_few_epochs_is_an_insufficient_data_error(data: tuple[np.ndarray, np.ndarray]) -> None:
    """One epoch (or epochs before the IMU starts) cannot be preintegrated: a clear error, not a crash."""
    t, gyr = data
    with pytest.raises(InsufficientDataError, match="at least two increasing magnetometer epochs"):
        preintegrate(t, gyr, np.array([0.5]), np.zeros(3), SIGMA)
