"""MCAP: ROS 2 CDR, ROS 1 and JSON channels, zstd and lz4 chunks, the extra sensor types, errors, real file.

Modules it covers (the mirrored test file aside): magcal_cli.readers.ros.mcap, magcal_cli.readers.ros.mcap_stream.
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcal_cli.errors import LogReadError, StreamError
from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.logs.rosbag import Builder, messages, topics
from magcal_cli.synth.simulate import Simulation, simulate

SCHEMA_ENCODING = {"cdr": "ros2msg", "ros1": "ros1msg", "json": "jsonschema"}


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A 12 s simulation plus battery, temperature and GNSS streams on a slower clock."""
    base = simulate("paper", 4, rate=80.0, mag_rate=40.0, duration=12.0)
    t = base.recording.select(Kind.ACCELEROMETER).t[::10]
    n = t.size
    extra = (Stream(Kind.BATTERY_CURRENT, "/battery", t, np.linspace(2, 30, n), "sim", "A"),
             Stream(Kind.BATTERY_VOLTAGE, "/battery", t, np.linspace(16.8, 15.1, n), "sim", "V"),
             Stream(Kind.TEMPERATURE, "/imu/temperature", t, np.linspace(21, 24, n), "sim", "degC"),
             Stream(Kind.POSITION, "/gps/fix", t, np.column_stack([np.full(n, 47.2), np.full(n, 8.4),
                                                                  np.linspace(400, 410, n)]), "sim", "deg"))
    rec = base.recording
    return replace(base, recording=Recording(rec.path, rec.format, rec.streams + extra, t0=rec.t0))


def plain(obj: Any) -> Any:
    """A rosbags message as JSON-ready dicts and lists (the ROS field names)."""
    if hasattr(obj, "__dataclass_fields__"):
        return {k: plain(getattr(obj, k)) for k in obj.__dataclass_fields__ if not k.startswith("__")}
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


def write_mcap(sim: Simulation, path: Path, encoding: str, compression: str = "zstd",
               edit: Any = None, chunk_size: int = 1 << 20) -> None:
    """The simulation as MCAP channels of one message encoding; `edit(dict) -> dict` alters JSON messages."""
    from mcap.writer import CompressionType, Writer
    from rosbags.typesys import Stores, get_typestore

    ros1 = encoding == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    builder = Builder(store, ros1, sim.truth.noise_std)
    with path.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType[compression.upper()], chunk_size=chunk_size)
        writer.start(profile="ros1" if ros1 else "ros2", library="magcal tests")
        channels = {}
        for topic, msgtype, _ in topics(sim.recording):
            name = msgtype.replace("/msg/", "/") if ros1 else msgtype
            text = "{}" if encoding == "json" else store.generate_msgdef(msgtype, ros_version=1 if ros1 else 2)[0]
            sid = writer.register_schema(name=name, encoding=SCHEMA_ENCODING[encoding], data=text.encode())
            channels[topic] = writer.register_channel(topic=topic, message_encoding=encoding, schema_id=sid)
        for seq, (ns, topic, msgtype, msg) in enumerate(messages(sim.recording, builder)):
            if encoding == "json":
                data = json.dumps((edit or (lambda d: d))(plain(msg))).encode()
            elif ros1:
                data = bytes(store.serialize_ros1(msg, msgtype))
            else:
                data = bytes(store.serialize_cdr(msg, msgtype))
            writer.add_message(channels[topic], log_time=ns + 1000, data=data, publish_time=ns, sequence=seq)
        writer.finish()  # type: ignore[no-untyped-call]


def assert_same(rec: Recording, sim: Simulation) -> None:
    """Every simulated stream read back: times to 2 ns, values to float32 quantisation (BatteryState)."""
    assert len(rec.streams) == len(sim.recording.streams)
    for s in sim.recording.streams:
        got = rec.select(s.kind, s.id)
        np.testing.assert_allclose(got.t + (rec.t0 - sim.recording.t0), s.t, atol=2e-9, rtol=0)
        tol = 1e-7 if s.kind in (Kind.BATTERY_CURRENT, Kind.BATTERY_VOLTAGE) else 0.0
        np.testing.assert_allclose(got.values, s.values, rtol=tol, atol=0)


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
@pytest.mark.parametrize("encoding", ["cdr", "ros1", "json"])
def test_round_trip(tmp_path: Path, sim: Simulation, encoding: str, compression: str) -> None:
    """ROS 2 CDR, ROS 1 and JSON channels of every sensor type, in zstd and lz4 chunks, read back exactly."""
    path = tmp_path / f"{encoding}-{compression}.mcap"
    write_mcap(sim, path, encoding, compression)
    rec = open_recording(path)
    assert rec.format == "mcap"
    assert_same(rec, sim)
    assert "/battery: current negated (ROS reports discharge as negative; magcal uses the current drawn)" in rec.notes


def test_simulated_mcap_from_magcal_simulate_reads_back(tmp_path: Path, sim: Simulation) -> None:
    """The foundation's MCAP writer (ROS 2 CDR, zstd) and this reader agree on IMU and field."""
    write_log(sim, tmp_path / "s.mcap")
    rec = open_recording(tmp_path / "s.mcap")
    for kind in (Kind.ACCELEROMETER, Kind.GYROSCOPE, Kind.MAGNETOMETER):
        np.testing.assert_array_equal(rec.select(kind).values, sim.recording.select(kind).values)


def test_receive_time_is_the_log_time(tmp_path: Path, sim: Simulation) -> None:
    """With receive_time the MCAP log_time (here 1 us after the header stamp) times the samples."""
    write_mcap(sim, tmp_path / "x.mcap", "cdr")
    stamped = open_recording(tmp_path / "x.mcap")
    received = open_recording(tmp_path / "x.mcap", options=ReadOptions(receive_time=True))
    assert received.t0 - stamped.t0 == pytest.approx(1e-6, abs=3e-7)    # t0 ~ 1.8e9 s: float64 step 2.4e-7


def test_json_with_ros1_stamp_spelling(tmp_path: Path, sim: Simulation) -> None:
    """JSON from ROS 1 bridges spells the stamp secs/nsecs; it reads the same."""
    def ros1_stamp(d: dict[str, Any]) -> dict[str, Any]:
        st = d["header"]["stamp"]
        d["header"]["stamp"] = {"secs": st["sec"], "nsecs": st["nanosec"]}
        return d

    write_mcap(sim, tmp_path / "j.mcap", "json", edit=ros1_stamp)
    assert_same(open_recording(tmp_path / "j.mcap"), sim)


def test_json_without_the_ros_fields_is_an_error(tmp_path: Path, sim: Simulation) -> None:
    """A JSON message that lacks a field of its ROS type names the channel and the documented layout."""
    def drop_field(d: dict[str, Any]) -> dict[str, Any]:
        d.pop("magnetic_field", None)
        return d

    write_mcap(sim, tmp_path / "j.mcap", "json", edit=drop_field)
    with pytest.raises(LogReadError, match=r"j.mcap: channel /imu/mag \(sensor_msgs/msg/MagneticField, json\): the "
                                           r"message at log time \d+ ns does not have the ROS fields of "
                                           r"sensor_msgs/msg/MagneticField \(AttributeError: .*magnetic_field.*\)\. "
                                           r"See docs/readers-ros-csv.md"):
        open_recording(tmp_path / "j.mcap")


def test_channels_magcal_cannot_decode_are_listed(tmp_path: Path) -> None:
    """A protobuf channel and an unknown type are skipped and named in one note."""
    from mcap.writer import Writer

    with (tmp_path / "p.mcap").open("wb") as fh:
        writer = Writer(fh)
        writer.start()
        pb = writer.register_schema(name="sensor_msgs/msg/Imu", encoding="protobuf", data=b"")
        other = writer.register_schema(name="tf2_msgs/msg/TFMessage", encoding="ros2msg", data=b"")
        writer.add_message(writer.register_channel("/imu/pb", "protobuf", pb), log_time=1, data=b"", publish_time=1)
        writer.add_message(writer.register_channel("/tf", "cdr", other), log_time=2, data=b"", publish_time=2)
        writer.finish()  # type: ignore[no-untyped-call]
    with pytest.raises(StreamError, match=r"p.mcap: no stream magcal reads; its topics are /imu/pb "
                                          r"\(sensor_msgs/msg/Imu in protobuf encoding\), /tf \(tf2_msgs/msg/TFMessage\); looked for"):
        open_recording(tmp_path / "p.mcap")


def test_truncated_mcap(tmp_path: Path, sim: Simulation) -> None:
    """A cut file: the complete messages (and those the cut chunk's bytes still hold) are read and noted;
    --strict refuses it."""
    write_mcap(sim, tmp_path / "x.mcap", "cdr", "lz4", chunk_size=32_000)
    data = (tmp_path / "x.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(LogReadError, match=r"cut.mcap: the log is cut: it ends inside a record at byte \d+ of \d+ "
                                           r"\(an? [a-z ]+ record, .*\)\. Re-copy the log, or leave out --strict"):
        open_recording(tmp_path / "cut.mcap", options=ReadOptions(allow_truncated=False))
    rec = open_recording(tmp_path / "cut.mcap")
    assert rec.cut is not None and rec.notes[0].startswith("the log is cut: it ends inside a record at byte ")
    assert 0 < len(rec.select(Kind.MAGNETOMETER)) < len(sim.recording.select(Kind.MAGNETOMETER))


def test_real_phidgets_mcap_storage_file(realdata: Path) -> None:
    """The .mcap inside the converted ROS 2 bag reads on its own: 13964 IMU messages, half the field NaN."""
    rec = open_recording(realdata / "ros" / "phidgets_imu_upside_down_mcap" / "phidgets_imu_upside_down_mcap.mcap")
    assert rec.format == "mcap"
    assert len(rec.select(Kind.ACCELEROMETER, "/imu/data_raw")) == 13964
    assert len(rec.select(Kind.MAGNETOMETER, "/imu/mag")) == 6974
    assert rec.notes == ("/imu/mag: dropped 6990 samples with NaN or inf",)


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_corrupt_chunk_is_skipped_and_counted_never_garbage(tmp_path: Path, sim: Simulation, compression: str) -> None:
    """Zeroed bytes inside a chunk fail its CRC (or decompression): that chunk is skipped and counted, every
    sample read is exact, and reading goes on with the next chunk (issue 6: skip corrupt records, as pymavlink)."""
    write_mcap(sim, tmp_path / "x.mcap", "cdr", compression, chunk_size=32_000)
    data = bytearray((tmp_path / "x.mcap").read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(64)
    (tmp_path / "bad.mcap").write_bytes(bytes(data))
    rec = open_recording(tmp_path / "bad.mcap")
    assert rec.notes[0] == ("corrupt data: skipped 1 chunks that fail their CRC or do not decompress; reading "
                            "resumed after each")
    got, want = rec.select(Kind.MAGNETOMETER), sim.recording.select(Kind.MAGNETOMETER)
    assert 0.5 * len(want) < len(got) < len(want)
    idx = np.searchsorted(want.t, got.t + (rec.t0 - sim.recording.t0) - 1e-6)
    np.testing.assert_array_equal(got.values, want.values[idx])


def test_broken_record_framing_resynchronises_on_the_next_chunk(tmp_path: Path, sim: Simulation) -> None:
    """Bytes inserted inside a chunk break the record lengths: the reader finds the next chunk header."""
    write_mcap(sim, tmp_path / "x.mcap", "cdr", "zstd", chunk_size=32_000)
    data = (tmp_path / "x.mcap").read_bytes()
    mid = len(data) // 3
    (tmp_path / "bad.mcap").write_bytes(data[:mid] + b"\x01" * 37 + data[mid:])
    rec = open_recording(tmp_path / "bad.mcap")
    assert re.fullmatch(r"corrupt data: skipped \d+ bytes with broken record framing; reading resumed after each",
                        rec.notes[0])
    got, want = rec.select(Kind.MAGNETOMETER), sim.recording.select(Kind.MAGNETOMETER)
    assert 0 < len(got) <= len(want)
    assert got.t[-1] + rec.t0 == pytest.approx(want.t[-1] + sim.recording.t0, abs=1e-6)   # read on to the end


def test_chunks_read_from_their_message_indexes_as_by_the_record_walk(tmp_path: Path, sim: Simulation,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Every chunk of message records only is read from its indexes (the first, which also holds the schema and
    channel records, by the walk), with the same streams as the walk gives."""
    from magcal_cli.readers.ros import mcap_chunk

    path = tmp_path / "x.mcap"
    write_mcap(sim, path, "cdr", chunk_size=32_000)
    used: list[bool] = []
    real = mcap_chunk.indexed

    def spy(data: bytes, index: list[Any]) -> Any:
        used.append((got := real(data, index)) is not None)
        return got

    monkeypatch.setattr(mcap_chunk, "indexed", spy)
    fast = open_recording(path)
    assert len(used) > 1 and not used[0] and all(used[1:])
    monkeypatch.setattr(mcap_chunk, "indexed", lambda data, index: None)
    walked = open_recording(path)
    assert fast.notes == walked.notes and len(fast.streams) == len(walked.streams)
    for a, b in zip(fast.streams, walked.streams, strict=True):
        assert (a.kind, a.id) == (b.kind, b.id)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.values, b.values)
    assert_same(fast, sim)


def test_an_index_that_disagrees_with_its_chunk_is_not_used() -> None:
    """Offsets that skip a record, point past the chunk or at another opcode: the walk reads the chunk."""
    from magcal_cli.readers.ros.mcap_chunk import MESSAGE_OPCODE, RawIndex, indexed

    def record(channel: int, payload: bytes) -> bytes:
        body = channel.to_bytes(2, "little") + bytes(4) + (7).to_bytes(8, "little") * 2 + payload
        return bytes([MESSAGE_OPCODE]) + len(body).to_bytes(8, "little") + body

    def index(*offsets: int) -> RawIndex:
        entries = b"".join((5).to_bytes(8, "little") + o.to_bytes(8, "little") for o in offsets)
        return RawIndex((1).to_bytes(2, "little") + len(entries).to_bytes(4, "little") + entries)

    a, b = record(1, b"abc"), record(1, b"defgh")
    data = a + b
    good = indexed(data, [index(0, len(a))])
    assert good is not None and good.start.tolist() == [31, len(a) + 31] and good.length.tolist() == [3, 5]
    assert indexed(data, [index(0)]) is None                         # a record not indexed
    assert indexed(data, [index(0, len(a) + 1)]) is None             # an offset inside a record
    assert indexed(data + bytes([0x03]) + bytes(8), [index(0, len(a))]) is None   # another record follows
    assert indexed(data, [RawIndex(b"\x01\x00\xff\xff\xff\xff")]) is None        # a length past the record
