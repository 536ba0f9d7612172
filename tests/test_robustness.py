"""Issue 6: bad input and faults. Every bad case ends in exit 0 with notes, or exit 1 with one pinned `Error:` line.

Readers: empty, random and mis-named files, truncation, corrupt records in the middle, directories, permissions,
NaN/inf, dead and saturated sensors, time faults, bounded-memory windows. Estimators: level/yaw-only motion, too
few still poses, a field normalised upstream. Outputs: all or nothing, also on Ctrl-C.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result

from magcal_cli import so3
from magcal_cli.cli.main import cli
from magcal_cli.errors import LogReadError
from magcal_cli.models.accel import G
from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.readers.dataflash.binary import parse_binary, parse_buffer
from magcal_cli.streams import Kind, Recording, Sampling, Stream
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.logs.csvfile import write_csv
from magcal_cli.synth.logs.mcap import write_mcap
from magcal_cli.synth.logs.rosbag import write_bag
from magcal_cli.synth.simulate import Simulation, draw_truth

ROOT = Path(__file__).resolve().parents[1]




def run(runner: CliRunner, *args: str | Path) -> Result:
    """`magcal ARGS` in-process."""
    return runner.invoke(cli, [str(a) for a in args])


def one_error(result: Result, code: int = 1) -> str:
    """The single `Error:` line of a failed run (asserting the exit code and that nothing else went wrong)."""
    assert result.exit_code == code, (result.exit_code, result.stderr)
    lines = [line for line in result.stderr.splitlines() if not line.startswith("magcal:")]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    return lines[0][len("Error: "):]


def fit(runner: CliRunner, path: Path, out: Path, *args: str) -> Result:
    """`magcal fit PATH -o OUT --outputs json` plus extra arguments."""
    return run(runner, "fit", path, "-o", out, "--outputs", "json", *args)


def edited(sim: Simulation, kind: Kind, fn) -> Simulation:  # noqa: ANN001 - fn(t, values) -> (t, values)
    """The simulation with the streams of one kind replaced by fn(t, values), bypassing Stream's time check."""
    streams = []
    for s in sim.recording.streams:
        if s.kind is kind:
            t, v = fn(s.t.copy(), s.values.copy())
            s = object.__new__(Stream)
            for name, value in (("kind", kind), ("id", sim.recording.select(kind).id), ("t", t), ("values", v),
                                ("source", "sim"), ("native_unit", sim.recording.select(kind).native_unit)):
                object.__setattr__(s, name, value)
        streams.append(s)
    rec = Recording(sim.recording.path, "simulation", tuple(streams), t0=sim.recording.t0)
    return replace(sim, recording=rec)


def rows_csv(path: Path, rows: list[str]) -> Path:
    """A CSV log in the canonical layout from text rows."""
    path.write_text("t [s],gx [rad/s],gy [rad/s],gz [rad/s],ax [m/s^2],ay [m/s^2],az [m/s^2],mx [uT],my [uT],"
                    "mz [uT]\n" + "\n".join(rows) + "\n")
    return path


# --- files that are not logs ------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["x.bin", "x.log", "x.ulg", "x.mcap", "x.bag", "x.csv", "x.px4log", "x.dat"])
def test_zero_length_file(runner: CliRunner, tmp_path: Path, name: str) -> None:
    """An empty file of any extension: one line saying so."""
    (tmp_path / name).write_bytes(b"")
    assert one_error(run(runner, "inspect", tmp_path / name)) == (f"{tmp_path / name}: the file is empty. Re-copy "
                                                                   "the log from the vehicle")


@pytest.mark.parametrize(("name", "message"), [
    ("x.bin", r"not a DataFlash log \(no A3 95 record header and no FMT text lines at the start\)\. Check the "
              r"file, or pass --format for another log type"),
    ("x.log", r"not a DataFlash log \(no A3 95 record header"),
    ("x.ulg", r"unrecognised log format \(no known magic bytes at the start\)\. Supported: .*use --format"),
    ("x.mcap", r"unrecognised log format \(no known magic bytes at the start\)"),
    ("x.bag", r"unrecognised log format \(no known magic bytes at the start\)"),
    ("x.csv", r"cannot read the CSV file \('utf-8' codec can't decode .*\)\. Save it as UTF-8 text"),
])
def test_random_bytes(runner: CliRunner, tmp_path: Path, name: str, message: str) -> None:
    """Random bytes under a log's extension: a clean error naming what is wrong."""
    (tmp_path / name).write_bytes(np.random.default_rng(0).integers(0, 256, 5000, np.uint8).tobytes())
    assert re.fullmatch(rf"{re.escape(str(tmp_path / name))}: {message}.*", one_error(run(runner, "inspect",
                                                                                       tmp_path / name)))


def test_wrong_extension(runner: CliRunner, tmp_path: Path, sim: Simulation) -> None:
    """Content decides, not the name: a DataFlash log named .csv reads; a CSV named .bin says what it is not and
    reads with --format csv."""
    write_log(sim, tmp_path / "a.bin")
    (tmp_path / "a.bin").rename(tmp_path / "flight.csv")
    assert run(runner, "inspect", tmp_path / "flight.csv").exit_code == 0
    write_csv(sim, tmp_path / "b.csv")
    (tmp_path / "b.csv").rename(tmp_path / "flight.bin")
    assert one_error(run(runner, "inspect", tmp_path / "flight.bin")).startswith(
        f"{tmp_path / 'flight.bin'}: not a DataFlash log (no A3 95 record header")
    assert run(runner, "inspect", tmp_path / "flight.bin", "--format", "csv").exit_code == 0


def test_directory_that_is_not_a_bag(runner: CliRunner, tmp_path: Path) -> None:
    """A directory without metadata.yaml is not a ROS 2 bag."""
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "a.db3").write_bytes(b"SQLite format 3\x00")
    assert one_error(run(runner, "inspect", tmp_path / "logs")) == (
        f"{tmp_path / 'logs'}: a directory that is not a ROS 2 bag (no metadata.yaml). Pass a log file or a bag "
        "directory")


def test_unreadable_file(runner: CliRunner, tmp_path: Path, sim: Simulation, monkeypatch: pytest.MonkeyPatch) -> None:
    """A file the user may not read (simulated: tests run as root here, which reads anything)."""
    write_log(sim, tmp_path / "x.bin")
    real_open = Path.open

    def denied(self: Path, *args: object, **kwargs: object):  # noqa: ANN202
        if self.name == "x.bin":
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "open", denied)
    assert one_error(run(runner, "inspect", tmp_path / "x.bin")) == (
        f"{tmp_path / 'x.bin'}: cannot read the file (Permission denied). Check the path and its permissions")


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root reads files without permission")
def test_unreadable_file_by_mode(runner: CliRunner, tmp_path: Path, sim: Simulation) -> None:
    """chmod 000: the same message, from the operating system's refusal."""
    write_log(sim, tmp_path / "x.bin")
    (tmp_path / "x.bin").chmod(0)
    assert "cannot read the file (Permission denied)" in one_error(run(runner, "inspect", tmp_path / "x.bin"))


# --- truncation and corruption --------------------------------------------------------------------------------

# cut logs (the end of a file inside a record): tests/readers/test_cut.py


def test_corrupt_dataflash_bytes_are_skipped_and_counted(tmp_path: Path, sim: Simulation) -> None:
    """Garbage inside a .bin: the reader resynchronises on the next record header and says how much it skipped."""
    write_log(sim, tmp_path / "x.bin")
    data = bytearray((tmp_path / "x.bin").read_bytes())
    mid = len(data) // 2
    data[mid:mid] = np.random.default_rng(1).integers(0, 256, 700, np.uint8).tobytes()
    (tmp_path / "bad.bin").write_bytes(bytes(data))
    rec = open_recording(tmp_path / "bad.bin")
    assert any(re.fullmatch(r"skipped \d+ bytes that are not complete records \(corrupt data or padding\); reading "
                            r"resynchronised on the next message header", n) for n in rec.notes)


def test_mostly_corrupt_dataflash_is_an_error_naming_the_damage(tmp_path: Path, sim: Simulation) -> None:
    """Damaged FMT records make most of a log unreadable: an error naming the damage, not 'record longer' or
    'MAG never written', whether --strict or not."""
    write_log(sim, tmp_path / "x.bin")
    data = bytearray((tmp_path / "x.bin").read_bytes())
    for name in (b"IMU\0", b"MAG\0", b"ATT\0", b"BAT\0", b"CTUN"):    # FMT: A3 95 80 type length name...
        at = data.index(name)
        assert data[at - 5:at - 2] == b"\xa3\x95\x80"
        data[at - 1] = 200                                             # a wrong record length
    (tmp_path / "bad.bin").write_bytes(bytes(data))
    damage = (r"bad.bin: \d+ of \d+ bytes are not complete records \(the log is mostly corrupt, or its FMT records "
              r"are damaged\); \d+ messages could be read\. ")
    with pytest.raises(LogReadError, match=damage + r"Re-copy the log, or leave out --strict to use them$"):
        open_recording(tmp_path / "bad.bin", options=ReadOptions(allow_truncated=False))
    with pytest.raises(LogReadError, match=damage + r"They are not enough to calibrate; re-copy the log from the "
                                                    r"vehicle$"):
        open_recording(tmp_path / "bad.bin")


def test_corrupt_ulog_message_is_skipped(tmp_path: Path, sim_ulg: Simulation) -> None:
    """A message header damaged in the middle of a ULog: pyulog resynchronises; the note counts the damage."""
    write_log(sim_ulg, tmp_path / "x.ulg")
    data = bytearray((tmp_path / "x.ulg").read_bytes())
    mid = len(data) // 2
    data[mid:mid + 40] = b"\xff" * 40
    (tmp_path / "bad.ulg").write_bytes(bytes(data))
    rec = open_recording(tmp_path / "bad.ulg")
    assert any(n.startswith("corrupt data: pyulog skipped damaged bytes and resynchronised on the next message; "
                            "read ") for n in rec.notes)
    assert len(rec.select(Kind.MAGNETOMETER)) > 0.9 * len(sim_ulg.recording.select(Kind.MAGNETOMETER))


def test_damaged_ulog_format_definition(tmp_path: Path, sim_ulg: Simulation) -> None:
    """A format definition whose timestamp field is garbled: that topic is ignored and named (found by fuzzing:
    it was a KeyError)."""
    write_log(sim_ulg, tmp_path / "x.ulg")
    data = (tmp_path / "x.ulg").read_bytes()
    at = data.index(b"timestamp", data.index(b"sensor_mag:"))
    (tmp_path / "bad.ulg").write_bytes(data[:at] + b"timestXmp" + data[at + 9:])
    rec = open_recording(tmp_path / "bad.ulg")
    assert "ignored sensor_mag: the format has no timestamp field (corrupt definition)" in rec.notes


def test_corrupt_bag_chunk_is_skipped(tmp_path: Path, sim: Simulation) -> None:
    """A damaged chunk in the middle of a ROS 1 bag: reading resumes after it and the note counts what was lost."""
    write_bag(sim, tmp_path / "x.bag", chunk_size=16_000)
    data = bytearray((tmp_path / "x.bag").read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(64)
    (tmp_path / "bad.bag").write_bytes(bytes(data))
    rec = open_recording(tmp_path / "bad.bag")
    assert any(re.fullmatch(r"corrupt data: skipped 1 unreadable chunks and 0 messages that did not decode \(\d+ of "
                            r"\d+ messages lost\); reading resumed after each", n) for n in rec.notes)
    total = len(sim.recording.select(Kind.MAGNETOMETER))
    assert 0.7 * total < len(rec.select(Kind.MAGNETOMETER)) < total


def test_corrupt_mcap_summary_is_not_trusted(tmp_path: Path, sim: Simulation) -> None:
    """A damaged chunk and a damaged summary: channel definitions are taken only from a summary whose CRC holds."""
    write_mcap(sim, tmp_path / "x.mcap", chunk_size=16_000)
    data = bytearray((tmp_path / "x.mcap").read_bytes())
    data[200:264] = bytes(64)                                     # the first chunk (schemas and channels)
    data[-200] ^= 0xFF                                            # the summary section
    (tmp_path / "bad.mcap").write_bytes(bytes(data))
    rec = open_recording(tmp_path / "bad.mcap")
    assert rec.notes[0].startswith("corrupt data: skipped 1 chunks that fail their CRC or do not decompress, ")
    assert rec.notes[0].endswith(" messages of channels whose definition was lost; reading resumed after each")


def test_corrupt_csv_rows_are_skipped_and_counted(tmp_path: Path, sim: Simulation) -> None:
    """A few rows that do not parse are skipped with a note naming the first; many mean the file is malformed."""
    write_csv(sim, tmp_path / "x.csv")
    lines = (tmp_path / "x.csv").read_text().splitlines()
    lines[100] = lines[100].replace(".", "#", 1)
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    rec = open_recording(tmp_path / "bad.csv")
    assert re.fullmatch(r"skipped 1 rows that do not parse \(corrupt data; the first is line 101: could not convert "
                        r"string '.*#.*' to a number\)", rec.notes[0])


def test_corrupt_text_dataflash_fields_are_skipped(tmp_path: Path) -> None:
    """A text log line whose number is garbled is dropped with the malformed ones."""
    text = ("FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns\n"
            "FMT, 132, 31, MAG, Qhhh, TimeUS,MagX,MagY,MagZ\n"
            "MAG, 1000, 1, 2, 3\nMAG, 2000, 1, 2x, 3\nMAG, 3000, 1, 2, 3, 4\nMAG, 4000, 4, 5, 6\n")
    (tmp_path / "x.log").write_text(text)
    from magcal_cli.readers.dataflash.text import parse_text

    raw = parse_text(tmp_path / "x.log", {"MAG"})
    assert raw.tables["MAG"].num("TimeUS").tolist() == [1000.0, 4000.0]
    assert raw.notes == ["skipped 2 malformed text records (wrong number of fields, or a field that is not a number)"]


# --- values and time ------------------------------------------------------------------------------------------

def test_nan_and_inf_values_are_dropped_and_counted(tmp_path: Path) -> None:
    """inf and NaN cells: those samples are dropped and counted, the IMU's accelerometer and gyro rows together."""
    rows = [f"{k * 0.01:.2f},0,0,0,0,0,9.8,{20 + k % 7},1,2" for k in range(40)]
    rows[5] = rows[5].replace(",9.8,", ",inf,")
    rows[9] = rows[9].replace(",1,2", ",nan,2")
    rec = open_recording(rows_csv(tmp_path / "x.csv", rows))
    assert "imu gyroscope/accelerometer: dropped 1 samples with NaN or inf" in rec.notes
    assert "mag: dropped 1 rows with some magnetometer cells or the time empty" in rec.notes     # NaN: no sample
    assert len(rec.select(Kind.GYROSCOPE)) == len(rec.select(Kind.ACCELEROMETER)) == 39


def test_values_beyond_physical_limits_are_dropped(tmp_path: Path) -> None:
    """A bit flip in a float's exponent (1e30 uT) is not a reading: dropped and counted."""
    rows = [f"{k * 0.01:.2f},0,0,0,0,0,9.8,{20 + k % 7},1,2" for k in range(40)]
    rows[7] = rows[7].replace(",1,2", ",1e30,2")
    rec = open_recording(rows_csv(tmp_path / "x.csv", rows))
    assert rec.notes == ("mag: dropped 1 magnetometer samples beyond physical limits (corrupt values)",)


def test_vanishing_readings_are_dropped(tmp_path: Path) -> None:
    """A zeroed record (an accelerometer reading exactly 0, a field at 0.001 % of its size) is not a reading
    (found by fuzzing: it made the MAP start fail with a LinAlgError)."""
    rows = [f"{k * 0.01:.2f},0,0,0,0,0,9.8,{20 + k % 7},1,2" for k in range(40)]
    rows[3] = rows[3].replace(",0,0,9.8,", ",0,0,0,")
    rows[8] = rows[8].replace(f",{20 + 8 % 7},1,2", ",0.0001,0,0")
    rec = open_recording(rows_csv(tmp_path / "x.csv", rows))
    assert rec.notes == ("imu gyroscope/accelerometer: dropped 1 samples whose field or specific force vanishes "
                         "(exactly zero, or the field below 1 % of its median: zeroed or corrupt records)",
                         "mag: dropped 1 samples whose field or specific force vanishes (exactly zero, or the field "
                         "below 1 % of its median: zeroed or corrupt records)")


def singular(problem: object, cfg: object) -> None:
    """A method that meets a singular system."""
    raise np.linalg.LinAlgError("SVD did not converge")


def test_numerical_failure_is_a_clean_error(runner: CliRunner, tmp_path: Path, sim: Simulation,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """A LinAlgError inside a method (degenerate data) is one line, not an internal error."""
    from magcal_cli.methods.table import METHODS

    monkeypatch.setitem(METHODS, "kok2012", METHODS["kok2012"]._replace(run="tests.test_robustness:singular"))
    write_log(sim, tmp_path / "x.bin")
    assert one_error(fit(runner, tmp_path / "x.bin", tmp_path / "o", "--method", "kok2012")) == (
        "x.bin: the kok2012 solver failed numerically (SVD did not converge); the data are degenerate for it "
        "(damaged or repeated samples?). Check the log with magcal inspect, or try another --method")


@pytest.mark.parametrize(("value", "what"), [(0.0, "zero"), (33.0, "the same value")])
def test_dead_magnetometer(runner: CliRunner, tmp_path: Path, sim: Simulation, value: float, what: str) -> None:
    """An all-zero or constant field (a stuck or disconnected sensor) cannot be calibrated: one line saying so."""
    write_csv(edited(sim, Kind.MAGNETOMETER, lambda t, v: (t, np.full_like(v, value * 1e-6))), tmp_path / "x.csv")
    n = len(sim.recording.select(Kind.MAGNETOMETER))
    assert one_error(fit(runner, tmp_path / "x.csv", tmp_path / "o")) == (
        f"x.csv#mx [uT], my [uT], mz [uT]: the magnetometer mag reads {what} in all {n} samples; the sensor is stuck, "
        "disconnected or not enabled (or the column is a placeholder). Check the sensor and its logging, and record "
        "again")


def test_saturated_field_samples_are_dropped(runner: CliRunner, tmp_path: Path, sim: Simulation) -> None:
    """Readings clipped at the sensor's range bias a calibration: they are dropped, named, and the fit holds."""
    lim = 0.7 * float(np.abs(sim.recording.select(Kind.MAGNETOMETER).values[:, 0]).max())
    write_csv(edited(sim, Kind.MAGNETOMETER, lambda t, v: (t, np.clip(v, -lim, lim))), tmp_path / "x.csv")
    rec = open_recording(tmp_path / "x.csv")
    assert any(re.fullmatch(r"mag: magnetometer readings sit at the limit of the sensor's range \(.*x = .*\): it "
                            r"saturated there, so the true value is unknown", n) for n in rec.notes)
    assert any(re.fullmatch(r"mag: dropped the \d+ saturated samples", n) for n in rec.notes)
    result = fit(runner, tmp_path / "x.csv", tmp_path / "o")
    assert result.exit_code == 0, result.stderr
    assert re.search(r"field-norm error 0\.\d\d %", result.stdout)


def test_quantised_still_signal_is_not_taken_for_saturation() -> None:
    """A still, integer-quantised axis repeats its top value often, but with a tail below it: not a range wall."""
    from magcal_cli.readers.checks import sensor_checks

    x = np.round(9.81 / 0.01 + np.random.default_rng(0).normal(0, 2, 2000)) * 0.01
    values = np.column_stack([x * 0, x * 0 + 0.1, x, np.zeros((2000, 3))])
    t, v, notes = sensor_checks((Kind.ACCELEROMETER, Kind.GYROSCOPE), np.arange(2000) * 0.01, values, "imu")
    assert notes == [] and len(t) == 2000


def test_time_going_backwards_and_duplicated(tmp_path: Path) -> None:
    """Out-of-order stamps are sorted, repeated ones dropped, both counted."""
    times = [0.0, 0.01, 0.03, 0.02, 0.04, 0.04, 0.05] + [0.06 + 0.01 * k for k in range(20)]
    rows = [f"{t:.2f},0,0,0,0,0,9.8,{20 + k % 7},1,2" for k, t in enumerate(times)]
    rec = open_recording(rows_csv(tmp_path / "x.csv", rows))
    assert "mag: 1 timestamps went backwards; samples were sorted by time" in rec.notes
    assert "mag: dropped 1 samples with duplicated timestamps" in rec.notes


def test_clock_reset_keeps_the_longest_part(runner: CliRunner, tmp_path: Path, sim: Simulation) -> None:
    """The clock starting again mid-log (a reboot): sorting would interleave two recordings, so the longest part
    is kept, said, and calibrates."""
    write_csv(sim, tmp_path / "x.csv")
    lines = (tmp_path / "x.csv").read_text().splitlines()
    head, rows = lines[0], lines[1:]
    cut = len(rows) * 2 // 5
    t_cut = float(rows[cut].split(",")[0])
    moved = [",".join([f"{float(r.split(',')[0]) - t_cut + 0.005:.6f}", *r.split(",")[1:]]) for r in rows[cut:]]
    (tmp_path / "x.csv").write_text("\n".join([head, *rows[:cut], *moved]) + "\n")
    rec = open_recording(tmp_path / "x.csv")
    assert any(re.fullmatch(r"mag: the clock jumps back 1 time \(by up to [\d.]+ s: a reboot or clock reset\); kept "
                            r"the longest part, \d+ of \d+ samples", n) for n in rec.notes)
    assert fit(runner, tmp_path / "x.csv", tmp_path / "o").exit_code == 0


def test_lone_corrupt_stamps_are_dropped(tmp_path: Path) -> None:
    """A stamp far from both neighbours (a bit flip in a time field) is dropped, not sorted to the far end."""
    times = [0.01 * k for k in range(30)]
    times[12] += 5e5
    rows = [f"{t:.2f},0,0,0,0,0,9.8,{20 + k % 7},1,2" for k, t in enumerate(times)]
    rec = open_recording(rows_csv(tmp_path / "x.csv", rows))
    assert ("mag: dropped 1 samples whose time stamp lies far from both neighbours' (corrupt time stamps)"
            in rec.notes)
    assert rec.select(Kind.MAGNETOMETER).t[-1] < 1.0


def test_time_gap_still_calibrates(runner: CliRunner, tmp_path: Path, sim: Simulation) -> None:
    """Logging paused for 1000 s mid-flight: nothing is bridged across the gap and the fit holds."""
    def gap(t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.where(t > 40.0, t + 1000.0, t), v

    shifted = edited(edited(edited(sim, Kind.MAGNETOMETER, gap), Kind.ACCELEROMETER, gap), Kind.GYROSCOPE, gap)
    write_csv(shifted, tmp_path / "x.csv")
    result = fit(runner, tmp_path / "x.csv", tmp_path / "o")
    assert result.exit_code == 0, result.stderr
    assert re.search(r"field-norm error 0\.\d\d %", result.stdout)


def test_dataflash_reads_in_bounded_windows(tmp_path: Path, sim: Simulation) -> None:
    """Gigantic logs: the parser holds one window plus the wanted records; the result does not depend on the
    window (byte for byte on a clean log), and unwanted types are counted but never decoded."""
    write_log(sim, tmp_path / "x.bin")
    whole = parse_buffer(np.fromfile(tmp_path / "x.bin", dtype=np.uint8), {"MAG", "IMU"})
    for window in (1500, 10_000):
        part = parse_binary(tmp_path / "x.bin", {"MAG", "IMU"}, window=window)
        assert part.counts == whole.counts and part.skipped_bytes == whole.skipped_bytes == 0
        for name, table in whole.tables.items():
            assert np.array_equal(part.tables[name].pos, table.pos)
            assert all(part.tables[name].columns[c].tobytes() == v.tobytes() for c, v in table.columns.items())
    assert "ATT" in whole.counts and "ATT" not in whole.tables


@pytest.mark.parametrize("fmt", ["csv", "log"])
def test_text_logs_read_in_blocks(tmp_path: Path, sim: Simulation, fmt: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """CSV and text DataFlash logs are parsed in blocks of lines (memory: one block plus the numbers); the
    result does not depend on the block size."""
    from magcal_cli.readers import csvfile
    from magcal_cli.readers.dataflash import text as dataflash_text

    write_log(sim, tmp_path / "x.bin")
    if fmt == "log":
        from .fuzzing import text_log

        text_log(tmp_path / "x.bin", tmp_path / "x.log")
    else:
        write_csv(sim, tmp_path / "x.csv")
    whole = open_recording(tmp_path / f"x.{fmt}")
    monkeypatch.setattr(csvfile, "CSV_BLOCK", 300)
    monkeypatch.setattr(dataflash_text.parse_text, "__defaults__", (None, 300))
    blocks = open_recording(tmp_path / f"x.{fmt}")
    assert blocks.notes == whole.notes
    for a, b in zip(whole.streams, blocks.streams, strict=True):
        assert a.id == b.id and np.array_equal(a.t, b.t) and np.array_equal(a.values, b.values)


# --- estimators -----------------------------------------------------------------------------------------------

def recording_of(rot: np.ndarray, rate: float, seed: int, mag_step: int = 2, accel: np.ndarray | None = None,
                 normalise: bool = False) -> Recording:
    """IMU and field along rotations rot (N+1, 3, 3), optionally with linear acceleration (N, 3) in the body."""
    rng = np.random.default_rng(seed)
    tr = draw_truth(rng, rate, rate / mag_step)
    sd = tr.noise_std
    n = rot.shape[0] - 1
    t = np.arange(n) / rate
    gyro = so3.log(rot[:-1].transpose(0, 2, 1) @ rot[1:]) * rate + tr.gyro_bias
    gyro += sd["gyroscope"] * rng.standard_normal((n, 3))
    acc = -np.einsum("nji,j->ni", rot[:-1], np.array([0.0, 0.0, G])) + tr.accel_bias
    acc += sd["accelerometer"] * rng.standard_normal((n, 3)) + (0.0 if accel is None else accel)
    idx = np.arange(0, n, mag_step)
    m_n = np.array([np.cos(tr.dip), 0.0, np.sin(tr.dip)])
    y = np.einsum("nji,j->ni", rot[idx], m_n) @ tr.D.T + tr.o + sd["magnetometer"] * rng.standard_normal((idx.size, 3))
    if normalise:
        y /= np.linalg.norm(y, axis=1, keepdims=True)
    return Recording(Path("x.sim"), "simulation", (
        Stream(Kind.ACCELEROMETER, "imu", t, acc, "sim", "m/s^2"),
        Stream(Kind.GYROSCOPE, "imu", t, gyro, "sim", "rad/s", sampling=Sampling.FOLLOWING),   # R_k^T R_k+1 / dt
        Stream(Kind.MAGNETOMETER, "mag", t[idx], y, "sim", "tesla")))


def write_rec(rec: Recording, path: Path) -> Path:
    """A recording as a CSV log."""
    write_csv(Simulation(rec, None, np.zeros(0), (), "test", 0), path)  # type: ignore[arg-type]
    return path


def yaw_only(rate: float = 50.0, poses: int = 8) -> np.ndarray:
    """Level yaw turns of 50 deg with 3 s still between them (rotations, N+1)."""
    yaw, parts = 0.0, []
    for _ in range(poses):
        parts += [np.full(int(3 * rate), yaw), np.linspace(yaw, yaw + np.deg2rad(50), int(2 * rate))]
        yaw += np.deg2rad(50)
    y = np.concatenate(parts)
    return so3.exp(np.stack([0 * y, 0 * y, y], axis=1))


def test_yaw_only_motion_is_a_partial_calibration_or_a_clear_refusal(runner: CliRunner, tmp_path: Path) -> None:
    """Level, yaw-only motion: MAP holds what it cannot determine (D's vertical column and the offsets it is
    confounded with) at a sphere fit and says so in the document; Kok 2012, which needs tilted still poses,
    says what motion to add."""
    path = write_rec(recording_of(yaw_only(), 50.0, 1), tmp_path / "yaw.csv")
    result = fit(runner, path, tmp_path / "o")
    assert result.exit_code == 0, result.stderr
    mag = json.loads((tmp_path / "o" / "calibration.json").read_text())["magnetometers"][0]
    held = {h["parameter"] for h in mag["held"]}
    assert {"D[0][2]", "D[1][2]", "D[2][2]"} <= held and all("sphere fit" in h["source"] for h in mag["held"])
    assert one_error(fit(runner, path, tmp_path / "o", "--method", "kok2012", "--force")) == (
        "yaw.csv: mag: every vertical measurement (8 still segments) lies within 0 deg of the same direction (level "
        "or yaw-only motion), which cannot determine the calibration; hold the sensor still in >= 6 orientations that "
        "differ in tilt -- on each side and upside down -- for 2-4 s each")


@pytest.mark.parametrize(("still_s", "message"), [
    (4.0, "few.csv: mag: the vertical measurements (300 quasi-static samples) show only 3 distinct orientations "
          "(15 deg apart); Kok 2012 needs >= 6: hold the sensor still in more orientations -- on each side and upside "
          "down -- for 2-4 s each"),
    (0.0, "few.csv: only 0 stationary segments and too few quasi-static samples for mag; hold the sensor still in "
          ">= 6 distinct orientations for 2-4 s each"),
])
def test_too_few_still_poses_for_kok2012(runner: CliRunner, tmp_path: Path, still_s: float, message: str) -> None:
    """Three still poses, or none, and otherwise shaken (never quasi-static): Kok 2012 needs more poses."""
    rate = 50.0
    rng = np.random.default_rng(4)
    angles = [np.zeros(3), np.array([1.2, 0.0, 0.3]), np.array([0.0, -1.4, 1.0])]
    parts, shake = [], []
    for k, a in enumerate(angles):
        parts.append(np.repeat(a[None], int(still_s * rate), axis=0))
        shake.append(np.zeros((int(still_s * rate), 3)))
        move = np.linspace(a, angles[(k + 1) % 3], int(6 * rate))
        parts.append(move)
        shake.append(rng.choice([-1.0, 1.0], size=(len(move), 3)) * 15.0)
    rot = so3.exp(np.concatenate([*parts, angles[0][None]]))
    path = write_rec(recording_of(rot, rate, 2, accel=np.concatenate(shake)), tmp_path / "few.csv")
    assert one_error(fit(runner, path, tmp_path / "o", "--method", "kok2012")) == message


def test_poorly_observable_parameters_are_named(runner: CliRunner, tmp_path: Path) -> None:
    """Mostly level motion with a little tilt: the fit runs and warns which parameters stay poorly determined and
    what motion would fix them."""
    rate = 50.0
    t = np.arange(int(90 * rate) + 1) / rate
    tilt = np.deg2rad(25.0)
    rot = so3.exp(np.stack([0 * t, 0 * t, 0.5 * t], 1)) @ so3.exp(
        np.stack([tilt * np.sin(0.31 * t), tilt * np.cos(0.23 * t), 0 * t], 1))
    path = write_rec(recording_of(rot, rate, 3), tmp_path / "flat.csv")
    result = fit(runner, path, tmp_path / "o", "-v")           # -v: every warning in full (else one line per kind)
    assert result.exit_code == 0, result.stderr
    assert re.search(r"magcal: warning: flat.csv: mag: this log leaves the .* poorly determined .*To fix: ",
                     result.stderr)


# --- outputs --------------------------------------------------------------------------------------------------

def test_interrupt_while_writing_leaves_nothing(runner: CliRunner, tmp_path: Path, sim: Simulation,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C after the first output file is written: exit 130, no output directory, no temporary files."""
    from magcal_cli.writers import calfile

    write_log(sim, tmp_path / "x.bin")
    real = calfile.YamlWriter.write

    def interrupted(self: object, result: object, outdir: Path) -> list[Path]:
        real(self, result, outdir)  # type: ignore[arg-type]
        raise KeyboardInterrupt

    monkeypatch.setattr(calfile.YamlWriter, "write", interrupted)
    result = run(runner, "fit", tmp_path / "x.bin", "-o", tmp_path / "out", "--outputs", "json,yaml,report")
    assert result.exit_code == 130
    assert result.stderr.endswith("Error: interrupted; outputs not yet renamed into place were discarded.\n")
    assert not (tmp_path / "out").exists()


def test_interrupt_keeps_the_previous_outputs(runner: CliRunner, tmp_path: Path, sim: Simulation,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """With --force over an earlier run, an interrupted run leaves the earlier files exactly as they were."""
    from magcal_cli.writers.report import text as report

    write_log(sim, tmp_path / "x.bin")
    assert run(runner, "fit", tmp_path / "x.bin", "-o", tmp_path / "out", "--outputs", "json,report").exit_code == 0
    before = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}

    def interrupted(self: object, result: object, outdir: Path) -> list[Path]:
        raise KeyboardInterrupt

    monkeypatch.setattr(report.TextReport, "write", interrupted)
    result = run(runner, "fit", tmp_path / "x.bin", "-o", tmp_path / "out", "--outputs", "json,report", "--force")
    assert result.exit_code == 130
    assert {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()} == before


def test_output_directory_that_cannot_be_made(runner: CliRunner, tmp_path: Path, sim: Simulation) -> None:
    """-o below a regular file: one line, nothing written."""
    write_log(sim, tmp_path / "x.bin")
    (tmp_path / "file").write_text("")
    assert one_error(fit(runner, tmp_path / "x.bin", tmp_path / "file" / "out")) == (
        f"{tmp_path / 'file' / 'out'}: cannot create the output directory (Not a directory). Choose another -o")


def test_sigint_mid_run_leaves_no_partial_files(tmp_path: Path) -> None:
    """A real Ctrl-C (SIGINT) to a running `magcal fit`: exit 130 and an output directory with nothing in it
    (no partial and no temporary files), whenever the signal lands."""
    log = ROOT / "sample_logs" / "handheld.bin"
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "magcal_cli", "fit", str(log), "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stderr is not None
    line = proc.stderr.readline()                     # "magcal: reading handheld.bin": the run has started
    assert line.startswith("magcal: reading"), line
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Error: interrupted; outputs not yet renamed into place were discarded." in err
    assert "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())


# --- the negative real logs of ../shared/realdata -------------------------------------------------------------

@pytest.mark.parametrize(("name", "args", "message"), [
    ("robert_lefebvre_octo_PM.log", (), "{path}: no magnetometer messages (MAG defined by FMT but never written); "
                                        "nothing to calibrate. Enable compass logging (LOG_BITMASK) and record the "
                                        "log again"),
    ("ap462_truncated_80k.bin", ("--strict",),
     "{path}: the log is cut: it ends inside a record at byte 81918 of 81920 (a record header, 2 of its 3 bytes "
     "present). Re-copy the log, or leave out --strict to calibrate from its complete records"),
    ("ap462_truncated_80k.bin", (),
     "ap462_truncated_80k.bin: none of the 2 magnetometers can be used: MAG[0], magnetometer MAG[0] has only 4 "
     "samples (0.3 s); a calibration needs a recording of at least a minute with the vehicle turned through many "
     "orientations; MAG[1], magnetometer MAG[1] has only 4 samples (0.3 s); a calibration needs a recording of at "
     "least a minute with the vehicle turned through many orientations"),
])
def test_negative_real_logs(runner: CliRunner, tmp_path: Path, realdata: Path, name: str, args: tuple[str, ...],
                            message: str) -> None:
    """No MAG with an old GPS format (pymavlink raises TypeError on it), and a log cut at 80 kB: one clean line."""
    path = realdata / "ardupilot" / name
    assert one_error(fit(runner, path, tmp_path / "o", *args)) == message.format(path=path)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("how", ["exec", "set_name"])
def test_a_ctrl_c_python_remembers_or_wraps_still_exits_130(tmp_path: Path, how: str) -> None:
    """Ctrl-C landing while a module imports on first use: inside exec() of a string (a dataclass being made), which
    makes CPython kill itself with SIGINT at exit (-2), or inside a class's __set_name__, which wraps it in a
    RuntimeError (an internal error, 123). Both are the interrupt: exit 130, one line, nothing written."""
    raise_it = ("exec('raise KeyboardInterrupt')" if how == "exec" else
                "type('T', (), {'f': type('D', (), {'__set_name__': lambda *a: exec('raise KeyboardInterrupt')})()})")
    script = (f"import sys\nfrom magcal_cli import pipeline\n"
              f"def interrupted(*a, **k):\n    {raise_it}\n"
              f"pipeline.calibrate = interrupted\n"
              f"from magcal_cli.cli.main import main\nsys.argv = ['magcal', 'fit', sys.argv[1], '-o', sys.argv[2]]\n"
              f"main()\n")
    (tmp_path / "interrupted_run.py").write_text(script)
    out = tmp_path / "out"
    # run as `python -m`, as `magcal` runs: with -c, CPython exits from its SystemExit handler before it looks
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "interrupted_run", str(ROOT / "sample_logs" / "handheld.bin"),
                           str(out)], capture_output=True, text=True, timeout=120, check=False, env=env, cwd=tmp_path)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines() == ["Error: interrupted; outputs not yet renamed into place were discarded."]
    assert not out.exists() or not any(out.iterdir())
