"""`magcal simulate --effect`: each injected effect has the physics of calibration-file.md, and every log format
carries the channels it needs back to the readers (kinds, units, current positive while discharging).

Modules it covers (the mirrored test file aside): magcal_cli.synth.inject, magcal_cli.synth.logs.rosbag,
magcal_cli.synth.physics.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation, Slerp

from magcal_cli import so3
from magcal_cli.cli.main import cli
from magcal_cli.models.accel import G
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind
from magcal_cli.synth.effects import EFFECTS, EffectSpec, EffectSpecError, parse_effect
from magcal_cli.synth.inject import InjectedEffect
from magcal_cli.synth.logs import imu_sampling, write_log
from magcal_cli.synth.motion import Trajectory
from magcal_cli.synth.physics import geodetic
from magcal_cli.synth.simulate import Simulation, simulate, truth_calibration

RATE = 100.0
W = np.array([0.3, -0.5, 0.8])                                 # rad/s, a constant-rate rotation


def constant_rate(n: int = 1001) -> np.ndarray:
    """R(t) = Exp(W t) at RATE, n knots."""
    return so3.exp(np.arange(n)[:, None] / RATE * W)


def quiet(*effects: EffectSpec, scenario: str = "paper", seed: int = 5, **kw: object) -> Simulation:
    """A noise-free simulation (60 s of the paper protocol unless given a trajectory)."""
    kw.setdefault("duration", 60.0)
    return simulate(scenario, seed, noise_scale=0.0, effects=effects, **kw)  # type: ignore[arg-type]


def mag(sim: Simulation) -> np.ndarray:
    return sim.recording.select(Kind.MAGNETOMETER).xyz


def effect(sim: Simulation, eid: str) -> InjectedEffect:
    return next(e for e in sim.effects if e.id == eid)


def m_n(sim: Simulation) -> np.ndarray:
    return sim.truth.m_n


@pytest.fixture(scope="module")
def base() -> Simulation:
    return quiet()


def test_effects_leave_the_base_draws_alone() -> None:
    """Effects draw from their own generators: the IMU of a magnetometer-only injection is bit-identical, and
    a simulation without effects is unchanged by the effects machinery (same noise, same trajectory)."""
    plain = simulate("handheld", 7, duration=40.0)
    with_mag = simulate("handheld", 7, duration=40.0, effects=(EffectSpec("current_interference"),))
    for kind in (Kind.ACCELEROMETER, Kind.GYROSCOPE):
        assert np.array_equal(plain.recording.select(kind).values, with_mag.recording.select(kind).values)
    assert [s.kind for s in plain.recording.streams] == [Kind.ACCELEROMETER, Kind.GYROSCOPE, Kind.MAGNETOMETER]


@pytest.mark.parametrize("tau", [0.03, 0.0137, -0.004])
def test_time_offset_is_a_real_delay(tau: float) -> None:
    """The sample stamped t equals D R(t - tau)^T m_n + o to 1e-9 (relative), R from scipy's slerp of the knots:
    for a constant-rate rotation the true trajectory between knots is the geodesic."""
    knots = constant_rate()
    sim = quiet(EffectSpec("time_offset", {"tau_s": tau}), rate=RATE, mag_rate=50.0, trajectory=knots)
    t = sim.recording.select(Kind.MAGNETOMETER).t
    inside = (t - tau >= 0) & (t - tau <= (len(knots) - 1) / RATE)
    slerp = Slerp(np.arange(len(knots)) / RATE, Rotation.from_matrix(knots))
    rot = slerp(t[inside] - tau).as_matrix()
    want = np.einsum("nji,j->ni", rot, m_n(sim)) @ sim.truth.D.T + sim.truth.o
    assert np.abs(mag(sim)[inside] - want).max() <= 1e-9 * np.abs(want).max()
    assert inside.sum() >= len(t) - 2


def test_time_offset_on_the_knots_of_a_hand_motion() -> None:
    """tau of two IMU periods, magnetometer at phase 0 and half the IMU rate: magnetometer sample j sees exactly
    the rotation at IMU stamp 2j - 2."""
    sim = quiet(EffectSpec("time_offset", {"tau_s": 0.02}), scenario="handheld", duration=None, mag_phase_s=0.0)
    rot = sim.rotations[::2][:-1]
    want = np.einsum("nji,j->ni", rot, m_n(sim)) @ sim.truth.D.T + sim.truth.o
    np.testing.assert_allclose(mag(sim)[1:], want[: len(mag(sim)) - 1], rtol=0, atol=1e-15)


def test_trajectory_interpolant_passes_through_the_knots_with_their_rates() -> None:
    """R(t_k) = R_k exactly, and the body rate is continuous across a knot (C1 Hermite in the local chart)."""
    sim = quiet(scenario="handheld", duration=None)
    knots = np.concatenate([sim.rotations, sim.rotations[-1:]])
    traj = Trajectory.from_knots(knots, 0.01)
    k = np.arange(1000, 1100)
    np.testing.assert_allclose(traj.at(k * 0.01), knots[k], atol=1e-14)
    w_left, _ = traj.rate_and_acceleration(k * 0.01 - 1e-4, 1e-6)
    w_right, _ = traj.rate_and_acceleration(k * 0.01 + 1e-4, 1e-6)
    assert np.abs(w_left - w_right).max() < 0.05 * max(1.0, np.abs(traj.rates[k]).max())


def test_lever_arm_centripetal_term_at_constant_rate() -> None:
    """Constant rate: f - (-R^T g) - b_a = w x (w x r) (no tangential term), to the fine-grid precision."""
    r = np.array([0.1, -0.2, 0.05])
    sim = quiet(EffectSpec("lever_arm", {"r_m": tuple(r)}), rate=RATE, mag_rate=50.0, trajectory=constant_rate())
    acc = sim.recording.select(Kind.ACCELEROMETER).xyz
    gravity = -np.einsum("nji,j->ni", sim.rotations, [0.0, 0.0, G]) + sim.truth.accel_bias
    np.testing.assert_allclose(acc - gravity, np.broadcast_to(np.cross(W, np.cross(W, r)), acc.shape),
                               rtol=0, atol=1e-8)


def test_lever_arm_tangential_term_at_constant_angular_acceleration() -> None:
    """theta = alpha t^2 / 2 about a fixed axis: w = alpha t a, w' = alpha a, f_extra = w' x r + w x (w x r)."""
    axis, alpha, r = np.array([0.0, 0.6, 0.8]), 0.7, np.array([0.05, 0.02, -0.08])
    t = np.arange(801) / RATE
    knots = so3.exp((0.5 * alpha * t**2)[:, None] * axis)
    sim = quiet(EffectSpec("lever_arm", {"r_m": tuple(r)}), rate=RATE, mag_rate=50.0, trajectory=knots)
    acc = sim.recording.select(Kind.ACCELEROMETER).xyz
    gravity = -np.einsum("nji,j->ni", sim.rotations, [0.0, 0.0, G]) + sim.truth.accel_bias
    w = alpha * t[:-1, None] * axis
    want = np.cross(alpha * axis, r) + np.cross(w, np.cross(w, r))
    # the first and last knots' rates are one-sided, so the two end segments are not exactly quadratic
    np.testing.assert_allclose((acc - gravity)[2:-2], want[2:-2], rtol=0, atol=1e-7)


def test_current_interference_adds_c_times_the_logged_current(base: Simulation) -> None:
    """y - y_base = c I(t) exactly (no noise), with I the logged battery current: 2..35 A, voltage sagging."""
    c = (2e-8, -1e-8, 3e-8)
    sim = quiet(EffectSpec("current_interference", {"c": c}))
    cur = sim.recording.select(Kind.BATTERY_CURRENT)
    volt = sim.recording.select(Kind.BATTERY_VOLTAGE)
    assert np.array_equal(cur.t, sim.recording.select(Kind.MAGNETOMETER).t)
    np.testing.assert_allclose(mag(sim) - mag(base), cur.values * np.array(c), rtol=0, atol=1e-19)
    assert cur.values.min() > 1.5 and cur.values.max() < 36.0 and np.ptp(cur.values) > 8.0
    assert np.corrcoef(cur.values[:, 0], volt.values[:, 0])[0, 1] < -0.9
    thr = sim.recording.select(Kind.THROTTLE).values
    assert thr.min() >= 0.0 and thr.max() <= 1.0


def test_throttle_interference_adds_c_times_u_to_the_p(base: Simulation) -> None:
    """y - y_base = c u^p with u the logged throttle."""
    sim = quiet(EffectSpec("throttle_interference", {"c": (5e-7, 0.0, -8e-7), "p": 1.3}))
    u = sim.recording.select(Kind.THROTTLE).values
    np.testing.assert_allclose(mag(sim) - mag(base), u**1.3 * np.array([5e-7, 0.0, -8e-7]), rtol=0, atol=1e-19)


def test_temperature_drift_follows_the_warm_up(base: Simulation) -> None:
    """y - y_base = k (T - T0); T warms from 25 degC towards 45 degC monotonically."""
    k = np.array([2e-8, -1.5e-8, 3e-8])
    sim = quiet(EffectSpec("temperature_drift", {"k": tuple(k), "T0": 30.0}))
    temp = sim.recording.select(Kind.TEMPERATURE).values
    np.testing.assert_allclose(mag(sim) - mag(base), (temp - 30.0) * k, rtol=0, atol=1e-19)
    assert temp[0, 0] == pytest.approx(25.0, abs=1e-3) and np.all(np.diff(temp[:, 0]) >= 0) and 25 < temp[-1, 0] < 45


def test_scale_factors(base: Simulation) -> None:
    """gyro: w_meas - b_g = (1 + s) w; accelerometer: f_meas - b_a = (1 + s) f."""
    s_g, s_a = (0.01, -0.02, 0.005), (0.004, 0.01, -0.015)
    sim = quiet(EffectSpec("gyro_scale", {"s": s_g}), EffectSpec("accel_scale", {"s": s_a}))
    tr = sim.truth
    for kind, s, bias in ((Kind.GYROSCOPE, s_g, tr.gyro_bias), (Kind.ACCELEROMETER, s_a, tr.accel_bias)):
        got, ref = sim.recording.select(kind).xyz - bias, base.recording.select(kind).xyz - bias
        np.testing.assert_allclose(got, ref * (1.0 + np.array(s)), rtol=1e-12, atol=1e-12)


def test_nongravity_acceleration_is_the_second_derivative_of_the_logged_path(base: Simulation) -> None:
    """f - f_base = R^T a_n, a_n = p_n'' (finite differences of the path), per-axis RMS sigma_a; the position
    stream is that path at 10 Hz around the default home."""
    sim = quiet(EffectSpec("nongravity_acceleration", {"sigma_a": 1.5}))
    e = effect(sim, "nongravity_acceleration")
    a_n, p_n = e.signals["a_n"], e.signals["p_n"]
    diff = sim.recording.select(Kind.ACCELEROMETER).xyz - base.recording.select(Kind.ACCELEROMETER).xyz
    np.testing.assert_allclose(diff, np.einsum("nji,nj->ni", sim.rotations, a_n), rtol=0, atol=1e-12)
    dt = 1.0 / sim.recording.select(Kind.ACCELEROMETER).rate_hz
    np.testing.assert_allclose((p_n[2:] - 2 * p_n[1:-1] + p_n[:-2]) / dt**2, a_n[1:-1], rtol=0, atol=1e-3)
    assert np.sqrt(np.mean(a_n**2)) == pytest.approx(1.5) == e.params["sigma_a"]
    assert 0.5 < np.abs(p_n).max() < 20.0
    pos = sim.recording.select(Kind.POSITION)
    assert pos.rate_hz == pytest.approx(10.0)
    north = np.deg2rad(pos.values[:, 0] - 47.397742) * 6.3674e6           # spherical, independent of the code
    idx = np.round(pos.t * sim.recording.select(Kind.ACCELEROMETER).rate_hz).astype(int)
    np.testing.assert_allclose(north, p_n[idx, 0], atol=0.05 + 0.005 * np.abs(p_n[:, 0]).max())
    np.testing.assert_allclose(pos.values[:, 2], 488.0 - p_n[idx, 2], atol=1e-9)


def test_transient_disturbance_only_inside_the_windows(base: Simulation) -> None:
    """An Earth-fixed field b_n inside the windows (ramped at the edges): y - y_base = D R^T b_n / |field|."""
    sim = quiet(EffectSpec("transient_disturbance", {"windows_s": ((10.0, 20.0), (40.0, 43.0))}))
    e = effect(sim, "transient_disturbance")
    t = sim.recording.select(Kind.MAGNETOMETER).t
    diff = np.linalg.norm(mag(sim) - mag(base), axis=1)
    outside = (t < 10.0) | ((t > 20.0) & (t < 40.0)) | (t > 43.0)
    assert diff[outside].max() < 1e-18
    full = ((t > 11.0) & (t < 19.0)) | ((t > 41.0) & (t < 42.0))
    assert sim.trajectory is not None
    rot = sim.trajectory.at(t[full])                               # at the magnetometer's own stamps
    want = np.einsum("nji,j->ni", rot, e.params["b_n"] / sim.truth.field_strength) @ sim.truth.D.T
    np.testing.assert_allclose((mag(sim) - mag(base))[full], want, rtol=0, atol=1e-18)
    assert 0.1 < np.linalg.norm(e.params["b_n"]) / sim.truth.field_strength < 0.3


def test_defaults_are_detectable_in_a_five_minute_log() -> None:
    """Default magnitudes: each magnetometer term swings by several per-sample noise std in the paper protocol
    (the time offset's RMS shift is > 2.5 std), and every effect's RMS signal over the noise std, times
    sqrt(samples), is a z-score far above detection (> 10; the gyro scale is seen far better still through
    the attitude it integrates to)."""
    sim = simulate("paper", 1, effects=tuple(EffectSpec(eid) for eid in EFFECTS))
    assert [e.id for e in sim.effects] == list(EFFECTS)
    acc, gyr = sim.recording.select(Kind.ACCELEROMETER), sim.recording.select(Kind.GYROSCOPE)
    assert acc.t[-1] > 300.0
    sd = sim.truth.noise_std
    for eid in ("current_interference", "throttle_interference", "temperature_drift"):
        assert np.ptp(effect(sim, eid).signals["term"], axis=0).max() > 5 * sd["magnetometer"], eid
    delay = effect(sim, "time_offset").signals["rotations"]
    shift = np.einsum("nji,j->ni", sim.rotations[::1][: len(delay)] - delay, m_n(sim)) @ sim.truth.D.T
    signals = {"time_offset": (shift, sd["magnetometer"]),
               "gyro_scale": ((gyr.xyz - sim.truth.gyro_bias) * 0.01, sd["gyroscope"]),
               "accel_scale": (acc.xyz * 0.006, sd["accelerometer"]),
               "lever_arm": (effect(sim, "lever_arm").signals["term"], sd["accelerometer"]),
               "nongravity_acceleration": (effect(sim, "nongravity_acceleration").signals["a_n"],
                                           sd["accelerometer"])}
    assert np.sqrt(np.mean(shift**2)) > 2.5 * sd["magnetometer"]
    for eid, (signal, noise) in signals.items():
        assert np.sqrt(np.mean(signal**2)) / noise * np.sqrt(len(signal)) > 10, eid


def test_parse_effect_converts_the_command_line_units() -> None:
    """uT keys become tesla; vectors x/y/z, windows t0-t1/t0-t1; omitted keys keep their defaults."""
    spec = parse_effect("current_interference:c_uT_per_A=0.2/-0.1/0.3")
    assert spec.params["c"] == pytest.approx((2e-7, -1e-7, 3e-7))
    spec = parse_effect("transient_disturbance: windows_s=100-130/200.5-215 , b_rel=0.1/0/0")
    assert spec.params["windows_s"] == ((100.0, 130.0), (200.5, 215.0))
    assert parse_effect("temperature_drift:T0=30").resolved(100.0)["k"] == (2e-8, -1.5e-8, 3e-8)
    assert parse_effect("time_offset").params == {}


@pytest.mark.parametrize(("text", "message"), [
    ("foo", "unknown effect 'foo'; valid ids: current_interference, throttle_interference"),
    ("current_interference:c=1/2/3", "effect current_interference has no key 'c'; valid keys: c_uT_per_A"),
    ("lever_arm:r_m=1/2", "effect lever_arm: r_m: expected 3 numbers separated by '/'"),
    ("time_offset:tau_s=abc", "effect time_offset: tau_s: 'abc' is not a number"),
    ("nongravity_acceleration:source=ekf", "effect nongravity_acceleration: source: expected one of gps, none"),
    ("transient_disturbance:windows_s=30-10", "expected a non-empty list of (t0, t1) with 0 <= t0 < t1"),
])
def test_bad_effects_are_refused(text: str, message: str) -> None:
    with pytest.raises(EffectSpecError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_effect(text)


def test_python_api_checks_ids_and_keys() -> None:
    with pytest.raises(EffectSpecError, match="effect gyro_scale has no parameter 'r_m'; valid parameters: s"):
        EffectSpec("gyro_scale", {"r_m": (0, 0, 0)})
    with pytest.raises(EffectSpecError, match="effect time_offset is given more than once"):
        simulate("paper", 0, duration=12.0, effects=(EffectSpec("time_offset"), EffectSpec("time_offset")))


# -- format round trips ------------------------------------------------------------------------------------

CHANNEL_EFFECTS = (EffectSpec("current_interference"), EffectSpec("throttle_interference"),
                   EffectSpec("temperature_drift"), EffectSpec("nongravity_acceleration"))
#: out name -> (current, throttle, temperature, position ids; magnetometer unit) as the readers report them
FORMATS = {
    "x.bin": ("BAT[0]", "CTUN", "IMU[0]", "GPS[0]", "milligauss"),
    "x.ulg": ("battery_status[0]", "vehicle_thrust_setpoint", "sensor_mag[0]", "vehicle_gps_position", "gauss"),
    "x.csv": ("battery", "throttle", "temperature", None, "microtesla"),
    "x.mcap": ("/battery", "/mavros/target_actuator_control", "/imu/temperature", "/gps/fix", "tesla"),
    "x.bag": ("/battery", "/mavros/target_actuator_control", "/imu/temperature", "/gps/fix", "tesla"),
    "ros2": ("/battery", "/mavros/target_actuator_control", "/imu/temperature", "/gps/fix", "tesla"),
}
#: (absolute) tolerance of each kind: float32 (ROS BatteryState, ULog, DataFlash), 6 digits (CSV), 1e-7 deg
#: and 1 cm (DataFlash GPS)
TOL = {Kind.BATTERY_CURRENT: 1e-4, Kind.BATTERY_VOLTAGE: 1e-4, Kind.THROTTLE: 1e-6, Kind.TEMPERATURE: 1e-4}


def channel_sim(out: Path) -> Simulation:
    """The channel effects simulated for `out`'s format (its IMU sampling; phase 0 for a CSV's rows)."""
    return simulate("paper", 3, rate=50.0, mag_rate=25.0, duration=12.0, effects=CHANNEL_EFFECTS,
                    imu_sampling=imu_sampling(out), mag_phase_s=0.0 if out.suffix == ".csv" else None)


@pytest.mark.parametrize("name", list(FORMATS))
def test_channels_round_trip(tmp_path: Path, name: str) -> None:
    """Battery current (positive while discharging), voltage, throttle, temperature and position come back
    with the right kinds, SI units and values; the truth names those channels and the log's unit."""
    out = tmp_path / name
    sim = channel_sim(out)
    write_log(sim, out)
    rec = open_recording(out)
    current, throttle, temperature, position, unit = FORMATS[name]
    ids = {Kind.BATTERY_CURRENT: current, Kind.BATTERY_VOLTAGE: current, Kind.THROTTLE: throttle,
           Kind.TEMPERATURE: temperature}
    for kind, sid in ids.items():
        want = sim.recording.select(kind)
        got = rec.select(kind, sid)
        assert got.native_unit in ({"A": ("A",), "V": ("V",)}.get(kind.si_unit, (kind.si_unit,)))
        if kind is Kind.TEMPERATURE and name == "x.bin":            # IMU.T: at the IMU rate, interpolated
            np.testing.assert_allclose(np.interp(want.t, got.t - got.t[0], got.values[:, 0]),
                                       want.values[:, 0], atol=0.05)
            continue
        assert len(got) == len(want)
        np.testing.assert_allclose(got.values, want.values, rtol=0, atol=TOL[kind])
        np.testing.assert_allclose(np.diff(got.t), np.diff(want.t), atol=2e-6)
    assert rec.select(Kind.BATTERY_CURRENT).values.min() > 0                     # drawn current, all formats
    if position is None:
        assert not rec.of_kind(Kind.POSITION)
    else:
        got, want = rec.select(Kind.POSITION, position), sim.recording.select(Kind.POSITION)
        np.testing.assert_allclose(got.values[:, :2], want.values[:, :2], rtol=0, atol=0.6e-7)
        np.testing.assert_allclose(got.values[:, 2], want.values[:, 2], rtol=0, atol=0.006)
    doc = {e["id"]: e for e in truth_calibration(sim, rec, "test", "now").effects}
    assert doc["current_interference"]["channels"] == [current]
    assert doc["current_interference"]["units"] == {"c": f"{unit}/ampere"}
    assert doc["throttle_interference"]["channels"] == [throttle]
    assert doc["temperature_drift"]["units"] == {"k": f"{unit}/degC", "T0": "degC"}
    assert doc["nongravity_acceleration"]["channels"] == ([position] if position else [])
    assert doc["nongravity_acceleration"]["params"]["source"] == ("gps" if position else "none")
    assert doc["nongravity_acceleration"]["sensor"] == rec.ids(Kind.ACCELEROMETER)[0]


def test_ros_battery_current_is_negative_in_the_bag_and_positive_when_read(tmp_path: Path) -> None:
    """sensor_msgs/BatteryState.current is negative while discharging; the reader negates it."""
    from rosbags.highlevel import AnyReader

    write_log(channel_sim(tmp_path / "x.bag"), tmp_path / "x.bag")
    with AnyReader([tmp_path / "x.bag"]) as reader:
        conn = [c for c in reader.connections if c.topic == "/battery"]
        raw = [reader.deserialize(d, c.msgtype).current for c, _, d in reader.messages(connections=conn)]
    assert max(raw) < 0
    rec = open_recording(tmp_path / "x.bag")
    np.testing.assert_allclose(rec.select(Kind.BATTERY_CURRENT).values[:, 0], -np.array(raw), rtol=1e-7)


# -- command line ------------------------------------------------------------------------------------------

def test_cli_writes_the_effect_in_the_logs_unit(tmp_path: Path) -> None:
    """`magcal simulate out.bin --effect current_interference` lists the effect in milligauss/ampere."""
    out = tmp_path / "out.bin"
    args = ["simulate", str(out), "--scenario", "paper", "--duration", "12", "-q",
            "--effect", "current_interference", "--effect", "time_offset:tau_s=0.01"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    doc = json.loads((tmp_path / "out.bin.truth.json").read_text())
    cur = next(e for e in doc["effects"] if e["id"] == "current_interference")
    assert cur["sensor"] == "MAG[0]" and cur["status"] == "injected" and cur["channels"] == ["BAT[0]"]
    assert cur["units"] == {"c": "milligauss/ampere"}
    np.testing.assert_allclose(cur["params"]["c"], [0.2, -0.1, 0.3], rtol=1e-12)
    off = next(e for e in doc["effects"] if e["id"] == "time_offset")
    assert off["params"] == {"tau_s": 0.01} and off["units"] == {"tau_s": "s"} and off["channels"] == []


@pytest.mark.parametrize(("value", "message"), [
    ("nope", "Error: Invalid value for '--effect': unknown effect 'nope'; valid ids: current_interference, "),
    ("gyro_scale:x=1", "Error: Invalid value for '--effect': effect gyro_scale has no key 'x'; valid keys: s"),
])
def test_cli_bad_effect_is_a_one_line_usage_error(tmp_path: Path, value: str, message: str) -> None:
    result = CliRunner().invoke(cli, ["simulate", str(tmp_path / "o.csv"), "--effect", value])
    assert result.exit_code == 2
    line = next(x for x in result.output.splitlines() if x.startswith("Error:"))
    assert line.startswith(message)
    assert not (tmp_path / "o.csv").exists()


def test_geodetic_round_numbers() -> None:
    """One metre north at Zurich is about 9.0e-6 deg of latitude; up is altitude."""
    lla = geodetic(np.array([[1.0, 0.0, -2.0]]))
    assert lla[0, 0] - 47.397742 == pytest.approx(1 / 111_180.0, rel=2e-3)
    assert lla[0, 2] == pytest.approx(490.0)
