"""`magcal inspect`: the table and --json on simulated and real logs, the parameters row, one-line errors.

Modules it covers (the mirrored test file aside): magcal_cli.cli.inspect, magcal_cli.readers.checks.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.readers.inspect import rows, to_dict, to_table
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.simulate import simulate


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 12 s simulated ROS 1 bag (80 Hz IMU, 40 Hz field)."""
    path = tmp_path_factory.mktemp("inspect") / "sim.bag"
    write_log(simulate("paper", 6, rate=80.0, mag_rate=40.0, duration=12.0), path)
    return path


def run(*args: str) -> tuple[int, str, str]:
    """Exit code, stdout and stderr of `magcal inspect ...`."""
    result = CliRunner().invoke(cli, ["inspect", *args])
    return result.exit_code, result.stdout, result.stderr


def test_table(bag: Path) -> None:
    """The human table: a title, one row per stream with count, rate, span, units and the topic's source (the field's
    own span: it starts at its phase, 2.5 ms after the IMU for this seed)."""
    code, out, _ = run(str(bag))
    assert code == 0
    lines = out.splitlines()
    assert lines[0].startswith("sim.bag: rosbag, 3 streams, t0 = 1763700000.000000 s (log clock)")
    assert lines[1].split() == ["id", "kind", "count", "rate", "Hz", "start", "s", "end", "s", "units", "source"]
    mag = next(ln for ln in lines if "magnetometer" in ln).split()
    assert mag[:7] == ["/imu/mag", "magnetometer", "480", "40.0", "0.002", "11.977", "tesla"]
    assert " ".join(mag[7:]) == "/imu/mag [sensor_msgs/msg/MagneticField magnetic_field]"


def test_json(bag: Path) -> None:
    """--json is one document that json.loads reads: streams with every column, notes, parameters."""
    code, out, _ = run(str(bag), "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["format"] == "rosbag" and doc["log"].endswith("sim.bag") and doc["notes"] == []
    by_kind = {s["kind"]: s for s in doc["streams"]}
    assert set(by_kind) == {"accelerometer", "gyroscope", "magnetometer"}
    acc = by_kind["accelerometer"]
    assert acc == {"id": "/imu/data", "kind": "accelerometer", "count": 960, "rate_hz": pytest.approx(80.0),
                   "start_s": 0.0, "end_s": pytest.approx(11.9875), "units": "m/s^2",
                   "source": "/imu/data [sensor_msgs/msg/Imu linear_acceleration, angular_velocity]"}


def test_parameters_row_and_notes() -> None:
    """A recording with firmware parameters gets a `parameters` row; notes follow the table."""
    s = Stream(Kind.MAGNETOMETER, "MAG[0]", np.arange(3.0), np.ones((3, 3)), "log.bin#MAG", "milligauss")
    rec = Recording(Path("log.bin"), "dataflash", (s,), params={"COMPASS_OFS_X": 10.0, "COMPASS_DEC": 0.1},
                    notes=("undid COMPASS_OFS",))
    last = rows(rec)[-1]
    assert (last.id, last.kind, last.count, last.rate_hz) == ("parameters", "parameters", 2, None)
    table = to_table(rec)
    row = next(ln for ln in table.splitlines() if ln.startswith("parameters"))
    assert row.split() == ["parameters", "parameters", "2", "-", "-", "-", "firmware", "parameters", "(last",
                           "value", "of", "each)"]
    assert table.endswith("notes:\n  - undid COMPASS_OFS")
    assert to_dict(rec)["parameters"] == {"COMPASS_OFS_X": 10.0, "COMPASS_DEC": 0.1}
    json.dumps(to_dict(rec), allow_nan=False)


def test_errors_are_one_line(tmp_path: Path) -> None:
    """An unreadable log exits 1 with one `Error:` line on stderr and nothing on stdout."""
    (tmp_path / "notes.txt").write_text("hello")
    code, out, err = run(str(tmp_path / "notes.txt"))
    assert code == 1 and out == ""
    assert err.startswith(f"Error: {tmp_path / 'notes.txt'}: unrecognised log format") and err.count("\n") == 1
    code, _, err = run(str(tmp_path / "missing.bag"))
    assert code == 2 and "does not exist" in err


def test_receive_time_flag(bag: Path) -> None:
    """--receive-time is accepted (the simulated bag records at the header stamps, so t0 is the same)."""
    code, out, _ = run(str(bag), "--json", "--receive-time")
    assert code == 0 and json.loads(out)["t0_s"] == pytest.approx(1763700000.0)


# --- every real ROS and CSV log, as ../shared/realdata/README.md describes it -----------------------------------

REAL = {
    "ros/phidgets_imu_upside_down.bag": [("/imu/data_raw", "accelerometer", 13964, 248.3, "m/s^2"),
                                         ("/imu/data_raw", "gyroscope", 13964, 248.3, "rad/s"),
                                         ("/imu/mag", "magnetometer", 6974, 124.0, "tesla")],
    "ros/phidgets_imu_upside_down_legacy_Vector3Stamped.bag": [
        ("/imu/data_raw", "accelerometer", 13964, 248.3, "m/s^2"), ("/imu/data_raw", "gyroscope", 13964, 248.3, "rad/s"),
        ("/imu/mag", "magnetometer", 6974, 124.0, "gauss")],
    "ros/phidgets_imu_upside_down_mcap": [("/imu/data_raw", "accelerometer", 13964, 248.3, "m/s^2"),
                                          ("/imu/data_raw", "gyroscope", 13964, 248.3, "rad/s"),
                                          ("/imu/mag", "magnetometer", 6974, 124.0, "tesla")],
    "ros/ardrone_imu.bag": [("/ardrone/imu", "accelerometer", 4308, 46.6, "m/s^2"),
                            ("/ardrone/imu", "gyroscope", 4308, 46.6, "rad/s"),
                            ("/ardrone/mag", "magnetometer", 4308, 46.6, "tesla")],
    "ros/sparkfun_razor.bag": [("/imu/data_raw", "accelerometer", 2144, 69.0, "m/s^2"),
                               ("/imu/data_raw", "gyroscope", 2144, 69.0, "rad/s"),
                               ("/imu/mag", "magnetometer", 107, 3.4, "tesla")],
    "ros/sparkfun_razor_sqlite3": [("/imu/data_raw", "accelerometer", 2144, 69.0, "m/s^2"),
                                   ("/imu/data_raw", "gyroscope", 2144, 69.0, "rad/s"),
                                   ("/imu/mag", "magnetometer", 107, 3.4, "tesla")],
    "csv/sensor_data.csv": [("imu", "gyroscope", 13514, 99.9, "deg/s"), ("imu", "accelerometer", 13514, 99.9, "g"),
                            ("mag", "magnetometer", 2669, 19.7, "microtesla")],
}


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_logs(realdata: Path, name: str) -> None:
    """Streams, counts, rates and units of every real ROS/CSV log; NaN and held field samples said in notes."""
    code, out, err = run(str(realdata / name), "--json")
    assert code == 0, err
    doc = json.loads(out)
    got = [(s["id"], s["kind"], s["count"], round(s["rate_hz"], 1), s["units"]) for s in doc["streams"]]
    assert got == REAL[name]
    notes = " | ".join(doc["notes"])
    if "phidgets" in name:
        assert "/imu/mag: dropped 6990 samples with NaN or inf" in notes
    if "ardrone" in name or "sparkfun" in name:
        assert "normalised to a unit vector upstream" in notes


def test_every_real_ros_and_csv_file_reads_or_fails_in_one_line(realdata: Path) -> None:
    """Every log in ros/ and csv/ is pinned above; the other files (licences) fail in one line, exit 1."""
    files = sorted([*(realdata / "ros").iterdir(), *(realdata / "csv").iterdir()])
    others = [p for p in files if str(p.relative_to(realdata)) not in REAL]
    assert len(files) - len(others) == len(REAL)
    for path in others:
        code, out, err = run(str(path))
        assert code == 1 and out == "", path
        assert err.startswith(f"Error: {path}: unrecognised log format") and err.count("\n") == 1


@pytest.mark.parametrize("name", ["handheld.bag", "handheld_ros2", "handheld.csv"])
def test_sample_logs(name: str) -> None:
    """The shipped sample logs of the ROS and CSV formats read: 50 Hz IMU, 25 Hz field, the truth's span."""
    root = Path(__file__).resolve().parents[2] / "sample_logs"
    code, out, err = run(str(root / name), "--json")
    assert code == 0, err
    truth = json.loads((root / f"{name}.truth.json").read_text())
    streams = {s["kind"]: s for s in json.loads(out)["streams"]}
    assert round(streams["accelerometer"]["rate_hz"]) == 50 and round(streams["magnetometer"]["rate_hz"]) == 25
    assert streams["accelerometer"]["end_s"] == pytest.approx(truth["source"]["end_s"], abs=1e-6)
