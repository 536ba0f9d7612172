"""Round trips: simulated raw readings + exported parameter files through each firmware's own formula (fwsim,
written from the design note, not from the exporter) reproduce magcal's calibrated field.

Where the rotation is exportable the error stays below 0.1 % of the field (float32 parameters leave ~1e-6);
where it is not, the firmware's field is exactly E b with E the residual the export reports.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.firmware.common import Export, Options
from magcal_cli.firmware.export import export
from magcal_cli.firmware.paramfile import render

from . import fwsim

F_MG = 500.0                     # field strength, mGauss
RNG = np.random.default_rng(7)
DIRECTIONS = so3.exp(RNG.normal(size=(4000, 3))) @ np.array([1.0, 0.0, 0.0])   # unit fields, all directions


def soft_iron(rng: np.random.Generator, size: float = 0.06) -> np.ndarray:
    """A symmetric positive definite matrix near identity."""
    a = rng.normal(scale=size, size=(3, 3))
    return np.eye(3) + 0.5 * (a + a.T)


def document(D: np.ndarray, o: np.ndarray, unit: str = "milligauss", field: float = F_MG, mag_id: str = "MAG[0]",
             effects: tuple[dict[str, Any], ...] = ()) -> Calibration:
    """A hand-made calibration document with one magnetometer."""
    mag = MagCalibration(mag_id, unit, D, o, 60.0, np.zeros((13, 13)), field)
    return Calibration(Source("sim.bin", "dataflash", "", 0.0, 1.0), "map", ImuCalibration("IMU[0]"), (mag,),
                       "0", "2026-01-01T00:00:00Z", effects=effects)


def written(exp: Export, style: str) -> dict[str, float]:
    """The parameters as the file on disk says them (the exporter's text, read back independently)."""
    return fwsim.read_param_file(render(exp.params, style, exp.header(), exp.integers))


def rel_error(a: np.ndarray, b: np.ndarray) -> float:
    """Largest |a - b| / |b| over the rows."""
    return float(np.max(np.linalg.norm(a - b, axis=1) / np.linalg.norm(b, axis=1)))


# --- ArduPilot ---------------------------------------------------------------------------------------------

def ardupilot_case(Q: np.ndarray, flown_id: int, params: dict[str, float], seed: int = 0,
                   ) -> tuple[Export, np.ndarray, np.ndarray, dict[str, float]]:
    """Export D = F Q P / o for a compass flown with COMPASS_ORIENT=flown_id; (export, b_fw, b_magcal, file)."""
    rng = np.random.default_rng(seed)
    D = F_MG * Q @ soft_iron(rng)
    o = rng.normal(scale=150.0, size=3)
    m = DIRECTIONS
    y = m @ D.T + o                                      # the body-frame raw the document was fitted on
    sensor = y @ fwsim.enum(flown_id)                    # the same readings in the compass's own frame
    cal = document(D, o)
    vehicle = {"COMPASS_ORIENT": float(flown_id)} | params
    exp = export(cal, "ardupilot", vehicle, Options(), None)
    p = written(exp, "mission-planner")
    b_fw = fwsim.ardupilot_field(sensor, vehicle | p)
    return exp, b_fw, F_MG * m, p


def test_ardupilot_external_custom_rotation_is_exact() -> None:
    """Any misalignment of an external compass on 4.3+: COMPASS_ORIENT=101 + CUST_ROT1, error below 0.1 %."""
    Q = so3.exp([0.05, -0.08, 0.12])
    exp, b_fw, b, p = ardupilot_case(Q, 0, {"COMPASS_EXTERNAL": 1, "CUST_ROT_ENABLE": 0, "COMPASS_SCALE": 0})
    assert p["COMPASS_ORIENT"] == 101 and p["CUST_ROT_ENABLE"] == 1
    assert rel_error(b_fw, b) < 1e-3
    assert exp.mags[0].lost()["max_field_error_pct"] < 0.1


def test_ardupilot_orientation_change_from_the_flown_one_is_exact() -> None:
    """Flown with ROLL_180 (8), the fit says the compass is also yawed 90 deg: the enum product is exported."""
    Q = fwsim.rz(90)                                      # relative to the flown orientation, in the body frame
    exp, b_fw, b, p = ardupilot_case(Q, 8, {"COMPASS_EXTERNAL": 1})
    expected = Q.T @ fwsim.enum(8)                        # A = P^-1 Q^T / F: the new orientation is Q^T R_flown
    assert np.allclose(fwsim.enum(int(p["COMPASS_ORIENT"])), expected, atol=1e-12)
    assert rel_error(b_fw, b) < 1e-3


def test_ardupilot_enum_only_leaves_exactly_the_reported_residual() -> None:
    """No custom rotations (3.x): a 0.5 deg misalignment stays; the firmware outputs E b with E reported."""
    Q = so3.exp(np.deg2rad(0.5) * np.array([0.6, 0.0, 0.8]))
    exp, b_fw, b, _ = ardupilot_case(Q, 0, {"COMPASS_EXTERNAL": 1})
    m = exp.mags[0]
    E = m.split.residual
    assert rel_error(b_fw, b @ E.T) < 2e-6                                  # exactly E b (float32 parameters)
    err_pct = 100 * np.linalg.norm(b_fw - b, axis=1) / np.linalg.norm(b, axis=1)
    assert err_pct.max() <= m.lost()["max_field_error_pct"] * 1.0001
    assert err_pct.max() >= m.lost()["max_field_error_pct"] * 0.98          # the bound is attained
    assert m.lost()["residual_misalignment_deg"] == pytest.approx(0.5, abs=0.05)
    assert rel_error(b_fw, b) > 1e-3                                         # and it is not exportable


def test_ardupilot_internal_compass_keeps_its_misalignment() -> None:
    """Internal: AHRS_ORIENTATION fixes the rotation; only sym(A) is written and E says what is lost."""
    Q = so3.exp(np.deg2rad([1.0, -2.0, 3.0]))
    exp, b_fw, b, p = ardupilot_case(Q, 0, {"COMPASS_EXTERNAL": 0, "AHRS_ORIENTATION": 0})
    assert "COMPASS_ORIENT" not in p
    m = exp.mags[0]
    assert rel_error(b_fw, b @ m.split.residual.T) < 2e-6
    assert m.lost()["residual_misalignment_deg"] == pytest.approx(np.rad2deg(so3.angle(Q)), rel=0.05)
    assert m.lost()["heading_error_deg"] > 2.0


def test_ardupilot_scale_is_used_within_its_range_and_exact() -> None:
    """With COMPASS_SCALE on the vehicle, SCALE x M = Ms, SCALE within 0.85..1.3, still exact."""
    exp, b_fw, b, p = ardupilot_case(np.eye(3), 0, {"COMPASS_EXTERNAL": 1, "COMPASS_SCALE": 0.0}, seed=3)
    assert 0.85 <= p["COMPASS_SCALE"] <= 1.3
    assert rel_error(b_fw, b) < 1e-3


def test_ardupilot_sign_smoke_test() -> None:
    """firmware-export.md section 3: a +100 mGauss x bias exports COMPASS_OFS_X = -100."""
    exp = export(document(F_MG * np.eye(3), np.array([100.0, 0.0, 0.0])), "ardupilot", {"COMPASS_EXTERNAL": 1})
    p = written(exp, "mission-planner")
    assert p["COMPASS_OFS_X"] == -100.0 and p["COMPASS_OFS_Y"] == 0.0 and p["COMPASS_ORIENT"] == 0
    assert [p[f"COMPASS_DIA_{a}"] for a in "XYZ"] == [1.0, 1.0, 1.0]


def test_px4_sign_smoke_test() -> None:
    """firmware-export.md section 3: a +100 mGauss x bias exports CAL_MAG0_XOFF = +0.1 (gauss)."""
    exp = export(document(F_MG * np.eye(3), np.array([100.0, 0.0, 0.0])), "px4", {})
    p = written(exp, "qgc")
    assert p["CAL_MAG0_XOFF"] == pytest.approx(0.1, abs=1e-8) and p["CAL_MAG0_YOFF"] == 0.0


def test_a_document_in_tesla_exports_in_each_firmware_unit() -> None:
    """Units: a ROS-style document (tesla) becomes mGauss for ArduPilot and gauss for PX4."""
    D = 50e-6 * soft_iron(np.random.default_rng(2))
    o = np.array([3e-6, -2e-6, 1e-6])
    cal = document(D, o, unit="tesla", field=50e-6)
    m = DIRECTIONS[:50]
    y = m @ D.T + o
    p = written(export(cal, "ardupilot", {"COMPASS_EXTERNAL": 1}), "mission-planner")
    assert rel_error(fwsim.ardupilot_field(y * 1e7, p | {"COMPASS_EXTERNAL": 1}), 500.0 * m) < 1e-3
    p = written(export(cal, "px4", {"CAL_MAG0_ROT": 0}), "qgc")
    assert rel_error(fwsim.px4_field(y * 1e4, p), 0.5 * m) < 1e-3


# --- PX4 ---------------------------------------------------------------------------------------------------

def px4_case(R: np.ndarray, params: dict[str, float], seed: int = 1) -> tuple[Export, np.ndarray, np.ndarray]:
    """Raw sensor_mag y = D m + o with D = F P R^T / ... : export, then PX4's formula; (export, b_fw, b)."""
    rng = np.random.default_rng(seed)
    F = 0.5
    D = F * soft_iron(rng) @ R.T                          # body -> sensor: the mounting rotation R^T
    o = rng.normal(scale=0.15, size=3)
    m = DIRECTIONS
    y = m @ D.T + o
    vehicle = {"sensor_mag[0].device_id": 396809.0, "CAL_MAG0_ID": 396809.0} | params
    exp = export(document(D, o, unit="gauss", field=F, mag_id="sensor_mag[0]"), "px4", vehicle)
    return exp, fwsim.px4_field(y, vehicle | written(exp, "qgc")), F * m


def test_px4_external_enum_rotation_is_exact() -> None:
    """An external magnetometer mounted yawed 90 deg: CAL_MAG0_ROT = 2, error below 0.1 %."""
    exp, b_fw, b = px4_case(fwsim.enum(2), {"CAL_MAG0_ROT": 0})
    assert exp.params["CAL_MAG0_ROT"] == 2 and exp.params["CAL_MAG0_ID"] == 396809
    assert rel_error(b_fw, b) < 1e-3


def test_px4_external_custom_euler_is_exact() -> None:
    """Firmware with CAL_MAG0_ROLL/PITCH/YAW: ROT = 100 and the Euler angles; any rotation is exact."""
    R = so3.exp([0.1, 0.2, -0.3])
    exp, b_fw, b = px4_case(R, {"CAL_MAG0_ROT": 0, "CAL_MAG0_ROLL": 0.0, "CAL_MAG0_PITCH": 0.0, "CAL_MAG0_YAW": 0.0})
    assert exp.params["CAL_MAG0_ROT"] == 100
    assert rel_error(b_fw, b) < 1e-3


def test_px4_internal_with_board_rotation_and_level_offsets() -> None:
    """Internal: R = Dcm(SENS_BOARD_*_OFF) rot(SENS_BOARD_ROT); a board exactly so mounted is exact."""
    board = {"CAL_MAG0_ROT": -1, "SENS_BOARD_ROT": 4, "SENS_BOARD_X_OFF": 1.5, "SENS_BOARD_Y_OFF": -2.0,
             "SENS_BOARD_Z_OFF": 0.5}
    R = fwsim.euler(1.5, -2.0, 0.5) @ fwsim.enum(4)
    exp, b_fw, b = px4_case(R, board)
    assert exp.params["CAL_MAG0_ROT"] == -1 and rel_error(b_fw, b) < 1e-3
    exp, b_fw, b = px4_case(R @ so3.exp(np.deg2rad([0.0, 0.0, 2.0])), board)     # mounted 2 deg off: residual
    m = exp.mags[0]
    assert rel_error(b_fw, b @ m.split.residual.T) < 2e-6
    assert m.lost()["residual_misalignment_deg"] == pytest.approx(2.0, abs=0.1)


# --- interference ------------------------------------------------------------------------------------------

def effect(kind: str, c: list[float], unit: str, sensor: str = "MAG[0]", status: str = "accepted",
           **params: float) -> dict[str, Any]:
    """A hand-made effects[] entry of the calibration document."""
    return {"id": kind, "sensor": sensor, "status": status, "params": {"c": c, **params}, "units": {"c": unit}}


@pytest.mark.parametrize("kind", ["current_interference", "throttle_interference"])
def test_ardupilot_motor_compensation_round_trip(kind: str) -> None:
    """y = D m + o + c s: MOT = -A_fw c and COMPASS_MOTCT (2 current, 1 throttle) cancel it in correct_field."""
    rng = np.random.default_rng(4)
    D, o = F_MG * soft_iron(rng), np.array([40.0, -20.0, 10.0])
    c = [2.0, -1.0, 3.0] if kind == "current_interference" else [60.0, 25.0, -90.0]
    unit = "milligauss/ampere" if kind == "current_interference" else "milligauss"
    cal = document(D, o, effects=(effect(kind, c, unit, p=1.0),))
    m = DIRECTIONS[:500]
    s = rng.uniform(0, 30, 500) if kind == "current_interference" else rng.uniform(0, 1, 500)
    y = m @ D.T + o + s[:, None] * np.array(c)
    p = written(export(cal, "ardupilot", {"COMPASS_EXTERNAL": 1}), "mission-planner")
    assert p["COMPASS_MOTCT"] == (2 if kind == "current_interference" else 1)
    b_fw = fwsim.ardupilot_field(y, p | {"COMPASS_EXTERNAL": 1}, signal=s)
    assert rel_error(b_fw, F_MG * m) < 1e-3
    uncompensated = fwsim.ardupilot_field(y, p | {"COMPASS_EXTERNAL": 1, "COMPASS_MOTCT": 0})
    assert rel_error(uncompensated, F_MG * m) > 0.05                # the term mattered


@pytest.mark.parametrize("kind", ["current_interference", "throttle_interference"])
def test_px4_power_compensation_round_trip(kind: str) -> None:
    """PX4: COMP = -c in the sensor frame (G/kA for current), CAL_MAG_COMP_TYP 2 / 1."""
    rng = np.random.default_rng(5)
    F = 0.5
    D, o = F * soft_iron(rng), np.array([0.04, -0.02, 0.01])
    c = [0.002, -0.001, 0.003] if kind == "current_interference" else [0.06, 0.025, -0.09]
    unit = "gauss/ampere" if kind == "current_interference" else "gauss"
    cal = document(D, o, unit="gauss", field=F, mag_id="sensor_mag[0]", effects=(effect(kind, c, unit,
                                                                                         "sensor_mag[0]"),))
    m = DIRECTIONS[:500]
    s = rng.uniform(0, 30, 500) if kind == "current_interference" else rng.uniform(0, 1, 500)
    y = m @ D.T + o + s[:, None] * np.array(c)
    p = written(export(cal, "px4", {"CAL_MAG0_ROT": 0}), "qgc")
    assert p["CAL_MAG_COMP_TYP"] == (2 if kind == "current_interference" else 1)
    if kind == "current_interference":
        assert p["CAL_MAG0_XCOMP"] == pytest.approx(-2.0, rel=1e-6)          # -c in G/kA
        b_fw = fwsim.px4_field(y, p, current_a=s)
    else:
        b_fw = fwsim.px4_field(y, p, throttle=s)
    assert rel_error(b_fw, F * m) < 1e-3


def test_one_motct_for_all_compasses_and_unaccepted_effects_ignored() -> None:
    """Current on MAG[0], throttle on MAG[1]: MOTCT=2, MAG[1]'s MOT zeroed and said; rejected effects unused."""
    D = F_MG * np.eye(3)
    mags = tuple(MagCalibration(i, "milligauss", D, np.zeros(3), 60.0, np.zeros((13, 13)), F_MG)
                 for i in ("MAG[0]", "MAG[1]"))
    effects = (effect("current_interference", [1.0, 0, 0], "milligauss/ampere", "MAG[0]"),
               effect("throttle_interference", [50.0, 0, 0], "milligauss", "MAG[1]"),
               effect("current_interference", [9.0, 9, 9], "milligauss/ampere", "MAG[1]", status="rejected"))
    cal = Calibration(Source("s.bin", "dataflash", "", 0, 1), "map", ImuCalibration("IMU[0]"), mags, "0", "t",
                      effects=effects)
    exp = export(cal, "ardupilot", {"COMPASS_EXTERNAL": 1, "COMPASS_EXTERN2": 0})
    assert exp.params["COMPASS_MOTCT"] == 2 and exp.params["COMPASS_MOT_X"] == -1.0
    assert [exp.params[f"COMPASS_MOT2_{a}"] for a in "XYZ"] == [0.0, 0.0, 0.0]
    assert any("MAG[1]: throttle interference not exported" in n for n in exp.notes)


def test_both_current_and_throttle_accepted_exports_current() -> None:
    """One compass with both terms accepted: current is exported, and the note says the throttle term is not."""
    effects = (effect("current_interference", [1.0, 0, 0], "milligauss/ampere"),
               effect("throttle_interference", [50.0, 0, 0], "milligauss", p=1.6))
    exp = export(document(F_MG * np.eye(3), np.zeros(3), effects=effects), "ardupilot", {"COMPASS_EXTERNAL": 1})
    assert exp.params["COMPASS_MOTCT"] == 2
    assert any("the current term is exported and the throttle term is not" in n for n in exp.notes)


def test_throttle_exponent_is_flagged() -> None:
    """A throttle term u^p with p != 1: written linearly, with the largest error stated."""
    effects = (effect("throttle_interference", [50.0, 0, 0], "milligauss", p=2.0),)
    exp = export(document(F_MG * np.eye(3), np.zeros(3), effects=effects), "ardupilot", {"COMPASS_EXTERNAL": 1})
    assert any("p=2.00 is dropped (largest error at u in [0,1]: 0.25 x |c|)" in n for n in exp.notes)
