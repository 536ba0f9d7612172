"""The Python API (issue 40 item 3): fit once, save, load, correct readings one at a time as a ROS node would;
the same numbers as `magcal apply`, and one clear error per bad argument.

Modules it covers (the mirrored test file aside): magcal_cli.api.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import api
from magcal_cli.calibration.apply import apply_rows
from magcal_cli.cli.main import cli
from magcal_cli.errors import CalibrationFileError, OptionError
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind

from .firmware.flightsim import flight

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_logs" / "handheld.mcap"


@pytest.fixture(scope="module")
def node_cal(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, api.Calibration]:
    """What a ROS node's launch step does once: fit the shipped MCAP sample and save the document."""
    path = tmp_path_factory.mktemp("api") / "calibration.json"
    cal = api.fit(SAMPLE, effects="none")
    return cal.save(path), cal


def test_a_node_corrects_readings_one_at_a_time_as_magcal_apply_does(
        node_cal: tuple[Path, api.Calibration], tmp_path: Path) -> None:
    """Load the saved calibration, correct each /imu/mag reading alone (tesla in, tesla out, the message's
    unit): every row equals `magcal apply`'s CSV as printed, and the unrounded batch field within 1e-12."""
    path, fitted = node_cal
    cal = api.Calibration.load(path)
    assert cal == fitted and isinstance(cal, api.Calibration)
    stream = open_recording(SAMPLE).select(Kind.MAGNETOMETER, "/imu/mag")
    one = np.array([api.apply(cal, y, t, unit="tesla") for t, y in zip(stream.t, stream.xyz, strict=True)])
    out = tmp_path / "field.csv"
    result = CliRunner().invoke(cli, ["apply", str(path), str(SAMPLE), "-o", str(out), "-q"])
    assert result.exit_code == 0, result.output
    lines = out.read_text().splitlines()
    assert lines[0] == "t [s],id,mx [T],my [T],mz [T],norm [T]" and len(lines) == len(one) + 1
    printed = np.array([ln.split(",")[2:5] for ln in lines[1:]], dtype=float)
    assert np.max(np.abs(one - printed) / np.linalg.norm(printed, axis=1)[:, None]) < 1e-12
    rows, unit, _ = apply_rows(cal, open_recording(SAMPLE))
    batch = np.array([v for _, _, v in rows])
    assert unit == "T" and np.max(np.abs(one - batch) / np.linalg.norm(batch, axis=1)[:, None]) < 1e-12
    many = api.apply(cal, stream.xyz * 1e6, stream.t, unit="microtesla")        # arrays, another unit
    assert np.allclose(many * 1e-6, batch, rtol=1e-12, atol=0)


def test_effect_channels_are_keywords_and_a_missing_one_is_an_error() -> None:
    """A calibration carrying current interference and a time offset: readings corrected one at a time with the
    current given per reading equal the batch `apply` (which resamples the log's current) within 1e-12, and the
    stamps move by the offset; without battery_current= it is an OptionError, skip_missing=True leaves it in."""
    fl = flight(0, noise=0.5)
    effects = ({"id": "current_interference", "sensor": "MAG[0]", "status": "accepted",
                "params": {"c": fl.c.tolist()}, "units": {"c": "milligauss/ampere"}},
               {"id": "time_offset", "sensor": "MAG[0]", "status": "accepted", "params": {"tau_s": 0.02}})
    cal = replace(fl.truth(), effects=effects)
    rec = fl.recording
    mag = rec.select(Kind.MAGNETOMETER, "MAG[0]")
    cur = rec.of_kind(Kind.BATTERY_CURRENT)[0]
    amps = np.interp(mag.t, cur.t, cur.values[:, 0])
    y = mag.xyz * 1e7                                   # tesla to the document's milligauss
    stamped = [api.apply_stamped(cal, yi, ti, battery_current=ai) for ti, yi, ai in zip(mag.t, y, amps, strict=True)]
    rows, _, notes = apply_rows(cal, rec)
    assert "MAG[0]: current_interference removed" in notes
    batch = np.array([v for _, _, v in rows])
    one = np.array([v for _, v in stamped])
    assert np.max(np.abs(one - batch) / np.linalg.norm(batch, axis=1)[:, None]) < 1e-12
    assert np.allclose([float(t) for t, _ in stamped], mag.t - 0.02, rtol=0, atol=1e-12)
    with pytest.raises(OptionError, match=r"apply\(MAG\[0\]\): the calibration carries the accepted "
                                          r"current_interference, which needs battery_current= \(A\); pass it"):
        api.apply(cal, y[0], mag.t[0])
    left_in = api.apply(cal, y, mag.t, skip_missing=True)
    assert np.allclose(left_in, api.apply(replace(cal, effects=effects[1:]), y, mag.t), rtol=1e-15, atol=0)


def test_bad_arguments_are_option_errors_saying_what_to_pass(node_cal: tuple[Path, api.Calibration],
                                                             tmp_path: Path) -> None:
    _, cal = node_cal
    cases = [
        (lambda: api.config(method="lsq"), r"fit\(method='lsq'\): unknown method; choose one of auto, "),
        (lambda: api.config(effects=["nope"]), r"fit\(effects=\['nope'\]\): .*nope"),
        (lambda: api.config(method="kok2012", effects="current_interference"),
         r"kok2012 cannot model current_interference; use method='map'"),
        (lambda: api.config(start=5, end=2), r"fit\(start=5, end=2\): start must be before end"),
        (lambda: api.config(start=float("nan")), r"fit\(start=nan\): expected a finite number"),
        (lambda: api.config(location=(95, 0)), r"fit\(location=\(95, 0\)\): expected \(lat, lon\)"),
        (lambda: api.config(date="30/06/2025"), r"fit\(date='30/06/2025'\): expected 'YYYY-MM-DD'"),
        (lambda: api.config(mag_timing="middle"), r"fit\(mag_timing='middle'\): expected one of instant"),
        (lambda: api.config(robust_loss="l1"), r"fit\(robust_loss='l1'\): unknown loss"),
        (lambda: api.apply(cal, [1.0, 2.0], 0.0), r"apply\(field of shape \(2,\)\): expected one reading \(3,\)"),
        (lambda: api.apply(cal, np.ones((4, 3)), [0.0, 1.0]), r"apply\(t of shape \(2,\)\): expected a number or"),
        (lambda: api.apply(cal, [1.0, 2.0, 3.0], 0.0, mag="MAG[0]"), r"apply\(mag='MAG\[0\]'\): not in the "
                                                                      r"calibration, which has /imu/mag"),
        (lambda: api.apply(cal, [1.0, 2.0, 3.0], 0.0, unit="furlong"), r"apply\(unit='furlong'\): unknown unit"),
        (lambda: api.save(cal, tmp_path / "cal.txt"), r"cannot tell the format from '.txt'"),
        (lambda: api.apply(cal, np.ones((2, 3)), [0.0, 1.0], motor_output=[0.5] * 3),
         r"apply\(motor_output of shape \(3,\)\): expected \(4,\) or \(N, 4\) for 2 readings"),
    ]
    for call, message in cases:
        with pytest.raises(OptionError, match=message):
            call()
    with pytest.raises(CalibrationFileError, match="cannot read the calibration"):
        api.load(tmp_path / "missing.json")


def test_yaml_round_trip_and_fit_config_is_the_commands(node_cal: tuple[Path, api.Calibration],
                                                        tmp_path: Path) -> None:
    """save/load through YAML keeps the document; `config` is what `magcal fit` calibrates with."""
    _, cal = node_cal
    assert api.load(api.save(cal, tmp_path / "cal.yaml")) == cal
    cfg = api.config(mag=["MAG[0]", "MAG[1]"], effects=(), location=(52.5, 13.4), date="2025-06-30")
    assert (cfg.mag, cfg.effects, cfg.diagnose, cfg.location, cfg.date) == (
        "MAG[0],MAG[1]", (), False, (52.5, 13.4, 0.0), "2025-06-30")
    assert api.config().diagnose and api.config().allow_truncated
