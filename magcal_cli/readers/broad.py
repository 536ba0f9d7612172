"""BROAD dataset trials (Laidig et al., "BROAD -- A Benchmark for Robust Inertial Orientation Estimation",
Data 2021): one IMU with optical motion capture, as HDF5 (.hdf5) or MATLAB (.mat) files.

Datasets: `imu_acc` (m/s^2), `imu_gyr` (rad/s), `imu_mag` (uT), `opt_quat` (w, x, y, z, IMU -> ENU, NaN when
tracking was lost), `sampling_rate` (Hz, an attribute in HDF5). All sensors share one clock: sample k is at
k / sampling_rate. The mocap orientation becomes an attitude stream (IMU -> NED) for scoring headings.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from magcal_cli import so3
from magcal_cli.align import clean_time
from magcal_cli.errors import LogReadError, UnsupportedFormatError
from magcal_cli.readers import ReadOptions
from magcal_cli.streams import Kind, Recording, Sampling, Stream

REQUIRED = ("imu_acc", "imu_gyr", "imu_mag")
#: ENU -> NED: swap x and y, flip z
ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def _load_hdf5(path: Path) -> dict[str, Any]:
    """The arrays and the sampling rate of a BROAD .hdf5 file."""
    import h5py

    with h5py.File(path, "r") as fh:
        out: dict[str, Any] = {k: np.asarray(fh[k][()]) for k in fh if isinstance(fh[k], h5py.Dataset)}
        if "sampling_rate" in fh.attrs:
            out["sampling_rate"] = float(np.asarray(fh.attrs["sampling_rate"]).ravel()[0])
    return out


def _load_mat(path: Path) -> dict[str, Any]:
    """The arrays and the sampling rate of a BROAD .mat file (MATLAB v5; v7.3 files are HDF5)."""
    from scipy.io import loadmat

    raw = loadmat(path)
    out: dict[str, Any] = {k: np.asarray(v) for k, v in raw.items() if not k.startswith("__")}
    if "sampling_rate" in out:
        out["sampling_rate"] = float(out["sampling_rate"].ravel()[0])
    return out


class BroadReader:
    """Reads a BROAD trial: IMU `imu` (accelerometer + gyro), magnetometer `mag`, mocap `opt_quat`."""

    name: ClassVar[str] = "broad"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Load the trial; anything that is not a BROAD file is an UnsupportedFormatError."""
        try:
            data = _load_hdf5(path) if path.read_bytes()[:8] == b"\x89HDF\r\n\x1a\n" else _load_mat(path)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            msg = (f"{path}: cannot read it as a BROAD HDF5/MAT trial ({type(exc).__name__}: {exc}). "
                   "Check that it is a BROAD trial, or pass --format for another log type")
            raise LogReadError(msg) from None
        missing = [k for k in REQUIRED if k not in data]
        if missing:
            msg = (f"{path}: an HDF5/MAT file without the BROAD datasets {', '.join(missing)}; magcal reads "
                   "HDF5 and MAT files only in the BROAD layout (imu_acc, imu_gyr, imu_mag, sampling_rate)")
            raise UnsupportedFormatError(msg)
        rate = float(data.get("sampling_rate", 0.0))
        if not rate > 0.0:
            msg = f"{path}: no positive sampling_rate; BROAD files carry it as an attribute or variable"
            raise LogReadError(msg)
        n = int(np.asarray(data["imu_acc"]).shape[0])
        t = np.arange(n) / rate
        notes: list[str] = []
        streams = []
        for kind, key, sid, unit, factor in ((Kind.ACCELEROMETER, "imu_acc", "imu", "m/s^2", 1.0),
                                             (Kind.GYROSCOPE, "imu_gyr", "imu", "rad/s", 1.0),
                                             (Kind.MAGNETOMETER, "imu_mag", "mag", "microtesla", 1e-6)):
            values = np.asarray(data[key], dtype=np.float64).reshape(n, 3) * factor
            tt, vv, nn = clean_time(t, values, f"{path.name}#{key}")
            notes += nn
            if kind is Kind.MAGNETOMETER:
                # BROAD resampled the slower magnetometer onto the IMU clock, repeating readings: a repeat
                # is a stale value stamped late, so keep only readings that changed
                fresh = np.concatenate([[True], np.any(vv[1:] != vv[:-1], axis=1)])
                if not fresh.all():
                    notes.append(f"{path.name}#{key}: dropped {int((~fresh).sum())} readings that repeat the "
                                 "previous one exactly (resampled onto the IMU clock)")
                tt, vv = tt[fresh], vv[fresh]
            # raw samples of one sensor board on one clock, each the value at its grid time (docs/timing.md)
            streams.append(Stream(kind, sid, tt, vv, f"{path.name}#{key}", unit, sampling=Sampling.INSTANT))
        if "opt_quat" in data:
            q = np.asarray(data["opt_quat"], dtype=np.float64).reshape(n, 4)
            ok = np.all(np.isfinite(q), axis=1)
            if ok.any():
                rot = ENU_TO_NED @ so3.from_quat(q[ok])                  # IMU -> ENU, then ENU -> NED
                streams.append(Stream(Kind.ATTITUDE, "opt_quat", t[ok], so3.as_quat(rot),
                                      f"{path.name}#opt_quat", "quaternion wxyz"))
                if not ok.all():
                    notes.append(f"{path.name}#opt_quat: motion capture lost the board in "
                                 f"{int((~ok).sum())} of {n} samples")
        return Recording(path, "broad", tuple(streams), 0.0, {}, tuple(notes))
