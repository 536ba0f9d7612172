"""The calibration document: exact JSON/YAML round trips, schema checks, the misalignment uncertainty.

Modules it covers (the mirrored test file aside): magcal_cli.calibration.types.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal_cli import so3
from magcal_cli.calibration.document import dumps_json, dumps_yaml, from_dict, load, to_dict
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Quality, Source
from magcal_cli.errors import CalibrationFileError
from magcal_cli.params import MAG

SAMPLE_TRUTH = Path(__file__).resolve().parents[2] / "sample_logs" / "handheld.bin.truth.json"


def _calibration(seed: int) -> Calibration:
    """A random but valid document with full covariance, an IMU without accelerometer bias, extra keys."""
    rng = np.random.default_rng(seed)
    d = 480.0 * so3.exp(rng.normal(size=3) * 0.1) @ (np.eye(3) + 0.05 * rng.normal(size=(3, 3)))
    a = rng.normal(size=(13, 13))
    held = ({"parameter": "D[2][2]", "held": True, "prior": float(rng.normal() * 480), "prior_std": 24.0,
             "source": "the calibration the vehicle flew with"},) if seed % 2 else ()
    mag = MagCalibration("MAG[0]", "milligauss", d, rng.normal(size=3) * 50, 66.2 + rng.normal(),
                         a @ a.T * 1e-4, 489.0, "wmm", Quality(2384, 4.1, 0.8, 91.0, True, 7), held)
    imu = ImuCalibration("IMU[0]", None, rng.normal(size=3) * 1e-3, None, np.full(3, 1e-5))
    return Calibration(Source("flight.bin", "dataflash", "ab" * 32, 0.0, 243.1), "kok2012", imu, (mag,),
                       "0.1.0", "2026-11-21T10:00:00Z", {"gyroscope_std": [0.01, 0.01, 0.01]},
                       notes=("a note",), extra={"simulation": {"seed": seed}})


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_json_and_yaml_round_trips_are_exact(seed: int) -> None:
    """load(dump(cal)) == cal bit for bit, for both encodings."""
    cal = _calibration(seed)
    assert from_dict(json.loads(dumps_json(cal))) == cal
    import yaml

    assert from_dict(yaml.safe_load(dumps_yaml(cal))) == cal


def test_document_follows_the_schema() -> None:
    """Keys, shapes and the derived quantities of calibration-file.md."""
    cal = _calibration(1)
    doc = to_dict(cal)
    assert doc["schema"] == "magcal.calibration/1"
    m = doc["magnetometers"][0]
    d = np.array(m["D"])
    np.testing.assert_allclose(np.array(m["A"]) @ d, np.eye(3), atol=1e-12)
    u = np.array(m["misalignment"]["rotation"])
    p = np.array(m["soft_iron"]) * m["field_strength"]
    np.testing.assert_allclose(u @ p, d, atol=1e-9)                       # D = U P
    np.testing.assert_allclose(so3.from_rpy(np.deg2rad(m["misalignment"]["rpy_deg"])), u, atol=1e-12)
    assert np.array(m["std"]["D"]).shape == (3, 3) and len(m["std"]["o"]) == 3
    assert doc["imu"]["accelerometer_bias"] is None and doc["imu"]["std"]["accelerometer_bias"] is None
    assert doc["simulation"] == {"seed": 1}


def test_apply_inverts_distort() -> None:
    """cal.apply(cal.distort(m)) == m."""
    cal = _calibration(2).magnetometers[0]
    m = np.random.default_rng(0).normal(size=(20, 3))
    np.testing.assert_allclose(cal.apply(cal.distort(m)), m, atol=1e-12)


def test_misalignment_covariance_matches_finite_differences() -> None:
    """The analytic polar-factor sensitivity equals a numerical one (relative 1e-5)."""
    cal = _calibration(3).magnetometers[0]
    u0 = cal.misalignment
    jac = np.zeros((3, 9))
    for k in range(9):
        dd = np.zeros(9)
        dd[k] = 1e-6 * 480
        u1 = so3.polar(cal.D + dd.reshape(3, 3, order="F"))[0]
        jac[:, k] = so3.log(u0.T @ u1) / dd[k]
    np.testing.assert_allclose(cal.misalignment_cov(), jac @ cal.cov[:9, :9] @ jac.T, rtol=1e-5, atol=1e-18)


def test_wrong_schema_and_malformed_documents_are_refused(tmp_path: Path) -> None:
    """Messages name the file and the problem."""
    with pytest.raises(CalibrationFileError, match=r"not a magcal calibration document \(schema 'x/2'"):
        from_dict({"schema": "x/2"}, "cal.json")
    doc = to_dict(_calibration(4))
    del doc["magnetometers"][0]["D"]
    with pytest.raises(CalibrationFileError, match=r"magnetometers\[0\]: 'D' is missing or not a 3x3 array"):
        from_dict(doc, "cal.json")
    bad = tmp_path / "cal.json"
    bad.write_text("{not json")
    with pytest.raises(CalibrationFileError, match="cal.json: not valid JSON"):
        load(bad)


def test_covariance_order_is_the_named_layout() -> None:
    """covariance.order lists [block, size, unit kind] of params.MAG and survives JSON and YAML round trips."""
    cal = _calibration(5)
    doc = json.loads(dumps_json(cal))
    order = doc["magnetometers"][0]["covariance"]["order"]
    assert order == [["D", 9, "field"], ["o", 3, "field"], ["dip", 1, "angle"]] == MAG.to_order()
    assert yaml.safe_load(dumps_yaml(cal))["magnetometers"][0]["covariance"]["order"] == order
    assert from_dict(doc) == cal


def test_old_documents_with_a_string_order_still_load(tmp_path: Path) -> None:
    """Documents written before the named layout carry the order as a string; they load unchanged."""
    cal = _calibration(6)
    doc = to_dict(cal)
    doc["magnetometers"][0]["covariance"]["order"] = "vec(D) column-major (9), o (3), dip_deg (1)"
    assert from_dict(json.loads(json.dumps(doc))) == cal
    old = json.loads(SAMPLE_TRUTH.read_text())
    old["magnetometers"][0]["covariance"]["order"] = "vec(D) column-major (9), o (3), dip_deg (1)"
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert load(tmp_path / "old.json").magnetometers[0].cov.shape == (MAG.size, MAG.size)


@pytest.mark.parametrize("order", [[["o", 3, "field"], ["D", 9, "field"], ["dip", 1, "angle"]],
                                   [["D", 9, "field"], ["o", 3, "field"]], "o (3), vec(D) (9), dip_deg (1)",
                                   [["D", 9]]])
def test_a_covariance_in_another_order_is_refused(order: object) -> None:
    """A covariance whose order is not MAG's is refused with a message naming both orders."""
    doc = to_dict(_calibration(7))
    doc["magnetometers"][0]["covariance"]["order"] = order
    with pytest.raises(CalibrationFileError, match=r"cal.json: magnetometers\[0\]: covariance.order is .*, but "
                                                   r"this magcal reads only \[\['D', 9, 'field'\]"):
        from_dict(doc, "cal.json")


def test_named_accessors_follow_the_layout() -> None:
    """std_of gives D (3, 3) column-major, o (3,) and the dip as a scalar; cov_of the joint blocks in order."""
    mag = _calibration(8).magnetometers[0]
    sd = np.sqrt(np.diag(mag.cov))
    np.testing.assert_array_equal(mag.std_of("D"), sd[MAG.slice("D")].reshape(3, 3, order="F"))
    np.testing.assert_array_equal(mag.std_of("o"), sd[MAG.slice("o")])
    assert mag.std_of("dip").shape == () and float(mag.std_of("dip")) == sd[MAG.slice("dip")][0]
    cols = np.r_[MAG.slice("o"), MAG.slice("D")]
    np.testing.assert_array_equal(mag.cov_of("o", "D"), mag.cov[np.ix_(cols, cols)])
