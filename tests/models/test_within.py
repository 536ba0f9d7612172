"""Epochs that average several readings (issue 39): the groups, their preintegration, the terms that say what a
group's mean predicts, and the fit, against a fit with a state at every reading and against the truth.

Modules it covers (the mirrored test file aside): magcal_cli.models.epochs (groups), magcal_cli.models.gyro
(grouped preintegration), magcal_cli.models.map.cost, magcal_cli.models.map.within.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.models import epochs as epochs_mod
from magcal_cli.models.epochs import Noise, epochs_for
from magcal_cli.models.gyro import preintegrate, preintegrate_log
from magcal_cli.models.map import fit as mapm
from magcal_cli.models.map.cost import make_linearize
from magcal_cli.synth.simulate import paper_trajectory

from .mapsim import noise_of, record, theta_of


def _problem(rate: float = 100.0, mag_step: int = 1, seconds: float = 12.0, seed: int = 0):  # noqa: ANN202
    """A paper trajectory with magnetometer readings between IMU samples."""
    rot = paper_trajectory(np.random.default_rng(seed), rate, seconds)
    return record(rot, rate, seed, mag_step=mag_step, mag_offset=0.3)


def _group_rotations(problem, g, k: int, bias: np.ndarray, sd: np.ndarray) -> list[np.ndarray]:  # noqa: ANN001
    """dR_kj for each reading j of group k, integrated on its own from the group's first reading."""
    s, e = int(g.start[k]), int(g.start[k + 1])
    out = [np.eye(3)]
    if e - s > 1:
        for d in preintegrate(problem.gyr.t, problem.gyr.xyz, g.t[s:e], bias, sd).delta:
            out.append(out[-1] @ d)
    return out


def test_groups_preintegrate_as_the_epochs_and_say_what_their_means_see() -> None:
    """The intervals between the groups' first readings are those of a preintegration over them (the covariance to
first order); A is the mean of
    each reading's dR^T, and B its first-order change with the bias (finite differences)."""
    problem, truths, _ = _problem()
    ep = epochs_for(problem, problem.mags[0], truths[0].field_strength, max_epochs=400, average=True)
    g = ep.groups
    assert g is not None and ep.t.size == 400 and np.all(g.counts[:-1] == 3) and g.counts[-1] == 2
    sd = noise_of(truths[0])[1]
    bias = truths[0].gyro_bias + 0.01
    pre = preintegrate_log(problem, ep.t, bias, sd, groups=g)
    direct = preintegrate(problem.gyr.t, problem.gyr.xyz, ep.t, bias, sd)
    for name in ("delta", "d_bias"):
        np.testing.assert_allclose(getattr(pre, name), getattr(direct, name), rtol=1e-9, atol=1e-15)
    # a sample cut at a reading adds J_r q J_r^T of two pieces, not of one: equal to first order in the angle
    np.testing.assert_allclose(pre.cov, direct.cov, atol=1e-6 * float(direct.cov.max()))
    assert pre.within is not None
    u = np.random.default_rng(1).normal(size=3)
    db = np.array([1e-4, -2e-4, 3e-4])
    for k in (0, 17, 399):
        rots = _group_rotations(problem, g, k, bias, sd)
        np.testing.assert_allclose(pre.within.A[k], np.mean([r.T for r in rots], axis=0), atol=1e-14)
        moved = np.mean([r.T @ u for r in _group_rotations(problem, g, k, bias + db, sd)], axis=0)
        first_order = pre.within.A[k] @ u + np.einsum("a,aij,j->i", u, pre.within.B[k], db)
        assert np.abs(moved - first_order).max() < 1e-3 * np.abs(moved - pre.within.A[k] @ u).max()


def test_grouped_preintegration_a_block_at_a_time_is_the_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """Blocks of 7 groups give the digits of one block (each interval is its own product)."""
    problem, truths, _ = _problem()
    ep = epochs_for(problem, problem.mags[0], 1.0, max_epochs=400, average=True)
    sd = noise_of(truths[0])[1]
    whole = preintegrate_log(problem, ep.t, truths[0].gyro_bias, sd, groups=ep.groups)
    from magcal_cli.models import gyro
    monkeypatch.setattr(gyro, "GROUP_BLOCK", 7)
    blocks = preintegrate_log(problem, ep.t, truths[0].gyro_bias, sd, groups=ep.groups)
    for name in ("delta", "d_bias", "cov", "l_inv"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))
    assert whole.within is not None and blocks.within is not None
    np.testing.assert_array_equal(blocks.within.A, whole.within.A)
    np.testing.assert_array_equal(blocks.within.B, whole.within.B)


def test_a_last_block_of_one_lone_reading_joins_the_block_before(monkeypatch: pytest.MonkeyPatch) -> None:
    """Groups in blocks of K - 1 leave the last group, a single reading, alone: it has no interval to integrate, and
    the preintegration is that of one block."""
    problem, truths, _ = _problem()
    mag = problem.mags[0]
    from dataclasses import replace
    cut = replace(mag, t=mag.t[:1198], values=mag.xyz[:1198])       # 1198 = 3 x 399 + 1: the last group is alone
    ep = epochs_for(problem, cut, 1.0, max_epochs=400, average=True)
    assert ep.groups is not None and ep.groups.counts[-1] == 1
    sd = noise_of(truths[0])[1]
    whole = preintegrate_log(problem, ep.t, truths[0].gyro_bias, sd, groups=ep.groups)
    from magcal_cli.models import gyro
    monkeypatch.setattr(gyro, "GROUP_BLOCK", ep.t.size - 1)
    blocks = preintegrate_log(problem, ep.t, truths[0].gyro_bias, sd, groups=ep.groups)
    assert whole.within is not None and blocks.within is not None
    np.testing.assert_array_equal(blocks.delta, whole.delta)
    np.testing.assert_array_equal(blocks.within.A, whole.within.A)


def test_groups_end_at_dropouts_and_windows_the_gyro_did_not_measure() -> None:
    """A reading after a gap of more than GROUP_GAP_PERIODS periods, or after a window the gyro could not measure,
    starts a group; the means are the readings' means."""
    problem, truths, _ = _problem()
    mag = problem.mags[0]
    keep = np.ones(mag.t.size, dtype=bool)
    keep[301:306] = False                                   # a dropout of 6 periods after reading 300
    from dataclasses import replace
    cut = replace(mag, t=mag.t[keep], values=mag.xyz[keep])
    window = (float(cut.t[600]) + 0.001, float(cut.t[600]) + 0.002)
    problem = replace(problem, unmeasured=(window,))
    ep = epochs_for(problem, cut, 1.0, max_epochs=400, average=True)
    g = ep.groups
    assert g is not None
    assert 301 in g.start and 601 in g.start                 # the readings after the gap and after the window
    assert np.all(g.counts <= 3)
    k = int(np.searchsorted(g.start, 301))
    np.testing.assert_allclose(ep.mag[k], cut.xyz[g.start[k]:g.start[k + 1]].mean(axis=0))


def test_the_mean_accelerometer_noise_counts_samples_readings_share() -> None:
    """Readings at the IMU rate interpolate shared samples: the mean's noise std over Monte Carlo draws of the IMU
    noise is the factor the epochs state."""
    problem, _, _ = _problem()
    ep = epochs_for(problem, problem.mags[0], 1.0, max_epochs=400, average=True)
    g = ep.groups
    assert g is not None
    t_imu = problem.acc.t
    rng = np.random.default_rng(2)
    draws = []
    for _ in range(400):
        z = rng.standard_normal(t_imu.size)
        draws.append(g.mean(np.interp(g.t, t_imu, z)))
    measured = np.std(draws, axis=0)
    np.testing.assert_allclose(measured, ep.acc_factor, rtol=0.12)
    assert np.all(ep.acc_factor < 0.75)       # not 1/sqrt(3) of the interpolation factor: shared samples
    independent = np.sqrt(np.add.reduceat(((1 - 0.3) ** 2 + 0.3**2) * np.ones(g.t.size), g.start[:-1])) / g.counts
    assert np.median(measured / independent) > 1.1


def test_grouped_factor_jacobians_against_finite_differences() -> None:
    """Every block of the factors of grouped epochs, the group terms' gyro bias, D and dip columns included."""
    rng = np.random.default_rng(0)
    problem, truths, r_m = _problem()
    scale = truths[0].field_strength
    ep = epochs_for(problem, problem.mags[0], scale, max_epochs=400, average=True)
    acc, gyr, mag = noise_of(truths[0])
    pre = preintegrate_log(problem, ep.t, truths[0].gyro_bias + 0.01, gyr, groups=ep.groups)
    theta = theta_of(truths[0]) / np.concatenate([np.ones(6), np.full(12, scale), [1.0]])
    theta[3:6] = rng.normal(size=3) * 0.01
    assert ep.groups is not None
    states = r_m[ep.groups.start[:-1]] @ so3.exp(0.02 * rng.normal(size=(ep.t.size, 3)))
    lin = make_linearize(ep, pre, Noise(acc, gyr, mag / scale))
    eps = 1e-6
    for k, f in enumerate(lin(states, theta, True)):
        for a in range(3):
            for parity in (0, 1):
                mask = (np.arange(states.shape[0]) % 2 == parity)[:, None]
                d = eps * np.eye(3)[a] * mask
                fd = (lin(states @ so3.exp(d), theta, False)[k].r - lin(states @ so3.exp(-d), theta, False)[k].r) / (
                    2 * eps)
                rows = mask[: f.r.shape[0], 0]
                np.testing.assert_allclose(fd[rows], f.J_x[rows, :, a], rtol=1e-5, atol=1e-4)
        cols = np.arange(theta.size) if f.theta_cols is None else f.theta_cols
        if f.name in ("accel", "mag"):
            assert set(range(3, 6)) <= set(cols.tolist())          # the groups' means move with the gyro bias
        for c, col in enumerate(cols):
            e = np.zeros(theta.size)
            e[col] = eps
            fd = (lin(states, theta + e, False)[k].r - lin(states, theta - e, False)[k].r) / (2 * eps)
            np.testing.assert_allclose(fd, f.J_theta[:, :, c], rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_fit_of_grouped_readings_is_the_fit_of_every_reading(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Readings averaged three per epoch give the estimate of a state at every reading within 0.1 of its std, with
    the same std (within 3 %) -- taking every third reading instead moves it and widens it by ~sqrt(3) -- and the
    truth within the reported covariance."""
    problem, truths, _ = _problem(rate=200.0, mag_step=2, seconds=60.0, seed=seed)
    monkeypatch.setattr(epochs_mod, "MAX_EPOCH_RATE_HZ", 1000.0)
    full = mapm.fit_map(problem, problem.mags[0])
    monkeypatch.setattr(epochs_mod, "MAX_EPOCHS", 2000)
    grouped = mapm.fit_map(problem, problem.mags[0])
    assert grouped.epochs.size == 2000 and full.epochs.size == 6000
    sd = full.std
    assert np.max(np.abs(grouped.theta - full.theta) / sd) < 0.1
    np.testing.assert_allclose(grouped.std / sd, 1.0, atol=0.03)
    assert abs(grouped.residual_rms / full.residual_rms - 1.0) < 0.02       # the readings' residual, not the means
    e = grouped.theta - theta_of(truths[0])
    assert float(e @ np.linalg.solve(grouped.cov, e)) < 43.8          # chi2(19) at 99.9 %


def test_reading_residuals_are_each_readings_own() -> None:
    """A group's mean residual and the readings' departures from their means give each reading's residual
    y_j - D (R_k dR_kj)^T m_n - o, dR_kj integrated on its own."""
    from magcal_cli.models.mag import field_nav
    from magcal_cli.models.map.within import reading_residuals

    rng = np.random.default_rng(3)
    problem, truths, r_m = _problem()
    ep = epochs_for(problem, problem.mags[0], truths[0].field_strength, max_epochs=400, average=True)
    g = ep.groups
    assert g is not None
    states = r_m[g.start[:-1]] @ so3.exp(0.05 * rng.normal(size=(ep.t.size, 3)))
    d = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    o, m_n, bias = rng.normal(size=3) * 0.1, field_nav(1.1), truths[0].gyro_bias + 0.002
    own = np.concatenate([[g.y[g.start[k] + j] - d @ (states[k] @ r).T @ m_n - o
                           for j, r in enumerate(_group_rotations(problem, g, k, bias, np.full(3, 1e-3)))]
                          for k in range(ep.t.size)])
    got = reading_residuals(problem, g, g.mean(own), states, d, m_n, bias)
    np.testing.assert_allclose(got, own, atol=1e-12)


@pytest.mark.parametrize(("n", "rate", "average", "k"), [
    (60_000, 50.0, True, 1), (60_001, 50.0, True, 2), (180_000, 50.0, True, 3),     # an hour at 50 Hz: threes
    (360_000, 50.0, True, 3), (360_001, 50.0, True, 4), (540_000, 50.0, True, 5),   # up to 120 000 epochs, then more
    (360_000, 50.0, False, 6), (40_000, 286.0, True, 3), (40_000, 286.0, False, 3), (0, 0.0, True, 1)])
def test_readings_per_epoch_groups_of_three_up_to_twice_the_epochs(n: int, rate: float, average: bool,
                                                                   k: int) -> None:
    """Averaged groups stay at 3 readings until 120 000 epochs (longer ones moved a 2-hour fit 0.34 std from full
    resolution), beyond which they grow; every k-th reading (the EKFs) keeps 60 000 epochs; 100 Hz at most."""
    from magcal_cli.models.epochs import readings_per_epoch

    assert readings_per_epoch(n, rate, average=average) == k
