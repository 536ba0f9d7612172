"""The ROS 2 messages magcal reads, as a rosbags typestore of just them (their fields as in the Humble store).

rosbags' Humble store imports the stores of four older distributions, some 800 message classes (0.1-0.15 s, a
fifth of the read of a 100 MB sqlite3 bag); these eleven types register in a few ms. tests/readers/
test_ros2_types.py holds them equal to Humble's.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

#: ROS 2 type -> its fields in wire order ("T name"; T[n] a fixed array, T[] a sequence); constants left out
DEFINITIONS = {
    "builtin_interfaces/msg/Time": "int32 sec, uint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/msg/Time stamp, string frame_id",
    "geometry_msgs/msg/Vector3": "float64 x, float64 y, float64 z",
    "geometry_msgs/msg/Quaternion": "float64 x, float64 y, float64 z, float64 w",
    "geometry_msgs/msg/Vector3Stamped": "std_msgs/msg/Header header, geometry_msgs/msg/Vector3 vector",
    "sensor_msgs/msg/Imu": "std_msgs/msg/Header header, geometry_msgs/msg/Quaternion orientation, "
                           "float64[9] orientation_covariance, geometry_msgs/msg/Vector3 angular_velocity, "
                           "float64[9] angular_velocity_covariance, geometry_msgs/msg/Vector3 linear_acceleration, "
                           "float64[9] linear_acceleration_covariance",
    "sensor_msgs/msg/MagneticField": "std_msgs/msg/Header header, geometry_msgs/msg/Vector3 magnetic_field, "
                                     "float64[9] magnetic_field_covariance",
    "sensor_msgs/msg/BatteryState": "std_msgs/msg/Header header, float32 voltage, float32 temperature, "
                                    "float32 current, float32 charge, float32 capacity, float32 design_capacity, "
                                    "float32 percentage, uint8 power_supply_status, uint8 power_supply_health, "
                                    "uint8 power_supply_technology, bool present, float32[] cell_voltage, "
                                    "float32[] cell_temperature, string location, string serial_number",
    "sensor_msgs/msg/Temperature": "std_msgs/msg/Header header, float64 temperature, float64 variance",
    "sensor_msgs/msg/NavSatStatus": "int8 status, uint16 service",
    "sensor_msgs/msg/NavSatFix": "std_msgs/msg/Header header, sensor_msgs/msg/NavSatStatus status, float64 latitude, "
                                 "float64 longitude, float64 altitude, float64[9] position_covariance, "
                                 "uint8 position_covariance_type",
}


def fielddefs() -> dict[str, tuple[list[Any], list[tuple[str, Any]]]]:
    """DEFINITIONS as rosbags' parse trees: type -> (constants, [(field, (node type, spec))])."""
    from rosbags.interfaces import Nodetype

    def spec(typ: str) -> tuple[Nodetype, Any]:
        if typ.endswith("]"):
            base, size = typ[:-1].split("[")
            return (Nodetype.ARRAY, (spec(base), int(size))) if size else (Nodetype.SEQUENCE, (spec(base), 0))
        return (Nodetype.NAME, typ) if "/" in typ else (Nodetype.BASE, (typ, 0))

    return {name: ([], [(field, spec(typ)) for typ, field in (f.split() for f in text.split(", "))])
            for name, text in DEFINITIONS.items()}


@functools.cache
def humble_subset() -> Typestore:
    """A typestore of DEFINITIONS (built once: its decoders, generated on first use, are kept for later reads)."""
    from rosbags.typesys.store import Typestore

    store = Typestore()
    store.register(fielddefs())
    return store
