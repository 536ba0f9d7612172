"""Vectorised ROS decoding (rosvec, MCAP chunk arrays, batched bags) against rosbags' per-message decoding.

Modules it covers (the mirrored test file aside): magcal_cli.readers.ros.bag1_fast,
magcal_cli.readers.ros.mcap_chunk, magcal_cli.readers.ros.vec.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.readers.ros import vec as rosvec
from magcal_cli.readers.ros.mcap import ros_decoder
from magcal_cli.readers.ros.msg import ROS_TYPES, Collector, stamp_ns, wanted
from magcal_cli.streams import Recording
from magcal_cli.synth.logs.mcap import write_mcap
from magcal_cli.synth.logs.rosbag import register_types, write_bag, write_ros2
from magcal_cli.synth.simulate import Simulation, simulate

TYPES = list(rosvec.VALUE_PATHS)
#: frame_id lengths 0..11 move every later field across CDR's 4- and 8-byte alignment boundaries
FRAMES = ["", "a", "ab", "imu", "imu_", "imu_l", "imu_li", "imu_lin", "imu_link", "base_link", "imu_link_0",
          "magnetometer"]


def store_of(ros1: bool) -> Any:
    """rosbags' stock store of ROS 1 Noetic or ROS 2 Humble, with mavros_msgs/ActuatorControl."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    register_types(store)
    return store


def make(store: Any, msgtype: str, frame: str, rng: np.random.Generator) -> Any:
    """A message of `msgtype` with random numbers, random-length sequences and strings, header frame_id `frame`."""
    from rosbags.typesys.base import Nodetype

    fields: dict[str, Any] = {}
    for name, (node, spec) in store.fielddefs[msgtype][1]:
        if node == Nodetype.NAME:
            fields[name] = make(store, spec, frame, rng)
        elif node == Nodetype.BASE:
            prim = spec[0]
            fields[name] = (frame if name == "frame_id" else "x" * int(rng.integers(0, 7))) if prim == "string" \
                else bool(rng.integers(0, 2)) if prim == "bool" \
                else float(np.float32(rng.normal())) if prim == "float32" else float(rng.normal()) if "float" in prim \
                else int(rng.integers(0, 100)) if prim not in ("int8",) else int(rng.integers(-5, 5))
        elif node == Nodetype.ARRAY:
            fields[name] = rng.normal(size=spec[1]).astype(np.float32 if spec[0][1][0] == "float32" else np.float64)
        else:
            fields[name] = rng.normal(size=int(rng.integers(0, 5))).astype(np.float32)
    return store.types[msgtype](**fields)


def decode_both(store: Any, msgtype: str, ros1: bool, raws: list[bytes]) -> tuple[Any, ...]:
    """(ok, stamps, values) of rosvec and of rosbags message by message."""
    def one(data: bytes) -> Any:
        return store.deserialize_ros1(data, msgtype) if ros1 else store.deserialize_cdr(data, msgtype)

    length = np.array([len(r) for r in raws], dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64)
    got = rosvec.BatchDecoder(store.fielddefs, msgtype, ros1, one)(np.frombuffer(b"".join(raws), np.uint8), start,
                                                                     length)
    ref_ok, ref_stamps, ref_values = [], [], []
    for r in raws:
        try:
            msg = one(r)
            ref_values.append(ROS_TYPES[msgtype][2](msg))
            ref_stamps.append(stamp_ns(msg))
            ref_ok.append(True)
        except Exception:  # noqa: BLE001 - corrupt on purpose
            ref_ok.append(False)
    return got, (np.array(ref_ok), np.array(ref_stamps, dtype=np.int64), np.array(ref_values, dtype=np.float64))


def assert_same_decoding(got: Any, ref: Any) -> None:
    """rosvec decoded the same messages to the same stamps and values."""
    ok, stamps, values = got
    np.testing.assert_array_equal(ok, ref[0])
    np.testing.assert_array_equal(stamps[ok], ref[1])
    np.testing.assert_array_equal(values[ok], ref[2].reshape(len(ref[1]), -1))


@pytest.mark.parametrize("ros1", [False, True])
@pytest.mark.parametrize("msgtype", TYPES)
def test_every_type_and_frame_id_length_matches_rosbags(msgtype: str, ros1: bool) -> None:
    """Messages with frame_ids of 0-12 characters and variable tails (BatteryState arrays, strings) interleaved."""
    store, rng = store_of(ros1), np.random.default_rng(len(msgtype))
    msgs = [make(store, msgtype, FRAMES[i % len(FRAMES)], rng) for i in range(120)]
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr
    got, ref = decode_both(store, msgtype, ros1, [bytes(ser(m, msgtype)) for m in msgs])
    assert ref[0].all()
    assert_same_decoding(got, ref)


@pytest.mark.parametrize("ros1", [False, True])
def test_corrupt_and_short_messages_are_rejected_like_rosbags(ros1: bool) -> None:
    """Cut messages, empty ones and (CDR) a big-endian encapsulation header: decided message by message."""
    store, rng = store_of(ros1), np.random.default_rng(3)
    msgtype = "sensor_msgs/msg/MagneticField"
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr
    raws = [bytes(ser(make(store, msgtype, "imu_link", rng), msgtype)) for _ in range(40)]
    raws[5] = raws[5][:30]
    raws[9] = b""
    raws[12] = raws[12][:-1]
    if not ros1:
        raws[20] = b"\x00\x00" + raws[20][2:]
    got, ref = decode_both(store, msgtype, ros1, raws)
    assert not ref[0][[5, 9]].any()
    assert_same_decoding(got, ref)


def test_layouts_it_cannot_vectorise_fall_back_to_rosbags() -> None:
    """A schema with a string before the field, or without a header: decoded message by message, same values."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    sep = "=" * 80 + "\n"
    text = (f"std_msgs/Header header\nstring note\ngeometry_msgs/Vector3 magnetic_field\n"
            f"float64[9] magnetic_field_covariance\n{sep}MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\n"
            f"string frame_id\n{sep}MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n{sep}"
            "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n")
    store.register(get_types_from_msg(text, "sensor_msgs/msg/MagneticField"))
    rng = np.random.default_rng(5)
    msgs = [make(store, "sensor_msgs/msg/MagneticField", FRAMES[i % 4], rng) for i in range(30)]
    dec = rosvec.BatchDecoder(store.fielddefs, "sensor_msgs/msg/MagneticField", False, lambda d: None)
    assert dec.layout(9) is None
    got, ref = decode_both(store, "sensor_msgs/msg/MagneticField", False,
                           [bytes(store.serialize_cdr(m, "sensor_msgs/msg/MagneticField")) for m in msgs])
    assert_same_decoding(got, ref)


def test_a_wrong_layout_is_caught_by_the_check_against_rosbags(monkeypatch: pytest.MonkeyPatch) -> None:
    """Offsets that are off by 8 bytes disagree with rosbags on the group's first message: per-message instead."""
    real = rosvec.offsets

    def shifted(*args: Any) -> Any:
        out = real(*args)
        return {k: (o + 8, d) for k, (o, d) in out.items()} if out else out

    monkeypatch.setattr(rosvec, "offsets", shifted)
    store, rng = store_of(False), np.random.default_rng(9)
    msgs = [make(store, "sensor_msgs/msg/Imu", FRAMES[i % 3], rng) for i in range(30)]
    got, ref = decode_both(store, "sensor_msgs/msg/Imu", False,
                           [bytes(store.serialize_cdr(m, "sensor_msgs/msg/Imu")) for m in msgs])
    assert_same_decoding(got, ref)


# --- whole logs: magcal's readers against a Collector fed message by message by mcap / rosbags ---------------

def per_message(path: Path) -> Recording:
    """The log decoded message by message (mcap's reader or rosbags' AnyReader, rosbags' deserializers)."""
    collector, options = Collector(), ReadOptions()
    if path.suffix == ".mcap":
        from mcap.reader import make_reader

        decoders: dict[int, Any] = {}
        with path.open("rb") as fh:
            for schema, channel, message in make_reader(fh).iter_messages():
                if wanted(channel.topic, schema.name):
                    if channel.id not in decoders:
                        decoders[channel.id] = ros_decoder(schema, channel.message_encoding)
                    collector.add(channel.topic, schema.name, message.log_time,
                                  decoders[channel.id].decode(message.data))
    else:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            conns = [c for c in reader.connections if wanted(c.topic, c.msgtype)]
            for conn, ns, raw in reader.messages(connections=conns):
                collector.add(conn.topic, conn.msgtype, ns, reader.deserialize(raw, conn.msgtype))
    return collector.recording(path, "ref", options, [])


def assert_same_recording(rec: Recording, ref: Recording) -> None:
    """Same streams, times, values and units; the reference's notes among the reader's."""
    assert rec.t0 == ref.t0
    assert [(s.kind, s.id, s.native_unit) for s in rec.streams] == [(s.kind, s.id, s.native_unit)
                                                                      for s in ref.streams]
    for s, u in zip(rec.streams, ref.streams, strict=True):
        np.testing.assert_array_equal(s.t, u.t)
        np.testing.assert_array_equal(s.values, u.values)
    assert set(ref.notes) <= set(rec.notes)


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A short simulation: IMU, field and the simulator's battery/temperature streams."""
    return simulate("paper", 2, rate=100.0, mag_rate=50.0, duration=20.0)


@pytest.mark.parametrize("kind", ["mcap", "bag", "ros2-mcap", "ros2-sqlite3"])
def test_round_trip_logs_read_like_per_message_decoding(tmp_path: Path, sim: Simulation, kind: str) -> None:
    """magcal's writers' MCAP, ROS 1 and ROS 2 logs: the vectorised readers give the per-message result exactly."""
    if kind == "mcap":
        path = tmp_path / "x.mcap"
        write_mcap(sim, path, chunk_size=20_000)
    elif kind == "bag":
        path = tmp_path / "x.bag"
        write_bag(sim, path, chunk_size=20_000)
    else:
        path = tmp_path / "bag"
        write_ros2(sim, path, kind.split("-")[1])
    assert_same_recording(open_recording(path), per_message(path))


def test_mcap_with_varying_frame_ids_and_unchunked_messages(tmp_path: Path) -> None:
    """An MCAP whose messages change frame_id length, some outside chunks: same as per-message decoding."""
    from mcap.writer import CompressionType, Writer

    store, rng = store_of(False), np.random.default_rng(11)
    for chunked, name in ((True, "chunked.mcap"), (False, "loose.mcap")):
        with (tmp_path / name).open("wb") as fh:
            writer = Writer(fh, compression=CompressionType.ZSTD, use_chunking=chunked, chunk_size=4000)
            writer.start(profile="ros2", library="test")
            ids = {}
            for topic, msgtype in (("/imu", "sensor_msgs/msg/Imu"), ("/imu/mag", "sensor_msgs/msg/MagneticField")):
                sid = writer.register_schema(msgtype, "ros2msg", store.generate_msgdef(msgtype, ros_version=2)[0]
                                             .encode())
                ids[topic] = (writer.register_channel(topic, "cdr", sid), msgtype)
            for i in range(600):
                topic = "/imu" if i % 3 else "/imu/mag"
                msg = make(store, ids[topic][1], FRAMES[(i // 7) % len(FRAMES)], rng)
                msg.header.stamp.sec, msg.header.stamp.nanosec = 100 + i // 100, (i % 100) * 10_000_000
                writer.add_message(ids[topic][0], log_time=i * 10_000_000, publish_time=0,
                                   data=bytes(store.serialize_cdr(msg, ids[topic][1])))
            writer.finish()  # type: ignore[no-untyped-call]
        assert_same_recording(open_recording(tmp_path / name), per_message(tmp_path / name))


REAL = ["phidgets_imu_upside_down.bag", "phidgets_imu_upside_down_legacy_Vector3Stamped.bag", "ardrone_imu.bag",
        "sparkfun_razor.bag", "phidgets_imu_upside_down_mcap", "sparkfun_razor_sqlite3",
        "phidgets_imu_upside_down_mcap/phidgets_imu_upside_down_mcap.mcap"]


@pytest.mark.parametrize("name", REAL)
def test_real_logs_read_like_per_message_decoding(realdata: Path, name: str) -> None:
    """The real ROS 1 bags, ROS 2 bags and MCAP file of ../shared/realdata/ros."""
    path = realdata / "ros" / name
    if not path.exists():
        pytest.skip(f"{path} is not there (see ../shared/realdata/README.md)")
    assert_same_recording(open_recording(path), per_message(path))


@pytest.mark.parametrize("kind", ["bag", "ros2-mcap", "ros2-sqlite3"])
def test_bags_take_the_fast_paths(tmp_path: Path, sim: Simulation, kind: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Whole bags are read chunk by chunk (ROS 1 index) or from their storage, not message by message."""
    from magcal_cli.readers.ros import bag as rosbag

    path = tmp_path / ("x.bag" if kind == "bag" else "bag")
    if kind == "bag":
        write_bag(sim, path, chunk_size=20_000)
    else:
        write_ros2(sim, path, kind.split("-")[1])
    ref = open_recording(path)

    def refuse(*args: Any) -> str:
        raise AssertionError(args)

    monkeypatch.setattr(rosbag, "_read_messages", refuse)
    assert_same_recording(open_recording(path), ref)


def test_ros1_fast_path_gives_way_on_a_corrupt_chunk(tmp_path: Path, sim: Simulation) -> None:
    """A damaged chunk: the chunk reader declines and rosbags' iteration resumes after it, as before."""
    from magcal_cli.readers.ros.bag1_fast import read_indexed_bag1

    write_bag(sim, tmp_path / "x.bag", chunk_size=20_000)
    data = bytearray((tmp_path / "x.bag").read_bytes())
    data[len(data) // 2:len(data) // 2 + 64] = bytes(64)
    (tmp_path / "bad.bag").write_bytes(bytes(data))
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([tmp_path / "bad.bag"], default_typestore=get_typestore(Stores.ROS1_NOETIC)) as reader:
        conns = [c for c in reader.connections if wanted(c.topic, c.msgtype)]
        assert read_indexed_bag1(tmp_path / "bad.bag", reader, conns, Collector()) is None
    assert any(n.startswith("corrupt data: skipped 1 unreadable chunks") for n in open_recording(
        tmp_path / "bad.bag").notes)


@pytest.mark.parametrize("mode", ["message", "file"])
def test_ros2_bags_rosbag2_compressed_read_like_per_message(tmp_path: Path, mode: str) -> None:
    """Per-message or per-file zstd compression by rosbag2: left to rosbags, which undoes it; same result."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    store, rng = store_of(False), np.random.default_rng(4)
    writer = Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode[mode.upper()], CompressionFormat.ZSTD)
    with writer:
        conn = writer.add_connection("/imu/mag", "sensor_msgs/msg/MagneticField", typestore=store)
        for i in range(200):
            msg = make(store, "sensor_msgs/msg/MagneticField", "imu", rng)
            msg.header.stamp.sec, msg.header.stamp.nanosec = 50, i * 1_000_000
            writer.write(conn, 50 * 10**9 + i * 1_000_000, bytes(store.serialize_cdr(msg, msg.__msgtype__)))
    rec = open_recording(tmp_path / "bag")
    assert len(rec.streams[0]) == 200
    assert_same_recording(rec, per_message(tmp_path / "bag"))


@pytest.mark.parametrize("ros1", [False, True])
def test_random_bytes_never_raise(ros1: bool) -> None:
    """Garbage of any length (including shorter than a header, and a whole buffer of 3 bytes) decodes to False."""
    store, rng = store_of(ros1), np.random.default_rng(8)
    for msgtype in TYPES:
        dec = rosvec.BatchDecoder(store.fielddefs, msgtype, ros1,
                                  lambda d, t=msgtype: store.deserialize_ros1(d, t) if ros1 else
                                  store.deserialize_cdr(d, t))
        for size in (0, 3, 40, 5000):
            buf = rng.integers(0, 256, size, dtype=np.uint8)
            buf[:2] = [0, 1][:size]
            n = 25
            start = np.sort(rng.integers(0, max(size - 1, 1), n)).astype(np.int64) if size else np.zeros(n, np.int64)
            length = np.minimum(rng.integers(0, 400, n), size - start).astype(np.int64)
            ok, stamps, values = dec(buf, start, length)
            assert ok.shape == stamps.shape == (n,) and values.shape[0] == n


def test_two_publishers_on_one_topic_stay_in_time_order(tmp_path: Path) -> None:
    """Two MCAP channels / two ROS 1 connections on one topic, interleaved: one stream in the per-message order."""
    from mcap.writer import CompressionType, Writer
    from rosbags.rosbag1 import Writer as Writer1

    store2, store1, rng = store_of(False), store_of(True), np.random.default_rng(2)
    mt = "sensor_msgs/msg/MagneticField"
    with (tmp_path / "two.mcap").open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD, chunk_size=3000)
        writer.start(profile="ros2", library="test")
        sid = writer.register_schema(mt, "ros2msg", store2.generate_msgdef(mt, ros_version=2)[0].encode())
        chans = [writer.register_channel("/imu/mag", "cdr", sid) for _ in range(2)]
        bag = Writer1(tmp_path / "two.bag")
        bag.set_compression(Writer1.CompressionFormat.LZ4)
        bag.chunk_threshold = 3000
        with bag:
            conns = [bag.add_connection("/imu/mag", mt, typestore=store1, callerid=f"/pub{k}") for k in range(2)]
            for i in range(400):
                k = int(rng.integers(0, 2))
                ns = 10**9 + i * 10_000_000
                msg2, msg1 = make(store2, mt, FRAMES[k * 3], rng), make(store1, mt, FRAMES[k * 3], rng)
                for m in (msg1, msg2):
                    m.header.stamp.sec, m.header.stamp.nanosec = 1, i * 10_000_000
                writer.add_message(chans[k], log_time=ns, publish_time=ns, data=bytes(store2.serialize_cdr(msg2, mt)))
                bag.write(conns[k], ns, bytes(store1.serialize_ros1(msg1, mt)))
        writer.finish()  # type: ignore[no-untyped-call]
    for name in ("two.mcap", "two.bag"):
        rec = open_recording(tmp_path / name)
        assert len(rec.streams) == 1 and len(rec.streams[0]) == 400
        assert not any("backwards" in n for n in rec.notes)
        assert_same_recording(rec, per_message(tmp_path / name))
