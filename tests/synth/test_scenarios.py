"""The `multirotor` and `rover` scenarios (issue 12): attitude as designed, a translation the accelerometer and
the logged GNSS position agree on, every output format, and reproducible draws."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import so3
from magcal_cli.cli.main import cli
from magcal_cli.errors import MagcalError
from magcal_cli.models.accel import G
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.physics import local
from magcal_cli.synth.simulate import Simulation, simulate

RATE = 100.0


def rpy_deg(sim: Simulation) -> np.ndarray:
    """Roll, pitch, yaw (deg, yaw unwrapped) of the true rotations."""
    rpy = so3.as_rpy(sim.rotations)
    rpy[:, 2] = np.unwrap(rpy[:, 2])
    out: np.ndarray = np.rad2deg(rpy)
    return out


def nav_acceleration(sim: Simulation) -> np.ndarray:
    """R (f - b_a) + g_n: the NED acceleration the accelerometer reports (N, 3)."""
    acc = sim.recording.select(Kind.ACCELEROMETER).xyz - sim.truth.accel_bias
    out: np.ndarray = np.einsum("nij,nj->ni", sim.rotations, acc) + [0.0, 0.0, G]
    return out


def moving(sim: Simulation) -> np.ndarray:
    """Mask of the IMU samples outside the still intervals."""
    t = sim.recording.select(Kind.ACCELEROMETER).t
    still = np.zeros(t.size, bool)
    for a, b in sim.still:
        still |= (t >= a - 1e-9) & (t <= b + 1e-9)
    return ~still


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_multirotor_attitude_as_designed(seed: int) -> None:
    """Roll and pitch within the 22 deg limit and often beyond 10 deg; yaw turned >= 5 full turns in total,
    every 10 deg heading sector flown; 10 s still at both ends; 100/50 Hz, 300 s."""
    sim = simulate("multirotor", seed)
    rpy = rpy_deg(sim)
    assert np.abs(rpy[:, :2]).max() < 22.0
    assert np.percentile(np.abs(rpy[:, :2]), 99) > 10.0
    assert np.abs(np.diff(rpy[:, 2])).sum() > 5 * 360.0
    assert np.unique(np.floor(np.mod(rpy[:, 2], 360.0) / 10.0)).size == 36
    (a0, b0), (a1, b1) = sim.still
    assert (a0, b1) == (0.0, pytest.approx(300.0 - 1 / RATE))
    assert b0 - a0 == pytest.approx(10.0, abs=0.02) and b1 - a1 == pytest.approx(10.0, abs=0.02)
    rec = sim.recording
    assert rec.select(Kind.GYROSCOPE).rate_hz == pytest.approx(RATE)
    assert rec.select(Kind.MAGNETOMETER).rate_hz == pytest.approx(50.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rover_attitude_and_turns_as_designed(seed: int) -> None:
    """Roll and pitch within 5 deg; >= 4 full turns of yaw, both ways (circles and figure-eights); the sideways
    acceleration is the centripetal v yaw_rate (to the terrain's tilt); a still stop half-way."""
    sim = simulate("rover", seed, noise_scale=0.0)
    rpy = rpy_deg(sim)
    assert np.abs(rpy[:, :2]).max() <= 5.0
    turn = np.diff(rpy[:, 2])
    assert np.abs(turn).sum() > 4 * 360.0 and turn.min() < 0 < turn.max()
    p_n = next(e for e in sim.effects if e.id == "nongravity_acceleration").signals["p_n"]
    a_n = nav_acceleration(sim)
    psi = np.deg2rad(rpy[:, 2])
    v = np.gradient(p_n, 1 / RATE, axis=0)
    speed = np.hypot(v[:, 0], v[:, 1])
    side = -np.sin(psi) * a_n[:, 0] + np.cos(psi) * a_n[:, 1]
    want = speed * np.gradient(psi, 1 / RATE)
    assert np.max(np.abs(side - want)) < 0.05 + 0.1 * np.abs(want).max()
    assert np.corrcoef(side, want)[0, 1] > 0.98
    assert len(sim.still) == 3 and 100.0 < sim.still[1][0] < 200.0


@pytest.mark.parametrize("scenario", ["multirotor", "rover"])
def test_specific_force_matches_the_logged_position(scenario: str) -> None:
    """The logged GNSS position differentiated twice (10 Hz) is the continuous a_n averaged over a triangle of
    +-0.1 s; R (f - b_a) + g_n from the instantaneous 100 Hz samples, averaged the same way by the trapezoid rule,
    matches it to 5e-4 m/s^2 without noise (the rule's error on a_n sampled at 100 Hz; a_n peaks near 4 m/s^2), to
    the accelerometer noise with it (per sample: the multirotor vibrates in flight). Still means a_n = 0."""
    for noise, tol in ((0.0, 5e-4), (1.0, None)):
        sim = simulate(scenario, 3, duration=120.0, noise_scale=noise)
        pos = sim.recording.select(Kind.POSITION)
        assert pos.rate_hz == pytest.approx(10.0)
        p = local(pos.values)
        dd = (p[2:] - 2 * p[1:-1] + p[:-2]) / 0.1**2
        m = 10                                      # IMU periods per GNSS period
        weights = (m - np.abs(np.arange(-m, m + 1))) / m**2          # the triangle at the stamps (trapezoid rule)
        a_n = nav_acceleration(sim)
        centres = np.arange(1, len(p) - 1) * m
        ok = centres + m < len(a_n)
        avg = np.array([weights @ a_n[c - m:c + m + 1] for c in centres[ok]])
        err = dd[ok] - avg
        if tol is not None:
            assert np.abs(err).max() < tol
            assert np.abs(a_n[~moving(sim)]).max() < 1e-9
        else:       # the multirotor's noise is the flight level while its motors run (vibration)
            sd = sim.imu_noise_std("accelerometer", sim.recording.select(Kind.ACCELEROMETER).t)
            want = np.sqrt(np.mean([weights**2 @ sd[c - m:c + m + 1] ** 2 for c in centres[ok]]))
            assert np.sqrt(np.mean(err**2)) < 1.5 * want
        assert np.abs(avg).max() > 1.0             # and it does accelerate


@pytest.mark.parametrize("name", ["x.bin", "x.ulg"])
def test_cli_writes_a_readable_multirotor_log(tmp_path: Path, name: str) -> None:
    """`magcal simulate x.bin --scenario multirotor` (and .ulg): IMU, field and GNSS position read back; the truth
    lists the flight's translation as nongravity_acceleration with the reader's position id."""
    out = tmp_path / name
    result = CliRunner().invoke(cli, ["simulate", str(out), "--scenario", "multirotor", "--seed", "1", "-q"])
    assert result.exit_code == 0, result.output
    rec = open_recording(out)
    sim = simulate("multirotor", 1)
    acc = rec.select(Kind.ACCELEROMETER)
    assert len(acc) == len(sim.recording.select(Kind.ACCELEROMETER))
    assert acc.rate_hz == pytest.approx(RATE, rel=1e-3)
    assert len(rec.select(Kind.MAGNETOMETER)) == len(sim.recording.select(Kind.MAGNETOMETER))
    got, want = rec.select(Kind.POSITION), sim.recording.select(Kind.POSITION)
    np.testing.assert_allclose(got.values[:, :2], want.values[:, :2], rtol=0, atol=0.6e-7)
    np.testing.assert_allclose(got.values[:, 2], want.values[:, 2], rtol=0, atol=0.006)
    doc = json.loads((tmp_path / f"{name}.truth.json").read_text())
    (entry,) = doc["effects"]
    assert entry["id"] == "nongravity_acceleration" and entry["channels"] == [got.id]
    assert entry["params"]["source"] == "gps" and 0.3 < entry["params"]["sigma_a"] < 2.0
    assert doc["simulation"]["scenario"] == "multirotor"


@pytest.mark.parametrize("name", ["x.mcap", "x.bag", "ros2", "x.csv"])
def test_rover_in_every_other_format(tmp_path: Path, name: str) -> None:
    """A rover log in the ROS formats carries /gps/fix; a CSV has no position column (spec/cli.md) and holds the
    magnetometer on IMU rows (phase 0)."""
    sim = simulate("rover", 2, duration=60.0, mag_phase_s=0.0 if name == "x.csv" else None)
    write_log(sim, tmp_path / name)
    rec = open_recording(tmp_path / name)
    assert len(rec.select(Kind.GYROSCOPE)) == len(sim.recording.select(Kind.GYROSCOPE))
    assert [s.id for s in rec.of_kind(Kind.POSITION)] == ([] if name == "x.csv" else ["/gps/fix"])


@pytest.mark.parametrize("scenario", ["multirotor", "rover"])
def test_same_seed_same_log(scenario: str) -> None:
    """Same seed: identical arrays, with or without effects; effects leave the base draws alone."""
    spec = (EffectSpec("current_interference"),)
    a, b = simulate(scenario, 5, duration=100.0), simulate(scenario, 5, duration=100.0)
    c = simulate(scenario, 5, duration=100.0, effects=spec)
    d = simulate(scenario, 5, duration=100.0, effects=spec)
    assert np.array_equal(a.rotations, b.rotations) and a.still == b.still
    for x, y in ((a, b), (c, d)):
        assert len(x.recording.streams) == len(y.recording.streams)
        for s, u in zip(x.recording.streams, y.recording.streams, strict=True):
            assert s.id == u.id and np.array_equal(s.t, u.t) and np.array_equal(s.values, u.values)
    for kind in (Kind.ACCELEROMETER, Kind.GYROSCOPE, Kind.POSITION):
        assert np.array_equal(a.recording.select(kind).values, c.recording.select(kind).values)
    assert not np.array_equal(a.rotations, simulate(scenario, 6, duration=100.0).rotations)


def test_nongravity_effect_adds_its_sway_to_the_flight() -> None:
    """--effect nongravity_acceleration on a multirotor adds a sway of the requested RMS to the flight's a_n; one
    position stream logs the summed path; the truth's sigma_a is the sum's RMS; source=none drops the stream."""
    ng = "nongravity_acceleration"
    base = simulate("multirotor", 2, duration=100.0, noise_scale=0.0)
    sway = simulate("multirotor", 2, duration=100.0, noise_scale=0.0, effects=(EffectSpec(ng, {"sigma_a": 0.5}),))
    (e0,), (e1,) = base.effects, sway.effects
    extra = e1.signals["a_n"] - e0.signals["a_n"]
    assert np.sqrt(np.mean(extra**2)) == pytest.approx(0.5, rel=1e-9)
    assert e1.params["sigma_a"] == pytest.approx(np.sqrt(np.mean(e1.signals["a_n"] ** 2)))
    (pos,) = sway.recording.of_kind(Kind.POSITION)
    moved = local(pos.values) - local(base.recording.select(Kind.POSITION).values)
    idx = np.round(pos.t * RATE).astype(int)
    np.testing.assert_allclose(moved, (e1.signals["p_n"] - e0.signals["p_n"])[idx], atol=1e-6)
    assert 0.1 < np.abs(moved).max() < 20.0
    blind = simulate("multirotor", 2, duration=100.0, effects=(EffectSpec(ng, {"source": "none"}),))
    assert not blind.recording.of_kind(Kind.POSITION) and blind.effects[0].params["source"] == "none"


def test_too_short_is_refused() -> None:
    with pytest.raises(MagcalError, match="the multirotor scenario needs --duration >= 90 s"):
        simulate("multirotor", 0, duration=60.0)


def test_flat_rover_with_nongravity_is_within_its_uncertainty(tmp_path: Path) -> None:
    """Rover seed 0 (tilt within 5 deg) with --effects nongravity_acceleration: the partial path must hold the
    base entries where the effect's layout puts them. It held two accelerometer-bias entries and o.y instead of
    the gyro biases and dip, and D came out 70 % off (max |z| 279)."""
    from magcal_cli.calibration.document import dumps_json, load
    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate
    from magcal_cli.synth.simulate import truth_calibration

    log = tmp_path / "rover.bin"
    sim = simulate("rover", 0)
    write_log(sim, log)
    (tmp_path / "t.json").write_text(dumps_json(truth_calibration(sim, open_recording(log), "test", "")))
    truth = load(tmp_path / "t.json")
    res = calibrate(log, Config(effects=("nongravity_acceleration",)))
    m, tm = res.calibration.magnetometers[0], truth.magnetometers[0]
    assert np.linalg.norm(m.D - tm.D) / np.linalg.norm(tm.D) < 0.01
    for got, want, std in ((m.D, tm.D, m.std_of("D")), (m.o, tm.o, m.std_of("o")),
                           (m.dip_deg, tm.dip_deg, m.std_of("dip"))):
        assert np.abs((np.asarray(got) - want) / std).max() < 5.0
