"""Cut logs (issue 12 item 4): every format is read up to its last complete record with a warning; --strict
refuses it with one `Error:` line, exit 1 and no output (spec/cli.md).

Modules it covers (the mirrored test file aside): magcal_cli.readers.ros.bag2_sqlite,
magcal_cli.readers.ros.partial.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from magcal_cli.cli.main import cli
from magcal_cli.errors import TruncatedLogError
from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.streams import Kind
from magcal_cli.synth.logs import imu_sampling, write_log
from magcal_cli.synth.logs.mcap import write_mcap
from magcal_cli.synth.logs.rosbag import write_bag, write_ros2
from magcal_cli.synth.simulate import Simulation

from ..fuzzing import seed_simulation, text_log

#: every format and layout a reader handles: DataFlash binary and text, ULog, MCAP, ROS 1, ROS 2 (both
#: storages), CSV
FORMATS = ("bin", "log", "ulg", "mcap", "bag", "ros2-mcap", "ros2-sqlite3", "csv")
#: where the cut falls: this share of the file, then inside the record there (a ROS 2 MCAP storage file here
#: is one chunk followed by its message index: cut inside the chunk)
CUT_AT = {"ros2-mcap": 0.5}


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A handheld simulation at 10 Hz IMU / 5 Hz field (about 80 s; fits in well under a second), instantaneous IMU
    samples (`write` re-samples it for .ulg) and the field on IMU stamps (a CSV log has one row per IMU sample)."""
    return seed_simulation(Path("x.bin"))


def write(sim: Simulation, root: Path, fmt: str) -> tuple[Path, Path]:
    """The log of `fmt` under `root`: (the path to give magcal, the file to cut); a .ulg from seed_simulation
    sampled as the format holds its IMU."""
    if fmt == "log":
        write_log(sim, root / "x.bin")
        text_log(root / "x.bin", root / "x.log")
        return root / "x.log", root / "x.log"
    if fmt == "mcap":
        write_mcap(sim, root / "x.mcap", chunk_size=16_000)       # several chunks, as real recorders write
        return root / "x.mcap", root / "x.mcap"
    if fmt == "bag":
        write_bag(sim, root / "x.bag", chunk_size=16_000)
        return root / "x.bag", root / "x.bag"
    if fmt.startswith("ros2"):
        write_ros2(sim, root / "bag", fmt.split("-")[1])
        storage = next(p for p in (root / "bag").iterdir() if p.suffix in (".mcap", ".db3"))
        return root / "bag", storage
    path = root / f"x.{fmt}"
    write_log(sim if imu_sampling(path) is sim.imu_sampling else seed_simulation(path), path)
    return path, path


def cut(victim: Path, fmt: str) -> int:
    """Cut `victim` inside a record, 80 % into it (text: after the second cell of a line); the new size."""
    data = victim.read_bytes()
    at = int(CUT_AT.get(fmt, 0.8) * len(data))
    if fmt in ("csv", "log"):
        at = data.index(b",", data.index(b",", data.index(b"\n", at) + 1) + 1) + 1
    else:
        at += 7
    victim.write_bytes(data[:at])
    return at


def fit(path: Path, out: Path, *args: str) -> Result:
    """`magcal fit PATH -o OUT --outputs json` in-process."""
    return CliRunner().invoke(cli, ["fit", str(path), "-o", str(out), "--outputs", "json", *args])


@pytest.mark.parametrize("fmt", FORMATS)
def test_cut_log_is_read_to_its_last_complete_record(tmp_path: Path, sim: Simulation, fmt: str) -> None:
    """Default: the complete records are read, the reader says where the log was cut, and the fit works."""
    path, victim = write(sim, tmp_path, fmt)
    full = open_recording(path)
    assert full.cut is None
    size = cut(victim, fmt)
    rec = open_recording(path)
    assert rec.cut is not None
    assert rec.cut.size == size
    assert rec.cut.offset is None or 0 < rec.cut.offset < size
    assert rec.notes[0] == rec.cut.message
    assert re.fullmatch(r"the log is cut: it ends inside a record( at byte \d+ of \d+)? \(.+\); read up to its "
                        r"last complete record; the data end at \d+\.\d{3} s", rec.cut.message)
    n_full, n_cut = len(full.select(Kind.MAGNETOMETER)), len(rec.select(Kind.MAGNETOMETER))
    assert 0.3 * n_full < n_cut < n_full                        # the part before the cut, no more
    result = fit(path, tmp_path / "o")
    assert result.exit_code == 0, result.stderr
    assert f"magcal: warning: {rec.cut.message}" in result.stderr.splitlines()
    doc = json.loads((tmp_path / "o" / "calibration.json").read_text())
    assert rec.cut.message in doc["notes"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_strict_refuses_a_cut_log(tmp_path: Path, sim: Simulation, fmt: str) -> None:
    """--strict: one `Error:` line saying where the log was cut and how to go on, exit 1, no outputs."""
    path, victim = write(sim, tmp_path, fmt)
    cut(victim, fmt)
    result = fit(path, tmp_path / "o", "--strict")
    assert result.exit_code == 1, result.stderr
    lines = [line for line in result.stderr.splitlines() if not line.startswith("magcal:")]
    assert len(lines) == 1, result.stderr
    where = re.escape(str(victim if fmt == "ros2-mcap" else path))
    assert re.fullmatch(rf"Error: {where}: the log is cut: it ends inside a record( at byte \d+ of \d+)? \(.+\)\. "
                        r"Re-copy the log, or leave out --strict to calibrate from its complete records", lines[0])
    assert not (tmp_path / "o").exists()
    with pytest.raises(TruncatedLogError):
        open_recording(path, options=ReadOptions(allow_truncated=False))


@pytest.mark.parametrize("fmt", ["bin", "mcap", "bag"])
def test_complete_log_is_not_cut(tmp_path: Path, sim: Simulation, fmt: str) -> None:
    """A whole log: no cut, no warning, and --strict changes nothing."""
    path, _ = write(sim, tmp_path, fmt)
    result = fit(path, tmp_path / "o", "--strict")
    assert result.exit_code == 0, result.stderr
    assert "the log is cut" not in result.stderr


def test_cut_single_chunk_keeps_the_messages_its_present_bytes_hold(tmp_path: Path, sim: Simulation) -> None:
    """A short log is one compressed chunk: cut inside it, the messages before the cut are still read."""
    write_mcap(sim, tmp_path / "x.mcap")                           # 1 MB chunks: the whole log in one
    data = (tmp_path / "x.mcap").read_bytes()
    (tmp_path / "x.mcap").write_bytes(data[:len(data) // 2])
    rec = open_recording(tmp_path / "x.mcap")
    assert rec.cut is not None
    assert re.search(r"a chunk record, \d+ of its \d+ bytes present; \d+ messages recovered from it", rec.cut.lost)
    assert len(rec.select(Kind.MAGNETOMETER)) > 0.3 * len(sim.recording.select(Kind.MAGNETOMETER))


def test_allow_truncated_is_a_hidden_deprecated_alias(tmp_path: Path, sim: Simulation) -> None:
    """Old scripts keep working: --allow-truncated is accepted, says it is deprecated, and is not in --help."""
    path, victim = write(sim, tmp_path, "bin")
    cut(victim, "bin")
    result = fit(path, tmp_path / "o", "--allow-truncated")
    assert result.exit_code == 0, result.stderr
    assert "--allow-truncated is deprecated" in result.stderr
    help_text = CliRunner().invoke(cli, ["fit", "--help"]).output
    assert "--strict" in help_text and "--allow-truncated" not in help_text
