"""What a sample stands for relative to its stamp (issue 25): readers state it, timing.py converts it into the
estimators' one convention, the option overrides it, the document records it, and getting it wrong shows up as
exactly the lag the estimator used to report on logs it had not simulated itself."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import timing
from magcal_cli.cli import options
from magcal_cli.cli.main import cli
from magcal_cli.config import Config
from magcal_cli.pipeline import calibrate
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind, Sampling, Stream
from magcal_cli.synth.logs import LOG_WRITERS, imu_sampling, write_log
from magcal_cli.synth.simulate import simulate


def _gyro(t: np.ndarray, sampling: Sampling, window: float | None = None) -> Stream:
    return Stream(Kind.GYROSCOPE, "imu", t, np.zeros((t.size, 3)), "x#imu", "rad/s", sampling=sampling,
                  window_s=window)


def test_the_options_offer_exactly_the_conventions_timing_converts() -> None:
    """cli/options.py spells the choices out so that the CLI starts without numpy; they must stay Sampling's."""
    assert options.TIMING_CHOICES == timing.CHOICES


def test_each_convention_becomes_the_estimators_interval_form() -> None:
    """A gyro sample k is held over [t_k, t_k+1) inside the estimators: a preceding mean moves to the start of its
    own interval (exactly), an instantaneous rate is held between the half-way points to its neighbours, a
    following mean stays; a shorter averaging window (a logger keeping every n-th message) centres on it."""
    t = np.array([0.0, 0.01, 0.02, 0.035, 0.045])
    np.testing.assert_allclose(timing.gyro_intervals(_gyro(t, Sampling.PRECEDING)).t, [-0.01, 0.0, 0.01, 0.02, 0.035])
    np.testing.assert_allclose(timing.gyro_intervals(_gyro(t, Sampling.INSTANT)).t,
                               [-0.005, 0.005, 0.015, 0.0275, 0.04])
    np.testing.assert_array_equal(timing.gyro_intervals(_gyro(t, Sampling.FOLLOWING)).t, t)
    short = timing.effective_times(_gyro(t, Sampling.PRECEDING, window=0.004))
    np.testing.assert_allclose(short, t - 0.002)
    acc = Stream(Kind.ACCELEROMETER, "imu", t, np.zeros((t.size, 3)), "x#imu", "m/s^2", sampling=Sampling.PRECEDING)
    np.testing.assert_allclose(timing.as_instants(acc).t, [-0.005, 0.005, 0.015, 0.0275, 0.04])
    assert timing.as_instants(acc).sampling is Sampling.INSTANT


@pytest.mark.parametrize("ext", sorted(e for e in LOG_WRITERS if e != ".csv") + [".csv"])
def test_every_reader_states_the_convention_its_writer_samples(ext: str, tmp_path: Path) -> None:
    """magcal simulate samples each format as its definition says (synth.logs.IMU_SAMPLING); the reader of that
    format must state the same, or the estimator would shift the trajectory by half a sample or more."""
    path = tmp_path / f"log{ext}"
    sim = simulate("handheld", 2, rate=50.0, mag_rate=25.0, duration=30.0, imu_sampling=imu_sampling(path),
                   mag_phase_s=0.0 if ext == ".csv" else None)
    write_log(sim, path)
    rec = open_recording(path)
    gyr, acc, mag = (rec.select(k) for k in (Kind.GYROSCOPE, Kind.ACCELEROMETER, Kind.MAGNETOMETER))
    assert gyr.sampling is acc.sampling is imu_sampling(path)
    assert mag.sampling is Sampling.INSTANT


@pytest.fixture(scope="module")
def lagless(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 100 Hz hand-held MCAP with no lag, the magnetometer stamped 2.5 ms after the IMU (as a real board)."""
    path = tmp_path_factory.mktemp("timing") / "log.mcap"
    write_log(simulate("handheld", 11, rate=100.0, mag_rate=50.0, duration=90.0, mag_phase_s=0.0025), path)
    return path


def test_no_lag_where_there_is_none_and_half_a_sample_when_the_convention_is_wrong(lagless: Path) -> None:
    """The estimator's old error, reproduced on purpose: read as the mean over the interval after its stamp, an
    instantaneous gyro puts the trajectory half a sample (5 ms) late, and the fit calls that a magnetometer lead."""
    tau = {}
    for told in (None, Sampling.FOLLOWING):
        doc = calibrate(lagless, Config(effects=("time_offset",), imu_timing=told)).calibration
        (e,) = [e for e in doc.effects if e["id"] == "time_offset"]
        tau[told] = (e["params"]["tau_s"], e["ci95"]["tau_s"])
    value, (lo, hi) = tau[None]
    assert lo <= 0.0 <= hi and abs(value) < 0.5e-3
    wrong, (lo, hi) = tau[Sampling.FOLLOWING]
    assert hi < 0.0 and -0.006 < wrong < -0.0015


def test_the_option_overrides_the_format_and_the_document_says_so(lagless: Path, tmp_path: Path) -> None:
    result = CliRunner().invoke(cli, ["fit", str(lagless), "-o", str(tmp_path / "o"), "--effects", "none",
                                      "--outputs", "json", "--imu-timing", "preceding", "-q"])
    assert result.exit_code == 0, result.output
    doc = json.loads((tmp_path / "o" / "calibration.json").read_text())
    assert doc["source"]["timing"] == {"imu": "preceding", "magnetometer": "instant", "set_by": "--imu-timing"}
    bad = CliRunner().invoke(cli, ["fit", str(lagless), "--imu-timing", "sideways"])
    assert bad.exit_code == 2 and "'sideways' is not one of 'instant', 'preceding', 'following'" in bad.output
