"""`magcal export --driver`: each driver's own correction formula, written here from the driver's source, gives
back magcal's calibrated field; and the errors (unknown driver, several compasses, a refused one).

Modules it covers: magcal_cli.firmware.drivers, magcal_cli.firmware.drivers.common,
magcal_cli.firmware.drivers.generic, magcal_cli.firmware.drivers.microstrain, magcal_cli.firmware.drivers.phidgets,
magcal_cli.cli.export.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from magcal_cli import so3
from magcal_cli.calibration.document import dumps_json, load
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Source
from magcal_cli.cli.export import DRIVER_NAMES
from magcal_cli.cli.main import cli
from magcal_cli.firmware import FirmwareError, FirmwareLimitError
from magcal_cli.firmware.drivers import DRIVERS, export_driver
from magcal_cli.readers import open_recording

ROOT = Path(__file__).resolve().parents[2]
MCAP = ROOT / "sample_logs" / "handheld.mcap"
#: tesla -> gauss, the unit both devices read in (written here, not taken from magcal)
GAUSS_PER_TESLA = 1e4
TOL = 1e-3   # the 0.1 %


def phidgets_correct(p: dict[str, float], y: np.ndarray) -> np.ndarray:
    """libphidget22 getCorrectedField, axis by axis as in spatialdevice.c, y in gauss."""
    dx, dy, dz = y[:, 0] - p["cc_offset0"], y[:, 1] - p["cc_offset1"], y[:, 2] - p["cc_offset2"]
    f = p["cc_mag_field"]
    return np.column_stack([f * (p["cc_gain0"] * dx + p["cc_t0"] * dy + p["cc_t1"] * dz),
                            f * (p["cc_gain1"] * dy + p["cc_t2"] * dx + p["cc_t3"] * dz),
                            f * (p["cc_gain2"] * dz + p["cc_t4"] * dx + p["cc_t5"] * dy)])


def microstrain_correct(p: dict[str, Any], y: np.ndarray) -> np.ndarray:
    """MIP 0x0C3A then 0x0C3B: the row-major soft-iron matrix times (y - hard-iron offset), y in gauss, as the
    device stores them (float32)."""
    h = np.asarray(p["mag_hard_iron_offset"], dtype=np.float32).astype(float)
    m = np.asarray(p["mag_soft_iron_matrix"], dtype=np.float32).astype(float).reshape(3, 3)
    out: np.ndarray = (y - h) @ m.T
    return out


def ros_params(text: str) -> dict[str, Any]:
    """The ros__parameters of a ROS 2 parameter file (its only node entry)."""
    (node,) = yaml.safe_load(text).values()
    params: dict[str, Any] = node["ros__parameters"]
    return params


def rel_err(got: np.ndarray, want: np.ndarray) -> float:
    """Largest |got - want| over the field's magnitude."""
    return float(np.max(np.linalg.norm(got - want, axis=1) / np.linalg.norm(want, axis=1)))


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Calibration, np.ndarray]:
    """magcal fit on the shipped simulated MCAP: (document path, document, the raw field readings in tesla)."""
    out = tmp_path_factory.mktemp("fit")
    result = CliRunner().invoke(cli, ["fit", str(MCAP), "-o", str(out), "-q"])
    assert result.exit_code == 0, result.output
    cal = load(out / "calibration.json")
    (mag,) = [s for s in open_recording(MCAP).streams if s.id == cal.magnetometers[0].id]
    return out / "calibration.json", cal, np.asarray(mag.values)


def truth(cal: Calibration, y_tesla: np.ndarray) -> np.ndarray:
    """magcal's calibrated field in tesla: F * MagCalibration.apply (the document is in tesla)."""
    mag = cal.magnetometers[0]
    assert mag.unit == "tesla"
    return mag.field_strength * mag.apply(y_tesla)


def test_phidgets_formula_gives_back_the_calibrated_field(fitted: tuple[Path, Calibration, np.ndarray]) -> None:
    """out = magField M (y - offset) in gauss, on every reading of the log; float32 (VINT devices) too."""
    _, cal, y = fitted
    p = ros_params(export_driver(cal, "phidgets_spatial").text)
    assert sorted(p) == sorted(["cc_mag_field", *(f"cc_offset{i}" for i in range(3)),
                                *(f"cc_gain{i}" for i in range(3)), *(f"cc_t{i}" for i in range(6))])
    want = truth(cal, y) * GAUSS_PER_TESLA
    assert rel_err(phidgets_correct(p, y * GAUSS_PER_TESLA), want) < 1e-9
    p32 = {k: float(np.float32(v)) for k, v in p.items()}
    assert rel_err(phidgets_correct(p32, y * GAUSS_PER_TESLA), want) < TOL


def test_microstrain_formula_gives_back_the_calibrated_field(fitted: tuple[Path, Calibration, np.ndarray]) -> None:
    _, cal, y = fitted
    p = ros_params(export_driver(cal, "microstrain_inertial_driver").text)
    assert len(p["mag_hard_iron_offset"]) == 3 and len(p["mag_soft_iron_matrix"]) == 9
    assert rel_err(microstrain_correct(p, y * GAUSS_PER_TESLA), truth(cal, y) * GAUSS_PER_TESLA) < TOL


def test_generic_formula_gives_back_the_calibrated_field(fitted: tuple[Path, Calibration, np.ndarray]) -> None:
    """m = S (y - h) in the document's unit, |m| = field_strength."""
    _, cal, y = fitted
    g = yaml.safe_load(export_driver(cal, "generic").text)
    assert g["unit"] == "tesla" and g["magnetometer"] == cal.magnetometers[0].id
    m = (y - np.asarray(g["hard_iron"])) @ np.asarray(g["soft_iron"]).T
    assert rel_err(m, truth(cal, y)) < 1e-9
    assert g["field_strength"] == pytest.approx(cal.magnetometers[0].field_strength, rel=1e-12)


def doc(D: np.ndarray, o: Any, unit: str = "milligauss", ids: tuple[str, ...] = ("MAG[0]",),
        refused: tuple[dict[str, str], ...] = (), effects: tuple[dict[str, Any], ...] = ()) -> Calibration:
    """A hand-made document: the given D, o for each id."""
    mags = tuple(MagCalibration(i, unit, D, o, 60.0, np.zeros((13, 13)), 480.0) for i in ids)
    return Calibration(Source("x.bin", "dataflash", "", 0, 1), "map", ImuCalibration("IMU[0]"), mags, "0", "t",
                       effects=effects, refused=refused)


def test_a_milligauss_document_with_a_large_misalignment_round_trips() -> None:
    """A non-symmetric D (20 deg misalignment, 8 % soft iron) in milligauss: every driver holds it."""
    rng = np.random.default_rng(3)
    U = so3.exp(np.radians(20.0) * np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74]))
    P = 480.0 * (np.eye(3) + 0.08 * (lambda a: (a + a.T) / 2)(rng.standard_normal((3, 3))))
    cal = doc(U @ P, np.array([120.0, -60.0, 35.0]))
    mag = cal.magnetometers[0]
    y = mag.distort((u := rng.standard_normal((500, 3))) / np.linalg.norm(u, axis=1, keepdims=True))
    want_g = mag.field_strength * mag.apply(y) / 1000.0
    p = ros_params(export_driver(cal, "phidgets_spatial").text)
    assert rel_err(phidgets_correct(p, y / 1000.0), want_g) < 1e-9
    p = ros_params(export_driver(cal, "microstrain_inertial_driver").text)
    assert rel_err(microstrain_correct(p, y / 1000.0), want_g) < TOL
    assert "the 20.00 deg misalignment to the IMU" in export_driver(cal, "generic").text


def test_driver_errors() -> None:
    cal = doc(480.0 * np.eye(3), (0.0, 0.0, 0.0), ids=("MAG[0]", "MAG[1]"),
              refused=({"id": "MAG[2]", "status": "refused", "reason": "it read a constant field"},))
    with pytest.raises(FirmwareError, match=r"no driver 'px4_driver'; --driver takes phidgets_spatial, "):
        export_driver(cal, "px4_driver")
    with pytest.raises(FirmwareError, match=r"the document has 2 magnetometers \(MAG\[0\], MAG\[1\]\); choose one "
                                            r"with --mag MAG\[0\]"):
        export_driver(cal, "generic")
    with pytest.raises(FirmwareError, match=r"MAG\[2\] was refused \(it read a constant field\), so it has no "
                                            r"calibration to export; choose --mag MAG\[0\] or MAG\[1\]"):
        export_driver(cal, "generic", ["MAG[2]"])
    with pytest.raises(FirmwareError, match="a driver file holds one magnetometer, but --mag gives 2"):
        export_driver(cal, "generic", ["MAG[0]", "MAG[1]"])
    assert export_driver(cal, "generic", ["MAG[1]"]).mag_id == "MAG[1]"
    none_left = doc(480.0 * np.eye(3), (0.0, 0.0, 0.0), ids=(), refused=cal.refused)
    with pytest.raises(FirmwareError, match=r"the document has no calibrated magnetometer \(refused: MAG\[2\]\); "
                                            "record the compass again"):
        export_driver(none_left, "microstrain_inertial_driver")
    flipped = doc(480.0 * np.diag([1.0, -1.0, -1.0]), (0.0, 0.0, 0.0))
    with pytest.raises(FirmwareLimitError, match=r"cc_gain1=-2.083 is outside libphidget22's 0..15"):
        export_driver(flipped, "phidgets_spatial")


def test_every_number_reads_back_as_a_float() -> None:
    """A whole-number exponent (1e-05) is a string to YAML 1.1 readers: the files write 1.0e-05."""
    cal = doc(1e-5 * np.eye(3), (1e-5, -2e-6, 0.0), unit="tesla")
    g = yaml.safe_load(export_driver(cal, "generic").text)
    assert g["hard_iron"] == [1e-5, -2e-6, 0.0] and isinstance(g["field_strength"], float)


def test_effects_are_said_not_held() -> None:
    effect = {"id": "time_offset", "sensor": "MAG[0]", "status": "accepted", "params": {"tau_s": 0.02}}
    text = export_driver(doc(480.0 * np.eye(3), (0.0, 0.0, 0.0), effects=(effect,)), "phidgets_spatial").text
    assert "# NOT HELD: effect time_offset (accepted) is not held: phidgets_spatial has no parameter" in text


def test_cli_writes_the_file_and_refuses_bad_input(tmp_path: Path) -> None:
    cal = doc(480.0 * np.eye(3), (100.0, 0.0, 0.0), ids=("MAG[0]", "MAG[1]"),
              refused=({"id": "MAG[2]", "status": "refused", "reason": "dead"},))
    path = tmp_path / "cal.json"
    path.write_text(dumps_json(cal))
    out = tmp_path / "params.yaml"
    run = CliRunner().invoke
    result = run(cli, ["export", str(path), "--driver", "phidgets_spatial", "--mag", "MAG[1]", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert result.stdout == f"wrote {out} (phidgets_spatial, MAG[1])\n"
    assert ros_params(out.read_text())["cc_offset0"] == pytest.approx(0.1)
    result = run(cli, ["export", str(path), "--driver", "phidgets_spatial", "-o", str(tmp_path / "b.yaml")])
    assert result.exit_code == 1 and "choose one with --mag MAG[0]" in result.stderr
    result = run(cli, ["export", str(path), "--driver", "generic", "--mag", "MAG[2]", "-o", str(tmp_path / "c.yaml")])
    assert result.exit_code == 1 and "MAG[2] was refused (dead)" in result.stderr
    result = run(cli, ["export", str(path), "--driver", "nope", "-o", str(tmp_path / "d.yaml")])
    assert result.exit_code == 2 and "'nope' is not one of" in result.stderr
    result = run(cli, ["export", str(path), "--driver", "generic", "--mag", "MAG[0]"])
    assert result.exit_code == 2 and "--driver generic needs -o FILE" in result.stderr
    result = run(cli, ["export", str(path), "--driver", "generic", "--px4", "x.params", "-o", "y"])
    assert result.exit_code == 2 and "leave out --ardupilot, --px4" in result.stderr


def test_the_cli_lists_every_registered_driver() -> None:
    assert set(DRIVER_NAMES) == set(DRIVERS)
