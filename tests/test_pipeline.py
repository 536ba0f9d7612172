"""Stream selection and the messages for logs that are too short; fit, diagnose and check calibrate a log alike.

Modules it covers (the mirrored test file aside): magcal_cli.calibration.assemble, magcal_cli.calibration.run,
magcal_cli.config.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import pipeline
from magcal_cli.cli.main import cli
from magcal_cli.config import Config
from magcal_cli.errors import InsufficientDataError, StreamError
from magcal_cli.pipeline import select_problem
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind, Recording, Stream

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "handheld.bin"


def _recording(n_mag: int) -> Recording:
    rng = np.random.default_rng(0)
    t = np.arange(2000) / 100.0
    tm = np.arange(n_mag) / 10.0
    return Recording(Path("short.bin"), "dataflash", (
        Stream(Kind.ACCELEROMETER, "IMU[0]", t, [0, 0, -9.8] + 0.05 * rng.normal(size=(2000, 3)), "short.bin#IMU",
               "m/s^2"),
        Stream(Kind.GYROSCOPE, "IMU[0]", t, 0.01 * rng.normal(size=(2000, 3)), "short.bin#IMU", "rad/s"),
        Stream(Kind.MAGNETOMETER, "MAG[0]", tm, 1e-5 + 1e-8 * rng.normal(size=(n_mag, 3)), "short.bin#MAG",
               "milligauss")))


def test_a_short_log_says_record_longer() -> None:
    """Without --start/--end the advice is about the recording, not the time window (ap462_truncated_80k.bin)."""
    with pytest.raises(StreamError, match=r"short.bin: magnetometer MAG\[0\] has only 4 samples \(0.3 s\); a "
                                          r"calibration needs a recording of at least a minute"):
        select_problem(_recording(4), Config())


def test_a_narrow_window_says_widen_it() -> None:
    """With --start/--end the advice is to widen the window."""
    with pytest.raises(StreamError, match="between --start and --end; widen the time window"):
        select_problem(_recording(200), Config(start_s=0.0, end_s=0.5))


def test_missing_imu_lists_what_is_there() -> None:
    """--imu with an unknown id names the ids available."""
    with pytest.raises(StreamError, match=r"no accelerometer stream 'IMU\[7\]'; available: IMU\[0\]. Use --imu"):
        select_problem(_recording(200), Config(imu="IMU[7]"))


def test_one_uncalibratable_magnetometer_does_not_cost_the_others() -> None:
    """A second, stuck magnetometer (constant readings) is reported as not calibrated; the good one is."""
    from dataclasses import replace

    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate_recording
    from magcal_cli.synth.simulate import simulate

    sim = simulate("handheld", 2)
    good = sim.recording.select(Kind.MAGNETOMETER)
    stuck = Stream(Kind.MAGNETOMETER, "/stuck/mag", good.t, np.tile(good.values[0], (len(good), 1)),
                   "sim#/stuck/mag", "tesla")
    rec = replace(sim.recording, streams=(*sim.recording.streams, stuck))
    result = calibrate_recording(rec, Config(method="kok2012"))
    assert [m.id for m in result.calibration.magnetometers] == ["/imu/mag"]
    (failed,) = [f for f in result.findings if f.code == "not_calibrated"]
    assert failed.message.startswith("/stuck/mag was not calibrated: ")


def test_a_dip_far_from_the_world_magnetic_model_is_flagged() -> None:
    """A fitted dip 10 deg from the WMM's is a warning that names both values (log171.bin in flight)."""
    import datetime as dt

    from magcal_cli.calibration.assemble import dip_check
    from magcal_cli.calibration.types import MagCalibration
    from magcal_cli.wmm import ReferenceField

    ref = ReferenceField(np.deg2rad(-66.0), 57e-6, 0.2, "WMM2025", -35.4, 149.2, 600.0, dt.date(2015, 6, 1))
    cov = np.diag(np.full(13, 1e-4))
    near = MagCalibration("MAG[0]", "milligauss", np.eye(3) * 570, np.zeros(3), -64.0, cov, 570.0)
    far = MagCalibration("MAG[1]", "milligauss", np.eye(3) * 570, np.zeros(3), -76.3, cov, 570.0)
    (finding,) = dip_check([near, far], ref)
    assert finding.code == "dip_disagrees_with_wmm"
    assert finding.message.startswith("MAG[1]: the fitted dip -76.3 deg differs from the World Magnetic "
                                      "Model's -66.0 deg at the log's position by -10.3 deg")
    assert dip_check([near, far], None) == []


def test_fit_diagnose_and_check_calibrate_a_log_with_one_config(monkeypatch: pytest.MonkeyPatch,
                                                                tmp_path: Path) -> None:
    """Issue 30 item 2: the Config each command hands the pipeline for the same log is the same
    (`pipeline.command_config`): diagnose forced --method map (and refused logs fit calibrates) and refused a cut
    log fit reads; check's refit modelled no effects and refused cut logs too."""
    seen: list[Config] = []

    def spy(path: Path, cfg: Config, fmt: str | None = None, progress: object = None) -> None:
        seen.append(cfg)
        msg = f"{path.name}: the Config is all this test needs"
        raise InsufficientDataError(msg)

    monkeypatch.setattr(pipeline, "calibrate", spy)
    for args in (["fit", SAMPLE, "-o", tmp_path / "fit"], ["diagnose", SAMPLE], ["check", SAMPLE]):
        CliRunner().invoke(cli, [*map(str, args), "-q"])
    fit, diagnose, check = seen
    assert diagnose == fit
    assert fit == pipeline.command_config()
    rec = open_recording(SAMPLE)
    assert [m.id for m in select_problem(rec, check).mags] == [m.id for m in select_problem(rec, fit).mags]
    assert replace(check, mag=fit.mag) == fit


def test_px4log_fit_and_diagnose_agree(realdata: Path, tmp_path: Path) -> None:
    """01_07_59.px4log (issue 30): fit exits 0 with the attitude method auto falls back to, while diagnose exited 1
    with the joint MAP's refusal. diagnose now makes the same choice and exits 0 as fit does, saying in one line
    why there is no diagnosis; fit's progress names the method that ran (it said "fitting map" only)."""
    log = str(realdata / "px4" / "01_07_59.px4log")
    fit = CliRunner().invoke(cli, ["fit", log, "-o", str(tmp_path / "fit"), "--outputs", "json"])
    assert fit.exit_code == 0, fit.output
    assert fit.stdout.startswith("MAG[0]: attitude, ")
    fitting = [line for line in fit.stderr.splitlines() if "fitting" in line]
    # each compass gets its own fallback (issue 38), named in its own line: MAG[0]'s motion determines too little
    # for the joint MAP method; MAG[1]'s field strength follows the battery current (0.3-51 A), which the joint MAP
    # method explains once it models it (8.1 % field-norm spread against the attitude method's 9.1 %)
    assert fitting[1].endswith("fitting attitude (against ATT and the World Magnetic Model) for MAG[0]"), fitting
    assert fitting[2].endswith("MAG[1]: the base model was refused; fitting it with current_interference"), fitting
    assert "\nMAG[1]: map, " in fit.stdout
    diagnose = CliRunner().invoke(cli, ["diagnose", log, "-q"])
    assert diagnose.exit_code == 0, diagnose.output
    assert diagnose.stdout == ("MAG[0]: not diagnosed: the mismatch diagnosis runs with the joint MAP method "
                               "only, and this log's own motion cannot determine the joint MAP calibration, so the "
                               "attitude method calibrated it\n"
                               "MAG[1]: not diagnosed: the base model left the readings unexplained, so "
                               "current_interference was modelled without the diagnosis\n")
