"""Writers of synthetic logs, one per format, chosen by the output path (used by `magcal simulate`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..errors import MagcalError
from ..registry import resolve
from ..synth import Simulation

#: file extension -> "module:function(sim, path)"; a directory path (no extension) is a ROS 2 bag
LOG_WRITERS: dict[str, str] = {
    ".mcap": "magcal_cli.logwriters.mcap:write_mcap",
    ".bin": "magcal_cli.logwriters.dataflash:write_bin",
    ".bag": "magcal_cli.logwriters.rosbag:write_bag",
    "": "magcal_cli.logwriters.rosbag:write_ros2",
    ".csv": "magcal_cli.logwriters.csvfile:write_csv",
    ".ulg": "magcal_cli.logwriters.ulog:write_ulg",
}


def write_log(sim: Simulation, path: Path) -> None:
    """Write `sim` in the format named by `path`'s extension."""
    target = LOG_WRITERS.get(path.suffix.lower())
    if target is None:
        msg = (f"{path}: cannot write a log with extension {path.suffix or '(none)'!r}; "
               f"use one of {', '.join(sorted(e or '(none: a ROS 2 bag directory)' for e in LOG_WRITERS))}")
        raise MagcalError(msg)
    writer: Callable[[Simulation, Path], None] = resolve(target, f"writing {path.suffix or 'bag'} logs")
    writer(sim, path)
