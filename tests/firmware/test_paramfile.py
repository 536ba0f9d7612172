"""Parameter file styles: exact layouts, float32 values, parsing every style back, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal_cli.firmware import FirmwareError
from magcal_cli.firmware.paramfile import load, parse, render, value_text

PARAMS = {"COMPASS_OFS_X": -97.79155731201172, "COMPASS_ORIENT": 38.0, "COMPASS_DIA_X": 1.0}


def test_mission_planner_layout() -> None:
    """NAME,VALUE sorted by name (ParamFile.cs SaveParamFile), '#' comment lines first."""
    assert render(PARAMS, "mission-planner", ["made by a test"], {"COMPASS_ORIENT"}) == (
        "# made by a test\nCOMPASS_DIA_X,1\nCOMPASS_OFS_X,-97.79156\nCOMPASS_ORIENT,38\n")


def test_mavproxy_layout() -> None:
    assert render(PARAMS, "mavproxy", [], {"COMPASS_ORIENT"}).splitlines()[0] == "COMPASS_DIA_X    1"


def test_qgc_layout() -> None:
    """QGroundControl: header, five tab-separated columns, MAV_PARAM_TYPE 6 (int32) or 9 (float)."""
    lines = render({"CAL_MAG0_ID": 396809.0, "CAL_MAG0_XOFF": 0.1}, "qgc", ["x"], {"CAL_MAG0_ID"}).splitlines()
    assert lines == ["# Onboard parameters for Vehicle 1", "#", "# x", "#",
                     "# Vehicle-Id Component-Id Name Value Type", "1\t1\tCAL_MAG0_ID\t396809\t6",
                     "1\t1\tCAL_MAG0_XOFF\t0.1\t9"]


def test_nsh_layout() -> None:
    assert render({"CAL_MAG0_XOFF": 0.1}, "nsh") == "param set CAL_MAG0_XOFF 0.1\n"


def test_values_are_the_shortest_text_of_the_float32() -> None:
    """Every written value reads back as the same float32 (the firmware stores float32); -0 is 0."""
    rng = np.random.default_rng(0)
    for v in rng.normal(scale=300, size=200).tolist() + [1e-9, 0.30000001192092896, -0.0]:
        assert np.float32(float(value_text(v))) == np.float32(v)
    assert value_text(-0.0) == "0" and value_text(0.1) == "0.1" and value_text(2.0, integer=True) == "2"


@pytest.mark.parametrize("style", ["mission-planner", "mavproxy", "qgc", "nsh"])
def test_every_style_parses_back(style: str) -> None:
    text = render(PARAMS, style, ["h"], {"COMPASS_ORIENT"})
    got = parse(text, "t")
    assert got.keys() == PARAMS.keys()
    assert all(np.float32(got[k]) == np.float32(v) for k, v in PARAMS.items())


def test_parse_errors_name_the_line_and_the_formats(tmp_path: Path) -> None:
    with pytest.raises(FirmwareError, match=r"t: line 2 is not a parameter \('COMPASS_OFS_X,abc'\); expected "
                                            r"NAME,VALUE \(Mission Planner\)"):
        parse("# ok\nCOMPASS_OFS_X,abc\n", "t")
    empty = tmp_path / "empty.param"
    empty.write_text("# nothing\n")
    with pytest.raises(FirmwareError, match="empty.param: no parameters in the file. Save the vehicle's parameters"):
        load(empty)
    with pytest.raises(FirmwareError, match="missing.param: cannot read the parameter file"):
        load(tmp_path / "missing.param")
    with pytest.raises(FirmwareError, match="parameter file style 'xml' is not known"):
        render(PARAMS, "xml")
