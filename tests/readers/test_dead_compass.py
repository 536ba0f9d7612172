"""Issue 38 item 4: a dead or stuck compass is judged on the field as logged, before the reader undoes the firmware
correction, refused by name, and the log's other compasses are still calibrated."""

from __future__ import annotations

import dataclasses
import json
import re
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.readers import open_recording
from magcal_cli.readers.checks import dead_field, rotates
from magcal_cli.readers.dataflash.binary import parse_binary
from magcal_cli.streams import Kind
from magcal_cli.synth.firmware import CompassParams, PreviousCalibration
from magcal_cli.synth.logs import imu_sampling, write_log
from magcal_cli.synth.logs.dataflash import build
from magcal_cli.synth.simulate import Simulation, simulate
from tests.fuzzing import text_log

#: byte offsets in a MAG record (header 3, TimeUS Q, I B): MagX/Y/Z (int16 each, then Ofs and MO), Health (uint8)
MAG_AT, HEALTH_AT = 12, 30
#: a vehicle flying with motor compensation on current: what made a dead compass's reconstruction vary (issue 38)
PREV = PreviousCalibration(mot=(12.0, -8.0, 20.0), motct=2, current_swing_a=15.0,
                           more=(CompassParams(dia=(0.987, 1.024, 0.979), odi=(-0.012, 0.017, -0.006),
                                               mot=(-9.0, 14.0, 25.0)),))

Patch = Callable[[bytearray, int], None]


def zero_unhealthy(data: bytearray, pos: int) -> None:
    """A dead compass: field zero and Health 0, while the offsets and motor offsets (COMPASS_OFS2, COMPASS_MOT2 x
    current) are logged as the firmware holds them: undone, they made the zeros a varying field."""
    data[pos + MAG_AT:pos + MAG_AT + 6] = bytes(6)
    data[pos + HEALTH_AT] = 0


def stuck(data: bytearray, pos: int) -> None:
    """A stuck compass: the same reading (120, -40, 380) mG every time, marked healthy."""
    data[pos + MAG_AT:pos + MAG_AT + 6] = struct.pack("<hhh", 120, -40, 380)


@pytest.fixture(scope="module")
def sim2() -> Simulation:
    """A handheld simulation with two magnetometers (about 80 s, 10 Hz IMU, 5 Hz field)."""
    return simulate("handheld", 0, rate=10.0, mag_rate=5.0, mag_phase_s=0.0, n_mags=2)


def two_compass_bin(sim2: Simulation, path: Path, patches: dict[int, Patch]) -> Path:
    """The simulation as an ArduPilot .bin flown with COMPASS_MOT on a swinging current; MAG instance i's records
    patched by patches[i]."""
    path.write_bytes(build(sim2, PREV).tobytes())
    data = bytearray(path.read_bytes())
    mag = parse_binary(path).tables["MAG"]
    for pos, inst in zip(mag.pos.tolist(), mag.num("I").astype(int).tolist(), strict=True):
        if inst in patches:
            patches[inst](data, pos)
    path.write_bytes(bytes(data))
    return path


def fit(path: Path, out: Path) -> tuple[int, str, dict[str, object]]:
    """`magcal fit` with default options: exit code, stderr and the calibration document (empty on failure)."""
    result = CliRunner().invoke(cli, ["fit", str(path), "-o", str(out), "--outputs", "json", "-q"])
    doc = json.loads((out / "calibration.json").read_text()) if (out / "calibration.json").is_file() else {}
    return result.exit_code, result.stderr, doc


def refused_text(doc: dict[str, object]) -> str:
    """Everything the document says about magnetometers it did not calibrate (findings, notes, refusals)."""
    return json.dumps({k: v for k, v in doc.items() if k != "magnetometers"})


def calibrated_ids(doc: dict[str, object]) -> list[str]:
    """The ids of the calibrated magnetometers of a document."""
    mags = doc.get("magnetometers", [])
    assert isinstance(mags, list)
    return [m["id"] for m in mags if m.get("status", "calibrated") == "calibrated"]


def test_a_dead_compass_is_refused_by_name_and_the_other_calibrated(sim2: Simulation, tmp_path: Path) -> None:
    """Issue 38: MAG[1] logged all zero with Health 0 on a vehicle with COMPASS_MOT and offsets: the reader used to
    add COMPASS_MOT x current back to the zeros, so fit calibrated it (5952 % field-norm error). It is refused by
    name, the correction is not undone, and MAG[0] is calibrated."""
    path = two_compass_bin(sim2, tmp_path / "dead1.bin", {1: zero_unhealthy})
    rec = open_recording(path)
    assert rec.dead == {"MAG[1]": "all readings are zero and Health 0 throughout"}
    assert not np.any(rec.select(Kind.MAGNETOMETER, "MAG[1]").values)       # as logged, nothing added back
    code, err, doc = fit(path, tmp_path / "o")
    assert code == 0, err
    assert calibrated_ids(doc) == ["MAG[0]"]
    said = refused_text(doc)
    assert "MAG[1]" in said and "all readings are zero and Health 0 throughout" in said


def test_every_compass_dead_is_an_error_naming_each(sim2: Simulation, tmp_path: Path) -> None:
    """Both compasses dead: exit 1, one line naming MAG[0] and MAG[1] with why."""
    path = two_compass_bin(sim2, tmp_path / "dead2.bin", {0: zero_unhealthy, 1: zero_unhealthy})
    code, err, _ = fit(path, tmp_path / "o")
    assert code == 1, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), err
    for name in ("MAG[0]", "MAG[1]"):
        assert re.search(re.escape(name) + r"[^;]*all readings are zero and Health 0 throughout", lines[0]), err
    assert not (tmp_path / "o").exists()


def test_a_stuck_compass_is_refused_as_constant(sim2: Simulation, tmp_path: Path) -> None:
    """A compass that reads (120, -40, 380) mG throughout, marked healthy: refused as constant at that value."""
    path = two_compass_bin(sim2, tmp_path / "stuck.bin", {1: stuck})
    rec = open_recording(path)
    assert rec.dead == {"MAG[1]": "constant at (120, -40, 380) milligauss"}
    code, err, doc = fit(path, tmp_path / "o")
    assert code == 0, err
    assert calibrated_ids(doc) == ["MAG[0]"]
    assert "MAG[1]" in refused_text(doc) and "constant at (120, -40, 380) milligauss" in refused_text(doc)


def _text_with_nan(sim2: Simulation, tmp_path: Path, every: int) -> Path:
    """A text log of the two-compass flight whose MAG[1] field reads nan on every `every`-th record."""
    binary = two_compass_bin(sim2, tmp_path / "flight.bin", {})
    path = tmp_path / "flight.log"
    text_log(binary, path)
    lines, k = [], 0
    for line in path.read_text(encoding="latin-1").splitlines():
        cells = line.split(", ")
        if cells[0] == "MAG" and cells[2] == "1":
            if k % every == 0:
                cells[3:6] = ["nan"] * 3
            k += 1
        lines.append(", ".join(cells))
    path.write_text("\n".join(lines) + "\n", encoding="latin-1")
    return path


def test_a_compass_that_reads_nan_throughout_is_refused(sim2: Simulation, tmp_path: Path) -> None:
    """A text log whose MAG[1] reads nan in every record: it used to vanish (every sample dropped); it is refused
    by name and MAG[0] calibrated."""
    path = _text_with_nan(sim2, tmp_path, 1)
    assert open_recording(path).dead == {"MAG[1]": "every reading is NaN"}
    code, err, doc = fit(path, tmp_path / "o")
    assert code == 0, err
    assert calibrated_ids(doc) == ["MAG[0]"]
    assert "MAG[1]" in refused_text(doc) and "every reading is NaN" in refused_text(doc)


def test_nan_readings_of_a_live_compass_are_dropped_with_a_note(sim2: Simulation, tmp_path: Path) -> None:
    """Some NaN readings in a live compass are dropped, and a note says how many; the compass is not dead."""
    path = _text_with_nan(sim2, tmp_path, 7)
    rec = open_recording(path)
    n = len([ln for ln in path.read_text(encoding="latin-1").splitlines() if ln.startswith("MAG, ")
             and ln.split(", ")[2] == "1" and "nan" in ln])
    assert rec.dead == {}
    assert f"MAG[1] magnetometer: dropped {n} samples with NaN or inf" in rec.notes
    assert np.isfinite(rec.select(Kind.MAGNETOMETER, "MAG[1]").values).all()


def test_dead_field_reasons() -> None:
    """The verdicts on readings as logged, and one count of spread counts as stuck only while the vehicle turns."""
    x = np.zeros((50, 3))
    assert dead_field(x, "mG") == "all readings are zero"
    assert dead_field(x + np.nan, "mG") == "every reading is NaN"
    assert dead_field(x + [1.0, 2.0, 3.5], "mG") == "constant at (1, 2, 3.5) mG"
    wobble = x + [100.0, 0.0, 400.0] + (np.arange(50) % 2)[:, None]
    assert dead_field(wobble, "mG", quantum=1.0) is None
    assert dead_field(wobble, "mG", quantum=1.0, rotated=True) == (
        "constant at (100.5, 0.5, 400.5) mG within 1 count while the IMU shows the vehicle turning")
    assert dead_field(wobble * 3, "mG", quantum=1.0, rotated=True) is None
    t = np.arange(0.0, 10.0, 0.01)
    assert rotates(t, np.tile([0.0, 0.0, 0.5], (t.size, 1)))                 # 0.5 rad/s for 10 s: 286 deg
    assert not rotates(t, np.tile([0.0, 0.0, 0.02], (t.size, 1)))            # drift, not a turn


@pytest.mark.parametrize("ext", [".mcap", ".bag", ".ulg"])
def test_a_nan_magnetometer_of_a_bag_or_ulog_is_refused_by_name(tmp_path: Path, ext: str) -> None:
    """ROS bags, MCAP and ULog pass the field as logged: a second magnetometer reading NaN throughout used to
    vanish (its every sample dropped); it is kept, refused by name, and the first one calibrated."""
    path = tmp_path / f"nan{ext}"
    sim = simulate("handheld", 0, rate=10.0, mag_rate=5.0, mag_phase_s=0.0, n_mags=2, imu_sampling=imu_sampling(path))
    second = sim.recording.of_kind(Kind.MAGNETOMETER)[1].id
    streams = tuple(dataclasses.replace(s, values=np.full_like(s.values, np.nan))
                    if s.kind is Kind.MAGNETOMETER and s.id == second else s for s in sim.recording.streams)
    write_log(dataclasses.replace(sim, recording=dataclasses.replace(sim.recording, streams=streams)), path)
    ids = open_recording(path).ids(Kind.MAGNETOMETER)
    assert len(ids) == 2
    code, err, doc = fit(path, tmp_path / "o")
    assert code == 0, err
    assert calibrated_ids(doc) == ids[:1]
    assert re.search(re.escape(ids[1]) + r" reads NaN in all \d+ samples", refused_text(doc)), refused_text(doc)


def test_a_csv_magnetometer_whose_every_cell_is_empty_is_the_dead_sensor_error(tmp_path: Path) -> None:
    """A CSV whose mx, my, mz cells are all empty exited 123 (`cannot reshape array of size 0`); it is the
    dead-sensor error naming the magnetometer."""
    path = tmp_path / "x.csv"
    sim = simulate("handheld", 0, rate=10.0, mag_rate=10.0, mag_phase_s=0.0)
    streams = tuple(dataclasses.replace(s, values=np.full_like(s.values, np.nan)) if s.kind is Kind.MAGNETOMETER
                    else s for s in sim.recording.streams)
    write_log(dataclasses.replace(sim, recording=dataclasses.replace(sim.recording, streams=streams)), path)
    code, err, _ = fit(path, tmp_path / "o")
    assert code == 1, err
    assert re.fullmatch(r"Error: x\.csv#mx \[uT\], my \[uT\], mz \[uT\]: the magnetometer mag reads NaN in all \d+ "
                        r"samples; the sensor is stuck, disconnected or not enabled \(or the column is a placeholder\)"
                        r"\. Check the sensor and its logging, and record again", err.strip()), err
