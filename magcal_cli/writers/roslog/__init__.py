"""`magcal apply CAL LOG -o OUT.mcap|OUT.bag|DIR`: the log copied with a calibrated `sensor_msgs/MagneticField`
topic per magnetometer (docs/ros.md).

A ROS log is copied in its own format (MCAP file, ROS 1 bag, ROS 2 bag folder), every original message's bytes
unchanged; any other log (DataFlash, ULog, CSV) becomes a new ROS 2 MCAP file of its IMU and magnetometers.
`apply_to_log` is the one entry point (the CLI's and the Python API's).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from magcal_cli.calibration.types import Calibration
from magcal_cli.errors import OutputError
from magcal_cli.streams import Recording

#: what each output kind is, for messages
KINDS = {"mcap": "MCAP file (.mcap)", "bag": "ROS 1 bag (.bag)", "ros2": "ROS 2 bag folder"}
#: the -o spelling that asks for each kind
SPELLING = {"mcap": "OUT.mcap", "bag": "OUT.bag", "ros2": "OUT_DIR (a folder)"}


@dataclass(frozen=True)
class Applied:
    """What `apply_to_log` wrote: the output, each calibrated topic with its message count, apply's notes."""

    out: Path
    topics: dict[str, int] = field(default_factory=dict)
    notes: tuple[str, ...] = ()


def output_kind(out: Path) -> str | None:
    """The log kind `-o` asks for: "mcap", "bag", "ros2" (a folder, or a name without extension), or None for
    the CSV of the calibrated field (any other extension, or '-')."""
    suffix = out.suffix.lower()
    if str(out) == "-":
        return None
    if suffix in (".mcap", ".bag"):
        return suffix[1:]
    if out.is_dir() or not suffix:
        return "ros2"
    return None


def log_kind(log: Path, fmt: str) -> str:
    """The output kind a copy of `log` (read as `fmt`) takes: its own, or MCAP for a non-ROS log."""
    if fmt in ("rosbag", "rosbag2", "rosbag1"):
        return "ros2" if log.is_dir() or (log.parent / "metadata.yaml").is_file() else "bag"
    return "mcap"


def check_output(log: Path, fmt: str, out: Path) -> str:
    """The kind to write, or OutputError when `out` asks for another format than the copy of `log` takes, is the
    input itself, or is a folder that is not a ROS 2 bag."""
    want, kind = output_kind(out), log_kind(log, fmt)
    if want != kind:
        asked = KINDS.get(want or "", "CSV")
        msg = (f"{out}: a {asked} output for a {fmt} log; apply writes a copy of a ROS log in its own format and "
               f"any other log as MCAP. Use -o {SPELLING[kind]}, or -o OUT.csv for the field as CSV")
        raise OutputError(msg)
    if out.exists() and out.resolve() == log.resolve():
        msg = f"{out}: is the input log; apply writes a copy. Choose another -o"
        raise OutputError(msg)
    if kind == "ros2" and out.exists() and not (out / "metadata.yaml").is_file():
        msg = f"{out}: exists and is not a ROS 2 bag folder; not replacing it. Choose another -o"
        raise OutputError(msg)
    return kind


def apply_to_log(cal: Calibration, log: Path, out: Path, topic: str | None = None, replace: bool = False, *,
                 mags: list[str] | None = None, fmt: str | None = None, rec: Recording | None = None) -> Applied:
    """Write `out`: `log` with each calibrated magnetometer of `cal` (or `mags`) as a `sensor_msgs/MagneticField`
    topic (`topic`, or `<topic>/calibrated`; with `replace`, in place of the original topic). `rec`: the log
    already read (and cut to a window), else it is read here."""
    from magcal_cli.readers import open_recording
    from magcal_cli.writers.roslog.bags import copy_bag
    from magcal_cli.writers.roslog.mcapfile import copy_mcap, new_mcap
    from magcal_cli.writers.roslog.series import calibrated_series, split_id

    log, out = Path(log), Path(out)
    rec = rec if rec is not None else open_recording(log, fmt)
    kind = check_output(log, rec.format, out)
    ros = rec.format in ("mcap", "rosbag", "rosbag2", "rosbag1")
    topics = {s.id for s in rec.streams} | {split_id(s.id, set())[0] for s in rec.streams}
    series, notes = calibrated_series(cal, rec, mags, topics if ros else set(), topic, replace)
    if topic and len(series) > 1:
        msg = (f"--topic {topic}: names one topic, and {len(series)} magnetometers are calibrated "
               f"({', '.join(s.mag_id for s in series)}). Choose one with --mag")
        raise OutputError(msg)
    if replace and any(s.path for s in series):
        nested = next(s for s in series if s.path)
        msg = (f"{nested.mag_id}: a field of {nested.source_topic}'s messages, which hold more than the field; "
               "--replace cannot swap it. Drop --replace (the calibrated field goes to its own topic)")
        raise OutputError(msg)
    if kind == "mcap" and ros:
        copy_mcap(log, out, series, cal.imu.id, replace)
    elif kind == "mcap":
        new_mcap(rec, out, series, cal.imu.id, replace)
    else:
        copy_bag(log, out, series, cal.imu.id, replace)
    return Applied(out, {s.topic: len(s.stamps) for s in series}, tuple(notes))
