"""The date of a PX4 ULog (issue 12): the vehicle clock counts from boot, so the flight's date comes from the GPS
receiver's UTC time (`time_utc_usec`) and the WMM is evaluated when the log was flown.

Modules it covers (the mirrored test file aside): magcal_cli.readers.ulog.topics.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from magcal_cli.config import Config
from magcal_cli.pipeline import with_position
from magcal_cli.readers import open_recording
from magcal_cli.synth.logs.ulog import START_US, Topic, UlogContent, write_content

GPS = (("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec"), ("double", "latitude_deg"),
       ("double", "longitude_deg"), ("double", "altitude_msl_m"))
#: 2019-06-01 12:00:00 UTC
NOON_US = 1_559_390_400_000_000


def _day(utc0: float | None) -> str | None:
    return None if utc0 is None else time.strftime("%Y-%m-%d", time.gmtime(utc0))


def _gps_log(path: Path, utc_us: np.ndarray, topic: str = "vehicle_gps_position") -> Path:
    t = START_US + 200_000 * np.arange(utc_us.size, dtype=np.int64)
    n = t.size
    write_content(UlogContent([Topic(topic, GPS, {
        "timestamp": t, "time_utc_usec": utc_us, "latitude_deg": np.full(n, 47.4), "longitude_deg": np.full(n, 8.5),
        "altitude_msl_m": np.full(n, 480.0)})]), path)
    return path


@pytest.mark.parametrize("topic", ["vehicle_gps_position", "sensor_gps"])
def test_round_trip_utc_of_the_clock_zero(tmp_path: Path, topic: str) -> None:
    """UTC minus the message stamp, placed at the recording's t = 0; fixes before the receiver has a time (0) are
    not used."""
    utc = NOON_US + 200_000 * np.arange(10, dtype=np.int64) + 5_000
    utc[:3] = 0
    rec = open_recording(_gps_log(tmp_path / "gps.ulg", utc, topic))
    assert rec.utc0 == pytest.approx(NOON_US * 1e-6 + 0.005 - START_US * 1e-6 + rec.t0, abs=1e-6)
    assert _day(rec.utc0) == "2019-06-01"
    assert with_position(rec, Config()).date == "2019-06-01"


def test_no_receiver_time_leaves_the_date_unknown(tmp_path: Path) -> None:
    rec = open_recording(_gps_log(tmp_path / "gps.ulg", np.zeros(5, np.int64)))
    assert rec.utc0 is None


@pytest.mark.parametrize(("name", "day"), [
    ("roboto_fmuv5_test.ulg", "2023-10-31"),
    ("sample_log_small.ulg", "2021-04-21"),
    ("sample_logging_tagged_and_default_params_SITL.ulg", "2022-04-29"),
    ("sample_px4_events_SITL.ulg", "2024-03-18"),
    ("sample.ulg", None),                              # no GPS topic
])
def test_real_ulogs_are_dated_by_their_gps(realdata: Path, name: str, day: str | None) -> None:
    rec = open_recording(realdata / "px4" / name)
    assert _day(rec.utc0) == day
    if day is not None:
        assert with_position(rec, Config()).date == day


def test_simulated_flight_ulog_is_dated_by_its_gps(tmp_path: Path) -> None:
    """`magcal simulate x.ulg` of a flight writes the receiver's UTC, so the log carries the date its truth's WMM
    field was taken at (T0_ROS), not today's."""
    from magcal_cli.streams import Sampling
    from magcal_cli.synth.logs.ulog import write_ulg
    from magcal_cli.synth.simulate import T0_ROS, simulate

    path = tmp_path / "flight.ulg"
    write_ulg(simulate("multirotor", 0, duration=90.0, imu_sampling=Sampling.PRECEDING), path)
    utc0 = open_recording(path).utc0
    assert utc0 is not None and abs(utc0 - T0_ROS) < 0.2
