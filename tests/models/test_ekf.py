"""The EKF baselines' shared core: measurement model, preintegrated prediction, batching."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.models.accel import accel_factor
from magcal_cli.models.ekf import core as ekf
from magcal_cli.models.ekf import ml as ekf_ml
from magcal_cli.models.gyro import preintegrate
from magcal_cli.models.mag import MagLayout, mag_factor
from magcal_cli.params import BASE, MAG
from magcal_cli.pipeline import select_problem
from magcal_cli.synth.simulate import simulate


@pytest.fixture(scope="module")
def prepared() -> ekf.Prepared:
    """The first 300 epochs of a 60 s handheld recording at 50/25 Hz."""
    sim = simulate("handheld", 3, rate=50.0, mag_rate=25.0, duration=60.0)
    return truncated(ekf.prepare(select_problem(sim.recording, Config()), sim.recording.streams[2]), 300)


def truncated(p: ekf.Prepared, k: int) -> ekf.Prepared:
    """The first k epochs of a prepared filter."""
    pre = preintegrate(p.gyr_t, p.gyr, p.t[:k], p.pre.bias, p.noise.gyr)
    return replace(p, t=p.t[:k], y=p.y[:k], acc_factor=p.acc_factor[:k], pre=pre)


def test_measurement_is_the_factors_prediction_and_jacobians() -> None:
    """h = y - r, H = -dr/dphi, J = -dr/dtheta of accel_factor and mag_factor (L = I) for 5 random filters."""
    rng = np.random.default_rng(0)
    rot = so3.exp(rng.normal(size=(5, 3)))
    theta = rng.normal(size=(5, BASE.size))
    y = rng.normal(size=(5, 6))
    h, big_h, jac = ekf.measurement(rot, theta)
    eye = np.eye(3)
    acc_at, mag_at = BASE.slice("accelerometer_bias").start, MagLayout(*(BASE.slice(n).start for n in MAG.names))
    for b in range(5):
        fa = accel_factor(rot[b:b + 1], y[b:b + 1, :3], eye, theta[b], acc_at, np.zeros(1, np.int64))
        fm = mag_factor(rot[b:b + 1], y[b:b + 1, 3:], eye, theta[b], mag_at, np.zeros(1, np.int64))
        np.testing.assert_allclose(h[b], y[b] - np.concatenate([fa.r[0], fm.r[0]]), atol=1e-12)
        np.testing.assert_allclose(big_h[b], -np.concatenate([fa.J_x[0], fm.J_x[0]]), atol=1e-12)
        np.testing.assert_allclose(jac[b], -np.concatenate([fa.J_theta[0], fm.J_theta[0]]), atol=1e-12)


def test_preintegrated_prediction_is_the_per_sample_ekf_prediction() -> None:
    """Gamma^T P Gamma + Q_pre equals L per-sample steps P <- F P F^T + J_r Q J_r^T dt^2, F = Exp(w dt)^T."""
    rng = np.random.default_rng(1)
    dt, n = 0.01, 9
    t = np.arange(n) * dt
    gyr = rng.normal(size=(n, 3))
    sigma = np.array([0.01, 0.02, 0.015])
    pre = preintegrate(t, gyr, np.array([0.0, 8 * dt]), np.zeros(3), sigma)
    p0 = np.diag([1e-3, 2e-3, 3e-3])
    p = p0.copy()
    rot = np.eye(3)
    for k in range(8):
        step = so3.exp(gyr[k] * dt)
        jr = so3.right_jacobian(gyr[k] * dt)
        rot = rot @ step
        p = step.T @ p @ step + jr @ np.diag(sigma**2) @ jr.T * dt**2
    np.testing.assert_allclose(pre.delta[0], rot, atol=1e-14)
    np.testing.assert_allclose(pre.delta[0].T @ p0 @ pre.delta[0] + pre.cov[0], p, rtol=1e-12, atol=1e-18)


def test_padding_leaves_each_filter_unchanged(prepared: ekf.Prepared) -> None:
    """A short filter stacked with a longer one has the likelihood and gradient it has alone."""
    short = truncated(prepared, 120)
    both = ekf.stack([prepared, short])
    theta = ekf_ml.start_theta([prepared, short])
    together = ekf_ml.filter_pass(both, theta)
    alone = ekf_ml.filter_pass(ekf.stack([short]), theta[1:])
    np.testing.assert_allclose(together.nll[1], alone.nll[0], rtol=1e-12)
    np.testing.assert_allclose(together.grad[1], alone.grad[0], rtol=1e-9, atol=1e-9 * np.abs(alone.grad).max())


def test_start_values_are_close_to_the_truth() -> None:
    """The joint MAP initialisation the filters start from: D within 3 %, gyro bias within 2e-3 rad/s.

    Regression: at 10 Hz the still detector reports a still segment in this rotating recording; its mean rate was
    0.07 rad/s from the bias and the augmented EKF diverged. The start now falls back to Wu & Luo's estimate.
    """
    sim = simulate("paper", 0, rate=10.0, mag_rate=10.0, duration=60.0)
    p = ekf.prepare(select_problem(sim.recording, Config()), sim.recording.streams[2])
    theta = p.theta0 * ekf.si_jacobian(p.scale)
    d = BASE.value(theta, "D")
    assert np.linalg.norm(d - sim.truth.D) / np.linalg.norm(sim.truth.D) < 0.03
    assert np.linalg.norm(BASE.get(theta, "gyroscope_bias") - sim.truth.gyro_bias) < 2e-3


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 5e-3, 0.5, 3.0])
def test_exp_and_right_jacobian_agree_with_so3(scale: float) -> None:
    """so3.exp_and_right_jacobian (the filters' update step) equals so3.exp and so3.right_jacobian on both of its
    branches (all angles below 1e-2 rad: Taylor series; otherwise the closed forms)."""
    phi = np.random.default_rng(4).normal(size=(7, 3)) * scale
    step, jr = so3.exp_and_right_jacobian(phi)
    np.testing.assert_allclose(step, so3.exp(phi), atol=1e-15)
    np.testing.assert_allclose(jr, so3.right_jacobian(phi), atol=1e-12)
