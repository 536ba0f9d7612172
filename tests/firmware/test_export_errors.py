"""Slot mapping, limits and every export error message.

Modules it covers (the mirrored test file aside): magcal_cli.firmware.ardupilot, magcal_cli.firmware.common,
magcal_cli.firmware.effects, magcal_cli.firmware.export, magcal_cli.firmware.px4.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.firmware import FirmwareError, FirmwareLimitError, NotExportableError
from magcal_cli.firmware.common import Options
from magcal_cli.firmware.export import export

F = 500.0


def doc(*ids: str, D: np.ndarray | None = None, o: Any = (0.0, 0.0, 0.0), unit: str = "milligauss",
        effects: tuple[dict[str, Any], ...] = ()) -> Calibration:
    """A document with the given magnetometer ids (identity calibration unless D/o say otherwise)."""
    D = F * np.eye(3) if D is None else D
    mags = tuple(MagCalibration(i, unit, D, o, 60.0, np.zeros((13, 13)), F) for i in ids)
    return Calibration(Source("x.bin", "dataflash", "", 0, 1), "map", ImuCalibration("IMU[0]"), mags, "0", "t",
                       effects=effects)


# --- ArduPilot slots ---------------------------------------------------------------------------------------

def test_log_instances_map_to_suffixes_by_priority() -> None:
    """MAG[i] -> suffix i+1; when COMPASS_PRIO1_ID names the device in slot 2, slot 2 is written (#5923)."""
    exp = export(doc("MAG[0]", "MAG[1]"), "ardupilot", {})
    assert {m.mag_id: m.slot for m in exp.mags} == {"MAG[0]": "COMPASS_*", "MAG[1]": "COMPASS_*2"}
    swapped = {"COMPASS_PRIO1_ID": 222.0, "COMPASS_DEV_ID": 111.0, "COMPASS_DEV_ID2": 222.0}
    exp = export(doc("MAG[0]"), "ardupilot", swapped)
    assert exp.mags[0].slot == "COMPASS_*2" and "COMPASS_OFS2_X" in exp.params
    assert any("COMPASS_PRIO1_ID=222 is COMPASS_DEV_ID2" in n for n in exp.notes)


def test_ardupilot_slot_errors() -> None:
    with pytest.raises(FirmwareError, match="export: --slot 4 does not exist; ArduPilot has compass slots 1, 2 "
                                            "and 3"):
        export(doc("MAG[0]"), "ardupilot", {}, Options(slot=4))
    with pytest.raises(FirmwareError, match=r"export: --slot 1 holds COMPASS_DEV_ID=111, but MAG\[0\] is the "
                                            r"device COMPASS_PRIO1_ID=222. Drop --slot"):
        export(doc("MAG[0]"), "ardupilot", {"COMPASS_PRIO1_ID": 222.0, "COMPASS_DEV_ID": 111.0}, Options(slot=1))
    with pytest.raises(FirmwareError, match=r"export: MAG\[3\] would need compass slot 4; ArduPilot has 3"):
        export(doc("MAG[3]"), "ardupilot", {})
    with pytest.raises(FirmwareError, match=r"map to the same compass slot; export them one at a time"):
        export(doc("MAG[1]", "/imu/mag"), "ardupilot", {})
    with pytest.raises(FirmwareError, match=r"export: --slot applies to one magnetometer, but 2 are selected"):
        export(doc("MAG[0]", "MAG[1]"), "ardupilot", {}, Options(slot=1))
    exp = export(doc("/imu/mag"), "ardupilot", {}, Options(slot=2))
    assert exp.mags[0].slot == "COMPASS_*2"
    exp = export(doc("/imu/mag"), "ardupilot", {})
    assert any("not an ArduPilot compass id; written to slot 1" in n for n in exp.notes)


def test_custom_rotation_needs_4_3() -> None:
    with pytest.raises(FirmwareError, match=r"--rotation custom needs ArduPilot 4.3 or newer with a free CUST_ROT "
                                            r"slot"):
        export(doc("MAG[0]"), "ardupilot", {"COMPASS_EXTERNAL": 1}, Options(rotation="custom"))


def test_custom_slots_in_use_elsewhere_are_not_taken() -> None:
    """AHRS_ORIENTATION=101 holds CUST_ROT1, so a compass gets CUST_ROT2 (COMPASS_ORIENT=102)."""
    from magcal_cli import so3

    D = F * so3.exp([0.0, 0.0, 0.1])
    exp = export(doc("MAG[0]", D=D), "ardupilot", {"COMPASS_EXTERNAL": 1, "CUST_ROT_ENABLE": 1,
                                                   "AHRS_ORIENTATION": 101})
    assert exp.params["COMPASS_ORIENT"] == 102 and "CUST_ROT2_YAW" in exp.params


def test_a_lost_misalignment_says_why_and_a_custom_one_how_it_is_enabled() -> None:
    """Issue 12 item 5b: where the firmware cannot hold a rotation the header names the reason; where it can, the
    custom rotation is written with the parameter that enables it."""
    from magcal_cli import so3

    D = F * so3.exp(np.deg2rad([3.0, -4.0, 4.0]))       # 6.6 deg, like the external compass of the issue
    cases = {"ArduPilot before 4.3": ("ardupilot", {"COMPASS_EXTERNAL": 1},
                                      "custom rotations need ArduPilot 4.3 or newer (CUST_ROT_ENABLE, then "
                                      "COMPASS_ORIENT=101); this vehicle's parameters have none"),
             "internal": ("ardupilot", {"COMPASS_EXTERNAL": 0, "CUST_ROT_ENABLE": 0},
                          "an internal compass takes the board's AHRS_ORIENTATION"),
             "PX4 without angles": ("px4", {"CAL_MAG0_ROT": 0}, "custom Euler angles need a PX4 version with "
                                                              "CAL_MAG0_ROLL/PITCH/YAW"),
             "PX4 internal": ("px4", {"CAL_MAG0_ROT": -1}, "an internal magnetometer (CAL_MAG0_ROT=-1)")}
    for why, (firmware, params, text) in cases.items():
        mag = "MAG[0]" if firmware == "ardupilot" else "sensor_mag[0]"
        line = export(doc(mag, D=D), firmware, params).mags[0].lost_text()
        assert "deg of misalignment is not representable" in line and text in line, (why, line)
    exp = export(doc("MAG[0]", D=D), "ardupilot", {"COMPASS_EXTERNAL": 1, "CUST_ROT_ENABLE": 0})
    assert exp.params["CUST_ROT_ENABLE"] == 1 and exp.params["COMPASS_ORIENT"] == 101
    assert "exported exactly with a custom orientation" in exp.mags[0].lost_text()
    assert any("COMPASS_ORIENT=101 selects it and CUST_ROT_ENABLE=1 enables it" in n for n in exp.mags[0].notes)


# --- ArduPilot limits --------------------------------------------------------------------------------------

def test_offsets_beyond_offs_max_are_refused() -> None:
    """|OFS| must stay below COMPASS_OFFS_MAX (1800 default; the vehicle's value when known)."""
    with pytest.raises(FirmwareLimitError, match=r"export MAG\[0\] \(ArduPilot\): MAG\[0\]: \|COMPASS_OFS\| = "
                                                 r"1900 mGauss is not below COMPASS_OFFS_MAX = 1800 \(pre-arm "
                                                 r"'compass offsets too high'\)"):
        export(doc("MAG[0]", o=(1900.0, 0.0, 0.0)), "ardupilot", {})
    exp = export(doc("MAG[0]", o=(1900.0, 0.0, 0.0)), "ardupilot", {"COMPASS_OFFS_MAX": 3000.0})
    assert exp.params["COMPASS_OFS_X"] == -1900.0
    assert any("COMPASS_OFS_X=-1900 is outside the typical -1500..1500" in w for w in exp.warnings)


def test_diagonal_and_off_diagonal_limits() -> None:
    with pytest.raises(FirmwareLimitError, match=r"COMPASS_DIA_X = 5.5 is outside 0.2..5 \(the firmware's own "
                                                 r"calibration rejects it\)"):
        export(doc("MAG[0]", D=F * np.diag([1 / 5.5, 1.0, 1.0])), "ardupilot", {})
    D = F * np.linalg.inv(np.array([[1.0, 1.2, 0.0], [1.2, 2.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(FirmwareLimitError, match=r"COMPASS_ODI_X = 1.2 is outside -1..1"):
        export(doc("MAG[0]", D=D), "ardupilot", {})


def test_fit_writers_leave_out_refused_compasses_and_say_so() -> None:
    """skip_refused (the fit writers): the good compass is written, the refused one named in the warnings."""
    mags = (MagCalibration("MAG[0]", "milligauss", F * np.eye(3), np.zeros(3), 60.0, np.zeros((13, 13)), F),
            MagCalibration("MAG[1]", "milligauss", F * np.eye(3), [2500.0, 0, 0], 60.0, np.zeros((13, 13)), F))
    cal = Calibration(Source("x", "dataflash", "", 0, 1), "map", ImuCalibration("I"), mags, "0", "t")
    exp = export(cal, "ardupilot", {}, Options(skip_refused=True))
    assert [m.mag_id for m in exp.mags] == ["MAG[0]"]
    assert any(w.startswith("MAG[1] not exported: export MAG[1] (ArduPilot)") for w in exp.warnings)
    with pytest.raises(NotExportableError, match=r"MAG\[1\] not exported: .*; MAG\[2\] not exported"):
        export(doc("MAG[1]", "MAG[2]", o=(2500.0, 0, 0)), "ardupilot", {}, Options(skip_refused=True))


# --- PX4 slots and limits ----------------------------------------------------------------------------------

def test_px4_slot_by_device_id() -> None:
    """The slot whose CAL_MAGn_ID is the device id, whatever the log index; a new device gets a free slot."""
    params = {"sensor_mag[0].device_id": 555.0, "CAL_MAG0_ID": 777.0, "CAL_MAG1_ID": 0.0, "CAL_MAG2_ID": 555.0}
    exp = export(doc("sensor_mag[0]"), "px4", params)
    assert exp.mags[0].slot == "CAL_MAG2_*" and exp.params["CAL_MAG2_ID"] == 555
    params["CAL_MAG2_ID"] = 999.0
    exp = export(doc("sensor_mag[0]"), "px4", params)
    assert exp.mags[0].slot == "CAL_MAG1_*" and any("had no calibration slot; CAL_MAG1_ID is set" in n
                                                     for n in exp.notes)
    exp = export(doc("sensor_mag[1]"), "px4", {})
    assert exp.mags[0].slot == "CAL_MAG1_*" and any("no device id known, so slot 1 is assumed" in n
                                                     for n in exp.notes)


def test_px4_slot_errors() -> None:
    with pytest.raises(FirmwareError, match="export: --slot 4 does not exist; PX4 has magnetometer slots 0 to 3"):
        export(doc("sensor_mag[0]"), "px4", {}, Options(slot=4))
    params = {"sensor_mag[0].device_id": 555.0, "CAL_MAG0_ID": 777.0}
    with pytest.raises(FirmwareError, match=r"export: --slot 0 holds CAL_MAG0_ID=777, but sensor_mag\[0\] is "
                                            r"device_id 555. Drop --slot"):
        export(doc("sensor_mag[0]"), "px4", params, Options(slot=0))
    full = {"sensor_mag[0].device_id": 555.0} | {f"CAL_MAG{n}_ID": 100.0 + n for n in range(4)}
    with pytest.raises(FirmwareError, match=r"has no CAL_MAGn_ID and all four slots are taken. Pass --slot"):
        export(doc("sensor_mag[0]"), "px4", full)
    with pytest.raises(FirmwareError, match=r"export: sensor_mag\[5\] would need slot 5; PX4 has slots 0 to 3"):
        export(doc("sensor_mag[5]"), "px4", {})
    with pytest.raises(FirmwareError, match=r"export: /mag and sensor_mag\[1\] map to slot 1; export them one at a time"):
        export(doc("sensor_mag[1]", "/mag"), "px4", {})
    with pytest.raises(FirmwareError, match=r"--rotation custom needs a PX4 version with CAL_MAG0_ROLL"):
        export(doc("sensor_mag[0]"), "px4", {"CAL_MAG0_ROT": 0}, Options(rotation="custom"))


def test_px4_scale_limit_and_offset_warning() -> None:
    with pytest.raises(FirmwareLimitError, match=r"CAL_MAG0_XSCALE = 3.5 is outside 0.1..3 \(CAL_MAGn_xSCALE "
                                                 r"range\)"):
        export(doc("sensor_mag[0]", D=F * np.diag([1 / 3.5, 1, 1])), "px4", {})
    exp = export(doc("sensor_mag[0]", o=(1500.0, 0, 0)), "px4", {})
    assert any("CAL_MAG0_XOFF=1.5 is outside the typical -1.3..1.3 (PX4's calibration warns)" in w
               for w in exp.warnings)


def test_px4_enum_clears_custom_angles_and_flags_new_layout() -> None:
    """Writing an enum where CAL_MAGn_ROLL exists zeroes the angles (non-zero angles force custom)."""
    exp = export(doc("sensor_mag[0]"), "px4", {"CAL_MAG0_ROT": 0, "CAL_MAG0_ROLL": 5.0, "SENS_MAG0_ROT": 0})
    assert exp.params["CAL_MAG0_ROT"] == 0 and exp.params["CAL_MAG0_ROLL"] == 0.0
    assert any("SENS_MAGn_* configuration parameters" in n for n in exp.notes)


# --- documents ---------------------------------------------------------------------------------------------

def test_document_errors() -> None:
    with pytest.raises(FirmwareError, match=r"calibration: MAG\[0\] has unit 'm/s\^2', not a magnetic field unit"):
        export(doc("MAG[0]", unit="m/s^2"), "ardupilot", {})
    with pytest.raises(FirmwareError, match=r"calibration: MAG\[0\] has a singular or non-finite D"):
        export(doc("MAG[0]", D=np.zeros((3, 3))), "ardupilot", {})
    with pytest.raises(FirmwareError, match="firmware 'betaflight' is not known; use ardupilot or px4"):
        export(doc("MAG[0]"), "betaflight", {})
    bad = {"id": "current_interference", "sensor": "MAG[0]", "status": "accepted", "params": {"c": [1, 2]}}
    with pytest.raises(FirmwareError, match=r"effects\[0\] \(current_interference, MAG\[0\]\): params.c is missing "
                                            r"or not 3 numbers"):
        export(doc("MAG[0]", effects=(bad,)), "ardupilot", {})
    bad = {"id": "current_interference", "sensor": "MAG[0]", "status": "accepted", "params": {"c": [1, 2, 3]},
           "units": {"c": "ampere/ampere"}}
    with pytest.raises(FirmwareError, match=r"units.c 'ampere' is not a magnetic field unit; expected e.g. "
                                            r"'milligauss/ampere'"):
        export(doc("MAG[0]", effects=(bad,)), "ardupilot", {})


def test_effect_units_are_converted() -> None:
    """c given in microtesla/ampere for a milligauss document: 1 uT = 10 mG."""
    e = {"id": "current_interference", "sensor": "MAG[0]", "status": "accepted", "params": {"c": [1.0, 0, 0]},
         "units": {"c": "microtesla/ampere"}}
    exp = export(doc("MAG[0]", effects=(e,)), "ardupilot", {"COMPASS_EXTERNAL": 1})
    assert exp.params["COMPASS_MOT_X"] == pytest.approx(-10.0)


def test_a_field_px4_already_corrected_is_not_exported() -> None:
    """sensor_combined in a ULog (or a legacy .px4log) holds the corrected field: no CAL_MAG parameters."""
    from dataclasses import replace

    cal = replace(doc("sensor_combined", "sensor_mag[1]"), source=Source("f.ulg", "ulog", "", 0, 1))
    with pytest.raises(NotExportableError, match=r"export sensor_combined \(PX4\): this field was already "
                                                 r"corrected by the firmware \(no raw sensor_mag in the log\)"):
        export(cal, "px4", {}, Options(), ["sensor_combined"])
    exp = export(cal, "px4", {}, Options(skip_refused=True))
    assert [m.mag_id for m in exp.mags] == ["sensor_mag[1]"]


def test_a_partial_calibration_exports_only_what_the_log_determined() -> None:
    """A held D entry leaves the iron matrix, scale and orientation as the vehicle has them; a held offset leaves
    that axis's offset; both say so in a note (ArduPilot and PX4)."""
    from dataclasses import replace

    held = ({"parameter": "D[2][2]", "held": True, "prior": F, "prior_std": 25.0, "source": "the vehicle's"},
            {"parameter": "o[1]", "held": True, "prior": 0.0, "prior_std": 25.0, "source": "the vehicle's"})
    for firmware, mag_id, iron, ofs_y, ofs_x in (
            ("ardupilot", "MAG[0]", "COMPASS_DIA_X", "COMPASS_OFS_Y", "COMPASS_OFS_X"),
            ("px4", "sensor_mag[0]", "CAL_MAG0_XSCALE", "CAL_MAG0_YOFF", "CAL_MAG0_XOFF")):
        cal = doc(mag_id, o=(10.0, 20.0, 30.0))
        full = export(cal, firmware, {})
        assert {iron, ofs_y, ofs_x} <= set(full.params)
        cal = replace(cal, magnetometers=(replace(cal.magnetometers[0], held=held),))
        part = export(cal, firmware, {})
        assert ofs_x in part.params and iron not in part.params and ofs_y not in part.params
        assert any("could not determine D[2][2], o[1]" in n and "the vehicle keeps its own values" in n
                   for n in part.notes)


def test_one_interference_signal_for_all_compasses_follows_most_of_them() -> None:
    """COMPASS_MOTCT / CAL_MAG_COMP_TYP are global: the signal most compasses carry, current on a tie. log171 carries
    throttle on two compasses and current on one (an ambiguous pair each): "current when any" zeroed two."""
    from magcal_cli.firmware.common import shared_signal

    assert shared_signal({"MAG[0]": "current", "MAG[1]": "throttle", "MAG[2]": "throttle"}) == "throttle"
    assert shared_signal({"MAG[0]": "current", "MAG[1]": "throttle"}) == "current"
    assert shared_signal({"MAG[0]": "throttle"}) == "throttle"
    assert shared_signal({"MAG[0]": "current"}) == "current"
