"""The joint MAP method through the pipeline and CLI: default method, every std in the document, the World
Magnetic Model reference, several magnetometers on one IMU.

Modules it covers (the mirrored test file aside): magcal_cli.models.consistency, magcal_cli.wmm.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.config import Config
from magcal_cli.methods import map_run
from magcal_cli.pipeline import calibrate
from magcal_cli.synth.simulate import paper_trajectory
from magcal_cli.wmm import reference_field

from .mapsim import record

LOG = Path(__file__).resolve().parents[2] / "sample_logs" / "handheld.mcap"


def _truth() -> dict:  # type: ignore[type-arg]
    return json.loads(LOG.with_name(LOG.name + ".truth.json").read_text())


def test_auto_picks_map_and_every_std_is_reported() -> None:
    """With gyro data `auto` is the joint MAP; biases, D, o and dip carry finite stds that cover the truth."""
    res = calibrate(LOG, Config())
    cal = res.calibration
    assert cal.method == "map"
    imu, truth = cal.imu, _truth()
    for key, std in (("accelerometer_bias", imu.accelerometer_bias_std),
                     ("gyroscope_bias", imu.gyroscope_bias_std)):
        est = getattr(imu, key)
        assert std is not None and np.all(np.isfinite(std)) and np.all(std > 0)
        assert np.all(np.abs(est - np.array(truth["imu"][key])) < 5 * std), key
    mag = cal.magnetometers[0]
    assert np.all(np.isfinite(mag.std)) and np.all(mag.std > 0)
    t_mag = truth["magnetometers"][0]
    assert np.all(np.abs(mag.o - np.array(t_mag["o"])) < 5 * mag.std[9:12])
    assert abs(mag.dip_deg - t_mag["dip_deg"]) < 5 * mag.std[12]
    assert cal.noise["source"].startswith("estimated by map")
    assert any(f.code == "fisher_condition" for f in res.findings)


def test_location_gives_wmm_field_strength_and_dip_start() -> None:
    """--location/--date: field strength from the WMM (field_strength_source "wmm"), dip started from it."""
    res = calibrate(LOG, Config(location=(52.52, 13.40, 35.0), date="2026-05-01"))
    mag = res.calibration.magnetometers[0]
    ref = reference_field(52.52, 13.40, 35.0, __import__("datetime").date(2026, 5, 1))
    assert mag.field_strength_source == "wmm"
    assert mag.field_strength == pytest.approx(ref.intensity)                      # the log's unit is tesla
    assert any("World Magnetic Model" in n or "WMM" in n for n in res.calibration.notes)
    assert abs(mag.dip_deg - _truth()["magnetometers"][0]["dip_deg"]) < 1.0      # estimated, not copied


def test_cli_location_option(tmp_path: Path) -> None:
    """The CLI passes --location/--date through; a malformed location is a usage error (exit 2)."""
    runner = CliRunner()
    ok = runner.invoke(cli, ["fit", str(LOG), "-o", str(tmp_path / "out"), "--outputs", "json", "--json",
                             "-q", "--location", "52.52,13.40", "--date", "2026-05-01"])
    assert ok.exit_code == 0, ok.output
    doc = json.loads(ok.output)
    assert doc["magnetometers"][0]["field_strength_source"] == "wmm"
    bad = runner.invoke(cli, ["fit", str(LOG), "-o", str(tmp_path / "out2"), "--location", "north"])
    assert bad.exit_code == 2
    assert "expected LAT,LON[,ALT]" in bad.output


def test_several_magnetometers_on_one_imu() -> None:
    """Three magnetometers with different D, o on one IMU: each calibrated within its covariance."""
    rng = np.random.default_rng(21)
    rot = paper_trajectory(rng, 50.0, 60.0)
    problem, truths, _ = record(rot, 50.0, 21, mag_step=2, n_mags=3)
    result = map_run.run(problem, Config(method="map"))
    assert [f.id for f in result.mags] == ["mag0", "mag1", "mag2"]
    for fit, truth in zip(result.mags, truths, strict=True):
        e = np.concatenate([(fit.D - truth.D).ravel(order="F"), fit.o - truth.o, [fit.dip - truth.dip]])
        assert float(e @ np.linalg.solve(fit.cov, e)) < 40.0          # chi2_13 99.99 % ~ 39
    assert result.imu.gyro_bias is not None and result.imu.gyro_bias_std is not None
    assert np.all(np.abs(result.imu.gyro_bias - truths[0].gyro_bias) < 5 * result.imu.gyro_bias_std)
