"""Legacy PX4 sdlog2 `.px4log`: detection by message set, TIME-stamped groups, gauss field, real log.

Modules it covers (the mirrored test file aside): magcal_cli.readers.dataflash.px4log.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from magcal_cli.errors import StreamError
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind

#: (type, name, format, columns) as sdlog2 defines them
FORMATS = [
    (129, "TIME", "Q", "StartTime"),
    (4, "IMU", "ffffffffffff", "AccX,AccY,AccZ,GyroX,GyroY,GyroZ,MagX,MagY,MagZ,tA,tG,tM"),
    (2, "ATT", "fffffffffffff", "qw,qx,qy,qz,Roll,Pitch,Yaw,RollRate,PitchRate,YawRate,GX,GY,GZ"),
    (20, "BATT", "ffff", "V,VFilt,C,Discharged"),
    (131, "PARM", "Nf", "Name,Value"),
]
CODES = {"Q": "Q", "f": "f", "N": "16s"}


def record(type_id: int, *values: object) -> bytes:
    """One sdlog2 record (header A3 95 <type>)."""
    fmt = next(f for t, _, f, _ in FORMATS if t == type_id)
    return bytes([0xA3, 0x95, type_id]) + struct.pack("<" + "".join(CODES[c] for c in fmt), *values)


def px4log(n: int, mag: np.ndarray) -> bytes:
    """FMT records, a parameter and n logging cycles of TIME, IMU, ATT (Euler only), BATT."""
    out = []
    for type_id, name, fmt, cols in FORMATS:
        size = struct.calcsize("<" + "".join(CODES[c] for c in fmt)) + 3
        out.append(bytes([0xA3, 0x95, 0x80]) + struct.pack("<BB4s16s64s", type_id, size, name.encode(),
                                                           fmt.encode(), cols.encode()))
    out.append(record(131, b"CAL_MAG0_XOFF", 0.09))
    for k in range(n):
        out.append(record(129, 500_000_000 + 12_000 * k))
        out.append(record(4, 0.0, 0.0, -9.8, 0.01, 0.0, 0.0, *mag[k], 37.0, 37.0, 28.5))
        out.append(record(2, 0.0, 0.0, 0.0, 0.0, 0.1, 0.0, np.pi / 2, 0, 0, 0, 0, 0, 0))
        out.append(record(20, 24.0, 24.0, 0.5 + k, 100.0))
    return b"".join(out)


def test_synthetic_px4log_is_detected_and_timed(tmp_path: Path) -> None:
    """TIME.StartTime (us) times the records after it; IMU.MagX.. is gauss; ATT from Euler when q is zero."""
    mag = np.array([[0.3, -0.06, 0.47], [0.31, -0.05, 0.46], [0.29, -0.07, 0.48]])
    path = tmp_path / "old.px4log"
    path.write_bytes(px4log(3, mag))
    rec = open_recording(path)
    assert rec.format == "px4log" and rec.t0 == pytest.approx(500.0)
    m = rec.select(Kind.MAGNETOMETER, "MAG[0]")
    assert m.native_unit == "gauss"
    np.testing.assert_allclose(m.t, [0.0, 0.012, 0.024])
    np.testing.assert_allclose(m.values * 1e4, mag, rtol=1e-6)
    q = rec.select(Kind.ATTITUDE, "ATT").values[0]                  # Rz(90 deg) Rx(0.1 rad): q_yaw q_roll
    cy, sy, cr, sr = np.cos(np.pi / 4), np.sin(np.pi / 4), np.cos(0.05), np.sin(0.05)
    np.testing.assert_allclose(q, [cy * cr, cy * sr, sy * sr, sy * cr], atol=1e-6)
    np.testing.assert_allclose(rec.select(Kind.BATTERY_CURRENT).values[:, 0], [0.5, 1.5, 2.5])
    assert rec.params == {"CAL_MAG0_XOFF": pytest.approx(0.09)}
    assert any("calibrated as logged" in n for n in rec.notes)


def test_px4log_with_an_empty_field_is_a_clean_error(tmp_path: Path) -> None:
    """All-zero MagX..Z: no magnetometer."""
    path = tmp_path / "nomag.px4log"
    path.write_bytes(px4log(3, np.zeros((3, 3))))
    with pytest.raises(StreamError, match="no magnetometer data in the IMU records"):
        open_recording(path)


def test_real_px4log(realdata: Path) -> None:
    """01_07_59.px4log: IMU.MagX..Z in gauss at ~81 Hz with temperatures, ATT, BATT.C 0.3-51 A."""
    rec = open_recording(realdata / "px4" / "01_07_59.px4log")
    assert rec.format == "px4log" and len(rec.params) == 567 and rec.params["SENS_BOARD_ROT"] == 4
    assert rec.ids(Kind.MAGNETOMETER) == ["MAG[0]", "MAG[1]"]
    assert rec.ids(Kind.ACCELEROMETER) == ["IMU[0]", "IMU[1]"]
    mag = rec.select(Kind.MAGNETOMETER, "MAG[0]")
    assert mag.native_unit == "gauss" and len(mag) == 5742
    assert len(mag) / (mag.t[-1] - mag.t[0]) == pytest.approx(81.5, abs=1.0)
    assert 0.5 < np.median(np.linalg.norm(mag.values, axis=1)) * 1e4 < 0.6
    temps = {s.id: s.values for s in rec.of_kind(Kind.TEMPERATURE)}
    assert set(temps) == {"IMU[0]", "MAG[0]", "IMU[1]", "MAG[1]"} and 20.0 < temps["MAG[0]"].mean() < 45.0
    cur = rec.select(Kind.BATTERY_CURRENT, "BAT[0]").values
    assert cur.min() == pytest.approx(0.3, abs=0.1) and cur.max() == pytest.approx(51.0, abs=0.5)
    att = rec.select(Kind.ATTITUDE, "ATT").values
    np.testing.assert_allclose(np.linalg.norm(att, axis=1), 1.0, atol=1e-9)
    assert rec.ids(Kind.THROTTLE) == ["ATTC"] and rec.ids(Kind.POSITION) == ["GPS[0]"]
