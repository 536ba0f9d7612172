"""The simulator produces data that obeys the models exactly (up to its stated noise).

Modules it covers (the mirrored test file aside): magcal_cli.synth.rotation.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.errors import MagcalError
from magcal_cli.models.accel import G
from magcal_cli.streams import Kind
from magcal_cli.synth.simulate import simulate


@pytest.mark.parametrize("scenario", ["paper", "handheld"])
def test_gyro_integrates_to_the_trajectory(scenario: str) -> None:
    """Integrating (gyro - bias) by the trapezoid rule (instantaneous samples) reproduces the true rotations at the
    IMU stamps (drift only from the gyro noise)."""
    sim = simulate(scenario, 1, duration=60.0 if scenario == "paper" else None)
    gyr = sim.recording.select(Kind.GYROSCOPE)
    dt = 1.0 / gyr.rate_hz
    w = gyr.xyz - sim.truth.gyro_bias
    steps = so3.exp(0.5 * (w[:-1] + w[1:]) * dt)
    path = sim.rotations[0] @ so3.cumulative_product(steps)
    err = so3.angle(path.transpose(0, 2, 1) @ sim.rotations[1:])
    # random walk of the gyro noise: sigma * dt * sqrt(k) per axis
    bound = 5 * sim.truth.noise_std["gyroscope"] * dt * np.sqrt(np.arange(1, len(err) + 1)) * np.sqrt(3)
    assert np.all(err < bound + 1e-9)


def test_models_hold_within_noise() -> None:
    """Accelerometer and magnetometer residuals against the truth at their own stamps have the stated per-sample
    std (the magnetometer's stamps are not the IMU's: the truth is evaluated there)."""
    sim = simulate("handheld", 2)
    rec, tr = sim.recording, sim.truth
    acc, mag = rec.select(Kind.ACCELEROMETER), rec.select(Kind.MAGNETOMETER)
    ra = acc.xyz + np.einsum("nji,j->ni", sim.rotations, [0, 0, G]) - tr.accel_bias
    assert sim.trajectory is not None and 0.0 < mag.t[0] < 0.005
    rm = mag.xyz - np.einsum("nji,j->ni", sim.trajectory.at(mag.t), tr.m_n) @ tr.D.T - tr.o
    assert np.std(ra) == pytest.approx(tr.noise_std["accelerometer"], rel=0.03)
    assert np.std(rm) == pytest.approx(tr.noise_std["magnetometer"], rel=0.05)


def test_handheld_protocol_shape() -> None:
    """10 s still at both ends, >= 12 still poses of 2-4 s, rotations in between, rates 100/50 Hz."""
    sim = simulate("handheld", 3)
    still = sim.still
    assert still[0][1] - still[0][0] == pytest.approx(10.0, abs=0.02)
    assert still[-1][1] - still[-1][0] == pytest.approx(10.0, abs=0.02)
    middle = [b - a for a, b in still[1:-1]]
    assert len(middle) >= 12 and all(1.98 <= d <= 4.0 for d in middle)
    ups = np.array([sim.rotations[int(a * 100)].T @ [0, 0, -1] for a, _ in still[1:-1]])
    assert np.linalg.svd(ups, compute_uv=False).min() > 0.3     # poses span all three axes
    rec = sim.recording
    assert rec.select(Kind.GYROSCOPE).rate_hz == pytest.approx(100.0)
    assert rec.select(Kind.MAGNETOMETER).rate_hz == pytest.approx(50.0)


def test_truth_is_drawn_like_the_paper() -> None:
    """Ranges of methods.md section 5 over 50 seeds."""
    for seed in range(50):
        tr = simulate("paper", seed, duration=30.0).truth
        assert np.all(np.abs(tr.accel_bias) <= 0.5) and np.all(np.abs(tr.o) <= 2e-6)
        assert abs(np.rad2deg(tr.dip) - 72.0) <= 5.0
        assert np.all(np.abs(tr.gyro_bias - 0.01) <= np.deg2rad(0.1))
        assert 27e-6 * 0.75 < tr.field_strength < 27e-6 * 1.15


def test_bad_rates_are_refused() -> None:
    """Rates must be positive and finite (any ratio is fine: 100 Hz IMU with a 30 Hz magnetometer simulates)."""
    with pytest.raises(MagcalError, match=r"simulate: mag_rate must be a finite number of Hz > 0, got -30"):
        simulate("handheld", 0, rate=100.0, mag_rate=-30.0)
    with pytest.raises(MagcalError, match=r"simulate: rate must be a finite number of Hz > 0, got inf"):
        simulate("handheld", 0, rate=float("inf"))
    mag = simulate("handheld", 0, rate=100.0, mag_rate=30.0, duration=30.0).recording.select(Kind.MAGNETOMETER)
    assert mag.rate_hz == pytest.approx(30.0)


@pytest.mark.parametrize("scenario", ["handheld", "multirotor", "rover"])
def test_logged_scenarios_carry_the_field_of_their_place_and_date(scenario: str) -> None:
    """The written logs claim HOME and T0_ROS: dip, declination and strength are the WMM's there, and the field
    points that way in the (true-north) NED frame the trajectory uses."""
    import datetime as dt

    from magcal_cli.synth.physics import HOME
    from magcal_cli.synth.simulate import T0_ROS
    from magcal_cli.wmm import reference_field

    sim = simulate(scenario, 3, duration=None if scenario == "handheld" else 100.0)
    ref = reference_field(*HOME, dt.datetime.fromtimestamp(T0_ROS, dt.timezone.utc).date())
    tr = sim.truth
    assert tr.dip == ref.dip and tr.declination == ref.declination != 0.0
    assert tr.field_strength == pytest.approx(ref.intensity, rel=0.2)
    assert np.rad2deg(np.arctan2(tr.m_n[1], tr.m_n[0])) == pytest.approx(np.rad2deg(ref.declination))
    mag = sim.recording.select(Kind.MAGNETOMETER)
    body = np.linalg.solve(tr.D, (mag.xyz - tr.o).T).T              # the unit field seen in the body
    assert sim.trajectory is not None
    nav = np.einsum("nij,nj->ni", sim.trajectory.at(mag.t), body)
    assert np.abs(nav.mean(axis=0) - tr.m_n).max() < 0.02
