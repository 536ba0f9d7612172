"""px4.params: golden files in QGroundControl and `param set` layout, and the fit writer."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.firmware.export import export
from magcal_cli.firmware.paramfile import render
from magcal_cli.writers import get_writer

from .golden import check_golden

#: two magnetometers by device id; slot 1 external (ROT 0), slot 0 internal; the log index differs from the slot
VEHICLE = {"sensor_mag[0].device_id": 396825.0, "sensor_mag[1].device_id": 396809.0, "CAL_MAG0_ID": 396809.0,
           "CAL_MAG1_ID": 396825.0, "CAL_MAG0_ROT": -1.0, "CAL_MAG1_ROT": 0.0, "SENS_BOARD_ROT": 0.0}


def calibration() -> Calibration:
    """sensor_mag[0] external mounted yawed 90 deg, with current interference; sensor_mag[1] internal."""
    d0 = 0.52 * np.array([[1.03, 0.02, 0.0], [0.02, 0.98, 0.01], [0.0, 0.01, 1.0]]) @ so3.from_rpy(
        np.deg2rad([0.0, 0.0, 90.0])).T
    d1 = 0.50 * np.diag([1.04, 0.97, 1.01])
    mags = (MagCalibration("sensor_mag[0]", "gauss", d0, [0.12, -0.05, 0.2], 64.0, np.zeros((13, 13)), 0.52),
            MagCalibration("sensor_mag[1]", "gauss", d1, [-0.03, 0.08, 0.01], 64.0, np.zeros((13, 13)), 0.52))
    effects = ({"id": "current_interference", "sensor": "sensor_mag[0]", "status": "accepted",
                "params": {"c": [0.0015, -0.0005, 0.0025]}, "units": {"c": "gauss/ampere"}},)
    return Calibration(Source("flight.ulg", "ulog", "", 0.0, 300.0), "map", ImuCalibration("sensor_combined"),
                       mags, "0.1.0", "2026-01-01T00:00:00Z", effects=effects)


def test_golden_qgc(update_golden: bool) -> None:
    """QGroundControl's layout: its header, then vehicle, component, name, value, MAV_PARAM_TYPE by tabs."""
    exp = export(calibration(), "px4", VEHICLE)
    text = render(exp.params, "qgc", exp.header(), exp.integers)
    check_golden("px4.params", text, update_golden)
    lines = text.splitlines()
    assert lines[0] == "# Onboard parameters for Vehicle 1"
    assert "# Vehicle-Id Component-Id Name Value Type" in lines
    rows = [ln.split("\t") for ln in lines if not ln.startswith("#")]
    assert all(len(r) == 5 and r[:2] == ["1", "1"] and r[4] in ("6", "9") for r in rows)
    values = {r[2]: r[3] for r in rows}
    assert values["CAL_MAG1_ROT"] == "2" and values["CAL_MAG0_ROT"] == "-1" and values["CAL_MAG_COMP_TYP"] == "2"
    assert values["CAL_MAG1_ID"] == "396825"                       # sensor_mag[0] lives in slot 1


def test_golden_nsh(update_golden: bool) -> None:
    exp = export(calibration(), "px4", VEHICLE)
    check_golden("px4_nsh.txt", render(exp.params, "nsh", exp.header(), exp.integers), update_golden)


def test_the_fit_writer_uses_the_logs_parameters(tmp_path: Path) -> None:
    result = SimpleNamespace(calibration=calibration(), recording=SimpleNamespace(params=VEHICLE))
    [path] = get_writer("px4").write(result, tmp_path)  # type: ignore[arg-type]
    exp = export(calibration(), "px4", VEHICLE)
    assert path.name == "px4.params" and path.read_text() == render(exp.params, "qgc", exp.header(), exp.integers)
