"""CSV: the canonical and x-io headers, units, empty cells, optional columns, held values, errors, round trip.

Modules it covers (the mirrored test file aside): magcal_cli.readers.csvfile, magcal_cli.units.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal_cli.errors import LogReadError
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.simulate import simulate

CANONICAL = "t [s],gx [rad/s],gy [rad/s],gz [rad/s],ax [m/s^2],ay [m/s^2],az [m/s^2],mx [uT],my [uT],mz [uT]"


def write(tmp_path: Path, text: str, name: str = "log.csv") -> Path:
    """A CSV file with `text`."""
    path = tmp_path / name
    path.write_text(text)
    return path


def test_round_trip_within_quantisation(tmp_path: Path) -> None:
    """simulate -> CSV -> read: same sample times (1 us) and values (9 significant digits)."""
    sim = simulate("paper", 5, rate=80.0, mag_rate=40.0, duration=12.0, mag_phase_s=0.0)    # CSV: IMU rows
    write_log(sim, tmp_path / "s.csv")
    rec = open_recording(tmp_path / "s.csv")
    assert rec.format == "csv"
    ids = {Kind.ACCELEROMETER: "imu", Kind.GYROSCOPE: "imu", Kind.MAGNETOMETER: "mag"}
    for s in sim.recording.streams:
        got = rec.select(s.kind, ids[s.kind])
        assert len(got) == len(s)
        np.testing.assert_allclose(got.t, s.t, atol=1e-6, rtol=0)
        np.testing.assert_allclose(got.values, s.values, rtol=1e-8, atol=1e-15)
    assert rec.select(Kind.MAGNETOMETER).native_unit == "microtesla"
    assert rec.notes == ()


def test_fit_recovers_the_truth_from_csv(tmp_path: Path) -> None:
    """The pipeline on a simulated CSV: |dD|/|D| < 5 %, |do| < 1 % of the field; document in microtesla."""
    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate

    sim = simulate("handheld", 3, rate=25.0, mag_rate=12.5, mag_phase_s=0.0)               # CSV: IMU rows
    write_log(sim, tmp_path / "h.csv")
    mag = calibrate(tmp_path / "h.csv", Config()).calibration.magnetometers[0]
    assert mag.unit == "microtesla"
    d, o = mag.D * 1e-6, mag.o * 1e-6
    assert np.linalg.norm(d - sim.truth.D) / np.linalg.norm(sim.truth.D) < 0.05
    assert np.linalg.norm(o - sim.truth.o) / sim.truth.field_strength < 0.01


@pytest.mark.parametrize(("unit", "native", "si"), [("T", "tesla", 1.0), ("mT", "millitesla", 1e-3),
                                                    ("uT", "microtesla", 1e-6), ("nT", "nanotesla", 1e-9),
                                                    ("G", "gauss", 1e-4), ("mG", "milligauss", 1e-7)])
def test_field_units(tmp_path: Path, unit: str, native: str, si: float) -> None:
    """Every field unit of the contract converts to tesla and is kept as the native unit."""
    path = write(tmp_path, f"t [ms],mx [{unit}],my ({unit}),mz [{unit}]\n0,1,2,3\n10,4,5,6\n")
    mag = open_recording(path).select(Kind.MAGNETOMETER, "mag")
    assert mag.native_unit == native
    np.testing.assert_allclose(mag.values, [[si, 2 * si, 3 * si], [4 * si, 5 * si, 6 * si]], rtol=1e-15)
    np.testing.assert_allclose(mag.t, [0.0, 0.01])


def test_xio_header_and_other_spellings(tmp_path: Path) -> None:
    """x-io's 'Gyroscope X (deg/s)', 'gyro_x [deg/s]', 'Accelerometer X (g)', 'Time (us)' are recognised."""
    text = ("Time (us),gyro_x [deg/s],Gyro Y [deg/s],GYR_Z [deg/s],Accelerometer X (g),Accelerometer Y (g),"
            "Accelerometer Z (g),Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT),quaternion w\n"
            "0,180,0,0,0,0,1,10,20,30,1\n"
            "10000,0,-90,0,0,0,-1,,,,1\n")
    rec = open_recording(write(tmp_path, text))
    gyr, acc, mag = (rec.select(k, i) for k, i in ((Kind.GYROSCOPE, "imu"), (Kind.ACCELEROMETER, "imu"),
                                                    (Kind.MAGNETOMETER, "mag")))
    np.testing.assert_allclose(gyr.values, [[np.pi, 0, 0], [0, -np.pi / 2, 0]])
    np.testing.assert_allclose(acc.values[:, 2], [9.80665, -9.80665])
    np.testing.assert_allclose(gyr.t, [0.0, 0.01])
    assert len(mag) == 1                                   # the empty cells are no sample
    assert (gyr.native_unit, acc.native_unit) == ("deg/s", "g")
    assert rec.notes == ("ignored columns: quaternion w",)


def test_optional_columns(tmp_path: Path) -> None:
    """temperature [degC], current [A], voltage [V] and throttle [1] (or no unit) become their streams."""
    text = "t [s],gx [rad/s],gy [rad/s],gz [rad/s],temperature [degC],current [A],voltage [V],throttle\n"
    text += "0,0,0,0,25.5,3.0,12.1,0.4\n0.1,0,0,0,,3.5,12.0,0.5\n"
    rec = open_recording(write(tmp_path, text))
    assert rec.select(Kind.TEMPERATURE, "temperature").values[:, 0].tolist() == [25.5]
    assert rec.select(Kind.BATTERY_CURRENT, "battery").values[:, 0].tolist() == [3.0, 3.5]
    assert rec.select(Kind.BATTERY_VOLTAGE, "battery").values[:, 0].tolist() == [12.1, 12.0]
    assert rec.select(Kind.THROTTLE, "throttle").values[:, 0].tolist() == [0.4, 0.5]


def test_partial_rows_unsorted_and_duplicate_times_are_reported(tmp_path: Path) -> None:
    """A row with some gyro cells empty is dropped and counted; unsorted and repeated times are cleaned."""
    text = "t [s],gx [rad/s],gy [rad/s],gz [rad/s]\n0,1,1,1\n0.2,3,3,3\n0.1,2,2,\n0.1,2,2,2\n0.1,9,9,9\n0.3,4,4,4\n"
    rec = open_recording(write(tmp_path, text))
    gyr = rec.select(Kind.GYROSCOPE)
    assert gyr.t.tolist() == [0.0, 0.1, 0.2, 0.3]
    assert gyr.values[:, 0].tolist() == [1.0, 2.0, 3.0, 4.0]
    assert rec.notes == ("imu gyroscope: dropped 1 rows with some gyroscope cells or the time empty",
                         "imu gyroscope: 1 timestamps went backwards; samples were sorted by time",
                         "imu gyroscope: dropped 1 samples with duplicated timestamps")


def test_held_field_values_are_dropped(tmp_path: Path) -> None:
    """A field repeated row after row (a 20 Hz sensor in 100 Hz rows) keeps only the rows where it changed."""
    rows = [f"{k * 0.01:.2f},{k // 5},1,1" for k in range(50)]
    rec = open_recording(write(tmp_path, "t [s],mx [uT],my [uT],mz [uT]\n" + "\n".join(rows) + "\n"))
    mag = rec.select(Kind.MAGNETOMETER)
    np.testing.assert_allclose(mag.t, np.arange(10) * 0.05, atol=1e-12)
    assert rec.notes == ("mag: 40 of 50 readings repeat the previous one exactly (the source holds its last "
                         "value between updates); kept the 10 that changed",)


@pytest.mark.parametrize(("text", "message"), [
    ("t [s],gx,gy [rad/s],gz [rad/s]\n0,1,2,3\n",
     "log.csv: column 'gx' declares no unit; write it as 'gx [unit]' with one of: rad/s, deg/s"),
    ("t [s],gx [rpm],gy [rpm],gz [rpm]\n0,1,2,3\n",
     "log.csv: column 'gx [rpm]': 'rpm' is not a gyroscope unit magcal knows; use one of: rad/s, deg/s"),
    ("t [s],mx [m/s^2],my [uT],mz [uT]\n0,1,2,3\n",
     "log.csv: column 'mx [m/s^2]': 'm/s^2' is not a magnetometer unit magcal knows; use one of: tesla, "),
    ("t [s],gx [rad/s],gy [rad/s]\n0,1,2\n",
     "log.csv: the gyroscope columns are gx [rad/s], gy [rad/s]; give each axis exactly once (x, y and z)"),
    ("t [s],mx [uT],my [uT],mz [G]\n0,1,2,3\n",
     "log.csv: the magnetometer columns declare different units (mx [uT], my [uT], mz [G])"),
    ("gx [rad/s],gy [rad/s],gz [rad/s]\n1,2,3\n",
     "log.csv: no time column in the header; name it 't [s]' (canonical header: t [s],gx [rad/s]"),
    ("t [s],speed [m/s]\n0,1\n",
     "log.csv: no gyroscope, accelerometer or magnetometer columns in the header; expected e.g. t [s],gx"),
    ("t [s],gx [rad/s],gy [rad/s],gz [rad/s]\n0,1,2,3\n0.1,1,2,x\n",
     "log.csv: line 3: could not convert string 'x' to a number. Fix or delete that row"),
    ("t [s],gx [rad/s],gy [rad/s],gz [rad/s]\n0,1,2,3\n0.1,1,2\n",
     "log.csv: line 3: the number of columns changed from 4 to 3. Fix or delete that row"),
    ("t [s],gx [rad/s],gy [rad/s],gz [rad/s]\n",
     "log.csv: the CSV file has a header but no rows"),
    ("t [s],gx [rad/s],gy [rad/s],gz [rad/s]\n0,1,2,3,4\n",
     "log.csv: rows have 5 cells but the header names 4 columns; make the header and the rows agree"),
    ("t [s];gx [rad/s];gy [rad/s];gz [rad/s]\n0;1;2;3\n",
     "log.csv: the header is not comma-separated; magcal reads comma-separated files (CSV)"),
    ("# exported by a tool\n\n", "log.csv: no header line; the first line must name the columns"),
])
def test_errors_name_the_cell_and_the_fix(tmp_path: Path, text: str, message: str) -> None:
    """Every header or table problem is a one-line LogReadError that names the column or line."""
    path = write(tmp_path, text)
    with pytest.raises(LogReadError) as info:
        open_recording(path)
    assert str(info.value).startswith(f"{tmp_path}/{message}")


def test_comment_lines_before_the_header_and_crlf(tmp_path: Path) -> None:
    """'#' comment lines before the header are skipped; Windows line ends read the same; errors count lines."""
    path = write(tmp_path, "# device 42\r\nt [s],gx [rad/s],gy [rad/s],gz [rad/s]\r\n0,1,2,3\r\n0.1,,,\r\n0.2,1,2,y\r\n")
    with pytest.raises(LogReadError, match=r"log.csv: line 5: could not convert string 'y'"):
        open_recording(path)
    path.write_text("# device 42\r\nt [s],gx [rad/s],gy [rad/s],gz [rad/s]\r\n0,1,2,3\r\n0.1,,,\r\n0.2,1,2,3\r\n")
    assert len(open_recording(path).select(Kind.GYROSCOPE)) == 2


# --- the real x-io file of ../shared/realdata/csv -------------------------------------------------------------

def test_real_xio_sensor_data(realdata: Path) -> None:
    """x-io Fusion example: 100 Hz gyro (deg/s) and accelerometer (g), 135 s; the field held between ~20 Hz updates."""
    rec = open_recording(realdata / "csv" / "sensor_data.csv")
    gyr, acc = rec.select(Kind.GYROSCOPE, "imu"), rec.select(Kind.ACCELEROMETER, "imu")
    mag = rec.select(Kind.MAGNETOMETER, "mag")
    assert len(gyr) == len(acc) == 13514
    assert (len(gyr) - 1) / (gyr.t[-1] - gyr.t[0]) == pytest.approx(99.9, abs=0.05)
    assert gyr.t[-1] == pytest.approx(135.3, abs=0.05)
    assert (gyr.native_unit, acc.native_unit, mag.native_unit) == ("deg/s", "g", "microtesla")
    assert len(mag) == 2669
    assert rec.notes == ("mag: 10845 of 13514 readings repeat the previous one exactly (the source holds its last "
                         "value between updates); kept the 2669 that changed",)
    assert 40e-6 < np.median(np.linalg.norm(mag.xyz, axis=1)) < 47e-6


def test_real_xio_fit_is_a_partial_calibration(realdata: Path) -> None:
    """Its field directions cover half the sphere and do not fit an ellipsoid (37-51 uT along a handheld path):
    magcal used to refuse it; now it starts from a sphere fit, holds what the motion cannot determine, says so
    in the document, and the calibrated field strength varies less than 10 % RMS. D and o are held at the sphere
    fit; with the gyro's own noise in motion counted (issue 25), the accelerometer's x bias is held too, at the
    factory calibration's zero."""
    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate

    m = calibrate(realdata / "csv" / "sensor_data.csv", Config()).calibration.magnetometers[0]
    assert m.held and all(h["held"] is True for h in m.held)
    calibration = [h for h in m.held if not h["parameter"].startswith("imu.")]
    assert calibration and all("sphere fit" in h["source"] for h in calibration)
    assert all("factory calibration" in h["source"] for h in m.held if h["parameter"].startswith("imu."))
    assert m.quality is not None and m.quality.field_norm_rms_pct < 10.0
