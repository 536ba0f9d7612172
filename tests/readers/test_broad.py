"""BROAD trials (HDF5 and MAT): streams, units, the mocap attitude in NED, repeated readings, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.errors import UnsupportedFormatError
from magcal_cli.readers import ReadOptions, open_recording, sniff
from magcal_cli.streams import Kind


@pytest.mark.parametrize("name", ["02_undisturbed_slow_rotation_B.hdf5",
                                  "01_undisturbed_slow_rotation_A.mat"])
def test_reads_both_layouts(realdata: Path, name: str) -> None:
    """IMU at 285.714 Hz in SI, the field in tesla (~44 uT), the mocap attitude as a unit quaternion."""
    path = realdata / "broad" / name
    assert sniff(path) == "broad"
    rec = open_recording(path)
    acc, gyr = rec.select(Kind.ACCELEROMETER), rec.select(Kind.GYROSCOPE)
    mag, att = rec.select(Kind.MAGNETOMETER), rec.select(Kind.ATTITUDE)
    assert acc.id == gyr.id == "imu" and mag.id == "mag"
    assert abs(acc.rate_hz - 285.714) < 0.01
    np.testing.assert_allclose(np.median(np.linalg.norm(acc.values, axis=1)), 9.81, atol=0.1)
    assert 40e-6 < np.median(np.linalg.norm(mag.values, axis=1)) < 48e-6
    assert mag.native_unit == "microtesla"
    np.testing.assert_allclose(np.linalg.norm(att.values, axis=1), 1.0, atol=1e-9)
    assert np.all(np.any(np.diff(mag.values, axis=0) != 0, axis=1))           # repeated readings dropped
    assert any("repeat the previous one" in n for n in rec.notes)


def test_attitude_is_imu_to_ned(realdata: Path) -> None:
    """The accelerometer reads ~ -R^T g_n: the converted mocap attitude predicts it (ENU -> NED done)."""
    rec = open_recording(realdata / "broad" / "02_undisturbed_slow_rotation_B.hdf5")
    acc, att = rec.select(Kind.ACCELEROMETER), rec.select(Kind.ATTITUDE)
    idx = np.searchsorted(acc.t, att.t[:2000])
    rot = so3.from_quat(att.values[:2000])
    predicted = -9.81 * rot[:, 2, :]                                     # -R^T [0, 0, g]
    err = np.degrees(np.arccos(np.clip(np.sum(predicted * acc.values[idx], axis=1)
                                       / np.linalg.norm(predicted, axis=1)
                                       / np.linalg.norm(acc.values[idx], axis=1), -1, 1)))
    assert np.median(err) < 3.0


def test_hdf5_without_broad_datasets_is_unsupported(tmp_path: Path) -> None:
    """Another HDF5 file is refused with a message naming the layout magcal reads."""
    import h5py

    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as fh:
        fh["something"] = np.zeros(3)
    with pytest.raises(UnsupportedFormatError, match="without the BROAD datasets imu_acc, imu_gyr, imu_mag"):
        open_recording(path, options=ReadOptions())
