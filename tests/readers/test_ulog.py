"""PX4 ULog: simulator round trip, topic variants built in code, every error message, the real logs, fits.

Modules it covers (the mirrored test file aside): magcal_cli.readers.ulog.load, magcal_cli.readers.ulog.reader,
magcal_cli.readers.ulog.sensors, magcal_cli.readers.ulog.vehicle, magcal_cli.streams.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.errors import LogReadError, MagcalError, StreamError
from magcal_cli.pipeline import calibrate
from magcal_cli.readers import ReadOptions, open_recording, sniff
from magcal_cli.readers.ulog.load import STUCK_READS, GuardFile, StuckError
from magcal_cli.readers.ulog.sensors import device_text
from magcal_cli.streams import Kind, Recording, Sampling
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.logs.ulog import START_US, Topic, UlogContent, sim_content, ulog_bytes, write_content
from magcal_cli.synth.simulate import Simulation, simulate

ROOT = Path(__file__).resolve().parents[2]
GAUSS = 1e-4
HEADER = b"ULog\x01\x12\x35\x01" + bytes(8)
STAMPS = (("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"))
XYZ_T = (("float", "x"), ("float", "y"), ("float", "z"), ("float", "temperature"))


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A short handheld simulation at the sample log's rates (sensor_combined's samples: PRECEDING)."""
    return simulate("handheld", 2, rate=50.0, mag_rate=25.0, duration=40.0, imu_sampling=Sampling.PRECEDING)


@pytest.fixture(scope="module")
def sim_bytes(sim: Simulation) -> bytes:
    """The simulation as a .ulg file's bytes."""
    return ulog_bytes(sim_content(sim))


def write(tmp_path: Path, data: bytes, name: str = "log.ulg") -> Path:
    """Bytes to a file in tmp_path."""
    path = tmp_path / name
    path.write_bytes(data)
    return path


def read(path: Path, **options: bool) -> Recording:
    """open_recording with ReadOptions."""
    return open_recording(path, None, ReadOptions(**options))


def log(tmp_path: Path, *topics: Topic, name: str = "log.ulg", **content: object) -> Recording:
    """Write the topics as a ULog and read it back."""
    return read(write(tmp_path, ulog_bytes(UlogContent(list(topics), **content)), name))  # type: ignore[arg-type]


def times(n: int, period_us: int, offset_us: int = 0) -> np.ndarray:
    """n evenly spaced log times (us) from the log start."""
    return START_US + offset_us + period_us * np.arange(n, dtype=np.int64)


def xyz_topic(name: str, t: np.ndarray, xyz: np.ndarray, instance: int = 0, device_id: int = 2424842,
              temperature: float = 40.0) -> Topic:
    """sensor_mag / sensor_accel / sensor_gyro as modern PX4 logs them (sampled 200 us before publication)."""
    n = len(t)
    data = {"timestamp": t + 200, "timestamp_sample": t, "device_id": np.full(n, device_id), "x": xyz[:, 0],
            "y": xyz[:, 1], "z": xyz[:, 2], "temperature": np.full(n, temperature)}
    return Topic(name, STAMPS + XYZ_T, data, instance)


def mag_topic(t: np.ndarray, xyz: np.ndarray, instance: int = 0, device_id: int = 396809) -> Topic:
    """sensor_mag in gauss with NaN temperature, as drivers without a temperature sensor log it."""
    return xyz_topic("sensor_mag", t, xyz, instance, device_id, np.nan)


def combined_topic(t: np.ndarray, gyr: np.ndarray, acc: np.ndarray, acc_rel: np.ndarray | None = None,
                   mag: np.ndarray | None = None, mag_rel: np.ndarray | None = None) -> Topic:
    """sensor_combined, optionally with the old magnetometer_ga fields."""
    fields = [("uint64_t", "timestamp"), ("float[3]", "gyro_rad"),
              ("int32_t", "accelerometer_timestamp_relative"), ("float[3]", "accelerometer_m_s2")]
    data = {"timestamp": t, "gyro_rad": gyr, "accelerometer_m_s2": acc,
            "accelerometer_timestamp_relative": np.zeros(len(t)) if acc_rel is None else acc_rel}
    if mag is not None:
        fields += [("int32_t", "magnetometer_timestamp_relative"), ("float[3]", "magnetometer_ga")]
        data |= {"magnetometer_ga": mag, "magnetometer_timestamp_relative": mag_rel}
    return Topic("sensor_combined", tuple(fields), data)


def still_imu(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gyro and accelerometer samples of a level vehicle at rest."""
    return np.zeros((n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1))


# --- round trip ------------------------------------------------------------------------------------------


def test_round_trip_same_streams_within_float32(tmp_path: Path, sim: Simulation) -> None:
    """simulate -> .ulg -> read: same times (integer us) and values within float32 rounding, in SI."""
    path = tmp_path / "sim.ulg"
    write_log(sim, path)
    assert sniff(path) == "ulog"
    rec = read(path)
    src = sim.recording
    for kind, new_id in ((Kind.ACCELEROMETER, "sensor_combined"), (Kind.GYROSCOPE, "sensor_combined"),
                         (Kind.MAGNETOMETER, "sensor_mag[0]")):
        a, b = src.select(kind), rec.select(kind, new_id)
        np.testing.assert_allclose(b.t, a.t, atol=0.6e-6)              # us stamps, t0 = the log start
        np.testing.assert_allclose(b.values, a.values, rtol=2**-23, atol=1e-30)
    assert rec.select(Kind.MAGNETOMETER).native_unit == "gauss"
    att = rec.select(Kind.ATTITUDE, "vehicle_attitude")
    np.testing.assert_allclose(att.values, so3.as_quat(sim.rotations[: len(att)]), atol=1e-7)
    np.testing.assert_array_equal(rec.select(Kind.TEMPERATURE, "sensor_mag[0]").values, 25.0)
    assert rec.t0 == START_US * 1e-6
    assert rec.params["CAL_MAG0_ID"] == rec.params["sensor_mag[0].device_id"] == 396804
    assert rec.params["CAL_MAG0_XSCALE"] == 1.0
    assert any("calibration slot CAL_MAG0_*" in n for n in rec.notes)


def test_writer_output_is_a_clean_ulog_written_atomically(tmp_path: Path, sim_bytes: bytes) -> None:
    """pyulog finds no corruption in the interleaved records; no temporary file is left behind."""
    from pyulog import ULog

    u = ULog(io.BytesIO(sim_bytes))
    assert not u.file_corruption
    assert sorted(d.name for d in u.data_list) == ["sensor_combined", "sensor_mag", "vehicle_attitude"]
    write_content(UlogContent([]), tmp_path / "empty.ulg")
    assert [p.name for p in tmp_path.iterdir()] == ["empty.ulg"]


# --- topic variants --------------------------------------------------------------------------------------


def test_multi_instance_mags_and_parameter_changes(tmp_path: Path) -> None:
    """sensor_mag[0] and [1] are separate streams with their device ids; params keep the last value."""
    t = times(50, 20_000)
    gyr, acc = still_imu(200)
    field = np.tile([0.2, 0.0, 0.4], (50, 1))
    rec = log(tmp_path, combined_topic(times(200, 5_000), gyr, acc), mag_topic(t, field, 0, 589858),
              mag_topic(t + 7, field * 2, 1, 592905),
              params={"CAL_MAG0_ID": 592905, "CAL_MAG1_ID": 589858, "CAL_MAG0_XOFF": 0.0},
              changed_params=[(int(t[10]), "CAL_MAG0_XOFF", 0.05)])
    assert rec.ids(Kind.MAGNETOMETER) == ["sensor_mag[0]", "sensor_mag[1]"]
    np.testing.assert_allclose(rec.select(Kind.MAGNETOMETER, "sensor_mag[1]").xyz[0], [0.4e-4, 0, 0.8e-4],
                               rtol=1e-7)
    assert rec.params["CAL_MAG0_XOFF"] == pytest.approx(0.05)
    assert rec.params["sensor_mag[1].device_id"] == 592905
    assert f"sensor_mag[0]: {device_text(589858)}, calibration slot CAL_MAG1_*" in rec.notes
    assert any("calibration parameters changed during the log (CAL_MAG0_XOFF)" in n for n in rec.notes)
    assert not rec.of_kind(Kind.TEMPERATURE)                         # all-NaN temperature: no stream


def test_device_id_in_words() -> None:
    """DeviceStructure: bus type 3 bits, bus 5 bits, address, devtype (the roboto log's first compass)."""
    assert device_text(396825) == "device_id 396825 (0x060e19: I2C bus 3, address 0x0e, devtype 0x06)"


def test_separate_accel_and_gyro_are_interpolated_onto_the_gyro_stamps(tmp_path: Path) -> None:
    """sensor_accel[i]/sensor_gyro[i] form IMU sensor_accel[i]; a linear signal interpolates exactly."""
    tg, ta = times(100, 4_000), times(60, 6_700, offset_us=1_500)
    rec = log(tmp_path, xyz_topic("sensor_gyro", tg, np.zeros((100, 3))),
              xyz_topic("sensor_accel", ta, np.stack([(ta - START_US) * 1e-6] * 3, axis=1)))
    acc = rec.select(Kind.ACCELEROMETER, "sensor_accel[0]")
    gyr = rec.select(Kind.GYROSCOPE, "sensor_accel[0]")
    np.testing.assert_array_equal(acc.t, gyr.t)
    assert acc.t[0] >= 0.0015 and acc.t[-1] <= (ta[-1] - START_US) * 1e-6
    np.testing.assert_allclose(acc.values[:, 0], acc.t, atol=1e-6)
    assert any("gyro epochs have no accelerometer samples on both sides" in n for n in rec.notes)
    assert rec.params["sensor_accel[0].device_id"] == 2424842
    assert rec.select(Kind.TEMPERATURE, "sensor_accel[0]").values[0, 0] == 40.0


def test_unpaired_accel_and_gyro_are_named(tmp_path: Path) -> None:
    """An accelerometer without the gyro of its instance is reported, not paired with another IMU's gyro."""
    t = times(20, 10_000)
    rec = log(tmp_path, xyz_topic("sensor_accel", t, np.zeros((20, 3)), 1),
              xyz_topic("sensor_gyro", t, np.zeros((20, 3))))
    assert not rec.of_kind(Kind.ACCELEROMETER)
    assert "sensor_accel[1]: no sensor_gyro[1] to pair it with, so it is not usable as an IMU" in rec.notes
    assert "sensor_gyro[0]: no sensor_accel[0] to pair it with, so it is not usable as an IMU" in rec.notes


def test_sensor_combined_accelerometer_offset_is_interpolated(tmp_path: Path) -> None:
    """accelerometer_timestamp_relative != 0: the accelerometer moves onto the gyro's stamps."""
    t = times(100, 4_000)
    rel = np.full(100, -2_000)
    acc = np.stack([(t + rel - START_US) * 1e-6] * 3, axis=1)
    rec = log(tmp_path, combined_topic(t, np.zeros((100, 3)), acc, rel))
    a = rec.select(Kind.ACCELEROMETER, "sensor_combined")
    assert rec.t0 == (START_US - 2_000) * 1e-6                       # the earliest stamp: an accelerometer's
    np.testing.assert_allclose(a.values[:, 0], a.t - 0.002, atol=1e-6)
    assert "sensor_combined: accelerometer interpolated onto the gyro's time stamps" in rec.notes


def test_old_sensor_combined_field_keeps_one_row_per_magnetometer_stamp(tmp_path: Path) -> None:
    """magnetometer_ga repeats in every IMU message; rows are kept where the field's own stamp changes."""
    t = times(40, 4_000)
    mag_t = START_US + 10_000 * ((t - START_US) // 10_000)            # a 100 Hz field in a 250 Hz topic
    mag = np.stack([mag_t * 1e-9, np.zeros(40), np.full(40, 0.4)], axis=1)
    gyr, acc = still_imu(40)
    rec = log(tmp_path, combined_topic(t, gyr, acc, mag=mag, mag_rel=mag_t - t))
    m = rec.select(Kind.MAGNETOMETER, "sensor_combined")
    assert len(m) == len(np.unique(mag_t)) == 16
    np.testing.assert_allclose(m.t, (np.unique(mag_t) - START_US) * 1e-6)
    assert any("magnetometer_ga is the firmware-calibrated field in the body frame" in n for n in rec.notes)


def test_vehicle_magnetometer_only_when_no_raw_field(tmp_path: Path) -> None:
    """The calibrated vehicle_magnetometer is read, with a note, only when no raw sensor_mag is logged."""
    t = times(30, 20_000)
    vm = Topic("vehicle_magnetometer", STAMPS + (("float[3]", "magnetometer_ga"),),
               {"timestamp": t, "timestamp_sample": t, "device_id": np.zeros(30),
                "magnetometer_ga": np.ones((30, 3))})
    rec = log(tmp_path, vm)
    assert rec.ids(Kind.MAGNETOMETER) == ["vehicle_magnetometer[0]"]
    assert any("vehicle_magnetometer is the firmware-calibrated field" in n for n in rec.notes)
    both = log(tmp_path, vm, mag_topic(times(5, 1_000_000), np.ones((5, 3))), name="both.ulg")
    assert both.ids(Kind.MAGNETOMETER) == ["sensor_mag[0]"]
    assert any("SDLOG_PROFILE bit 6 (sensor comparison)" in n for n in both.notes)   # 1 Hz: raw but slow


def test_legacy_driver_corrected_sensor_mag_is_said(tmp_path: Path) -> None:
    """PX4 <= 1.10 sensor_mag (with x_raw..) carries the driver's offsets and scales; the note says so."""
    t = times(10, 20_000)
    topic = mag_topic(t, np.ones((10, 3)))
    legacy = Topic("sensor_mag", (*topic.fields, ("int16_t", "x_raw")), {**topic.data, "x_raw": np.zeros(10)})
    rec = log(tmp_path, legacy)
    assert any("logs x, y, z with the driver's CAL_MAG offsets and scales applied" in n for n in rec.notes)


def test_gps_scaling_old_and_new_and_no_fix(tmp_path: Path) -> None:
    """int32 lat/lon in 1e-7 deg and alt in mm (old) or doubles in deg and m (new); (0, 0) is no fix."""
    t = times(3, 200_000)
    old = Topic("vehicle_gps_position", (("uint64_t", "timestamp"), ("int32_t", "lat"), ("int32_t", "lon"),
                                         ("int32_t", "alt")),
                {"timestamp": t, "lat": [0, 473977419, 473977420], "lon": [0, 85455939, 85455940],
                 "alt": [0, 488004, 488010]})
    rec = log(tmp_path, old)
    pos = rec.select(Kind.POSITION, "vehicle_gps_position")
    np.testing.assert_allclose(pos.values[0], [47.3977419, 8.5455939, 488.004])
    assert len(pos) == 2 and "vehicle_gps_position: dropped 1 samples at lat = lon = 0 (no fix)" in rec.notes
    new = Topic("sensor_gps", (("uint64_t", "timestamp"), ("double", "latitude_deg"),
                               ("double", "longitude_deg"), ("double", "altitude_msl_m")),
                {"timestamp": t, "latitude_deg": [47.5, 47.5, 47.5], "longitude_deg": [8.5] * 3,
                 "altitude_msl_m": [400.25] * 3})
    rec = log(tmp_path, new, name="new.ulg")
    np.testing.assert_allclose(rec.select(Kind.POSITION, "sensor_gps[0]").values[-1], [47.5, 8.5, 400.25])


def test_battery_current_minus_one_means_not_measured(tmp_path: Path) -> None:
    """battery_status.current_a = -1 is 'unknown' (msg/BatteryStatus.msg): no current stream, voltage kept."""
    t = times(5, 200_000)
    bat = Topic("battery_status", (("uint64_t", "timestamp"), ("float", "voltage_v"), ("float", "current_a")),
                {"timestamp": t, "voltage_v": np.full(5, 16.2), "current_a": np.full(5, -1.0)})
    rec = log(tmp_path, bat)
    assert not rec.of_kind(Kind.BATTERY_CURRENT)
    assert rec.select(Kind.BATTERY_VOLTAGE, "battery_status[0]").values[0, 0] == pytest.approx(16.2)
    assert "battery_status[0]: current_a is -1 throughout (no current sensor); no current stream" in rec.notes


def test_timestamp_sample_or_publication_time(tmp_path: Path) -> None:
    """timestamp_sample by default; --receive-time takes the publication time; implausible ones fall back."""
    t = times(30, 20_000)
    path = write(tmp_path, ulog_bytes(UlogContent([mag_topic(t, np.ones((30, 3)))])))
    np.testing.assert_allclose(read(path).select(Kind.MAGNETOMETER).t, (t - START_US) * 1e-6)
    late = read(path, receive_time=True).select(Kind.MAGNETOMETER).t
    np.testing.assert_allclose(late, (t + 200 - START_US) * 1e-6)
    bad = mag_topic(t, np.ones((30, 3)))
    bad = Topic(bad.name, bad.fields, {**bad.data, "timestamp_sample": np.zeros(30)})
    rec = log(tmp_path, bad, name="b.ulg")
    assert ("sensor_mag[0]: timestamp_sample is zero or not within 1 s before timestamp; used timestamp"
            in rec.notes)


def test_nan_samples_and_dropouts_are_reported(tmp_path: Path) -> None:
    """NaN rows are dropped by align.clean_time and counted; logger dropouts are summed."""
    t = times(30, 20_000)
    xyz = np.ones((30, 3))
    xyz[[3, 7]] = np.nan
    rec = log(tmp_path, mag_topic(t, xyz), dropouts=[(int(t[5]), 30), (int(t[9]), 12)])
    assert len(rec.select(Kind.MAGNETOMETER)) == 28
    assert "sensor_mag[0]: dropped 2 samples with NaN or inf" in rec.notes
    assert "the logger dropped data 2 times (42 ms in total); samples are missing there" in rec.notes


# --- errors: one message each ----------------------------------------------------------------------------


def test_truncated_is_read_unless_strict(tmp_path: Path, sim: Simulation, sim_bytes: bytes) -> None:
    """A cut-off file: the complete part is read and the note names the byte; --strict refuses it."""
    cut = len(sim_bytes) // 2 + 5
    path = write(tmp_path, sim_bytes[:cut])
    with pytest.raises(LogReadError, match=(
            rf"log.ulg: the log is cut: it ends inside a record at byte \d+ of {cut} \(a message, \d+ bytes "
            r"present\)\. Re-copy the log, or leave out --strict to calibrate from its complete records$")):
        read(path, allow_truncated=False)
    rec = read(path)
    assert rec.notes[0].startswith("the log is cut: it ends inside a record at byte")
    assert 0 < len(rec.select(Kind.MAGNETOMETER)) < len(sim.recording.select(Kind.MAGNETOMETER))


def test_truncated_in_the_definitions(tmp_path: Path, sim_bytes: bytes) -> None:
    """A file that ends among the parameter messages has no data at all."""
    cut = sim_bytes.index(b"CAL_MAG0_XSCALE") + 4
    with pytest.raises(LogReadError, match=(rf"the ULog is truncated at byte \d+ of {cut}, before any data "
                                            r"message\. Re-copy the log from the vehicle$")):
        read(write(tmp_path, sim_bytes[:cut]))


def test_no_magnetometer_is_a_clean_stream_error_listing_what_is_there(tmp_path: Path) -> None:
    """The reader still returns the IMU (inspect lists it); fit fails naming the streams there are."""
    gyr, acc = still_imu(400)
    content = UlogContent([combined_topic(times(400, 5_000), gyr, acc)])
    path = write(tmp_path, ulog_bytes(content), "nomag.ulg")
    rec = read(path)
    assert rec.notes[-1] == ("no magnetometer topic (sensor_mag, sensor_combined.magnetometer_ga or "
                             "vehicle_magnetometer); the log has: sensor_combined")
    with pytest.raises(StreamError, match=(r"^nomag.ulg: no magnetometer stream; available: sensor_combined "
                                           r"\(accelerometer\), sensor_combined \(gyroscope\)$")):
        calibrate(path, Config())


def test_no_topic_magcal_reads(tmp_path: Path) -> None:
    """A log with none of the topics lists what it has."""
    cpu = Topic("cpuload", (("uint64_t", "timestamp"), ("float", "load")),
                {"timestamp": times(3, 1000), "load": [0.5] * 3})
    with pytest.raises(StreamError, match=(r"log.ulg: no topic magcal reads \(sensor_mag, .*\); the log has: "
                                           r"cpuload\. Log sensor_mag and sensor_combined")):
        log(tmp_path, cpu)


@pytest.mark.parametrize(("seed", "size", "message"), [
    (0, 100, r"the ULog sets a format flag this pyulog cannot parse \(a newer PX4 log format, or a "
             r"corrupt header\)\. Update pyulog \(pip install --upgrade pyulog\) or re-copy the log$"),
    (0, 200_000, r"the ULog sets a format flag this pyulog cannot parse \(a newer PX4 log format, or a "
                 r"corrupt header\)\. Update pyulog \(pip install --upgrade pyulog\) or re-copy the log$"),
    (1, 200_000, r"no data messages could be decoded after the ULog header \(the file is corrupt or not a "
                 r"PX4 log\)\. Re-copy the log from the vehicle$"),
])
def test_random_bytes_after_a_valid_header(tmp_path: Path, capsys: pytest.CaptureFixture[str], seed: int,
                                           size: int, message: str) -> None:
    """Garbage after the magic is a one-line LogReadError (pyulog would loop, print or raise its own)."""
    data = HEADER + np.random.default_rng(seed).integers(0, 256, size, np.uint8).tobytes()
    with pytest.raises(LogReadError, match=message):
        read(write(tmp_path, data))
    assert capsys.readouterr().out == ""                              # pyulog's prints never reach stdout


@pytest.mark.parametrize("seed", range(12))
def test_no_garbage_hangs_or_leaks_a_library_exception(tmp_path: Path, seed: int) -> None:
    """Random tails of random length: always a LogReadError, never a hang or a pyulog exception."""
    rng = np.random.default_rng(100 + seed)
    data = HEADER + rng.integers(0, 256, int(rng.integers(1, 20_000)), np.uint8).tobytes()
    with pytest.raises(LogReadError):
        read(write(tmp_path, data))


def test_a_parser_that_keeps_rereading_is_stopped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """pyulog's endless re-read loop (a seek back past a short read) ends in LogReadError, not a hang."""
    from pyulog import ULog

    def loop(self: ULog, log_file: GuardFile, *args: object) -> None:
        while True:
            log_file.seek(16)
            log_file.read(3)
    monkeypatch.setattr(ULog, "_load_file", loop)
    with pytest.raises(LogReadError, match=(r"the ULog is corrupt near byte 16 \(the parser cannot find the "
                                            r"next message\)\. Re-copy the log from the vehicle$")):
        read(write(tmp_path, HEADER + bytes(100)))
    guard = GuardFile(io.BytesIO(bytes(10)), 10)
    for _ in range(STUCK_READS + 1):                                  # resynchronising re-reads are fine
        guard.seek(0)
        assert guard.read(3) == bytes(3)
    guard.seek(0)
    with pytest.raises(StuckError):
        guard.read(3)


def test_header_only_and_short_header(tmp_path: Path) -> None:
    """A bare header has no data; a shorter file is not a ULog (pyulog's ULogException, translated)."""
    with pytest.raises(LogReadError, match="no data messages could be decoded after the ULog header"):
        read(write(tmp_path, HEADER))
    with pytest.raises(LogReadError, match=(r"short.ulg: not a readable ULog \(Invalid file format \(Header "
                                            r"too short\)\)\. Re-copy the log from the vehicle$")):
        read(write(tmp_path, HEADER[:8], "short.ulg"))


def test_pyulog_type_errors_are_translated_and_its_switch_restored(tmp_path: Path, sim_bytes: bytes,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """pyulog's TypeError on bad input becomes LogReadError; its class-level string switch is left alone."""
    from pyulog import ULog

    monkeypatch.setattr(ULog, "_disable_str_exceptions", False)
    read(write(tmp_path, sim_bytes))
    assert ULog._disable_str_exceptions is False

    def broken(self: ULog, *args: object) -> None:
        msg = "Invalid file format"
        raise TypeError(msg)
    monkeypatch.setattr(ULog, "_load_file", broken)
    with pytest.raises(LogReadError, match=(r"the ULog is corrupt \(pyulog: TypeError: Invalid file "
                                            r"format\)\. Re-copy the log from the vehicle$")):
        read(tmp_path / "log.ulg")


# --- the real logs (../shared/realdata/px4) --------------------------------------------------------------

#: file -> {(kind, id): (count, rate Hz over the span)} for the streams the README describes
REAL = {
    "roboto_fmuv5_test.ulg": {
        ("magnetometer", "sensor_mag[0]"): (10, 1.1), ("magnetometer", "sensor_mag[1]"): (10, 1.1),
        ("accelerometer", "sensor_combined"): (1737, 194.2),
        ("battery_current", "battery_status[0]"): (46, 5.1),
        ("attitude", "vehicle_attitude"): (113, 20.2), ("position", "vehicle_gps_position"): (19, 2.1),
        ("motor_output", "motor[4]"): (91, 10.1)},                 # actuator_outputs (issue 28)
    "sample.ulg": {
        ("magnetometer", "sensor_combined"): (6759, 98.1),
        ("accelerometer", "sensor_combined"): (17070, 247.8),
        ("attitude", "vehicle_attitude"): (6461, 93.7)},
    "sample_appended_multiple.ulg": {
        ("magnetometer", "sensor_combined"): (444, 46.0), ("gyroscope", "sensor_combined"): (2373, 246.6)},
    "sample_log_small.ulg": {
        ("magnetometer", "sensor_mag[0]"): (6, 1.0), ("magnetometer", "sensor_mag[1]"): (6, 1.0),
        ("battery_current", "battery_status[1]"): (21, 3.3), ("accelerometer", "sensor_accel[2]"): (6, 1.0)},
    "sample_logging_tagged_and_default_params_SITL.ulg": {
        ("magnetometer", "sensor_mag[1]"): (11, 1.0), ("temperature", "sensor_mag[0]"): (11, 1.0)},
    "sample_px4_events_SITL.ulg": {
        ("magnetometer", "sensor_mag[0]"): (31, 1.0), ("position", "vehicle_gps_position"): (583, 19.2),
        ("motor_output", "motor[1]"): (313, 10.0)},                # actuator_motors (issue 28)
}


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_logs_read_as_the_readme_says(realdata: Path, name: str) -> None:
    """Counts and rates of the streams the README names; field in gauss of plausible size; no damage."""
    rec = read(realdata / "px4" / name)
    for (kind, sid), (count, rate) in REAL[name].items():
        s = rec.select(Kind(kind), sid)
        span = s.t[-1] - s.t[0]
        assert (len(s), round((len(s) - 1) / span, 1)) == (count, rate), (kind, sid)
    for m in rec.of_kind(Kind.MAGNETOMETER):
        assert m.native_unit == "gauss"
        assert 0.2 < np.median(np.linalg.norm(m.xyz, axis=1)) / GAUSS < 1.3
    assert not [n for n in rec.notes if "truncated" in n or "corrupt" in n]


def test_real_roboto_battery_and_old_logs_field(realdata: Path) -> None:
    """roboto: current 0-12 A; the older logs carry the corrected field in sensor_combined.magnetometer_ga."""
    rec = read(realdata / "px4" / "roboto_fmuv5_test.ulg")
    cur = rec.select(Kind.BATTERY_CURRENT).values
    assert cur.min() == 0.0 and 12.0 < cur.max() < 12.3
    assert rec.params["sensor_mag[0].device_id"] == rec.params["CAL_MAG0_ID"] == 396825
    for old in ("sample.ulg", "sample_appended_multiple.ulg"):
        assert read(realdata / "px4" / old).ids(Kind.MAGNETOMETER) == ["sensor_combined"]


@pytest.mark.parametrize(("name", "message"), [
    ("roboto_fmuv5_test.ulg", "sensor_mag[0] has only 8 readings inside the IMU's time span"),
    ("sample.ulg", "as the field directions moved through an arc of only 8 deg (2.3 deg RMS about their mean); the "
                   "offsets need 20 deg: turn the vehicle through at least that about an axis away from the field"),
    ("sample_appended_multiple.ulg", "sensor_combined: the motion in this log determines no part"),
    ("sample_log_small.ulg", "magnetometer sensor_mag[0] has only 6 samples (5.0 s); a calibration needs a recording"),
    ("sample_logging_tagged_and_default_params_SITL.ulg", "sensor_mag[0] has only 11 readings inside the IMU's"),
    ("sample_px4_events_SITL.ulg", "sensor_mag[0] has only 31 readings inside the IMU's time span"),
])
def test_real_logs_have_too_little_rotation_to_calibrate(realdata: Path, name: str, message: str) -> None:
    """The README's 'little rotation': fit ends in a clean one-line error that says so, not a reader error."""
    with pytest.raises(MagcalError) as info:
        calibrate(realdata / "px4" / name, Config())
    assert not isinstance(info.value, LogReadError)
    assert message in str(info.value) and "\n" not in str(info.value)


# --- fit on the simulated sample log ---------------------------------------------------------------------


def test_sample_log_fit_recovers_the_truth() -> None:
    """sample_logs/handheld.ulg, default method: D within 5 % (Frobenius), hard iron within 1 % of |m|."""
    path = ROOT / "sample_logs" / "handheld.ulg"
    truth = json.loads((ROOT / "sample_logs" / "handheld.ulg.truth.json").read_text())["magnetometers"][0]
    mag = calibrate(path, Config()).calibration.magnetometers[0]
    assert mag.id == "sensor_mag[0]" and mag.unit == "gauss"
    assert (truth["id"], truth["units"]) == ("sensor_mag[0]", "gauss")   # the truth speaks the log's language
    d_true, o_true = np.array(truth["D"]), np.array(truth["o"])
    assert np.linalg.norm(mag.D - d_true) / np.linalg.norm(d_true) < 0.05
    assert np.linalg.norm(mag.o - o_true) / np.cbrt(np.linalg.det(d_true)) < 0.01
