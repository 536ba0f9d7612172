"""ROS 2 MCAP writer: sensor_msgs/msg/Imu on /imu/data, sensor_msgs/msg/MagneticField (tesla) on /imu/mag."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..streams import Kind
from ..synth import Simulation

_SEP = "=" * 80 + "\n"
_DEPS = (
    f"{_SEP}MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    f"{_SEP}MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)
_VEC = f"{_SEP}MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
_QUAT = f"{_SEP}MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
IMU_MSGDEF = (
    "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"
    + _DEPS + _QUAT + _VEC
)
MAG_MSGDEF = (
    "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\nfloat64[9] magnetic_field_covariance\n"
    + _DEPS + _VEC
)


def _stamp(ns: int) -> dict[str, int]:
    """builtin_interfaces/Time of an absolute time in integer nanoseconds."""
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _vec(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def write_mcap(sim: Simulation, path: Path, chunk_size: int = 1 << 20) -> None:
    """Write the simulation's IMU and magnetometer streams as ROS 2 CDR messages in zstd chunks of `chunk_size` bytes."""
    from mcap_ros2.writer import Writer

    rec = sim.recording
    acc, gyr = rec.select(Kind.ACCELEROMETER), rec.select(Kind.GYROSCOPE)
    mag = rec.select(Kind.MAGNETOMETER)
    var = {k: v**2 for k, v in sim.truth.noise_std.items()}
    no_orientation = [-1.0] + [0.0] * 8
    events = [(t, 0, i) for i, t in enumerate(acc.t)] + [(t, 1, i) for i, t in enumerate(mag.t)]
    events.sort()
    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        writer = Writer(fh, chunk_size=chunk_size)
        imu_schema = writer.register_msgdef("sensor_msgs/msg/Imu", IMU_MSGDEF)
        mag_schema = writer.register_msgdef("sensor_msgs/msg/MagneticField", MAG_MSGDEF)
        for seq, (t, which, i) in enumerate(events):
            ns = int(round(rec.t0 * 1e9)) + int(round(t * 1e9))   # integer ns: no float rounding at 1e9 s
            if which == 0:
                msg = {"header": {"stamp": _stamp(ns), "frame_id": "imu_link"},
                       "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                       "orientation_covariance": no_orientation,
                       "angular_velocity": _vec(gyr.values[i]),
                       "angular_velocity_covariance": list(np.eye(3).ravel() * var["gyroscope"]),
                       "linear_acceleration": _vec(acc.values[i]),
                       "linear_acceleration_covariance": list(np.eye(3).ravel() * var["accelerometer"])}
                writer.write_message("/imu/data", imu_schema, msg, log_time=ns, publish_time=ns, sequence=seq)
            else:
                msg = {"header": {"stamp": _stamp(ns), "frame_id": "imu_link"},
                       "magnetic_field": _vec(mag.values[i]),
                       "magnetic_field_covariance": list(np.eye(3).ravel() * var["magnetometer"])}
                writer.write_message("/imu/mag", mag_schema, msg, log_time=ns, publish_time=ns, sequence=seq)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap_ros2 ships no annotations
