"""EKF2_MAG_DELAY and TC_M* (firmware/extras.py): simulated readings with a known lag or temperature drift, the
exported file read back, and PX4's formulas (fwsim: the EKF's re-stamping, calc_thermal_offsets_3D) give the truth;
units, signs, ranges, several compasses, TC slots; what ArduPilot cannot hold is said.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.firmware.export import export

from . import fwsim
from .test_roundtrip import DIRECTIONS, document, rel_error, soft_iron, written

F = 0.5                                   # gauss
DEV = 396809
VEHICLE = {"sensor_mag[0].device_id": float(DEV), "CAL_MAG0_ID": float(DEV), "CAL_MAG0_ROT": 0.0}


def lag_entry(tau_s: float, std: float = 0.001, sensor: str = "sensor_mag[0]", status: str = "accepted"
              ) -> dict[str, Any]:
    """A time_offset entry of the document."""
    return {"id": "time_offset", "sensor": sensor, "status": status, "params": {"tau_s": tau_s},
            "std": {"tau_s": std}, "units": {"tau_s": "s"}}


def drift_entry(k: list[float], t0: float, t_min: float, t_max: float, unit: str = "gauss/degC",
                channels: tuple[str, ...] = ("sensor_mag[0]",)) -> dict[str, Any]:
    """A temperature_drift entry of the document (with the range the fit saw)."""
    return {"id": "temperature_drift", "sensor": "sensor_mag[0]", "status": "accepted", "channels": list(channels),
            "params": {"k": k, "T0": t0, "T_min": t_min, "T_max": t_max}, "units": {"k": unit, "T0": "degC"}}


def px4_doc(D: np.ndarray, o: np.ndarray, effects: tuple[dict[str, Any], ...]) -> Calibration:
    """One PX4 magnetometer (gauss) with the given effects."""
    return document(D, o, unit="gauss", field=F, mag_id="sensor_mag[0]", effects=effects)


def test_lag_round_trip_through_the_ekf_restamping() -> None:
    """y stamped t sensed R(t - tau): EKF2_MAG_DELAY = 1000 tau (ms); the EKF fuses it at the time it was sensed."""
    rng = np.random.default_rng(11)
    D, o, tau = F * soft_iron(rng), np.array([0.05, -0.03, 0.02]), 0.0378
    t = np.arange(0.0, 20.0, 0.01)
    rot = so3.exp(np.column_stack([0.9 * np.sin(0.7 * t), 0.6 * np.sin(1.1 * t), 1.5 * t]))   # body -> nav
    m_n = np.array([0.42, 0.0, 0.91])
    sensed = so3.exp(np.column_stack([0.9 * np.sin(0.7 * (t - tau)), 0.6 * np.sin(1.1 * (t - tau)), 1.5 * (t - tau)]))
    y = np.einsum("nji,j->ni", sensed, m_n) @ D.T + o
    p = written(export(px4_doc(D, o, (lag_entry(tau),)), "px4", VEHICLE), "qgc")
    assert p["EKF2_MAG_DELAY"] == pytest.approx(37.8, abs=1e-4)                  # ms, positive: the mag lags
    b_fw, t_fw = fwsim.px4_field(y, VEHICLE | p), fwsim.ekf_mag_time(t, p)
    truth_at = so3.exp(np.column_stack([0.9 * np.sin(0.7 * t_fw), 0.6 * np.sin(1.1 * t_fw), 1.5 * t_fw]))
    truth = F * np.einsum("nji,j->ni", truth_at, m_n)
    assert rel_error(b_fw, truth) < 1e-4
    stale = F * np.einsum("nji,j->ni", rot, m_n)                                 # fused at its stamp instead
    assert rel_error(b_fw, stale) > 0.03


@pytest.mark.parametrize(("tau", "written_ms", "warning"), [(-0.012, None, "cannot be negative"),
                                                             (0.35, 300.0, "beyond EKF2_MAG_DELAY's 300 ms")])
def test_lag_outside_the_parameter_range(tau: float, written_ms: float | None, warning: str) -> None:
    """EKF2_MAG_DELAY is 0..300 ms: a lead is not written, a longer lag is clipped; each said."""
    exp = export(px4_doc(F * np.eye(3), np.zeros(3), (lag_entry(tau),)), "px4", VEHICLE)
    assert exp.params.get("EKF2_MAG_DELAY") == written_ms
    assert any(warning in w for w in exp.warnings)


def two_mags(lags: dict[str, float], prio: tuple[float, float]) -> tuple[Calibration, dict[str, float]]:
    """Two PX4 magnetometers with lags (s) and CAL_MAGn_PRIO."""
    mags = tuple(MagCalibration(f"sensor_mag[{i}]", "gauss", F * np.eye(3), np.zeros(3), 60.0, np.zeros((13, 13)), F)
                 for i in range(2))
    effects = tuple(lag_entry(v, 0.002, k) for k, v in lags.items())
    cal = Calibration(Source("s.ulg", "ulog", "", 0, 1), "map", ImuCalibration("sensor_accel[0]"), mags, "0", "t",
                      effects=effects)
    params = {"sensor_mag[0].device_id": 1.0, "sensor_mag[1].device_id": 2.0, "CAL_MAG0_ID": 1.0, "CAL_MAG1_ID": 2.0,
              "CAL_MAG0_ROT": 0.0, "CAL_MAG1_ROT": 0.0, "CAL_MAG0_PRIO": prio[0], "CAL_MAG1_PRIO": prio[1]}
    return cal, params


def test_several_compasses_the_primary_lag_is_written() -> None:
    """One EKF2_MAG_DELAY: the highest-priority magnetometer's; a lag outside the intervals is warned about."""
    cal, params = two_mags({"sensor_mag[0]": 0.020, "sensor_mag[1]": 0.045}, (50.0, 75.0))
    exp = export(cal, "px4", params)
    assert exp.params["EKF2_MAG_DELAY"] == pytest.approx(45.0)
    assert any("sensor_mag[0] lags by 20.0 ms" in w and "one value for all" in w for w in exp.warnings)
    cal, params = two_mags({"sensor_mag[0]": 0.020, "sensor_mag[1]": 0.022}, (75.0, 50.0))
    exp = export(cal, "px4", params)
    assert exp.params["EKF2_MAG_DELAY"] == pytest.approx(20.0) and not exp.warnings     # within the intervals
    cal, params = two_mags({"sensor_mag[1]": 0.030}, (75.0, 50.0))
    exp = export(cal, "px4", params)
    assert "EKF2_MAG_DELAY" not in exp.params
    assert any("primary magnetometer sensor_mag[0] carries no time_offset" in n for n in exp.notes)


def drift_case(temps: np.ndarray, t_range: tuple[float, float], params: dict[str, float] | None = None
               ) -> tuple[dict[str, float], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """y = D m + o + k (T - T0): (file, firmware field, truth F m, readings, k)."""
    rng = np.random.default_rng(12)
    D, o = F * soft_iron(rng), np.array([0.06, -0.02, 0.04])
    k, t0 = np.array([0.0021, -0.0014, 0.0030]), 31.0
    m = DIRECTIONS[: len(temps)]
    y = m @ D.T + o + (temps - t0)[:, None] * k
    cal = px4_doc(D, o, (drift_entry(list(k * 1000.0), t0, *t_range, unit="milligauss/degC"),))
    vehicle = VEHICLE | (params or {})
    p = written(export(cal, "px4", vehicle), "qgc")
    return p, fwsim.px4_field(y, vehicle | p, temperature=temps, device_id=DEV), F * m, y, k


def test_temperature_drift_round_trip_through_tc_m() -> None:
    """TC_M0_*: TREF = T0, X1 = k in gauss/degC (from mG/degC), TMIN/TMAX the fit's range; the field is the truth."""
    temps = np.linspace(22.0, 40.0, 3000)
    p, b_fw, truth, y, k = drift_case(temps, (22.0, 40.0))
    assert p["TC_M_ENABLE"] == 1 and p["TC_M0_ID"] == DEV
    assert (p["TC_M0_TREF"], p["TC_M0_TMIN"], p["TC_M0_TMAX"]) == (31.0, 22.0, 40.0)
    assert [p[f"TC_M0_X1_{i}"] for i in range(3)] == pytest.approx(list(k), rel=1e-6)
    assert p["TC_M0_X0_0"] == p["TC_M0_X2_1"] == p["TC_M0_X3_2"] == 0.0
    assert rel_error(b_fw, truth) < 1e-4
    off = fwsim.px4_field(y, VEHICLE | p)                        # without the thermal offset: the drift mattered
    assert rel_error(off, truth) > 0.01


def test_the_firmware_never_extrapolates_beyond_the_logged_range() -> None:
    """TMIN/TMAX are the log's range and the firmware clamps to it: at 55 degC it applies the slope at 40 degC."""
    temps = np.full(200, 55.0)
    p, b_fw, truth, y, _ = drift_case(temps, (22.0, 40.0))
    at_max = fwsim.px4_field(y, VEHICLE | p, temperature=np.full(200, 40.0), device_id=DEV)
    assert np.allclose(b_fw, at_max, atol=1e-12)
    assert rel_error(b_fw, truth) > 0.01                  # the drift beyond the range is left, not extrapolated


def test_tc_slot_follows_the_device_id() -> None:
    """A TC_Mj_ID that already names the device is reused; another device's slot is left alone."""
    p, *_ = drift_case(np.linspace(22.0, 40.0, 100), (22.0, 40.0), {"TC_M0_ID": 7.0, "TC_M2_ID": float(DEV)})
    assert p["TC_M2_ID"] == DEV and "TC_M0_ID" not in p
    p, *_ = drift_case(np.linspace(22.0, 40.0, 100), (22.0, 40.0), {"TC_M0_ID": 7.0})
    assert p["TC_M1_ID"] == DEV


def test_drift_without_device_id_or_range_is_not_written() -> None:
    """TC_Mj_ID must name the device; a document without T_min/T_max cannot bound the slope: said, not written."""
    entry = drift_entry([1.0, 0.0, 0.0], 30.0, 20.0, 40.0, unit="milligauss/degC")
    exp = export(px4_doc(F * np.eye(3), np.zeros(3), (entry,)), "px4", {"CAL_MAG0_ROT": 0.0})
    assert "TC_M_ENABLE" not in exp.params and any("device id is unknown" in w for w in exp.warnings)
    del entry["params"]["T_min"]
    exp = export(px4_doc(F * np.eye(3), np.zeros(3), (entry,)), "px4", VEHICLE)
    assert "TC_M_ENABLE" not in exp.params and any("no T_min/T_max" in w for w in exp.warnings)


def test_ardupilot_says_what_it_cannot_hold() -> None:
    """ArduPilot: EKF3's magnetometer delay is a constant, and there is no compass thermal compensation."""
    effects = ({**lag_entry(0.04), "sensor": "MAG[0]"},
               {**drift_entry([1.0, 0, 0], 30.0, 20.0, 40.0, unit="milligauss/degC"), "sensor": "MAG[0]"})
    exp = export(document(500.0 * np.eye(3), np.zeros(3), effects=effects), "ardupilot", {"COMPASS_EXTERNAL": 1})
    assert not any(k.startswith(("EKF", "TC_")) for k in exp.params)
    assert any("40.0 ms lag is not exported" in n for n in exp.not_held)
    assert any("temperature drift is not exported" in n for n in exp.not_held)
    assert any(h.startswith("not held: MAG[0]: its 40.0 ms lag") for h in exp.header())


# --- per-motor compensation (ArduPilot COMPASS_PMOT*) ------------------------------------------------------

C_MOTORS = np.array([[9.0, -4.5, 6.0], [-7.5, 6.0, 3.0], [3.0, 9.0, -6.0], [-6.0, -7.5, 7.5]])   # mG per unit


def motor_entry(sensor: str = "MAG[0]") -> dict[str, Any]:
    """A carried motor_interference entry (mG per unit of (u V)^0.65)."""
    return {"id": "motor_interference", "sensor": sensor, "status": "ambiguous",
            "params": {f"c{n + 1}": list(C_MOTORS[n]) for n in range(4)} | {"expo": 0.65},
            "units": {f"c{n + 1}": "milligauss" for n in range(4)}}


def test_per_motor_round_trip_through_compass_per_motor() -> None:
    """y = D m + o + sum c_n (u_n V)^0.65: PMOTn = -A_fw c_n and the firmware's compensate() cancel it."""
    rng = np.random.default_rng(13)
    D, o = 500.0 * soft_iron(rng), np.array([40.0, -20.0, 10.0])
    n = 2000
    pwm = np.round(rng.uniform(1000.0, 1900.0, size=(n, 4)))
    pwm[:100] = 1000.0                                                       # motors off: no offset
    volts = rng.uniform(14.0, 16.8, n)
    s = np.where(pwm > 1000, ((pwm - 1000.0) / 1000.0 * volts[:, None]) ** 0.65, 0.0)
    m = DIRECTIONS[:n]
    y = m @ D.T + o + s @ C_MOTORS
    vehicle = {"COMPASS_EXTERNAL": 1.0, "COMPASS_PMOT_EN": 0.0, "MOT_PWM_MIN": 1000.0, "MOT_PWM_MAX": 2000.0}
    exp = export(document(D, o, effects=(motor_entry(),)), "ardupilot", vehicle)
    p = written(exp, "mission-planner")
    assert p["COMPASS_PMOT_EN"] == 1 and p["COMPASS_PMOT_EXP"] == pytest.approx(0.65)
    b_fw = fwsim.ardupilot_field(y, vehicle | p, pwm=pwm, volts=volts)
    assert rel_error(b_fw, 500.0 * m) < 1e-3
    off = fwsim.ardupilot_field(y, vehicle | p | {"COMPASS_PMOT_EN": 0.0}, pwm=pwm, volts=volts)
    assert rel_error(off, 500.0 * m) > 0.05                                 # the term mattered
    assert "COMPASS_MOTCT" not in p                                          # the throttle rival is not carried


def test_per_motor_only_for_the_first_compass_and_firmware_that_has_it() -> None:
    """PMOT applies to compass 1 only; a firmware without COMPASS_PMOT_EN (3.3) cannot hold it: said, not written."""
    mags = tuple(MagCalibration(i, "milligauss", 500.0 * np.eye(3), np.zeros(3), 60.0, np.zeros((13, 13)), 500.0)
                 for i in ("MAG[0]", "MAG[1]"))
    cal = Calibration(Source("s.bin", "dataflash", "", 0, 1), "map", ImuCalibration("IMU[0]"), mags, "0", "t",
                      effects=(motor_entry("MAG[1]"),))
    exp = export(cal, "ardupilot", {"COMPASS_EXTERNAL": 1, "COMPASS_EXTERN2": 0, "COMPASS_PMOT_EN": 0.0})
    assert not any(k.startswith("COMPASS_PMOT") for k in exp.params)
    assert any("first compass (COMPASS_*, slot 1) only" in n for n in exp.not_held)
    exp = export(document(500.0 * np.eye(3), np.zeros(3), effects=(motor_entry(),)), "ardupilot",
                 {"COMPASS_EXTERNAL": 1})
    assert not any(k.startswith("COMPASS_PMOT") for k in exp.params)
    assert any("no per-motor compass compensation" in n for n in exp.not_held)
