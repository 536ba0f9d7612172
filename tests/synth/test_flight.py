"""Flights as real vehicles log them: IMU vibration while the motors run, several compasses in one `.bin`, the
firmware's stale motor compensation, a bounded flight envelope, a PX4 flight with its power channels, and the
paper protocol's band-limited rate. Checked against the truth and the physics only, never against the
estimator (reading a log back through its reader is not estimation).

Modules it covers (the mirrored test file aside): magcal_cli.synth.firmware, magcal_cli.synth.logs.dataflash,
magcal_cli.synth.logs.ulog, magcal_cli.synth.truth, magcal_cli.synth.vibration.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.errors import MagcalError
from magcal_cli.models.accel import G
from magcal_cli.readers import open_recording
from magcal_cli.readers.dataflash.ardupilot import reconstruct_mags
from magcal_cli.readers.dataflash.compass import Correction
from magcal_cli.readers.dataflash.load import load
from magcal_cli.streams import Kind, Sampling
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.firmware import STALE_CURRENT_COMPENSATION, PreviousCalibration
from magcal_cli.synth.logs import imu_sampling, write_log
from magcal_cli.synth.logs.dataflash import DEV_IDS, build, default_offsets
from magcal_cli.synth.motion import OVERSAMPLE
from magcal_cli.synth.rotation import PAPER_BAND, PAPER_RATE_STD
from magcal_cli.synth.simulate import NOISE_DENSITY, Simulation, simulate, truth_calibration
from magcal_cli.synth.vibration import SPIN_S, VIBRATION_STD


def imu_noise(sim: Simulation, quiet: Simulation, kind: Kind) -> np.ndarray:
    """The noise the simulation added to an IMU stream: it minus the noise-free one of the same seed."""
    out: np.ndarray = sim.recording.select(kind).xyz - quiet.recording.select(kind).xyz
    return out


def phases(sim: Simulation, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the samples with the motors off (beyond the spin ramps) and at flight speed."""
    ((t_to, t_td),) = sim.motors
    return (t < t_to - SPIN_S) | (t > t_td + SPIN_S), (t >= t_to) & (t <= t_td)


def body_field(sim: Simulation, k: int, t: np.ndarray) -> np.ndarray:
    """D_k R(t)^T m_n + o_k (N, 3) tesla: what magnetometer k reads without noise."""
    assert sim.trajectory is not None
    tr = sim.truths[k]
    out: np.ndarray = np.einsum("nji,j->ni", sim.trajectory.at(t), tr.m_n) @ tr.D.T + tr.o
    return out


# -- vibration -----------------------------------------------------------------------------------------------

def test_vibration_raises_the_imu_noise_while_the_motors_run() -> None:
    """Multirotor default: gyro 0.003 -> 0.01 rad/s and accelerometer 0.03 -> 0.15 m/s^2 from take-off to
    touchdown, the rest level on the pad before and after, 1 s ramps between; each sample's noise over its own std
    is unit normal throughout; the magnetometer's noise is the same as without vibration."""
    sim, quiet = (simulate("multirotor", 6, duration=120.0, noise_scale=s) for s in (1.0, 0.0))
    assert sim.vibration and sim.motors == ((10.0, 108.0),)
    t = sim.recording.select(Kind.GYROSCOPE).t
    ground, air = phases(sim, t)
    for sensor, kind in (("gyroscope", Kind.GYROSCOPE), ("accelerometer", Kind.ACCELEROMETER)):
        noise = imu_noise(sim, quiet, kind)
        rest, flight = VIBRATION_STD[sensor]
        assert sim.truth.noise_std[sensor] == rest and sim.truth.noise_std_flight is not None
        assert sim.truth.noise_std_flight[sensor] == flight
        assert np.std(noise[ground]) == pytest.approx(rest, rel=0.04)      # ~2000 samples x 3 axes
        assert np.std(noise[air]) == pytest.approx(flight, rel=0.02)
        z = noise / sim.imu_noise_std(sensor, t)[:, None]
        spin = ~ground & ~air
        assert np.std(z[spin]) == pytest.approx(1.0, rel=0.1) and np.std(z) == pytest.approx(1.0, rel=0.01)
    mag = sim.recording.select(Kind.MAGNETOMETER).xyz - quiet.recording.select(Kind.MAGNETOMETER).xyz
    calm = simulate("multirotor", 6, duration=120.0, vibration=False)
    assert np.std(mag) == pytest.approx(calm.truth.noise_std["magnetometer"], rel=0.03)
    assert sim.truth.noise_std["magnetometer"] == calm.truth.noise_std["magnetometer"]


def test_without_vibration_every_scenario_keeps_its_noise() -> None:
    """vibration=False (the default off the multirotor) keeps the paper's densities times sqrt(rate), one level."""
    for scenario, kw in (("multirotor", {"vibration": False, "duration": 100.0}), ("handheld", {}),
                         ("rover", {"duration": 70.0})):
        sim = simulate(scenario, 2, **kw)  # type: ignore[arg-type]
        assert not sim.vibration and sim.truth.noise_std_flight is None
        assert sim.truth.noise_std["gyroscope"] == pytest.approx(NOISE_DENSITY["gyroscope"] * 10.0)
        t = sim.recording.select(Kind.GYROSCOPE).t
        assert np.all(sim.imu_noise_std("accelerometer", t) == sim.truth.noise_std["accelerometer"])


def test_vibration_needs_motors() -> None:
    """Off the multirotor, motors run only with a power model: then the flight level holds the whole log."""
    with pytest.raises(MagcalError, match=r"simulate: vibration needs motors, and the paper scenario has none"):
        simulate("paper", 1, duration=30.0, vibration=True)
    sim = simulate("paper", 1, duration=30.0, vibration=True, effects=(EffectSpec("current_interference"),))
    quiet = simulate("paper", 1, duration=30.0, vibration=True, noise_scale=0.0,
                     effects=(EffectSpec("current_interference"),))
    t = sim.recording.select(Kind.GYROSCOPE).t
    np.testing.assert_allclose(sim.imu_noise_std("gyroscope", t), VIBRATION_STD["gyroscope"][1])
    assert np.std(imu_noise(sim, quiet, Kind.GYROSCOPE)) == pytest.approx(VIBRATION_STD["gyroscope"][1], rel=0.03)


def test_truth_reports_both_levels(tmp_path: Path) -> None:
    """The truth's noise keeps `<sensor>_std` as the rest level and adds `_std_rest` and `_std_flight` (the
    magnetometer's equal), and `simulation` says when the motors ran."""
    sim = simulate("multirotor", 1, duration=100.0)
    path = tmp_path / "v.bin"
    write_log(sim, path)
    doc = truth_calibration(sim, open_recording(path), "test", "now")
    noise = doc.noise
    assert noise["gyroscope_std"] == noise["gyroscope_std_rest"] == [0.003] * 3
    assert noise["gyroscope_std_flight"] == [0.01] * 3 and noise["accelerometer_std_flight"] == [0.15] * 3
    assert noise["magnetometer_std_flight"] == noise["magnetometer_std"]
    assert doc.extra["simulation"]["motors_s"] == [[10.0, 88.0]] and doc.extra["simulation"]["spin_s"] == SPIN_S


# -- several compasses ---------------------------------------------------------------------------------------

def test_more_magnetometers_leave_the_first_and_the_imu_alone() -> None:
    """n_mags=3 adds /imu/mag1 and /imu/mag2, each reading its own D m_b + o at the first one's stamps with the
    same noise std; the IMU and /imu/mag are those of n_mags=1, bit for bit."""
    one, three = simulate("handheld", 3), simulate("handheld", 3, n_mags=3)
    assert three.recording.ids(Kind.MAGNETOMETER) == ["/imu/mag", "/imu/mag1", "/imu/mag2"]
    for a, b in zip(one.recording.streams[:3], three.recording.streams[:3], strict=True):
        assert a.id == b.id and np.array_equal(a.t, b.t) and np.array_equal(a.xyz, b.xyz)
    sd = one.truth.noise_std["magnetometer"]
    for k in (1, 2):
        tr, mag = three.truths[k], three.recording.of_kind(Kind.MAGNETOMETER)[k]
        assert np.array_equal(mag.t, one.recording.select(Kind.MAGNETOMETER).t)
        assert np.std(mag.xyz - body_field(three, k, mag.t)) == pytest.approx(sd, rel=0.05)
        assert tr.field_strength == pytest.approx(one.truth.field_strength, rel=0.25)
        assert np.abs(tr.D - one.truth.D).max() > 1e-7 and tr.dip == one.truth.dip
    with pytest.raises(MagcalError, match=r"simulate: n_mags must be a whole number >= 1, got 0"):
        simulate("handheld", 3, n_mags=0)


@pytest.fixture(scope="module")
def two_compass_bin(tmp_path_factory: pytest.TempPathFactory) -> tuple[Simulation, Path]:
    """A noise-free multirotor with two compasses and its power channels, flown with a stale COMPASS_MOT."""
    sim = simulate("multirotor", 7, duration=100.0, n_mags=2, noise_scale=0.0, log_power=True, mag_rate=10.0)
    sim = replace(sim, previous=STALE_CURRENT_COMPENSATION)
    path = tmp_path_factory.mktemp("bin") / "two.bin"
    write_log(sim, path)
    return sim, path


def quantisation_bound(c: Correction) -> float:
    """Largest raw error (mG) from int16 truncation of MagX..: one count through |M^-1|_inf, per SCALE, twice
    (the half count added back, and MOX's own count where the reader takes it)."""
    inv = np.linalg.inv(c.matrix)
    return float(np.max(np.abs(inv).sum(axis=2).max(axis=1) * 2.0 / c.scale)) + 1e-6


def test_two_compasses_read_back_as_their_truths(two_compass_bin: tuple[Simulation, Path]) -> None:
    """MAG instances 0 and 1, each with its own COMPASS_OFS/DIA/ODI(2) and DEV_ID(2): the reader's raw field of
    each is D_k m_b + o_k within the int16 quantisation, at the simulated stamps, and the truth lists MAG[0] and
    MAG[1] in milligauss with the raw D and o."""
    sim, path = two_compass_bin
    rec = open_recording(path)
    assert rec.ids(Kind.MAGNETOMETER) == ["MAG[0]", "MAG[1]"]
    for k, m in enumerate(reconstruct_mags(path)):
        mag, t = rec.select(Kind.MAGNETOMETER, f"MAG[{k}]"), sim.recording.of_kind(Kind.MAGNETOMETER)[k].t
        np.testing.assert_allclose(mag.t, t, atol=1e-6)
        err = np.abs(mag.xyz - body_field(sim, k, t)).max() * 1e7
        assert 0.0 < err <= quantisation_bound(m.correction)
        suffix = "" if k == 0 else str(k + 1)
        cp = STALE_CURRENT_COMPENSATION.compass(k)
        assert rec.params[f"COMPASS_DEV_ID{suffix}"] == rec.params[f"COMPASS_PRIO{k + 1}_ID"] == DEV_IDS[k]
        np.testing.assert_allclose([rec.params[f"COMPASS_OFS{suffix}_{a}"] for a in "XYZ"],
                                   default_offsets(sim, k), atol=1e-3)
        np.testing.assert_allclose([rec.params[f"COMPASS_DIA{suffix}_{a}"] for a in "XYZ"], cp.dia, atol=1e-6)
        np.testing.assert_allclose([rec.params[f"COMPASS_ODI{suffix}_{a}"] for a in "XYZ"], cp.odi, atol=1e-6)
    doc = truth_calibration(sim, rec, "test", "now")
    assert [(c.id, c.unit) for c in doc.magnetometers] == [("MAG[0]", "milligauss"), ("MAG[1]", "milligauss")]
    for cal, tr in zip(doc.magnetometers, sim.truths, strict=True):
        np.testing.assert_allclose(cal.D, tr.D * 1e7, rtol=1e-12)
        np.testing.assert_allclose(cal.o, tr.o * 1e7, rtol=1e-12)


def test_stale_motor_compensation_is_in_parm_and_mox(two_compass_bin: tuple[Simulation, Path]) -> None:
    """COMPASS_MOTCT=2 with the stale COMPASS_MOT and MOT2 in PARM; each instance's MOX.. is MOT x the logged
    battery current within a count (int16 truncation toward zero) and tens of mG at flight currents, though the
    simulated field has no current interference."""
    sim, path = two_compass_bin
    rec = open_recording(path)
    assert rec.params["COMPASS_MOTCT"] == 2.0 and [e.id for e in sim.effects] == ["nongravity_acceleration"]
    raw = load(path)
    mag, bat = raw.table("MAG"), raw.table("BAT")
    assert mag is not None and bat is not None
    current = bat.num("Curr")
    np.testing.assert_allclose(current, sim.recording.select(Kind.BATTERY_CURRENT).values[:, 0], rtol=1e-6)
    for k in (0, 1):
        suffix = "" if k == 0 else str(k + 1)
        mot = np.array([rec.params[f"COMPASS_MOT{suffix}_{a}"] for a in "XYZ"])
        np.testing.assert_allclose(mot, STALE_CURRENT_COMPENSATION.compass(k).mot, rtol=1e-6)
        rows = mag.num("I") == k
        mox = np.stack([mag.num(c)[rows] for c in ("MOX", "MOY", "MOZ")], axis=1)
        product = current[:, None] * mot.astype(np.float32)
        assert np.abs(mox - product).max() < 1.0
        np.testing.assert_array_equal(mox, np.trunc(product))
        assert np.abs(mox).max() > 20.0


def test_a_bin_holds_at_most_three_compasses() -> None:
    sim = simulate("handheld", 1, duration=40.0, n_mags=4)
    with pytest.raises(MagcalError, match=r"an ArduPilot log holds at most 3 calibrated compasses"):
        build(sim)
    with pytest.raises(ValueError, match=r"ArduPilot calibrates compasses 0..2, not 3"):
        PreviousCalibration().compass(3)


@pytest.mark.parametrize(("name", "ids"), [("x.ulg", ["sensor_mag[0]", "sensor_mag[1]"]),
                                           ("x.mcap", ["/imu/mag", "/imu/mag1"]), ("x.csv", ["mag"])])
def test_other_formats_write_every_magnetometer_they_can(tmp_path: Path, name: str, ids: list[str]) -> None:
    """ULog: sensor_mag instances with their own device ids; ROS: one MagneticField topic each; CSV (one field
    column set in spec/cli.md): the first. The truth lists the magnetometers the log holds, by the reader's ids."""
    path = tmp_path / name
    sim = simulate("handheld", 5, duration=40.0, n_mags=2, imu_sampling=imu_sampling(path),
                   mag_phase_s=0.0 if name.endswith(".csv") else None)
    write_log(sim, path)
    rec = open_recording(path)
    assert rec.ids(Kind.MAGNETOMETER) == ids
    doc = truth_calibration(sim, rec, "test", "now")
    assert [c.id for c in doc.magnetometers] == ids
    for k, mag in enumerate(rec.of_kind(Kind.MAGNETOMETER)):
        np.testing.assert_allclose(mag.xyz, sim.recording.of_kind(Kind.MAGNETOMETER)[k].xyz, rtol=1e-6, atol=1e-12)
    if name.endswith(".ulg"):
        assert rec.params["CAL_MAG1_ID"] != rec.params["CAL_MAG0_ID"]


# -- flight envelope -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1])
def test_tilt_and_acceleration_limits_hold(seed: int) -> None:
    """tilt_limit_deg=15, accel_limit_mps2=1.5: the tilt (body z from vertical) stays within 15 deg at every
    fine knot, the horizontal NED acceleration (the truth, and the noise-free accelerometer's R f + g_n) within
    1.5 m/s^2; the flight still uses its envelope."""
    sim = simulate("multirotor", seed, noise_scale=0.0, tilt_limit_deg=15.0, accel_limit_mps2=1.5)
    assert sim.trajectory is not None
    fine = np.arange(round(sim.trajectory.end * 100.0 * OVERSAMPLE)) / (100.0 * OVERSAMPLE)
    tilt = np.rad2deg(np.arccos(np.clip(sim.trajectory.at(fine)[:, 2, 2], -1.0, 1.0)))
    assert tilt.max() <= 15.0 and np.percentile(tilt, 99) > 12.0
    a_n = next(e for e in sim.effects if e.id == "nongravity_acceleration").signals["a_n"]
    acc = sim.recording.select(Kind.ACCELEROMETER).xyz - sim.truth.accel_bias
    sensed = np.einsum("nij,nj->ni", sim.rotations, acc) + [0.0, 0.0, G]
    for a in (a_n, sensed):
        assert np.linalg.norm(a[:, :2], axis=1).max() <= 1.5 + 1e-9
    assert np.linalg.norm(a_n[:, :2], axis=1).max() > 1.3


def test_limits_are_for_the_multirotor_and_within_sense() -> None:
    with pytest.raises(MagcalError, match=r"tilt_limit_deg and accel_limit_mps2 shape the multirotor's own flight"):
        simulate("rover", 1, tilt_limit_deg=10.0)
    with pytest.raises(MagcalError, match=r"tilt_limit_deg must be within 3..45 deg"):
        simulate("multirotor", 1, tilt_limit_deg=60.0)
    with pytest.raises(MagcalError, match=r"accel_limit_mps2 must be within 0.2..20 m/s\^2, got 0.0"):
        simulate("multirotor", 1, accel_limit_mps2=0.0)


# -- PX4 ---------------------------------------------------------------------------------------------------

def test_px4_flight_carries_current_throttle_gps_and_vibration(tmp_path: Path) -> None:
    """A multirotor with current_interference sampled as PX4 does, written to .ulg: battery_status, the thrust
    setpoint and the GNSS fix read back as simulated, and sensor_combined carries the vibration (rest level on
    the pad, flight level in the air)."""
    effects = (EffectSpec("current_interference"),)
    sim, quiet = (simulate("multirotor", 4, duration=120.0, effects=effects, imu_sampling=Sampling.PRECEDING,
                           noise_scale=s) for s in (1.0, 0.0))
    path = tmp_path / "flight.ulg"
    write_log(sim, path)
    rec = open_recording(path)
    for kind in (Kind.BATTERY_CURRENT, Kind.THROTTLE):
        got, want = rec.select(kind), sim.recording.select(kind)
        np.testing.assert_allclose(got.values, want.values, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(rec.select(Kind.POSITION).xyz, sim.recording.select(Kind.POSITION).xyz, atol=1e-9)
    acc = rec.select(Kind.ACCELEROMETER)
    ground, air = phases(sim, acc.t)
    noise = acc.xyz - quiet.recording.select(Kind.ACCELEROMETER).xyz
    assert np.std(noise[ground]) == pytest.approx(VIBRATION_STD["accelerometer"][0], rel=0.05)
    assert np.std(noise[air]) == pytest.approx(VIBRATION_STD["accelerometer"][1], rel=0.03)
    doc = truth_calibration(sim, rec, "test", "now")
    assert [e["channels"] for e in doc.effects] == [["battery_status[0]"], ["vehicle_gps_position"]]


# -- paper ---------------------------------------------------------------------------------------------------

def test_paper_rate_is_band_limited_and_integrates_by_the_trapezoid_rule() -> None:
    """The paper's random rate has no content above rate / 8 and std 0.05 rad/s per axis; so the noise-free INSTANT
    gyro integrated by the trapezoid rule follows the truth's every step to well below the gyro's noise per step
    (RMS under 0.2 of sigma_g dt, 99 % under 0.5; re-drawn every sample, the RMS was 0.55)."""
    sim = simulate("paper", 1, noise_scale=0.0)
    gyr = sim.recording.select(Kind.GYROSCOPE)
    rate, dt = gyr.rate_hz, 1.0 / gyr.rate_hz
    w = gyr.xyz - sim.truth.gyro_bias
    first = w[2:5000] - [0.1, 0.0, 0.0]                        # inside the first segment (62.8 s), v = 0.1 x
    assert np.std(first, axis=0) == pytest.approx([PAPER_RATE_STD] * 3, rel=0.1)
    power = np.abs(np.fft.rfft(first - first.mean(axis=0), axis=0)) ** 2
    above = np.fft.rfftfreq(len(first), dt) > PAPER_BAND * rate * 1.05
    assert power[above].sum() / power.sum() < 1e-3
    step = so3.exp(0.5 * (w[:-1] + w[1:]) * dt)
    true_step = np.swapaxes(sim.rotations[:-1], -1, -2) @ sim.rotations[1:]
    err = np.abs(so3.log(np.swapaxes(step, -1, -2) @ true_step))
    per_step = NOISE_DENSITY["gyroscope"] * np.sqrt(rate) * dt
    assert np.sqrt(np.mean(err**2)) < 0.2 * per_step and np.percentile(err, 99) < 0.5 * per_step
