"""ArduPilot DataFlash: vectorised parser, firmware correction and inverse, round trips, text, real logs.

Modules it covers (the mirrored test file aside): magcal_cli.readers.dataflash.ardupilot,
magcal_cli.readers.dataflash.binary, magcal_cli.readers.dataflash.compass,
magcal_cli.readers.dataflash.format, magcal_cli.readers.dataflash.load, magcal_cli.readers.dataflash.rawfield,
magcal_cli.readers.dataflash.reader, magcal_cli.readers.dataflash.streams, magcal_cli.readers.dataflash.text.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.errors import LogReadError, StreamError, UnsupportedFormatError
from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.readers.dataflash.ardupilot import reconstruct_mags
from magcal_cli.readers.dataflash.binary import follow_chain, parse_buffer
from magcal_cli.readers.dataflash.compass import (
    Correction,
    ParamHistory,
    apply_correction,
    effective_scale,
    iron_matrix,
    param_suffix,
    undo_correction,
)
from magcal_cli.readers.dataflash.rawfield import sample_time
from magcal_cli.streams import Kind
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.logs.dataflash import PreviousCalibration, build
from magcal_cli.synth.simulate import Simulation, simulate

from ..fuzzing import DeadSensor


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A short handheld simulation (about 90 s: 12 poses at least)."""
    return simulate("handheld", 1, duration=40.0)


def quantisation_bound(c: Correction, motor_truncated: bool) -> float:
    """Largest raw error (mG) from int16 truncation of MagX.. (and MOX..): |M^-1|_inf (1 + [MO]) / SCALE."""
    inv = np.linalg.inv(c.matrix)
    return float(np.max(np.abs(inv).sum(axis=2).max(axis=1) * (1.0 + motor_truncated) / c.scale)) + 1e-6


def write_bin(tmp_path: Path, sim: Simulation, prev: PreviousCalibration | None = None) -> Path:
    """The simulation as a .bin flown with `prev`."""
    path = tmp_path / "sim.bin"
    build(sim, prev).tofile(path)
    return path


# --- the firmware correction (design/firmware-export.md section 1) ---------------------------------------


def test_correction_follows_the_firmware_formula() -> None:
    """correct_field: x = M ((raw + OFS) * SCALE) + MO, written out by hand for one sample."""
    raw, ofs, mo = np.array([100.0, -50.0, 400.0]), np.array([-100.0, 20.0, 30.0]), np.array([5.0, -5.0, 2.0])
    m = np.array([[1.1, 0.01, 0.02], [0.01, 0.9, -0.03], [0.02, -0.03, 1.0]])
    c = Correction(ofs[None], iron_matrix(np.array([[1.1, 0.9, 1.0]]), np.array([[0.01, 0.02, -0.03]])),
                   np.array([1.2]), mo[None])
    x = (raw + ofs) * 1.2
    expected = m @ x + mo
    np.testing.assert_allclose(apply_correction(raw[None], c)[0], expected, rtol=1e-12)
    np.testing.assert_allclose(undo_correction(expected[None], c)[0], raw, rtol=1e-12)


def test_a_positive_bias_needs_a_negative_offset() -> None:
    """Sign smoke test of the design note: a +100 mG x bias is removed by COMPASS_OFS_X = -100."""
    field = np.array([[200.0, 0.0, 400.0]])
    c = Correction(np.array([[-100.0, 0.0, 0.0]]), iron_matrix(np.zeros((1, 3)), np.zeros((1, 3))),
                   np.ones(1), np.zeros((1, 3)))
    np.testing.assert_allclose(apply_correction(field + [100.0, 0.0, 0.0], c), field)


def test_old_firmware_adds_motor_offsets_before_the_matrix() -> None:
    """Firmware before 3.6 added MO to the offset-corrected field and then applied the iron matrix."""
    raw, mo = np.array([[10.0, 20.0, 30.0]]), np.array([[4.0, -6.0, 8.0]])
    m = iron_matrix(np.array([[1.2, 0.8, 1.0]]), np.array([[0.1, 0.0, 0.0]]))
    c = Correction(np.zeros((1, 3)), m, np.ones(1), mo, motor_after_matrix=False)
    np.testing.assert_allclose(apply_correction(raw, c), (m[0] @ (raw + mo)[0])[None])
    np.testing.assert_allclose(undo_correction(apply_correction(raw, c), c), raw)


def test_scale_outside_its_range_and_zero_diagonals_are_ignored() -> None:
    """have_scale_factor: 0.85 <= SCALE <= 1.4 (inclusive); DIA = (0, 0, 0) means ones."""
    np.testing.assert_array_equal(effective_scale(np.array([0.0, 0.84, 0.85, 1.2, 1.4, 1.41])),
                                  [1.0, 1.0, 0.85, 1.2, 1.4, 1.0])
    np.testing.assert_array_equal(iron_matrix(np.zeros((1, 3)), np.zeros((1, 3)))[0], np.eye(3))


def test_parameters_in_force_at_each_time() -> None:
    """The latest record at or before t applies; before the first record, the first value."""
    hist = ParamHistory(["A", "A", "B"], np.array([10.0, 20.0, 5.0]), np.array([1.0, 2.0, 7.0]))
    np.testing.assert_array_equal(hist.at("A", np.array([0.0, 10.0, 15.0, 20.0, 99.0]), 0.0), [1, 1, 1, 2, 2])
    np.testing.assert_array_equal(hist.at("C", np.array([1.0]), 3.5), [3.5])
    assert hist.changes("A") == 1 and hist.last() == {"A": 2.0, "B": 7.0}


def test_param_suffix_follows_the_priority_list() -> None:
    """MAG instance I uses suffix I+1 unless COMPASS_PRIO{I+1}_ID names another slot's device."""
    assert param_suffix(1, {}) == ("2", None)
    params = {"COMPASS_PRIO1_ID": 5.0, "COMPASS_DEV_ID": 7.0, "COMPASS_DEV_ID2": 5.0}
    suffix, note = param_suffix(0, params)
    assert suffix == "2" and note is not None and "COMPASS_DEV_ID2" in note


def test_sample_time_unwraps_the_uint32_stamp() -> None:
    """MAG.S is uint32 microseconds: after 71.6 min it wraps, TimeUS does not."""
    time_us = np.array([5_000_000_150.0, 1_000_000.0])
    s = np.array([5_000_000_000.0 % 2**32, 0.0])
    np.testing.assert_allclose(sample_time(time_us, s), [5000.0, 1.0])


# --- the vectorised binary parser -------------------------------------------------------------------------


def test_chain_skips_a_header_inside_a_payload() -> None:
    """A3 95 inside a payload is a candidate but not on the chain; corrupt bytes are skipped."""
    heads = np.array([0, 5, 10, 20, 33, 40])          # 5: inside record 0; 33: in the corrupt bytes 30..39
    lengths = np.array([10, 10, 10, 10, 4, 10])
    offs, _ = follow_chain(heads, lengths, 50)
    np.testing.assert_array_equal(offs, [0, 10, 40])  # record 20 ends in garbage: dropped with it


def test_round_trip_within_quantisation(tmp_path: Path, sim: Simulation) -> None:
    """simulate -> .bin -> read: raw field within int16 truncation, IMU within float32, same times."""
    path = write_bin(tmp_path, sim)
    rec = open_recording(path)
    assert rec.format == "dataflash" and rec.t0 == pytest.approx(30.0)
    mag, truth = rec.select(Kind.MAGNETOMETER, "MAG[0]"), sim.recording.select(Kind.MAGNETOMETER)
    assert mag.native_unit == "milligauss" and len(mag) == len(truth)
    np.testing.assert_allclose(mag.t, truth.t, atol=1e-6)
    (m,) = reconstruct_mags(path)
    err = np.abs(mag.values - truth.values).max() * 1e7
    assert err <= quantisation_bound(m.correction, False)
    for kind in (Kind.ACCELEROMETER, Kind.GYROSCOPE):
        got, want = rec.select(kind, "IMU[0]"), sim.recording.select(kind)
        np.testing.assert_allclose(got.values, want.values, rtol=1e-6, atol=1e-6)
    assert {s.id for s in rec.streams} == {"IMU[0]", "MAG[0]", "ATT", "BAT[0]", "CTUN", "GPS[0]"}
    assert rec.params["COMPASS_DIA_X"] == pytest.approx(1.031, abs=1e-6)
    assert any("undid the firmware correction" in n and "DIA=(1.031, 0.968, 1.012)" in n for n in rec.notes)


def test_round_trip_with_scale_motor_current_and_a_parameter_change(tmp_path: Path, sim: Simulation) -> None:
    """SCALE, MOT x current (MOTCT=2) and a mid-log COMPASS_OFS change are all undone per sample."""
    prev = PreviousCalibration(scale=1.1, mot=(3.0, -2.0, 5.0), motct=2, current_swing_a=20.0,
                               change_at_s=40.0, ofs_after=(40.0, -30.0, 20.0))
    path = write_bin(tmp_path, sim, prev)
    (m,) = reconstruct_mags(path)
    truth = sim.recording.select(Kind.MAGNETOMETER).values * 1e7
    assert np.abs(m.raw - truth).max() <= quantisation_bound(m.correction, True)
    assert np.abs(m.correction.motor).max() > 50.0                     # the test exercises MO
    late = m.t - m.t[0] >= 40.0 - 1e-3
    np.testing.assert_allclose(m.correction.ofs[late][0], [40.0, -30.0, 20.0])
    assert "changed during the log" in m.notes[-1] and "SCALE=1.1" in m.notes[-1]


def test_reapplying_the_parameters_reproduces_the_logged_field(tmp_path: Path, sim: Simulation) -> None:
    """apply_correction(reconstruction) is the logged integers plus the half count the int16 cast truncated
    toward zero, and the firmware's own truncation of it gives back exactly the logged integers."""
    (m,) = reconstruct_mags(write_bin(tmp_path, sim, PreviousCalibration(scale=0.9)))
    again = apply_correction(m.raw, m.correction)
    np.testing.assert_allclose(again, m.logged + 0.5 * np.sign(m.logged), atol=1e-9)
    np.testing.assert_array_equal(np.trunc(np.round(again, 6)), m.logged)


def test_corrupt_bytes_are_skipped_and_counted(tmp_path: Path, sim: Simulation) -> None:
    """Garbage (with fake headers) inserted at three places: the rest reads, the skipped bytes are noted."""
    data = build(sim)
    rng = np.random.default_rng(4)
    garbage = rng.integers(0, 256, 300).astype(np.uint8)
    garbage[::37], garbage[1::37], garbage[2::37] = 0xA3, 0x95, 163          # fake IMU headers
    cuts = [len(data) // 4, len(data) // 2, 3 * len(data) // 4]
    pieces = np.split(data, cuts)
    corrupt = np.concatenate([pieces[0], garbage, pieces[1], garbage, pieces[2], garbage, pieces[3]])
    clean, broken = parse_buffer(data), parse_buffer(corrupt)
    assert clean.skipped_bytes == 0
    assert 3 * 300 <= broken.skipped_bytes <= 3 * 300 + 3 * 2 * 54
    assert clean.counts["IMU"] - 6 <= broken.counts["IMU"] <= clean.counts["IMU"]
    path = tmp_path / "corrupt.bin"
    corrupt.tofile(path)
    rec = open_recording(path)
    assert any("skipped" in n and "resynchronised" in n for n in rec.notes)
    got = rec.select(Kind.MAGNETOMETER).values
    field = np.linalg.norm(sim.truth.D, 2) * 1e7          # the largest |D m| (mG): no sample beyond it (+ hard iron)
    assert np.all(np.linalg.norm(got, axis=1) * 1e7 < field + 60.0)   # no garbage samples
    assert np.all(np.linalg.norm(got, axis=1) * 1e7 > np.linalg.norm(sim.truth.D, -2) * 1e7 - 60.0)


def test_truncated_mid_record_reads_the_complete_messages(tmp_path: Path, sim: Simulation) -> None:
    """A log cut inside a record yields every complete message and a note saying where it was cut (issue 12);
    --strict refuses it (as for every format)."""
    data = build(sim)
    path = tmp_path / "cut.bin"
    data[: len(data) // 2 + 7].tofile(path)
    with pytest.raises(LogReadError, match=r"cut.bin: the log is cut: it ends inside a record at byte \d+ of \d+ "
                                           r"\(an? \w+ record, \d+ of its \d+ bytes present\)\. Re-copy the log, "
                                           r"or leave out --strict"):
        open_recording(path, options=ReadOptions(allow_truncated=False))
    rec = open_recording(path)
    assert rec.cut is not None and rec.notes[0] == rec.cut.message
    assert 0.4 < rec.select(Kind.ACCELEROMETER).t[-1] / sim.recording.select(Kind.ACCELEROMETER).t[-1] < 0.6


def test_not_a_dataflash_log_is_a_clean_error(tmp_path: Path) -> None:
    """Random bytes named .bin: one line naming the problem."""
    path = tmp_path / "noise.bin"
    path.write_bytes(np.random.default_rng(0).integers(1, 160, 4000).astype(np.uint8).tobytes())
    with pytest.raises(UnsupportedFormatError, match="not a DataFlash log"):
        open_recording(path)


def test_headers_only_is_a_clean_error(tmp_path: Path, sim: Simulation) -> None:
    """FMT records and nothing else."""
    data = build(sim)
    path = tmp_path / "fmt.bin"
    data[: 89 * 13].tofile(path)
    with pytest.raises(LogReadError, match="no data records"):
        open_recording(path)


def test_simulate_cli_writes_bin(tmp_path: Path, sim: Simulation) -> None:
    """`magcal simulate out.bin` goes through the LOG_WRITERS registry."""
    write_log(sim, tmp_path / "x.bin")
    assert open_recording(tmp_path / "x.bin").select(Kind.MAGNETOMETER).id == "MAG[0]"


# --- text logs ---------------------------------------------------------------------------------------------

TEXT_FMT = """FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns
FMT, 129, 31, PARM, QNf, TimeUS,Name,Value
FMT, 133, 75, MSG, QZ, TimeUS,Message
FMT, 132, 49, IMU, QffffffIIfBB, TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG,ErrA,Temp,GyHlt,AcHlt
FMT, 169, 30, MAG, QhhhhhhhhhB, TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health
FMT, 168, 25, CURR, QhhhHfh, TimeUS,Throttle,Volt,Curr,Vcc,CurrTot,Volt2
FMT, 4, 39, CTUN, Qhhfffecchh, TimeUS,ThrIn,AngBst,ThrOut,DAlt,Alt,BarAlt,DSAlt,SAlt,DCRt,CRt
"""


def text_log(raw: np.ndarray, version: str = "V3.4-dev") -> tuple[str, Correction]:
    """A Copter 3.x text log of raw readings (N, 3) mG with a calibration and motor offsets applied."""
    n = len(raw)
    ofs, mo = np.array([-30.0, 20.0, -50.0]), np.array([5.0, -3.0, 8.0])
    dia, odi = np.array([1.05, 0.95, 1.0]), np.array([0.02, -0.01, 0.03])
    matrix = iron_matrix(np.tile(dia, (n, 1)), np.tile(odi, (n, 1)))
    corr = Correction(np.tile(ofs, (n, 1)), matrix, np.ones(n), np.tile(mo, (n, 1)), motor_after_matrix=False)
    logged = np.trunc(apply_correction(raw, corr)).astype(int)
    lines = [TEXT_FMT, "ArduCopter V3.0.1 (5c6503e2)", "Free RAM: 1331",
             f"MSG, 900000, APM:Copter {version} (461eff25)"]
    for name, vals in [("OFS", ofs), ("DIA", dia), ("ODI", odi)]:
        lines += [f"PARM, 1000000, COMPASS_{name}_{a}, {v}" for a, v in zip("XYZ", vals, strict=True)]
    for k in range(n):
        t = 2_000_000 + 100_000 * k
        lines.append(f"IMU, {t - 10}, 0.01, 0.02, 0.03, 0.1, 0.2, -9.8, 0, 0, 43.5, 1, 1")
        lines.append(f"MAG, {t}, {', '.join(map(str, logged[k]))}, -30, 20, -50, 5, -3, 8, 1")
        lines.append(f"CURR, {t + 5}, 87, 1215, {131 + k}, 5164, 20.5, 0")
        lines.append(f"CTUN, {t + 7}, 0, 0, {250.0 + k}, 0, 0, 0, 0, 0, 0, 0")
    lines.append("IMU, 5")                                                  # a malformed record
    return "\r\n".join(lines) + "\r\n", corr


def test_text_log_reconstruction_before_copter_36(tmp_path: Path) -> None:
    """Text records, centi-amps, 0..1000 throttle and the 3.x order (motor offsets before the matrix)."""
    rng = np.random.default_rng(2)
    u = rng.standard_normal((40, 3))
    raw = 450.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [30.0, -20.0, 50.0]
    text, corr = text_log(raw)
    path = tmp_path / "old.log"
    path.write_text(text)
    rec = open_recording(path)
    got = rec.select(Kind.MAGNETOMETER, "MAG[0]").values * 1e7
    assert np.abs(got - raw).max() <= quantisation_bound(corr, False)
    cur = rec.select(Kind.BATTERY_CURRENT, "BAT[0]")
    np.testing.assert_allclose(cur.values[:3, 0], [1.31, 1.32, 1.33])
    assert cur.native_unit == "cA"
    np.testing.assert_allclose(rec.select(Kind.THROTTLE).values[:2, 0], [0.25, 0.251])
    assert rec.select(Kind.TEMPERATURE, "IMU[0]").values[0, 0] == pytest.approx(43.5)
    assert any("malformed" in n for n in rec.notes)
    assert any("before the iron matrix" in n and "3.4" in n for n in rec.notes)


def test_text_log_without_mag_records_is_a_clean_error(tmp_path: Path) -> None:
    """An old log that defines MAG but never writes it (like robert_lefebvre_octo_PM.log)."""
    path = tmp_path / "nomag.log"
    path.write_text(TEXT_FMT + "PARM, 1, COMPASS_OFS_X, 3\r\nIMU, 5, 0, 0, 0, 0, 0, -9.8, 0, 0, 40, 1, 1\r\n")
    with pytest.raises(StreamError, match=r"no magnetometer messages \(MAG defined by FMT but never written"):
        open_recording(path)


# --- real logs (../shared/realdata/ardupilot; README expectations) ------------------------------------------

#: file -> (magnetometer ids, IMU ids, duration s, MAG rate Hz, IMU rate Hz, current range A)
REAL = {
    "log171.bin": (("MAG[0]", "MAG[1]", "MAG[2]"), ("IMU[0]", "IMU[1]", "IMU[2]"), 243.0, 10.0, 49.0,
                   (0.5, 27.0)),
    "2015-10-11_19-53-46.log": (("MAG[0]", "MAG[1]"), ("IMU[0]", "IMU[1]"), 106.0, 10.0, 48.0, (1.0, 24.0)),
    "2015-10-11_19-59-09.log": (("MAG[0]", "MAG[1]"), ("IMU[0]", "IMU[1]"), 68.0, 10.0, 48.0, (1.2, 25.0)),
    "2015-10-11_20-17-22.log": (("MAG[0]", "MAG[1]"), ("IMU[0]", "IMU[1]"), 113.0, 10.0, 48.0, (1.2, 23.5)),
}


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_logs_read_as_the_readme_says(realdata: Path, name: str) -> None:
    """Streams, counts, rates, units and current ranges of the real ArduPilot logs."""
    mags, imus, duration, mag_hz, imu_hz, (lo, hi) = REAL[name]
    rec = open_recording(realdata / "ardupilot" / name)
    assert tuple(rec.ids(Kind.MAGNETOMETER)) == mags
    assert tuple(rec.ids(Kind.ACCELEROMETER)) == imus == tuple(rec.ids(Kind.GYROSCOPE))
    for s in rec.of_kind(Kind.MAGNETOMETER):
        assert s.native_unit == "milligauss"
        assert abs(len(s) / (s.t[-1] - s.t[0]) - mag_hz) < 0.6
        assert 150.0 < np.median(np.linalg.norm(s.values, axis=1)) * 1e7 < 1000.0
    imu = rec.select(Kind.ACCELEROMETER, "IMU[0]")
    assert abs(len(imu) / (imu.t[-1] - imu.t[0]) - imu_hz) < 1.5
    assert abs(np.median(np.linalg.norm(imu.values, axis=1)) - 9.8) < 0.3
    assert imu.t[-1] == pytest.approx(duration, abs=1.5)
    cur = rec.select(Kind.BATTERY_CURRENT, "BAT[0]").values
    assert cur.min() == pytest.approx(lo, abs=0.3) and cur.max() == pytest.approx(hi, abs=1.0)
    assert rec.ids(Kind.ATTITUDE) == ["ATT", "AHR2"] and rec.ids(Kind.POSITION) == ["GPS[0]"]
    assert len([n for n in rec.notes if "undid the firmware correction" in n]) == len(mags)


def test_text_logs_have_no_motor_compensation_and_little_tilt(realdata: Path) -> None:
    """2015-10-11 logs: COMPASS_MOTCT = 0, yaw over 0..360 deg, tilt within about 24 deg (ATT)."""
    from magcal_cli import so3

    rec = open_recording(realdata / "ardupilot" / "2015-10-11_19-53-46.log")
    assert rec.params["COMPASS_MOTCT"] == 0
    rpy = np.rad2deg(so3.as_rpy(so3.from_quat(rec.select(Kind.ATTITUDE, "ATT").values)))
    assert np.abs(rpy[:, :2]).max() < 26.0 and np.ptp(np.mod(rpy[:, 2], 360.0)) > 300.0


def test_log171_reconstruction_fits_as_well_and_reapplies_exactly(realdata: Path) -> None:
    """log171: the raw field of each compass fits an ellipsoid as well as the logged field (an affine image
    of the same points: equal up to the algebraic fit's 1 % non-invariance), MAG3 (uncalibrated) is its
    logged sphere (centre (484, 263, 466), radius 569, residual 56 mG), and re-applying the logged
    parameters reproduces the logged field within 1 mG."""
    from magcal_cli.ellipsoid import fit_ellipsoid

    mags = reconstruct_mags(realdata / "ardupilot" / "log171.bin")
    assert [m.instance for m in mags] == [0, 1, 2]
    for m in mags:
        raw_fit, logged_fit = fit_ellipsoid(m.raw).residual_rms, fit_ellipsoid(m.logged).residual_rms
        assert raw_fit <= 1.01 * logged_fit
        assert np.abs(apply_correction(m.raw, m.correction) - m.logged).max() < 1.0
    assert np.abs(mags[0].raw - mags[0].logged).max() > 100.0          # compass 1 was calibrated
    y = mags[2].raw
    a = np.c_[2.0 * y, np.ones(len(y))]
    sol = np.linalg.lstsq(a, (y**2).sum(axis=1), rcond=None)[0]
    radius = np.sqrt(sol[3] + sol[:3] @ sol[:3])
    resid = np.sqrt(np.mean((np.linalg.norm(y - sol[:3], axis=1) - radius) ** 2))
    np.testing.assert_allclose(sol[:3], [484.0, 263.0, 466.0], atol=2.0)
    assert radius == pytest.approx(569.0, abs=2.0) and resid == pytest.approx(56.0, abs=1.0)


def test_truncated_462_log_reads_its_complete_messages(realdata: Path) -> None:
    """ap462_truncated_80k.bin: instanced MAG/IMU, FMTU units, ends inside a record header."""
    rec = open_recording(realdata / "ardupilot" / "ap462_truncated_80k.bin")
    assert rec.cut is not None and rec.cut.lost == "a record header, 2 of its 3 bytes present"
    assert rec.cut.offset == rec.cut.size - 2
    assert rec.ids(Kind.MAGNETOMETER) == ["MAG[0]", "MAG[1]"]
    assert rec.ids(Kind.ACCELEROMETER) == ["IMU[0]", "IMU[1]"]
    assert [len(s) for s in rec.of_kind(Kind.MAGNETOMETER)] == [4, 4]
    assert len(rec.params) == 1077 and rec.params["COMPASS_DIA2_X"] == pytest.approx(1.02298, abs=1e-5)
    assert any(n.startswith("MAG[1]: undid") and "DIA2=(1.023, 1.039, 1.011)" in n for n in rec.notes)


def test_log_without_mag_is_a_clean_error(realdata: Path) -> None:
    """robert_lefebvre_octo_PM.log: no MAG records (pymavlink raises TypeError on its old GPS format)."""
    with pytest.raises(StreamError, match="no magnetometer messages") as info:
        open_recording(realdata / "ardupilot" / "robert_lefebvre_octo_PM.log")
    assert "\n" not in str(info.value)


# --- magcal fit end to end ---------------------------------------------------------------------------------

SAMPLE = Path(__file__).resolve().parents[2] / "sample_logs" / "handheld.bin"


def test_fit_recovers_the_truth_from_the_sample_bin() -> None:
    """sample_logs/handheld.bin: D within 5 % (relative Frobenius) and hard iron within 1 % of the field."""
    import json

    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate

    truth = json.loads(SAMPLE.with_name(SAMPLE.name + ".truth.json").read_text())["magnetometers"][0]
    assert (truth["id"], truth["units"]) == ("MAG[0]", "milligauss")     # the truth speaks the log's language
    (cal,) = calibrate(SAMPLE, Config()).calibration.magnetometers
    assert cal.id == "MAG[0]" and cal.unit == "milligauss"
    d_true, o_true = np.array(truth["D"]), np.array(truth["o"])
    assert np.linalg.norm(cal.D - d_true) / np.linalg.norm(d_true) < 0.05
    assert np.linalg.norm(cal.o - o_true) < 0.01 * np.cbrt(np.linalg.det(d_true))


@pytest.mark.parametrize("name", ["log171.bin", "2015-10-11_19-59-09.log"])
def test_fit_on_real_logs_writes_results_or_one_clean_line(realdata: Path, tmp_path: Path, name: str) -> None:
    """`magcal fit` on real logs: a calibration and report, or exit 1 with a single `Error:` line. The base model
    only: this is the reader's test; the default diagnosis of log171 runs in test_report_browser (a minute each)."""
    from click.testing import CliRunner

    from magcal_cli.cli.main import cli

    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["fit", str(realdata / "ardupilot" / name), "-o", str(out), "-q",
                                          "--outputs", "json,report", "--effects", "none"])
    assert result.exit_code in (0, 1), result.output
    if result.exit_code == 0:
        assert (out / "calibration.json").is_file() and (out / "report.txt").is_file()
        assert "undid the firmware correction" in (out / "report.txt").read_text()
    else:
        lines = [ln for ln in result.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("Error: ") and "Traceback" not in result.output


def test_dead_compass_with_all_fields_zero_is_the_dead_sensor_error(tmp_path: Path) -> None:
    """Issue 12: MAG records whose fields are all zero (Health too) exited 123 with `cannot reshape array of
    size 0`; the firmware's 'unhealthy' marks no longer empty the stream, so fit names the dead sensor, judged on
    the field as logged (issue 38)."""
    path = DeadSensor("magnetometer", "zero").write("bin", tmp_path)
    rec = open_recording(path)
    mag = rec.select(Kind.MAGNETOMETER, "MAG[0]")
    assert len(mag) > 500 and not np.any(mag.values)
    assert any(re.fullmatch(r"MAG\[0\]: the firmware marked all \d+ samples unhealthy", n) for n in rec.notes)
    result = CliRunner().invoke(cli, ["fit", str(path), "-o", str(tmp_path / "o"), "--outputs", "json", "-q"])
    assert result.exit_code == 1, result.stderr
    assert result.stderr.strip() == (
        f"Error: {path.name}: MAG[0]: the magnetometer measures no field as logged (all readings are zero and "
        "Health 0 throughout); the sensor is stuck, disconnected or not enabled (or the column is a "
        "placeholder). Check the sensor and its logging, and record again")
    assert not (tmp_path / "o").exists()


def test_reconstructed_counts_keep_their_resolution(tmp_path: Path, sim: Simulation) -> None:
    """The raw field behind int16 mG counts carries their quantisation (count/sqrt 12 through the undone DIA/ODI)
    as Stream.resolution, and the still detector finds the simulation's still poses in the log as in the source
    (without it, the transformed counts looked noise-free and the sample log kept 1 of 14 segments)."""
    from magcal_cli.config import Config
    from magcal_cli.detect import detect_still

    path = tmp_path / "r.bin"
    write_log(sim, path)
    rec = open_recording(path)
    mag = rec.select(Kind.MAGNETOMETER)
    (m,) = reconstruct_mags(path)
    inv = np.linalg.inv(m.correction.matrix[0]) / m.correction.scale[0]
    assert mag.resolution is not None
    np.testing.assert_allclose(mag.resolution, 1e-7 / np.sqrt(12) * np.linalg.norm(inv, axis=1), rtol=1e-9)
    assert mag.between(1.0, 5.0).resolution is mag.resolution

    cfg = Config().still
    src = sim.recording
    want = detect_still(src.select(Kind.ACCELEROMETER), src.select(Kind.GYROSCOPE), cfg,
                        (src.select(Kind.MAGNETOMETER),))
    got = detect_still(rec.select(Kind.ACCELEROMETER), rec.select(Kind.GYROSCOPE), cfg, (mag,))
    assert len(got.segments) == len(want.segments) >= 12


def test_the_date_comes_from_gps_time(tmp_path: Path, sim: Simulation) -> None:
    """A boot-clock log states its date through GPS week and time of week: utc0 is the simulation's start (the
    World Magnetic Model is evaluated on that date, not today's), and a log without GPS time has none."""
    path = tmp_path / "d.bin"
    write_log(sim, path)
    rec = open_recording(path)
    assert rec.t0 < 1e6 and rec.utc0 == pytest.approx(sim.recording.t0, abs=0.01)


def _sweeps(n: int = 6000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Times (n,) s and (n, 3) a field sweeping smoothly through zero on every axis at 100 Hz, mG, 2 mG of noise."""
    t = np.arange(n) / 100.0
    rng = np.random.default_rng(seed)
    return t, 300.0 * np.sin(np.outer(t, [0.31, 0.47, 0.23]) + [0.0, 1.0, 2.0]) + 2.0 * rng.standard_normal((n, 3))


def test_the_zero_bin_tells_a_truncating_cast_from_rounding() -> None:
    """Issue 25: AP_Compass's (int16_t) truncates toward zero (half a count is added back); a log rounded to the
    count (the independent simulator's flight) has no dead zone at zero, and nothing may be added."""
    from magcal_cli.readers.dataflash.compass import ROUNDED_EVIDENCE, truncation_evidence

    t, x = _sweeps()
    assert truncation_evidence([np.trunc(x)], [t]) > 2.0                     # the firmware's cast stands
    assert truncation_evidence([np.rint(x)], [t]) < -np.log(ROUNDED_EVIDENCE)
    # a pose held for 30 s with an axis near zero, truncated: its noise about -1.6 is no sweep through the zero bin
    still = np.array([-1.6, 0.4, 250.0]) + 2.0 * np.random.default_rng(1).standard_normal((3000, 3))
    both = np.concatenate([x, still]), np.concatenate([t, t[-1] + 0.01 + np.arange(3000) / 100.0])
    assert truncation_evidence([np.trunc(both[0])], [both[1]]) > 2.0


def test_motor_offsets_show_the_cast_they_went_through() -> None:
    """MO = COMPASS_MOT x current, logged as an int16: which of trunc and round it matches where they differ."""
    from magcal_cli.readers.dataflash.compass import motor_cast_evidence

    product = np.outer(np.linspace(0.5, 18.0, 500), [0.255, 0.126, -0.247])
    assert motor_cast_evidence(np.trunc(product), product) > 20.0
    assert motor_cast_evidence(np.rint(product), product) < -20.0
    assert motor_cast_evidence(np.rint(product), np.zeros_like(product)) == 0.0


def test_logged_offsets_show_the_cast_each_distinct_value_once() -> None:
    """OfsX.. = (int16_t)COMPASS_OFS in every record: one distinct pair per axis counts, however many records."""
    from magcal_cli.readers.dataflash.compass import ROUNDED_EVIDENCE, offset_cast_evidence

    params = np.repeat([[-11.40, -137.32, -27.70]], 500, axis=0)          # only z tells the casts apart
    assert offset_cast_evidence(np.trunc(params), params) == pytest.approx(np.log(ROUNDED_EVIDENCE))
    assert offset_cast_evidence(np.rint(params), params) == pytest.approx(-np.log(ROUNDED_EVIDENCE))


def test_rcou_motor_outputs_round_trip(tmp_path: Path) -> None:
    """issue 28: RCOU C1..C4 become motor[1..4] (0..1 of MOT_PWM_MIN..MAX, channel from SERVOn_FUNCTION); a log
    written without per-motor outputs has no RCOU and no motor streams."""
    sim = simulate("multirotor", 2, duration=90.0, effects=(EffectSpec("motor_interference"),))
    path = tmp_path / "motors.bin"
    write_log(sim, path)
    rec = open_recording(path)
    got = {s.id: s for s in rec.of_kind(Kind.MOTOR_OUTPUT)}
    assert sorted(got) == [f"motor[{k}]" for k in range(1, 5)]
    for s in sim.recording.of_kind(Kind.MOTOR_OUTPUT):
        g = got[s.id]                                                        # logged 600 us after the sample
        assert np.max(np.abs(g.values[:, 0] - np.interp(g.t - 6e-4, s.t, s.values[:, 0]))) < 6e-4   # whole us PWM
    plain = tmp_path / "plain.bin"
    write_log(simulate("multirotor", 2, duration=90.0), plain)
    assert not open_recording(plain).of_kind(Kind.MOTOR_OUTPUT)


def test_an_imu_temperature_shares_the_imus_stamps() -> None:
    """The IMU record's temperature has the IMU's own stamps after cleaning: one frozen array, not a second copy
    of a 400 Hz time base (issue 39); a record with other stamps keeps its own."""
    from pathlib import Path

    from magcal_cli.readers import open_recording
    from magcal_cli.streams import Kind

    rec = open_recording(Path(__file__).resolve().parents[2] / "sample_logs" / "handheld.bin")
    acc, temp = rec.select(Kind.ACCELEROMETER, "IMU[0]"), rec.select(Kind.TEMPERATURE, "IMU[0]")
    assert temp.t is acc.t and not temp.t.flags.writeable
    mag = rec.select(Kind.MAGNETOMETER, "MAG[0]")
    assert mag.t is not acc.t
