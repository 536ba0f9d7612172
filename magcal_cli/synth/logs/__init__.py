"""Writers of synthetic logs, one per format, chosen by the output path (used by `magcal simulate`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from magcal_cli.errors import MagcalError
from magcal_cli.registry import resolve
from magcal_cli.streams import Sampling
from magcal_cli.synth.simulate import Simulation

#: file extension -> "module:function(sim, path)"; a directory path (no extension) is a ROS 2 bag
LOG_WRITERS: dict[str, str] = {
    ".mcap": "magcal_cli.synth.logs.mcap:write_mcap",
    ".bin": "magcal_cli.synth.logs.dataflash:write_bin",
    ".bag": "magcal_cli.synth.logs.rosbag:write_bag",
    "": "magcal_cli.synth.logs.rosbag:write_ros2",
    ".csv": "magcal_cli.synth.logs.csvfile:write_csv",
    ".ulg": "magcal_cli.synth.logs.ulog:write_ulg",
}
#: what an IMU sample of each format stands for: PX4's sensor_combined holds the mean rate and specific force over
#: the gyro's last integration period (ending at its stamp); ROS sensor_msgs/Imu, ArduPilot's IMU message and CSV
#: exports hold the values at the stamp
IMU_SAMPLING: dict[str, Sampling] = {
    ".mcap": Sampling.INSTANT,
    ".bin": Sampling.INSTANT,
    ".bag": Sampling.INSTANT,
    "": Sampling.INSTANT,
    ".csv": Sampling.INSTANT,
    ".ulg": Sampling.PRECEDING,
}


def imu_sampling(path: Path) -> Sampling:
    """The IMU sampling of the format `path`'s extension names (INSTANT for an unknown one)."""
    return IMU_SAMPLING.get(path.suffix.lower(), Sampling.INSTANT)


def write_log(sim: Simulation, path: Path) -> None:
    """Write `sim` in the format named by `path`'s extension; refuse a simulation sampled another way."""
    ext = path.suffix.lower()
    target = LOG_WRITERS.get(ext)
    if target is None:
        msg = (f"{path}: cannot write a log with extension {path.suffix or '(none)'!r}; "
               f"use one of {', '.join(sorted(e or '(none: a ROS 2 bag directory)' for e in LOG_WRITERS))}")
        raise MagcalError(msg)
    want = IMU_SAMPLING[ext]
    if sim.imu_sampling is not want:
        msg = (f"{path}: a {ext or 'ROS 2 bag'} log holds {want.value} IMU samples but the simulation's are "
               f"{sim.imu_sampling.value}; simulate with imu_sampling=Sampling.{want.name} "
               "(synth.logs.imu_sampling(path) gives it; magcal simulate chooses it from OUT)")
        raise MagcalError(msg)
    writer: Callable[[Simulation, Path], None] = resolve(target, f"writing {path.suffix or 'bag'} logs")
    writer(sim, path)
