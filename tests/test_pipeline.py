"""Stream selection and the messages for logs that are too short."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal_cli.config import Config
from magcal_cli.errors import StreamError
from magcal_cli.pipeline import select_problem
from magcal_cli.streams import Kind, Recording, Stream


def _recording(n_mag: int) -> Recording:
    t = np.arange(2000) / 100.0
    tm = np.arange(n_mag) / 10.0
    return Recording(Path("short.bin"), "dataflash", (
        Stream(Kind.ACCELEROMETER, "IMU[0]", t, np.tile([0, 0, -9.8], (2000, 1)), "short.bin#IMU", "m/s^2"),
        Stream(Kind.GYROSCOPE, "IMU[0]", t, np.zeros((2000, 3)), "short.bin#IMU", "rad/s"),
        Stream(Kind.MAGNETOMETER, "MAG[0]", tm, np.ones((n_mag, 3)), "short.bin#MAG", "milligauss")))


def test_a_short_log_says_record_longer() -> None:
    """Without --start/--end the advice is about the recording, not the time window (ap462_truncated_80k.bin)."""
    with pytest.raises(StreamError, match=r"short.bin: magnetometer MAG\[0\] has only 4 samples \(0.3 s\); a "
                                          r"calibration needs a recording of at least a minute"):
        select_problem(_recording(4), Config())


def test_a_narrow_window_says_widen_it() -> None:
    """With --start/--end the advice is to widen the window."""
    with pytest.raises(StreamError, match="between --start and --end; widen the time window"):
        select_problem(_recording(200), Config(start_s=0.0, end_s=0.5))


def test_missing_imu_lists_what_is_there() -> None:
    """--imu with an unknown id names the ids available."""
    with pytest.raises(StreamError, match=r"no accelerometer stream 'IMU\[7\]'; available: IMU\[0\]. Use --imu"):
        select_problem(_recording(200), Config(imu="IMU[7]"))
