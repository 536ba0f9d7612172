"""Kok & Schoen 2016 (`ekf-ml`): exact sensitivities, Fisher information, truth recovered within its uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli.config import Config
from magcal_cli.models.ekf import core as ekf
from magcal_cli.models.ekf import ml as ekf_ml
from magcal_cli.params import BASE
from magcal_cli.pipeline import select_problem
from magcal_cli.synth.simulate import simulate
from tests.models.test_ekf import truncated


@pytest.fixture(scope="module")
def short() -> ekf.Prepared:
    """The first 400 epochs (16 s) of a handheld recording at 50/25 Hz: a 10 s still start, then moves."""
    # the paper's lab magnetometer (a given truth keeps its noise): the numerical checks need a sharp optimum
    sim = simulate("handheld", 5, rate=50.0, mag_rate=25.0, duration=60.0,
                   truth=simulate("paper", 5, duration=60.0).truth)
    return truncated(ekf.prepare(select_problem(sim.recording, Config()), sim.recording.streams[2]), 400)


def _numeric_gradient(batch: ekf.Batch, theta: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    """Central differences of the negative log-likelihood, one value pass per parameter and side."""
    out = np.zeros_like(theta)
    for c in range(theta.shape[1]):
        d = np.zeros_like(theta)
        d[:, c] = eps
        out[:, c] = (ekf_ml.filter_pass(batch, theta + d, False).nll
                     - ekf_ml.filter_pass(batch, theta - d, False).nll) / (2 * eps)
    return out


def test_gradient_matches_finite_differences(short: ekf.Prepared) -> None:
    """Forward-mode sensitivities give the gradient of every parameter (biases, D, o, dip, noise factors) to 1e-6,
    away from the start values (the gyro bias off by 3 mrad/s, so the first-order bias correction is exercised)."""
    batch = ekf.stack([short, short])
    theta = ekf_ml.start_theta([short, short])
    theta[1] += np.random.default_rng(2).normal(size=ekf_ml.P) * 1e-3
    theta[:, ekf_ml.LAYOUT.slice("gyroscope_bias")] += 3e-3
    analytic = ekf_ml.filter_pass(batch, theta).grad
    numeric = _numeric_gradient(batch, theta)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())


def test_fisher_information_is_the_hessian_at_the_optimum(short: ekf.Prepared) -> None:
    """At the maximum-likelihood point the Fisher information approximates the Hessian (finite differences of the
    exact gradient): diagonal within 10 % for the 19 calibration parameters and 50 % for the three noise factors
    (they differ by residual-weighted second-order terms, largest for the weakly determined gyro noise), which a
    factor of 2 or a missing term would break."""
    batch = ekf.stack([short])
    fit = ekf_ml.fisher_scoring(batch, ekf_ml.start_theta([short]))
    assert fit.converged.all()
    eps = 1e-6                                  # forward differences: the gradient is ~0 at the optimum
    hess = np.zeros((ekf_ml.P, ekf_ml.P))
    for c in range(ekf_ml.P):
        d = np.zeros_like(fit.theta)
        d[:, c] = eps
        hess[c] = (ekf_ml.filter_pass(batch, fit.theta + d).grad[0] - fit.last.grad[0]) / eps
    ratio = np.diag(fit.last.fisher[0]) / np.diag(hess)
    assert np.all(np.abs(ratio[ekf_ml.THETA] - 1.0) < 0.1), ratio
    assert np.all(np.abs(ratio[ekf_ml.NOISE] - 1.0) < 0.5), ratio


def test_recovers_handheld_truth_within_its_reported_uncertainty() -> None:
    """4 handheld seeds in one batch: >= 90 % of the 4 x 19 parameters within 3 reported std, D within
    1 %, o within 0.1 % of the field, and the noise levels it estimates within 5 % of the simulated ones (15 % for
    the gyro, whose level the likelihood determines to ~3.5 %)."""
    sims = [simulate("handheld", seed) for seed in range(4)]
    preps = [ekf.prepare(select_problem(s.recording, Config()), s.recording.streams[2]) for s in sims]
    inside = total = 0
    for sim, est in zip(sims, ekf_ml.fit_batch(preps), strict=True):
        tr = sim.truth
        z = (est.theta - tr.theta) / est.std
        inside += int(np.sum(np.abs(z) <= 3.0))
        total += z.size
        d, o = BASE.value(est.theta, "D"), BASE.get(est.theta, "o")
        assert est.converged
        assert np.linalg.norm(d - tr.D) / np.linalg.norm(tr.D) < 0.01
        assert np.linalg.norm(o - tr.o) / tr.field_strength < 0.001
        np.testing.assert_allclose(est.noise.acc, tr.noise_std["accelerometer"], rtol=0.05)
        np.testing.assert_allclose(est.noise.gyr, tr.noise_std["gyroscope"], rtol=0.15)
        np.testing.assert_allclose(est.noise.mag, tr.noise_std["magnetometer"], rtol=0.05)
    assert inside / total >= 0.9, f"{inside}/{total} within 3 sigma"
