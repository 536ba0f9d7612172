"""ROS 1 `.bag` and ROS 2 bag directory writers (rosbags): Imu, MagneticField, and the other sensor types.

Streams sharing an id become one topic: accelerometer + gyroscope -> sensor_msgs/Imu, magnetometer ->
MagneticField (tesla), battery current + voltage -> BatteryState (current negative while discharging, as
ROS defines it), temperature -> Temperature, position -> NavSatFix, throttle -> mavros_msgs/ActuatorControl
(controls[3] of mixer group 0, as mavros publishes PX4's actuator controls). Both writers build the bag under
a temporary name and rename it into place.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli.atomic import atomic_dir, atomic_path
from magcal_cli.errors import OutputError
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.synth.simulate import Simulation

#: kinds that make up one message type, in the order the message takes them
MESSAGE_KINDS: dict[str, tuple[Kind, ...]] = {
    "sensor_msgs/msg/Imu": (Kind.ACCELEROMETER, Kind.GYROSCOPE),
    "sensor_msgs/msg/MagneticField": (Kind.MAGNETOMETER,),
    "sensor_msgs/msg/BatteryState": (Kind.BATTERY_CURRENT, Kind.BATTERY_VOLTAGE),
    "sensor_msgs/msg/Temperature": (Kind.TEMPERATURE,),
    "sensor_msgs/msg/NavSatFix": (Kind.POSITION,),
    "mavros_msgs/msg/ActuatorControl": (Kind.THROTTLE,),
}
#: mavros_msgs/ActuatorControl (mavros 1 and 2): PX4 mixer-group controls, throttle at index 3 of group 0
ACTUATOR_CONTROL = "mavros_msgs/msg/ActuatorControl"
ACTUATOR_CONTROL_MSG = """uint8 PX4_MIX_FLIGHT_CONTROL = 0
uint8 PX4_MIX_FLIGHT_CONTROL_VTOL_ALT = 1
uint8 PX4_MIX_PAYLOAD = 2
uint8 PX4_MIX_MANUAL_PASSTHROUGH = 3
std_msgs/Header header
uint8 group_mix
float32[8] controls
"""
#: index of the throttle in mixer group 0 (PX4 actuator_controls_s::INDEX_THROTTLE)
THROTTLE_INDEX = 3


def register_types(store: Any) -> None:
    """Add the message types rosbags' stock typestores lack (mavros_msgs/ActuatorControl) to `store`."""
    from rosbags.typesys import get_types_from_msg

    if ACTUATOR_CONTROL not in store.types:
        store.register(get_types_from_msg(ACTUATOR_CONTROL_MSG, ACTUATOR_CONTROL))


def topic_name(stream_id: str) -> str:
    """A valid ROS topic for a stream id (`imu` -> `/imu`)."""
    name = "".join(c if c.isalnum() or c in "/_" else "_" for c in stream_id)
    return name if name.startswith("/") else f"/{name}"


def topics(rec: Recording) -> list[tuple[str, str, tuple[Stream, ...]]]:
    """(topic, msgtype, streams) for every id whose kinds form a message type (first stream of each kind)."""
    out = []
    ids = list(dict.fromkeys(s.id for s in rec.streams))
    for msgtype, kinds in MESSAGE_KINDS.items():
        for sid in ids:
            found = [next((s for s in rec.streams if s.id == sid and s.kind is k), None) for k in kinds]
            parts = tuple(s for s in found if s is not None)
            if len(parts) == len(kinds) and all(np.array_equal(p.t, parts[0].t) for p in parts):
                out.append((topic_name(sid), msgtype, parts))
    return out


class Builder:
    """Makes rosbags message objects of one typestore (ROS 1 Noetic or ROS 2 Humble)."""

    def __init__(self, store: Any, ros1: bool, noise_std: dict[str, float]) -> None:
        register_types(store)
        self.types = store.types
        self.ros1 = ros1
        self.var = {k: v**2 for k, v in noise_std.items()}

    def header(self, ns: int, seq: int) -> Any:
        """std_msgs/Header with an integer-ns stamp."""
        stamp = self.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if self.ros1:
            return self.types["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id="imu_link")
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id="imu_link")

    def vec(self, v: np.ndarray) -> Any:
        """geometry_msgs/Vector3."""
        return self.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def cov(self, kind: str) -> np.ndarray:
        """Diagonal covariance of the simulated noise (zero when unknown: ROS's 'unknown')."""
        return np.eye(3).ravel() * self.var.get(kind, 0.0)

    def message(self, msgtype: str, parts: tuple[Stream, ...], i: int, ns: int, seq: int) -> Any:
        """Message `i` of a topic's streams."""
        t, h = self.types, self.header(ns, seq)
        if msgtype == "sensor_msgs/msg/Imu":
            return t[msgtype](header=h, orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                              orientation_covariance=np.array([-1.0] + [0.0] * 8),
                              angular_velocity=self.vec(parts[1].values[i]),
                              angular_velocity_covariance=self.cov("gyroscope"),
                              linear_acceleration=self.vec(parts[0].values[i]),
                              linear_acceleration_covariance=self.cov("accelerometer"))
        if msgtype == "sensor_msgs/msg/MagneticField":
            return t[msgtype](header=h, magnetic_field=self.vec(parts[0].values[i]),
                              magnetic_field_covariance=self.cov("magnetometer"))
        if msgtype == "sensor_msgs/msg/Temperature":
            return t[msgtype](header=h, temperature=float(parts[0].values[i, 0]), variance=0.0)
        if msgtype == "sensor_msgs/msg/NavSatFix":
            lat, lon, alt = (float(x) for x in parts[0].values[i])
            status = t["sensor_msgs/msg/NavSatStatus"](status=0, service=1)
            return t[msgtype](header=h, status=status, latitude=lat, longitude=lon, altitude=alt,
                              position_covariance=np.zeros(9), position_covariance_type=0)
        if msgtype == ACTUATOR_CONTROL:
            controls = np.zeros(8, dtype=np.float32)
            controls[THROTTLE_INDEX] = parts[0].values[i, 0]
            return t[msgtype](header=h, group_mix=0, controls=controls)
        return self._battery(h, float(parts[0].values[i, 0]), float(parts[1].values[i, 0]))

    def _battery(self, h: Any, current: float, voltage: float) -> Any:
        """sensor_msgs/BatteryState; ROS reports discharge as negative current."""
        nan = float("nan")
        fields = {"header": h, "voltage": voltage, "current": -current, "charge": nan, "capacity": nan,
                  "design_capacity": nan, "percentage": nan, "power_supply_status": 2,
                  "power_supply_health": 0, "power_supply_technology": 0, "present": True,
                  "cell_voltage": np.zeros(0), "location": "", "serial_number": "", "temperature": nan,
                  "cell_temperature": np.zeros(0)}
        return self.types["sensor_msgs/msg/BatteryState"](**fields)


def messages(rec: Recording, builder: Builder) -> Iterator[tuple[int, str, str, Any]]:
    """(stamp ns, topic, msgtype, message) of every topic, in time order."""
    base = int(round(rec.t0 * 1e9))
    tops = topics(rec)
    events = sorted((int(round(t * 1e9)), k, i) for k, (_, _, parts) in enumerate(tops)
                    for i, t in enumerate(parts[0].t))
    for seq, (ns, k, i) in enumerate(events):
        topic, msgtype, parts = tops[k]
        yield base + ns, topic, msgtype, builder.message(msgtype, parts, i, base + ns, seq)


def write_bag(sim: Simulation, path: Path, chunk_size: int = 1 << 20) -> None:
    """ROS 1 bag (LZ4 chunks of about `chunk_size` bytes) of the simulation's streams; header stamp = receive time."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    builder = Builder(store, True, sim.truth.noise_std)
    with atomic_path(path) as tmp:
        tmp.unlink()                                      # rosbags refuses to overwrite the placeholder
        writer = Writer(tmp)
        writer.set_compression(Writer.CompressionFormat.LZ4)
        writer.chunk_threshold = chunk_size
        with writer:
            conns = {top: writer.add_connection(top, mt, typestore=store) for top, mt, _ in topics(sim.recording)}
            for ns, top, mt, msg in messages(sim.recording, builder):
                writer.write(conns[top], ns, store.serialize_ros1(msg, mt))


def write_ros2(sim: Simulation, path: Path, storage: str = "mcap") -> None:
    """ROS 2 bag directory (MCAP storage with zstd chunks, or sqlite3) of the simulation's streams."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore

    if path.exists() and not (path / "metadata.yaml").is_file():
        msg = f"{path}: exists and is not a ROS 2 bag directory; not replacing it. Choose another output path"
        raise OutputError(msg)
    store = get_typestore(Stores.ROS2_HUMBLE)
    builder = Builder(store, False, sim.truth.noise_std)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with atomic_dir(path) as tmp:
        writer = Writer(tmp, version=9, storage_plugin=plugin)
        if plugin is StoragePlugin.MCAP:
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with writer:
            conns = {top: writer.add_connection(top, mt, typestore=store) for top, mt, _ in topics(sim.recording)}
            for ns, top, mt, msg in messages(sim.recording, builder):
                writer.write(conns[top], ns, store.serialize_cdr(msg, mt))
