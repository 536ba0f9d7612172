"""ardupilot.param: golden files in Mission Planner and MAVProxy layout, and the fit writer."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.firmware.export import export
from magcal_cli.firmware.paramfile import render
from magcal_cli.writers import WRITERS, get_writer

from .golden import check_golden

#: a 4.x vehicle: compass 1 external (ORIENT 0), compass 2 internal, device ids and priorities saved
VEHICLE = {"COMPASS_EXTERNAL": 1.0, "COMPASS_EXTERN2": 0.0, "COMPASS_ORIENT": 0.0, "COMPASS_ORIENT2": 0.0,
           "COMPASS_DEV_ID": 97539.0, "COMPASS_DEV_ID2": 131874.0, "COMPASS_PRIO1_ID": 97539.0,
           "COMPASS_PRIO2_ID": 131874.0, "COMPASS_SCALE": 0.0, "COMPASS_SCALE2": 0.0, "CUST_ROT_ENABLE": 0.0,
           "AHRS_ORIENTATION": 0.0}


def calibration() -> Calibration:
    """Two compasses: MAG[0] external, 2.5 deg off its mount, with current interference; MAG[1] internal."""
    d0 = 560.0 * so3.exp(np.deg2rad([1.0, -2.0, 1.2])) @ np.array([[1.02, 0.01, 0.0], [0.01, 0.97, 0.005],
                                                                   [0.0, 0.005, 1.01]])
    d1 = 540.0 * so3.exp(np.deg2rad([0.0, 0.0, 0.8])) @ np.diag([1.05, 0.95, 1.0])
    mags = (MagCalibration("MAG[0]", "milligauss", d0, [98.0, -118.0, -213.0], 64.0, np.zeros((13, 13)), 560.0),
            MagCalibration("MAG[1]", "milligauss", d1, [140.0, 68.0, 256.0], 64.0, np.zeros((13, 13)), 560.0))
    effects = ({"id": "current_interference", "sensor": "MAG[0]", "status": "accepted",
                "params": {"c": [1.5, -0.5, 2.5]}, "units": {"c": "milligauss/ampere"}},)
    return Calibration(Source("flight.bin", "dataflash", "", 0.0, 243.0), "map", ImuCalibration("IMU[0]"), mags,
                       "0.1.0", "2026-01-01T00:00:00Z", effects=effects)


def mission_planner_load(text: str) -> dict[str, float]:
    """Mission Planner's ParamFile.loadParamFile: skip '#' lines, split on space/comma/tab, two items."""
    out = {}
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        items = [i for i in line.replace(",", " ").replace("\t", " ").split(" ") if i]
        assert len(items) == 2, line
        out[items[0]] = float(items[1])
    return out


def test_golden_mission_planner(update_golden: bool) -> None:
    """The layout Mission Planner saves and loads: NAME,VALUE sorted by name; header lines are '#' comments."""
    exp = export(calibration(), "ardupilot", VEHICLE)
    text = render(exp.params, "mission-planner", exp.header(), exp.integers)
    check_golden("ardupilot.param", text, update_golden)
    body = [ln for ln in text.splitlines() if not ln.startswith("#")]
    assert body == sorted(body) and all(ln.count(",") == 1 for ln in body)
    loaded = mission_planner_load(text)
    assert loaded["COMPASS_ORIENT"] == 101 and loaded["COMPASS_MOTCT"] == 2 and "COMPASS_ORIENT2" not in loaded


def test_golden_mavproxy(update_golden: bool) -> None:
    exp = export(calibration(), "ardupilot", VEHICLE)
    check_golden("ardupilot_mavproxy.param", render(exp.params, "mavproxy", exp.header(), exp.integers),
                 update_golden)


def test_the_fit_writer_uses_the_logs_parameters(tmp_path: Path) -> None:
    """`fit --outputs ardupilot` writes ardupilot.param from the document and the recording's parameters."""
    assert "ardupilot" in WRITERS
    result = SimpleNamespace(calibration=calibration(), recording=SimpleNamespace(params=VEHICLE))
    [path] = get_writer("ardupilot").write(result, tmp_path)  # type: ignore[arg-type]
    assert path.name == "ardupilot.param"
    exp = export(calibration(), "ardupilot", VEHICLE)
    assert path.read_text() == render(exp.params, "mission-planner", exp.header(), exp.integers)
