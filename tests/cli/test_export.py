"""`magcal export` and `fit --fail-on` / automatic firmware outputs on the command line.

Modules it covers (the mirrored test file aside): magcal_cli.writers.fitrun.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from magcal_cli.calibration.document import dumps_json
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.cli.main import cli

from ..firmware import fwsim

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_logs" / "handheld.bin"


def write_doc(path: Path, o: tuple[float, float, float] = (100.0, 0.0, 0.0), source: str = "") -> Path:
    """A hand-made document: MAG[0], identity iron, offset o (mGauss); no source log unless `source`."""
    mag = MagCalibration("MAG[0]", "milligauss", 500.0 * np.eye(3), o, 60.0, np.zeros((13, 13)), 500.0)
    cal = Calibration(Source(source, "dataflash", "", 0, 1), "map", ImuCalibration("IMU[0]"), (mag,), "0", "t")
    path.write_text(dumps_json(cal))
    return path


def test_export_both_firmwares_and_styles(tmp_path: Path) -> None:
    doc = write_doc(tmp_path / "cal.json")
    ap, px = tmp_path / "out.param", tmp_path / "out.params"
    result = CliRunner().invoke(cli, ["export", str(doc), "--ardupilot", str(ap), "--px4", str(px), "-q"])
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == [
        "MAG[0] -> COMPASS_*: exported exactly with the board orientation (internal compass) (field error below "
        "0.1 %)", f"wrote {ap}",
        "MAG[0] -> CAL_MAG0_*: exported exactly with the board orientation (internal compass) (field error below "
        "0.1 %)", f"wrote {px}"]
    assert fwsim.read_param_file(ap.read_text())["COMPASS_OFS_X"] == -100
    assert fwsim.read_param_file(px.read_text())["CAL_MAG0_XOFF"] == np.float32(0.1)
    result = CliRunner().invoke(cli, ["export", str(doc), "--ardupilot", str(ap), "--style", "mavproxy", "--force"])
    assert result.exit_code == 0 and "COMPASS_OFS_X    -100" in ap.read_text()
    assert "no accepted current or throttle interference" in result.stderr


def test_export_with_vehicle_parameters(tmp_path: Path) -> None:
    """--params: an external compass gets its orientation; the slot follows COMPASS_PRIO1_ID."""
    params = tmp_path / "vehicle.param"
    params.write_text("COMPASS_EXTERNAL,0\nCOMPASS_EXTERN2,1\nCOMPASS_ORIENT2,4\nCOMPASS_PRIO1_ID,22\n"
                      "COMPASS_DEV_ID,11\nCOMPASS_DEV_ID2,22\n")
    out = tmp_path / "o.param"
    result = CliRunner().invoke(cli, ["export", str(write_doc(tmp_path / "c.json")), "--ardupilot", str(out),
                                      "--params", str(params), "-q"])
    assert result.exit_code == 0, result.output
    p = fwsim.read_param_file(out.read_text())
    assert p["COMPASS_ORIENT2"] == 4 and p["COMPASS_OFS2_X"] == -100 and "COMPASS_OFS_X" not in p


def test_export_takes_the_parameters_of_the_documents_source_log(tmp_path: Path) -> None:
    doc = write_doc(tmp_path / "c.json", source=str(SAMPLE))
    result = CliRunner().invoke(cli, ["export", str(doc), "--ardupilot", str(tmp_path / "o.param")])
    assert result.exit_code == 0, result.output
    assert "vehicle parameters from the document's source log handheld.bin" in result.stderr
    assert "COMPASS_SCALE,1" in (tmp_path / "o.param").read_text()        # the 4.6 log has COMPASS_SCALE


def test_export_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    doc = write_doc(tmp_path / "cal.json")
    result = runner.invoke(cli, ["export", str(doc)])
    assert result.exit_code == 2 and "give -o FILE (the parameters of the firmware that wrote the calibrated log), " \
                                     "or --ardupilot OUT.param or --px4 OUT.params" in result.output
    result = runner.invoke(cli, ["export", str(doc), "--ardupilot", str(tmp_path / "a"), "--style", "nsh"])
    assert result.exit_code == 2 and "nsh is not a ardupilot parameter format" in result.output
    (tmp_path / "exists.param").write_text("")
    result = runner.invoke(cli, ["export", str(doc), "--ardupilot", str(tmp_path / "exists.param")])
    assert result.exit_code == 2 and "exists.param: exists already. Pass --force to overwrite it" in result.stderr
    big = write_doc(tmp_path / "big.json", o=(2000.0, 0.0, 0.0))
    result = runner.invoke(cli, ["export", str(big), "--ardupilot", str(tmp_path / "b.param")])
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1
    assert lines[0].startswith("Error: export MAG[0] (ArduPilot): MAG[0]: |COMPASS_OFS| = 2000 mGauss is not below")
    assert not (tmp_path / "b.param").exists()


def test_fit_adds_firmware_parameters_and_gates(tmp_path: Path) -> None:
    """An ArduPilot log: fit writes ardupilot.param by default; --fail-on exits 3 after writing, with --json too."""
    out = tmp_path / "o"
    result = CliRunner().invoke(cli, ["fit", str(SAMPLE), "-o", str(out), "-q", "--fail-on", "coverage_pct<1"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["ardupilot.param", "calibration.json", "calibration.yaml",
                                                     "report.html", "report.txt"]
    assert "COMPASS_OFS_X," in (out / "ardupilot.param").read_text()
    result = CliRunner().invoke(cli, ["fit", str(SAMPLE), "-o", str(out), "-q", "--force", "--json", "--outputs",
                                      "json", "--fail-on", "heading_std_deg>10,coverage_pct<101"])
    assert result.exit_code == 3
    assert json.loads(result.stdout)["schema"] == "magcal.calibration/1"
    assert result.stderr.startswith("Error: fit --fail-on: MAG[0]: coverage_pct<101 (measured")


def test_fit_fail_on_usage_errors() -> None:
    result = CliRunner().invoke(cli, ["fit", str(SAMPLE), "--fail-on", "heading_std_dg>1"])
    assert result.exit_code == 2
    assert "Invalid value for --fail-on: unknown metric 'heading_std_dg'; this command measures" in result.output
    result = CliRunner().invoke(cli, ["fit", str(SAMPLE), "--fail-on", "interference_pct>>1"])
    assert result.exit_code == 2 and "'interference_pct>>1' is not METRIC OP NUMBER" in result.output
