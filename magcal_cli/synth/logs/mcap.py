"""ROS 2 MCAP writer: the topics of the ROS bag writers (Imu, MagneticField in tesla, BatteryState, Temperature,
NavSatFix, mavros ActuatorControl) as CDR messages with ros2msg schemas, in zstd chunks."""

from __future__ import annotations

from pathlib import Path

from magcal_cli.atomic import atomic_path
from magcal_cli.synth.logs.rosbag import Builder, messages, topics
from magcal_cli.synth.simulate import Simulation


def write_mcap(sim: Simulation, path: Path, chunk_size: int = 1 << 20) -> None:
    """Write the simulation's streams as ROS 2 CDR messages in zstd chunks of `chunk_size` bytes."""
    from mcap.writer import CompressionType, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    builder = Builder(store, False, sim.truth.noise_std)          # registers the types the stock store lacks
    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD, chunk_size=chunk_size)
        writer.start(profile="ros2", library="magcal simulate")
        channels = {}
        for topic, msgtype, _ in topics(sim.recording):
            text = store.generate_msgdef(msgtype, ros_version=2)[0]
            schema = writer.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
            channels[topic] = writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schema)
        for seq, (ns, topic, msgtype, msg) in enumerate(messages(sim.recording, builder)):
            writer.add_message(channels[topic], log_time=ns, data=bytes(store.serialize_cdr(msg, msgtype)),
                               publish_time=ns, sequence=seq)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap ships no annotations for finish
