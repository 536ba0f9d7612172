"""The simulator samples its continuous-time truth as real sensors do: IMU values at (INSTANT) or averaged over the
period ending at (PRECEDING) their stamps, the magnetometer at its own rate and phase. Checked against the truth
and closed-form motions only, never against the estimator.

Modules it covers (the mirrored test file aside): magcal_cli.synth.logs.csvfile, magcal_cli.synth.logs.mcap,
magcal_cli.synth.motion.
"""

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
from magcal_cli.streams import Kind, Sampling
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.logs import IMU_SAMPLING, LOG_WRITERS, imu_sampling, write_log
from magcal_cli.synth.motion import Trajectory
from magcal_cli.synth.simulate import Simulation, simulate, truth_calibration

RATE = 100.0
W = np.array([0.3, -0.5, 0.8])                                 # rad/s, a constant-rate rotation
G_N = np.array([0.0, 0.0, G])


def quiet(scenario: str = "handheld", **kw: object) -> Simulation:
    """A noise-free simulation."""
    return simulate(scenario, 4, noise_scale=0.0, **kw)  # type: ignore[arg-type]


def truth(sim: Simulation) -> Trajectory:
    assert sim.trajectory is not None
    return sim.trajectory


def imu(sim: Simulation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps, gyro - b_g and accelerometer - b_a."""
    gyr, acc = sim.recording.select(Kind.GYROSCOPE), sim.recording.select(Kind.ACCELEROMETER)
    return gyr.t, gyr.xyz - sim.truth.gyro_bias, acc.xyz - sim.truth.accel_bias


def constant_rate(n: int = 1001) -> np.ndarray:
    """Knots of R(t) = Exp(W t) at RATE."""
    return so3.exp(np.arange(n)[:, None] / RATE * W)


SCENARIOS = {"handheld": {}, "paper": {"duration": 60.0}, "multirotor": {"duration": 100.0}}


# -- IMU -----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_instant_gyro_is_the_body_rate_at_the_stamp(scenario: str) -> None:
    """Noise-free INSTANT gyro k is the central difference (h = 1e-7 s) of the true attitude at t_k: to 1e-6 rad/s,
    the difference's own error where w' jumps at a knot of the fine grid (rates reach 2.6 rad/s)."""
    sim = quiet(scenario, **SCENARIOS[scenario])
    t, w, _ = imu(sim)
    h = 1e-7
    rt = np.swapaxes(truth(sim).at(t), -1, -2)
    central = (so3.log(rt @ truth(sim).at(t + h)) - so3.log(rt @ truth(sim).at(t - h))) / (2 * h)
    assert np.abs(w - central).max() < 1e-6
    assert np.abs(w).max() > 0.2


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_preceding_gyro_is_the_rotation_over_the_last_period(scenario: str) -> None:
    """Noise-free PRECEDING gyro k times dt is Log(R(t_k - dt)^T R(t_k)) to 1e-9 rad; chained, the samples rebuild
    the attitude at every stamp (1e-9 rad after thousands of steps)."""
    sim = quiet(scenario, imu_sampling=Sampling.PRECEDING, **SCENARIOS[scenario])
    t, w, _ = imu(sim)
    dt = 1.0 / sim.recording.select(Kind.GYROSCOPE).rate_hz
    rot = truth(sim).at(t)
    np.testing.assert_allclose(w * dt, so3.log(np.swapaxes(truth(sim).at(t - dt), -1, -2) @ rot), rtol=0, atol=1e-9)
    chained = rot[0] @ so3.cumulative_product(so3.exp(w[1:] * dt))
    assert so3.angle(np.swapaxes(chained, -1, -2) @ rot[1:]).max() < 1e-9


def test_instant_samples_are_instantaneous_not_a_forward_hold() -> None:
    """The convention, proven by integration: the noise-free INSTANT gyro integrated by the trapezoid rule follows
    the truth 20 times better than read as a rate held over [t_k, t_k+1) (the old simulator's meaning), which
    lags by half a period."""
    sim = quiet("handheld")
    t, w, _ = imu(sim)
    dt = 1.0 / RATE
    rot = sim.rotations
    trapezoid = rot[0] @ so3.cumulative_product(so3.exp(0.5 * (w[:-1] + w[1:]) * dt))
    hold = rot[0] @ so3.cumulative_product(so3.exp(w[:-1] * dt))
    err_trapezoid = so3.angle(np.swapaxes(trapezoid, -1, -2) @ rot[1:]).max()
    err_hold = so3.angle(np.swapaxes(hold, -1, -2) @ rot[1:]).max()
    assert err_trapezoid < err_hold / 20 and err_trapezoid < 1e-3


def test_closed_form_rates() -> None:
    """Constant rate W: every sample is W. theta = alpha t^2 / 2 about a fixed axis: INSTANT alpha t_k a,
    PRECEDING alpha (t_k - dt / 2) a (the mean over the period ending at t_k); the ends, where the knot rates are
    one-sided, are left out."""
    for sampling in (Sampling.INSTANT, Sampling.PRECEDING):
        sim = quiet("paper", rate=RATE, mag_rate=50.0, trajectory=constant_rate(), imu_sampling=sampling)
        np.testing.assert_allclose(imu(sim)[1], np.broadcast_to(W, (1000, 3)), rtol=0, atol=1e-12)
    axis, alpha = np.array([0.0, 0.6, 0.8]), 0.7
    knots = so3.exp((0.5 * alpha * (np.arange(801) / RATE) ** 2)[:, None] * axis)
    for sampling, lag in ((Sampling.INSTANT, 0.0), (Sampling.PRECEDING, 0.5 / RATE)):
        sim = quiet("paper", rate=RATE, mag_rate=50.0, trajectory=knots, imu_sampling=sampling)
        t, w, _ = imu(sim)
        np.testing.assert_allclose(w[2:-2], (alpha * (t[2:-2] - lag))[:, None] * axis, rtol=0, atol=1e-11)


def _mean_over_period(fn: object, t: np.ndarray, dt: float, points: int = 4001) -> np.ndarray:
    """The mean of fn(times) (M, 3) over [t - dt, t] by a dense trapezoid rule (independent of the simulator's)."""
    s = np.linspace(-1.0, 0.0, points)
    weights = np.full(points, 1.0 / (points - 1))
    weights[[0, -1]] *= 0.5
    values = fn((t[:, None] + s * dt).ravel()).reshape(len(t), points, 3)  # type: ignore[operator]
    out: np.ndarray = np.einsum("q,mqj->mj", weights, values)
    return out


def test_preceding_accelerometer_is_the_mean_specific_force() -> None:
    """PRECEDING accelerometer k is the mean of R(t)^T (-g_n) over [t_k - dt, t_k] (1e-9 m/s^2 against a dense
    trapezoid rule) in the handheld protocol; at constant rate with a lever arm, the centripetal term is constant
    and the gravity term the closed-form mean."""
    sim = quiet("handheld", imu_sampling=Sampling.PRECEDING)
    t, _, f = imu(sim)
    k = np.arange(1, len(t), 97)
    want = _mean_over_period(lambda x: -np.einsum("nji,j->ni", truth(sim).at(x), G_N), t[k], 1.0 / RATE)
    np.testing.assert_allclose(f[k], want, rtol=0, atol=1e-9)
    r = np.array([0.1, -0.2, 0.05])
    sim = quiet("paper", rate=RATE, mag_rate=50.0, trajectory=constant_rate(), imu_sampling=Sampling.PRECEDING,
                effects=(EffectSpec("lever_arm", {"r_m": tuple(r)}),))
    t, _, f = imu(sim)
    gravity = _mean_over_period(lambda x: -np.einsum("nji,j->ni", so3.exp(x[:, None] * W), G_N), t, 1.0 / RATE)
    np.testing.assert_allclose(f - gravity, np.broadcast_to(np.cross(W, np.cross(W, r)), f.shape), rtol=0,
                               atol=1e-8)


def test_imu_effects_act_before_the_averaging() -> None:
    """gyro_scale and accel_scale multiply the instantaneous quantity, so a PRECEDING sample is (1 + s) times the
    mean without them; nongravity_acceleration's a_n enters the mean too."""
    s_g, s_a = (0.01, -0.02, 0.005), (0.004, 0.01, -0.015)
    base = quiet("handheld", duration=60.0, imu_sampling=Sampling.PRECEDING)
    sim = quiet("handheld", duration=60.0, imu_sampling=Sampling.PRECEDING,
                effects=(EffectSpec("gyro_scale", {"s": s_g}), EffectSpec("accel_scale", {"s": s_a})))
    np.testing.assert_allclose(imu(sim)[1], imu(base)[1] * (1.0 + np.array(s_g)), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(imu(sim)[2], imu(base)[2] * (1.0 + np.array(s_a)), rtol=1e-12, atol=1e-12)
    sway = quiet("handheld", duration=60.0, imu_sampling=Sampling.PRECEDING,
                 effects=(EffectSpec("nongravity_acceleration", {"sigma_a": 1.0}),))
    a_n = next(e for e in sway.effects if e.id == "nongravity_acceleration").signals["a_n"]
    t, _, f = imu(sway)
    k = np.arange(1, len(t), 211)
    # the sway is smooth (<= 0.3 Hz): the mean of R^T a_n over 10 ms is its value half a period back, to 1e-4
    half = t[k] - 0.5 / RATE
    a_half = np.column_stack([np.interp(half, t, a_n[:, i]) for i in range(3)])
    np.testing.assert_allclose(f[k] - imu(base)[2][k], np.einsum("nji,nj->ni", truth(sway).at(half), a_half),
                               rtol=0, atol=1e-3)


def test_paper_draws_keep_their_statistics_at_any_oversampling(monkeypatch: pytest.MonkeyPatch) -> None:
    """methods.md's rate v + 0.05 randn(3) is drawn once per IMU sample: with 10 or 20 fine knots per IMU period the
    noise-free gyro has the same draws (std 0.05 rad/s about v, equal to 1 %) and differs by far less than a draw."""
    import magcal_cli.synth.motion as motion
    import magcal_cli.synth.rotation as rotation
    import magcal_cli.synth.simulate as synth

    gyros = []
    for factor in (10, 20):
        for module in (synth, motion, rotation):
            monkeypatch.setattr(module, "OVERSAMPLE", factor)
        sim = quiet("paper", duration=60.0)
        assert sim.oversample == factor
        gyros.append(imu(sim)[1])
    first = gyros[0][1:790] - [0.1, 0.0, 0.0]                     # inside the first segment, v = 0.1 x
    assert np.std(first, axis=0) == pytest.approx([0.05] * 3, rel=0.1)
    np.testing.assert_allclose(np.std(gyros[1][1:790], axis=0), np.std(gyros[0][1:790], axis=0), rtol=0.01)
    assert np.abs(gyros[1][1:-1] - gyros[0][1:-1]).max() < 0.005


def test_following_is_refused() -> None:
    with pytest.raises(MagcalError, match="simulate: imu_sampling following is not simulated"):
        simulate("paper", 0, duration=12.0, imu_sampling=Sampling.FOLLOWING)


# -- magnetometer --------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("rate", "mag_rate", "phase"), [(50.0, 10.0, 0.0037), (50.0, 100.0, 0.0012),
                                                         (400.0, 100.0, 0.0), (100.0, 30.0, 0.02)])
def test_magnetometer_reads_the_field_at_its_own_stamps(rate: float, mag_rate: float, phase: float) -> None:
    """Stamps phase + j / mag_rate inside the IMU log; noise-free readings are D Exp(W t_j)^T m_n + o (closed form,
    1e-18 T), with a time offset D Exp(W (t_j - tau))^T m_n + o."""
    knots = so3.exp(np.arange(int(12 * rate) + 1)[:, None] / rate * W)
    for tau in (0.0, 0.013):
        effects = (EffectSpec("time_offset", {"tau_s": tau}),) if tau else ()
        sim = quiet("paper", rate=rate, mag_rate=mag_rate, trajectory=knots, mag_phase_s=phase, effects=effects)
        mag = sim.recording.select(Kind.MAGNETOMETER)
        t_imu = sim.recording.select(Kind.GYROSCOPE).t
        np.testing.assert_allclose(mag.t, phase + np.arange(len(mag)) / mag_rate, rtol=0, atol=1e-12)
        assert mag.t[-1] <= t_imu[-1] < mag.t[-1] + 1.0 / mag_rate
        want = np.einsum("nji,j->ni", so3.exp((mag.t - tau)[:, None] * W), sim.truth.m_n) @ sim.truth.D.T
        np.testing.assert_allclose(mag.xyz, want + sim.truth.o, rtol=0, atol=1e-18)
        assert sim.mag_phase_s == phase


def test_magnetometer_on_a_hand_motion_at_its_stamps() -> None:
    """In the handheld protocol the noise-free field is D R(t_j)^T m_n + o at the magnetometer's own stamps, which
    are not IMU stamps."""
    sim = quiet("handheld")
    mag = sim.recording.select(Kind.MAGNETOMETER)
    want = np.einsum("nji,j->ni", truth(sim).at(mag.t), sim.truth.m_n) @ sim.truth.D.T + sim.truth.o
    np.testing.assert_allclose(mag.xyz, want, rtol=0, atol=1e-18)
    off = np.abs((mag.t * RATE) - np.round(mag.t * RATE)) / RATE
    assert off.min() > 1e-4


def test_default_phase_is_drawn_from_the_seed_alone() -> None:
    """0 <= phase < min(5 ms, 1 / mag_rate), the same for the same seed, different across seeds, and drawn apart
    from the base simulation: the IMU samples do not change with the phase."""
    phases = [simulate("paper", s, duration=12.0).mag_phase_s for s in range(20)]
    assert all(0.0 <= p < 0.005 for p in phases) and len(set(phases)) == 20
    assert simulate("paper", 3, duration=12.0).mag_phase_s == phases[3]
    assert 0.0 <= simulate("paper", 3, duration=12.0, mag_rate=400.0, rate=400.0).mag_phase_s < 0.0025
    a, b = simulate("paper", 3, duration=12.0), simulate("paper", 3, duration=12.0, mag_phase_s=0.0)
    for kind in (Kind.ACCELEROMETER, Kind.GYROSCOPE):
        assert np.array_equal(a.recording.select(kind).values, b.recording.select(kind).values)
    assert b.recording.select(Kind.MAGNETOMETER).t[0] == 0.0


@pytest.mark.parametrize("phase", [-0.001, 0.02, float("nan")])
def test_bad_phase_is_refused(phase: float) -> None:
    with pytest.raises(MagcalError, match=r"simulate: mag_phase_s must be >= 0 and < 1/mag_rate = 0.02 s"):
        simulate("handheld", 0, mag_rate=50.0, mag_phase_s=phase)


# -- streams, truth, formats ---------------------------------------------------------------------------------

@pytest.mark.parametrize("sampling", [Sampling.INSTANT, Sampling.PRECEDING])
def test_streams_and_truth_state_the_sampling(tmp_path: Path, sampling: Sampling) -> None:
    """Accelerometer and gyro streams carry the IMU sampling (PRECEDING with its window, the IMU period), the
    magnetometer INSTANT; the truth records imu_sampling, mag_phase_s and oversample."""
    sim = simulate("paper", 1, duration=12.0, imu_sampling=sampling, mag_phase_s=0.002)
    rec = sim.recording
    for kind in (Kind.ACCELEROMETER, Kind.GYROSCOPE):
        assert rec.select(kind).sampling is sampling
        assert rec.select(kind).window_s == (None if sampling is Sampling.INSTANT else pytest.approx(1 / 80.0))
    assert rec.select(Kind.MAGNETOMETER).sampling is Sampling.INSTANT
    out = tmp_path / ("x.ulg" if sampling is Sampling.PRECEDING else "x.bin")
    write_log(sim, out)
    info = truth_calibration(sim, open_recording(out), "test", "now").extra["simulation"]
    assert info["imu_sampling"] == sampling.value and info["mag_phase_s"] == 0.002 and info["oversample"] == 10


def test_formats_state_their_convention() -> None:
    """PX4's sensor_combined is PRECEDING; ROS Imu, ArduPilot IMU and CSV are INSTANT; every writer has an entry."""
    assert set(IMU_SAMPLING) == set(LOG_WRITERS)
    assert {e for e, s in IMU_SAMPLING.items() if s is Sampling.PRECEDING} == {".ulg"}
    assert imu_sampling(Path("a/flight.ULG")) is Sampling.PRECEDING and imu_sampling(Path("bag")) is Sampling.INSTANT


@pytest.mark.parametrize(("name", "sampling"), [("x.ulg", Sampling.INSTANT), ("x.bin", Sampling.PRECEDING),
                                                ("x.mcap", Sampling.PRECEDING)])
def test_write_log_refuses_a_mismatched_convention(tmp_path: Path, name: str, sampling: Sampling) -> None:
    sim = simulate("paper", 1, duration=12.0, imu_sampling=sampling)
    want = IMU_SAMPLING[Path(name).suffix]
    with pytest.raises(MagcalError, match=(
            rf"x\.{name[2:]}: a \.{name[2:]} log holds {want.value} IMU samples but the simulation's are "
            rf"{sampling.value}; simulate with imu_sampling=Sampling\.{want.name}")):
        write_log(sim, tmp_path / name)
    assert not (tmp_path / name).exists()


@pytest.mark.parametrize(("rate", "mag_rate"), [(50.0, 10.0), (50.0, 100.0), (400.0, 10.0), (400.0, 100.0)])
def test_any_rates_and_phase_write_to_every_format(tmp_path: Path, rate: float, mag_rate: float) -> None:
    """IMU 50 or 400 Hz, magnetometer 10 or 100 Hz at a random phase: every format but CSV holds it, and the
    magnetometer comes back at its own stamps (to the formats' 1 us); a CSV, one row per IMU sample, refuses it
    and holds the same rates at phase 0 when the magnetometer rate divides the IMU rate."""
    for name in LOG_WRITERS:
        out = tmp_path / (f"x{name}" if name else "ros2")
        sim = simulate("paper", 7, rate=rate, mag_rate=mag_rate, duration=6.0, imu_sampling=imu_sampling(out))
        assert 0.0 < sim.mag_phase_s < 0.005
        if name == ".csv":
            with pytest.raises(MagcalError, match="a CSV log holds one row per IMU sample"):
                write_log(sim, out)
            if rate % mag_rate:
                continue
            sim = simulate("paper", 7, rate=rate, mag_rate=mag_rate, duration=6.0, mag_phase_s=0.0)
        write_log(sim, out)
        rec = open_recording(out)
        want_imu, want_mag = sim.recording.select(Kind.GYROSCOPE), sim.recording.select(Kind.MAGNETOMETER)
        gyr, mag = rec.select(Kind.GYROSCOPE), rec.select(Kind.MAGNETOMETER)
        assert (len(gyr), len(mag)) == (len(want_imu), len(want_mag)), name
        np.testing.assert_allclose(mag.t - gyr.t[0], want_mag.t, rtol=0, atol=2e-6)


# -- command line --------------------------------------------------------------------------------------------

def test_cli_simulates_with_the_convention_of_the_format(tmp_path: Path) -> None:
    """`magcal simulate x.ulg` samples PRECEDING (sensor_combined with integral_dt = the IMU period), `x.bin`
    INSTANT; --mag-phase sets the phase; a .csv takes phase 0."""
    from pyulog import ULog

    runner = CliRunner()
    for name, sampling, extra in (("x.ulg", "preceding", ["--mag-phase", "0.003"]), ("x.bin", "instant", []),
                                  ("x.csv", "instant", [])):
        out = tmp_path / name
        result = runner.invoke(cli, ["simulate", str(out), "--scenario", "paper", "--duration", "12", "-q",
                                     "--rate", "50", "--mag-rate", "25", *extra])
        assert result.exit_code == 0, result.output
        info = json.loads((tmp_path / f"{name}.truth.json").read_text())["simulation"]
        assert info["imu_sampling"] == sampling and info["oversample"] == 10
        if name == "x.ulg":
            assert info["mag_phase_s"] == 0.003
            comb = ULog(str(out), ["sensor_combined"]).get_dataset("sensor_combined").data
            assert set(comb["gyro_integral_dt"]) == {20_000} and set(comb["accelerometer_integral_dt"]) == {20_000}
        if name == "x.csv":
            assert info["mag_phase_s"] == 0.0


@pytest.mark.parametrize(("args", "message"), [
    (["x.bin", "--mag-phase", "0.05"], "Invalid value for --mag-phase: must be >= 0 s and below one magnetometer "
                                       "period (1/50 Hz = 0.02 s), got 0.05"),
    (["x.bin", "--mag-phase", "-0.001"], "Invalid value for --mag-phase: must be >= 0 s"),
    (["x.csv", "--mag-phase", "0.001"], "a .csv log holds one row per IMU sample, so its magnetometer has phase 0"),
    (["x.csv", "--mag-rate", "30"], "the magnetometer rate must divide the IMU rate 100 Hz; got 30 Hz"),
])
def test_cli_bad_phase_is_a_usage_error(tmp_path: Path, args: list[str], message: str) -> None:
    result = CliRunner().invoke(cli, ["simulate", str(tmp_path / args[0]), *args[1:]])
    assert result.exit_code == 2
    line = next(x for x in result.output.splitlines() if x.startswith("Error:"))
    assert message in line
    assert not (tmp_path / args[0]).exists()
