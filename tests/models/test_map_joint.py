"""The joint fit of many magnetometers on one IMU (models/map_joint*.py, issue 14 item 3) and the consistency check.

Modules it covers (the mirrored test file aside): magcal_cli.models.factor, magcal_cli.models.map.joint,
magcal_cli.models.map.joint_cov, magcal_cli.models.map.joint_solve, magcal_cli.models.map.start,
magcal_cli.models.normal, magcal_cli.models.observability, magcal_cli.synth.array.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.methods import map_run
from magcal_cli.models import consistency, normal
from magcal_cli.models.map import init as map_init
from magcal_cli.models.map import joint as map_joint
from magcal_cli.models.map import joint_solve as mjs
from magcal_cli.models.map.joint_cov import factors
from magcal_cli.pipeline import select_problem
from magcal_cli.synth.array import simulate_array


@pytest.fixture(scope="module")
def small() -> tuple:
    """3 magnetometers, 30 s of the paper protocol at 62.5 Hz / 3, and a perturbed point of the joint model."""
    sim = simulate_array("paper", 1, 3, 62.5, 62.5 / 3, 30.0)
    prob = select_problem(sim.recording, Config())
    intr = [map_init.intrinsic_fit(m.xyz, "test") for m in prob.mags]
    je = map_joint.joint_epochs(prob, prob.mags, [s.scale for s in intr])
    noise = map_joint.JointNoise(np.array([0.1, 0.2, 0.3]), np.full(3, 1e-3), np.array([[1e-3, 2e-3, 3e-3]] * 3))
    layout = map_joint.joint_layout(3)
    states, theta, pre, _ = map_joint._start(prob, je, intr, noise, None, layout)
    rng = np.random.default_rng(0)
    states = states @ so3.exp(0.01 * rng.standard_normal((states.shape[0], 3)))
    theta = theta + 1e-3 * rng.standard_normal(theta.size)
    weights = rng.uniform(0.5, 1.0, je.t.size)
    return map_joint.joint_data(je, pre, noise, layout, weights), states, theta


def test_structured_normal_equations_match_the_reference_factors(small: tuple) -> None:
    """Every block of the structured normal equations (H_xtheta through the 42-vector basis) equals the generic
    assembly of accel_factor, gyro_factor and mag_factor (normal.assemble), row weights included."""
    data, states, theta = small
    fs = factors(data, states, theta)
    ref = normal.assemble(fs, [np.ones(f.r.shape[0]) for f in fs], states.shape[0], theta.size)
    cost, ne = mjs.normal(data, states, theta)
    assert cost == pytest.approx(0.5 * sum(float(np.sum(f.r**2)) for f in fs), rel=1e-12)
    for mine, theirs in ((ne.diag, ref.diag), (ne.off, ref.off), (ne.basis @ ne.coef, ref.hxt), (ne.htt, ref.htt),
                         (ne.gx, ref.gx), (ne.gt, ref.gt)):
        assert np.allclose(mine, theirs, rtol=1e-10, atol=1e-10 * np.abs(theirs).max())


def test_gradient_matches_finite_differences(small: tuple) -> None:
    """J^T r of the structured equations is the derivative of the cost (states by right perturbation)."""
    data, states, theta = small
    _, ne = mjs.normal(data, states, theta)
    h = 1e-7
    for col in (*data.mag_cols(2), *data.layout.cols("accelerometer_bias", "gyroscope_bias")):
        step = np.zeros(theta.size)
        step[col] = h
        fd = (mjs.cost(data, states, theta + step) - mjs.cost(data, states, theta - step)) / (2 * h)
        assert fd == pytest.approx(ne.gt[col], rel=2e-4, abs=1e-4 * np.abs(ne.gt).max())
    for k in (0, 7, states.shape[0] - 1):
        for a in range(3):
            phi = np.zeros((states.shape[0], 3))
            phi[k, a] = h
            fd = (mjs.cost(data, states @ so3.exp(phi), theta) - mjs.cost(data, states @ so3.exp(-phi), theta)) / (2 * h)
            assert fd == pytest.approx(ne.gx[k, a], rel=2e-4, abs=1e-4 * np.abs(ne.gx).max())


def test_basis_coefficients_reproduce_each_magnetometer_coupling(small: tuple) -> None:
    """basis @ C_i is J_x^T J_theta of magnetometer i alone (mag.mag_factor's Jacobians)."""
    data, states, theta = small
    f = factors(data, states, theta)[2 + 1]
    d, _, dip = data.mag_at(1).unpack(theta)
    w2 = data.mag_rows**2
    mine = mjs.basis(states) * w2[:, None, None] @ mjs.coefficients(d, np.diag(data.mag_std[1] ** -2.0),
                                                                    np.cos(dip), np.sin(dip))
    assert np.allclose(mine, f.J_x.transpose(0, 2, 1) @ f.J_theta, rtol=1e-10, atol=1e-6)


def test_joint_fit_is_within_its_uncertainty_of_the_truth() -> None:
    """4 magnetometers x 60 s on one IMU through `map_run.run`: one joint fit; every magnetometer's (D, o, dip) and
    the IMU biases are within their reported covariance of the truth, and they agree (no inconsistency)."""
    sim = simulate_array("paper", 3, 4, 62.5, 62.5 / 3, 60.0)
    prob = select_problem(sim.recording, Config())
    result = map_run.run(prob, Config(method="map"))
    assert any("joint fit of 4 magnetometers" in n for n in result.notes)
    for fit, truth in zip(result.mags, sim.truths, strict=True):
        e = np.concatenate([(fit.D - truth.D).ravel(order="F"), fit.o - truth.o, [fit.dip - truth.dip]])
        assert float(e @ np.linalg.solve(fit.cov, e)) < 39.0          # chi2_13 at 99.99 %
    imu, truth = result.imu, sim.truths[0]
    assert imu.gyro_bias is not None and imu.gyro_bias_std is not None and imu.accel_bias_std is not None
    assert np.all(np.abs(imu.gyro_bias - truth.gyro_bias) < 4.5 * imu.gyro_bias_std)
    assert np.all(np.abs(imu.accel_bias - truth.accel_bias) < 4.5 * imu.accel_bias_std)
    codes = [f.code for f in result.findings]
    assert "magnetometer_consistency" in codes and "magnetometer_inconsistent" not in codes


def test_noisy_magnetometer_is_flagged_and_fitted_on_its_own() -> None:
    """A magnetometer with 200x the noise disagrees with the others: a WARNING names it, the other three share the
    joint fit and it is fitted separately."""
    sim = simulate_array("paper", 4, 4, 62.5, 62.5 / 3, 60.0, noise_factors=(1, 1, 200, 1))
    prob = select_problem(sim.recording, Config())
    result = map_run.run(prob, Config(method="map"))
    bad = [f for f in result.findings if f.code == "magnetometer_inconsistent"]
    assert [f.evidence["sensor"] for f in bad] == ["/mag/2"]
    assert any("joint fit of 3 magnetometers" in n for n in result.notes)
    assert any("/mag/2 disagreed" in n for n in result.notes)
    assert [f.id for f in result.mags] == [f"/mag/{i}" for i in range(4)]


def test_wrong_calibration_is_the_outlier() -> None:
    """Consistency of the true calibrations: none flagged; one D turned by 8 deg: that one is flagged."""
    sim = simulate_array("paper", 5, 4, 62.5, 62.5 / 3, 30.0)
    prob = select_problem(sim.recording, Config())

    class Fit:
        def __init__(self, i: int, d: np.ndarray) -> None:
            self.id, self.D, self.o = f"/mag/{i}", d, sim.truths[i].o

    good = [Fit(i, t.D) for i, t in enumerate(sim.truths)]
    c = consistency.measure(good, prob.mags)
    assert c is not None and c.outliers == ()
    assert float(c.closest()[0].max()) < 0.1                 # the paper's lab magnetometers: hundredths of a degree
    wrong = [*good[:1], Fit(1, sim.truths[1].D @ so3.exp([0.0, np.deg2rad(8.0), 0.0])), *good[2:]]
    c = consistency.measure(wrong, prob.mags)
    assert c is not None and c.outliers == (1,)
    assert 4.0 < float(c.closest()[0][1]) < 8.0          # 8 deg about y: less for directions near y
    warn = [f for f in consistency.findings(c, "log") if f.code == "magnetometer_inconsistent"]
    assert len(warn) == 1 and "/mag/1" in warn[0].message


def test_joint_path_is_not_taken_with_effects_or_a_robust_loss() -> None:
    """Effects, the diagnosis and robust losses keep the separate fits (every existing behaviour)."""
    sim = simulate_array("paper", 3, 2, 62.5, 62.5 / 3, 30.0)
    prob = select_problem(sim.recording, Config())
    assert map_joint.joint_eligible(prob, Config(method="map"), "l2")
    assert not map_joint.joint_eligible(prob, Config(method="map", diagnose=True), "l2")
    assert not map_joint.joint_eligible(prob, Config(method="map", effects=("time_offset",)), "l2")
    assert not map_joint.joint_eligible(prob, Config(method="map"), "huber")
    assert not map_joint.joint_eligible(replace(prob, mags=prob.mags[:1]), Config(method="map"), "l2")


def test_magnetometers_without_common_epochs_are_fitted_separately() -> None:
    """Readings one IMU period apart share no state: a method note says why, and each is fitted on its own."""
    sim = simulate_array("paper", 6, 2, 62.5, 62.5 / 3, 30.0)
    prob = select_problem(sim.recording, Config())
    late = replace(prob.mags[1], t=prob.mags[1].t + 1.0 / 62.5)
    result = map_run.run(replace(prob, mags=(prob.mags[0], late)), Config(method="map"))
    assert any("no joint fit of the 2 magnetometers" in n and "common epochs" in n for n in result.notes)
    assert any("IMU biases from the fit against" in n for n in result.notes)
    assert [f.id for f in result.mags] == ["/mag/0", "/mag/1"]


def test_consistency_compares_calibrations_not_the_interference_one_magnetometer_sees() -> None:
    """Two magnetometers, the second next to a power lead (c I, up to 8 uT), fitted with
    current_interference: the check measures the calibrated fields with the modelled term removed, so they agree
    (log171's three compasses read 10.7 deg apart with their motor fields left in, 1.9 deg without)."""
    from magcal_cli.streams import Kind, Stream

    sim = simulate_array("paper", 2, 2, 62.5, 62.5 / 3, 40.0)
    rec = sim.recording
    mag = rec.select(Kind.MAGNETOMETER, "/mag/1")
    t = rec.select(Kind.ACCELEROMETER).t
    current = Stream(Kind.BATTERY_CURRENT, "BAT[0]", t, (10.0 + 8.0 * np.sin(2 * np.pi * t / 7.0))[:, None], "sim", "A")
    c = np.array([3e-7, -2e-7, 2.5e-7])                                  # T/A: 7.9 uT at 18 A
    loaded = replace(mag, values=mag.values + np.interp(mag.t, t, current.values[:, 0])[:, None] * c)
    rec = replace(rec, streams=tuple(loaded if s is mag else s for s in rec.streams) + (current,))
    cfg = Config(method="map", effects=("current_interference",))
    result = map_run.run(select_problem(rec, cfg), cfg)
    found = next(f for f in result.findings if f.code == "magnetometer_consistency")
    angles = [s["closest_angle_rms_deg"] for s in found.evidence["sensors"].values()]
    assert max(angles) < 0.5, found.message
    assert not [f for f in result.findings if f.code == "magnetometer_inconsistent"]


def test_separate_fits_share_the_imus_accelerometer_bias_and_stay_within_their_uncertainty() -> None:
    """Three magnetometers fitted one by one (an effect keeps them off the joint path): the two that did not give
    the IMU's biases are refitted with its accelerometer bias held at the reference fit's (one IMU, one bias),
    which is no partial calibration (nothing in `held`), and each calibration stays within its reported
    uncertainty of the truth (Mahalanobis distance of vec D, o, dip: chi2(13) 0.999 quantile 34.5)."""
    sim = simulate_array("paper", 4, 3, 62.5, 62.5 / 3, 40.0)
    cfg = Config(method="map", effects=("time_offset",))
    result = map_run.run(select_problem(sim.recording, cfg), cfg)
    shared = [n for n in result.notes if "one IMU, one bias" in n]
    assert len(shared) == 2, result.notes
    for fit, truth in zip(result.mags, sim.truths, strict=True):
        assert not any("accelerometer_bias" in h.name for h in fit.held)
        err = np.concatenate([(fit.D - truth.D).ravel(order="F"), fit.o - truth.o, [fit.dip - truth.dip]])
        assert float(err @ np.linalg.solve(fit.cov, err)) < 34.5, fit.id
