"""Standard messages nested in custom ones (issue 38 item 5): ROS 1 bags, ROS 2 bags, MCAP, the zoo VectorNav logs.

Modules it covers (the mirrored test file aside): magcal_cli.readers.ros.nested.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.errors import StreamError
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind, Recording
from magcal_cli.synth.simulate import Simulation, simulate

#: a VectorNav-style wrapper (outer header only filled) and a message holding a MagneticField two levels down
WRAPPER = "test_msgs/msg/Wrapper"
WRAPPER_MSG = """std_msgs/Header header
sensor_msgs/Imu imu
sensor_msgs/MagneticField mag_field
string raw
"""
INNER = "test_msgs/msg/Inner"
INNER_MSG = "string label\nsensor_msgs/MagneticField b\n"
DEEP = "test_msgs/msg/Deep"
DEEP_MSG = "std_msgs/Header header\ntest_msgs/Inner a\n"
#: a custom GPS message that holds no standard message (the zoo ROS 2 bag's /gps)
GPS = "test_msgs/msg/Gps"
GPS_MSG = "std_msgs/Header header\nfloat64 latitude\nfloat64 longitude\n"
ZOO = ("vectornav-ros1/calibration_circle.bag", "vectornav-ros1/calibration_square.bag",
       "vectornav-ros2/going_in_circles1")


@pytest.fixture(scope="module")
def sim() -> Simulation:
    """A 12 s simulation (40 Hz IMU and field): the wrapper carries both in one message, as VectorNav's does."""
    return simulate("paper", 3, rate=40.0, mag_rate=40.0, duration=12.0)


def _store(ros1: bool) -> Any:
    """A stock typestore with the test's custom types registered from their message definitions."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    for name, text in ((INNER, INNER_MSG), (WRAPPER, WRAPPER_MSG), (DEEP, DEEP_MSG), (GPS, GPS_MSG)):
        store.register(get_types_from_msg(text, name))
    return store


def _messages(sim: Simulation, store: Any, ros1: bool, scale: float = 1.0) -> list[tuple[int, str, Any]]:
    """(receive ns, topic, message): /w wraps the IMU and field with only its outer header stamped; /d holds the
    field as a.b with its own header stamped 2 ms after the outer one."""
    ty = store.types
    rec = sim.recording
    acc, gyr, mag = (rec.select(k) for k in (Kind.ACCELEROMETER, Kind.GYROSCOPE, Kind.MAGNETOMETER))
    n = min(len(acc), len(mag))           # one wrapper holds both: the field is stamped with the IMU's time

    def header(ns: int) -> Any:
        stamp = ty["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return ty["std_msgs/msg/Header"](**({"seq": 0} if ros1 else {}), stamp=stamp, frame_id="imu")

    def vec(v: np.ndarray) -> Any:
        return ty["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    zero9 = np.zeros(9)
    out = []
    for i, t in enumerate(acc.t[:n]):
        ns = int(round((rec.t0 + t) * 1e9))
        imu = ty["sensor_msgs/msg/Imu"](header=header(0), orientation=ty["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=zero9, angular_velocity=vec(gyr.values[i]),
            angular_velocity_covariance=zero9, linear_acceleration=vec(acc.values[i]),
            linear_acceleration_covariance=zero9)
        field = ty["sensor_msgs/msg/MagneticField"](header=header(0), magnetic_field=vec(mag.values[i] * scale),
                                                     magnetic_field_covariance=zero9)
        out.append((ns + 5_000_000, "/w", ty[WRAPPER](header=header(ns), imu=imu, mag_field=field, raw="$VNYMR")))
        own = ty["sensor_msgs/msg/MagneticField"](header=header(ns + 2_000_000), magnetic_field=vec(mag.values[i]),
                                                   magnetic_field_covariance=zero9)
        out.append((ns + 5_000_000, "/d", ty[DEEP](header=header(ns), a=ty[INNER](label="x", b=own))))
        if i % 40 == 0:
            out.append((ns, "/gps", ty[GPS](header=header(ns), latitude=42.0, longitude=-71.0)))
    return out


TYPES = {"/w": WRAPPER, "/d": DEEP, "/gps": GPS}


def write_bag1(sim: Simulation, path: Path, scale: float = 1.0, topics: tuple[str, ...] = ("/w", "/d", "/gps")) -> None:
    """A ROS 1 bag of the custom messages (rosbags writes each connection's full definition)."""
    from rosbags.rosbag1 import Writer

    store = _store(ros1=True)
    with Writer(path) as writer:
        conns = {top: writer.add_connection(top, TYPES[top], typestore=store) for top in topics}
        for ns, top, msg in _messages(sim, store, True, scale):
            if top in conns:
                writer.write(conns[top], ns, store.serialize_ros1(msg, TYPES[top]))


def write_bag2(sim: Simulation, path: Path, storage: str) -> None:
    """A ROS 2 bag directory (MCAP or sqlite3 storage) of the custom messages, definitions embedded."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = _store(ros1=False)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {top: writer.add_connection(top, typ, typestore=store) for top, typ in TYPES.items()}
        for ns, top, msg in _messages(sim, store, False):
            writer.write(conns[top], ns, store.serialize_cdr(msg, TYPES[top]))


def write_mcap(sim: Simulation, path: Path) -> None:
    """An MCAP file written by mcap-ros2-support with the custom schemas (ros2msg, dependencies appended)."""
    from mcap_ros2.writer import Writer

    sep = "=" * 80
    deps = {"sensor_msgs/Imu": "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
                               "float64[9] orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\n"
                               "float64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n"
                               "float64[9] linear_acceleration_covariance\n",
            "sensor_msgs/MagneticField": "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\n"
                                         "float64[9] magnetic_field_covariance\n",
            "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
            "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
            "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
            "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
            "test_msgs/Inner": INNER_MSG}
    store = _store(ros1=False)
    with path.open("wb") as fh:
        writer = Writer(fh)
        schemas = {top: writer.register_msgdef(typ.replace("/msg/", "/"), text + "".join(
            f"{sep}\nMSG: {name}\n{body}" for name, body in deps.items()))
                   for top, typ, text in (("/w", WRAPPER, WRAPPER_MSG), ("/d", DEEP, DEEP_MSG), ("/gps", GPS, GPS_MSG))}
        for ns, top, msg in _messages(sim, store, False):
            writer.write_message(top, schemas[top], _as_dict(msg), log_time=ns, publish_time=ns)
        writer.finish()


def _as_dict(msg: Any) -> Any:
    """A rosbags message as the nested dicts mcap-ros2-support serialises."""
    if hasattr(msg, "__dataclass_fields__"):
        return {k: _as_dict(getattr(msg, k)) for k in msg.__dataclass_fields__ if k != "__msgtype__"}
    return msg.tolist() if isinstance(msg, np.ndarray) else msg


WRITERS = {"bag1": lambda s, p: write_bag1(s, p / "log.bag"),
           "bag2-mcap": lambda s, p: write_bag2(s, p / "b", "mcap"),
           "bag2-sqlite3": lambda s, p: write_bag2(s, p / "b", "sqlite3"),
           "mcap": lambda s, p: write_mcap(s, p / "l.mcap")}
PATHS = {"bag1": "log.bag", "bag2-mcap": "b", "bag2-sqlite3": "b", "mcap": "l.mcap"}


@pytest.mark.parametrize("kind", list(WRITERS))
def test_nested_messages_are_read_as_topic_dot_field(tmp_path: Path, sim: Simulation, kind: str) -> None:
    """A wrapper's Imu and MagneticField become /w.imu and /w.mag_field (timed by the outer header, their own
    being zero); a field two levels down becomes /d.a.b, timed by its own header. Before issue 38 the log had no
    stream ("no accelerometer stream; available: none")."""
    WRITERS[kind](sim, tmp_path)
    rec = open_recording(tmp_path / PATHS[kind])
    truth = sim.recording
    ids = sorted({(s.id, s.kind.value) for s in rec.streams})
    assert ids == [("/d.a.b", "magnetometer"), ("/w.imu", "accelerometer"), ("/w.imu", "gyroscope"),
                   ("/w.mag_field", "magnetometer")]
    for kind_, sid in ((Kind.ACCELEROMETER, "/w.imu"), (Kind.GYROSCOPE, "/w.imu"), (Kind.MAGNETOMETER, "/w.mag_field"),
                       (Kind.MAGNETOMETER, "/d.a.b")):
        got, want = rec.select(kind_, sid), truth.select(kind_)
        t = truth.select(Kind.ACCELEROMETER).t[:len(got)]       # every message is stamped with the IMU's time
        shift = 2e-3 if sid == "/d.a.b" else 0.0                 # /d.a.b's own stamp is 2 ms after the outer one
        np.testing.assert_allclose(got.t + (rec.t0 - truth.t0), t + shift, atol=1e-6, rtol=0)   # t0: 1.7e9 s
        np.testing.assert_allclose(got.values, want.values[:len(got)], rtol=1e-15, atol=0)
        assert got.native_unit == ("tesla" if kind_ is Kind.MAGNETOMETER else got.native_unit)
    deep, outer = rec.select(Kind.MAGNETOMETER, "/d.a.b").t, rec.select(Kind.MAGNETOMETER, "/w.mag_field").t
    np.testing.assert_allclose(deep - outer, 2e-3, atol=1e-9, rtol=0)
    assert not any("/w " in n or "(test_msgs/msg/Wrapper)" in n for n in rec.notes)   # not listed as ignored
    assert any("/gps (test_msgs" in n for n in rec.notes)


def test_a_cut_ros1_bag_keeps_its_nested_messages(tmp_path: Path, sim: Simulation) -> None:
    """A ROS 1 bag cut before its index (read record by record) still yields /w.imu and /w.mag_field."""
    write_bag1(sim, tmp_path / "full.bag", topics=("/w",))
    data = (tmp_path / "full.bag").read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[:len(data) * 7 // 10])
    rec = open_recording(tmp_path / "cut.bag")
    got = rec.select(Kind.MAGNETOMETER, "/w.mag_field")
    assert 0 < len(got) < len(sim.recording.select(Kind.MAGNETOMETER))
    assert len(rec.select(Kind.ACCELEROMETER, "/w.imu")) == len(got)
    want = sim.recording.select(Kind.MAGNETOMETER).values[:len(got)]
    np.testing.assert_allclose(got.values, want, rtol=1e-15, atol=0)


def test_gauss_in_a_magneticfield_is_read_as_gauss(tmp_path: Path, sim: Simulation) -> None:
    """VectorNav's ROS 1 driver fills MagneticField with gauss: a magnitude 1e4 times the Earth's field in tesla
    is read as gauss, with a note (docs/decisions.md)."""
    write_bag1(sim, tmp_path / "g.bag", scale=1e4, topics=("/w",))
    rec = open_recording(tmp_path / "g.bag")
    mag = rec.select(Kind.MAGNETOMETER, "/w.mag_field")
    assert mag.native_unit == "gauss"
    np.testing.assert_allclose(mag.values, sim.recording.select(Kind.MAGNETOMETER).values[:len(mag)], rtol=1e-12)
    assert any("/w.mag_field: sensor_msgs/msg/MagneticField read as the field in gauss" in n for n in rec.notes)


def test_a_log_without_usable_streams_names_its_topics_and_what_was_looked_for(tmp_path: Path,
                                                                                sim: Simulation) -> None:
    """Only a custom GPS message: one error that says where, lists the topics with their types, the types and
    fields looked for, and how to fix it (was "no accelerometer stream; available: none")."""
    write_bag1(sim, tmp_path / "gps.bag", topics=("/gps",))
    with pytest.raises(StreamError) as err:
        open_recording(tmp_path / "gps.bag")
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"{tmp_path / 'gps.bag'}: no stream magcal reads; its topics are /gps "
                           "(test_msgs/msg/Gps); looked for these types as topics or as fields of any message at any "
                           "depth: sensor_msgs/msg/Imu (linear_acceleration, angular_velocity), "
                           "sensor_msgs/msg/MagneticField (magnetic_field)")
    assert text.endswith("Publish the sensors as these standard messages, or export them to CSV "
                         "(docs/readers-ros-csv.md)")
    res = CliRunner().invoke(cli, ["fit", str(tmp_path / "gps.bag"), "-o", str(tmp_path / "out")])
    assert res.exit_code == 1
    assert "Error: " in res.output and "its topics are /gps (test_msgs/msg/Gps)" in res.output


def test_mag_and_imu_select_nested_streams(tmp_path: Path, sim: Simulation) -> None:
    """--mag /d.a.b and --imu /w.imu pick the nested streams; an unknown id lists the TOPIC.FIELD ids."""
    write_bag1(sim, tmp_path / "s.bag", topics=("/w", "/d"))
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["fit", str(tmp_path / "s.bag"), "--mag", "/d.a.b", "--imu", "/w.imu", "-o",
                                    str(out), "-q"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "calibration.json").read_text())
    assert [m["id"] for m in doc["magnetometers"]] == ["/d.a.b"]
    res = CliRunner().invoke(cli, ["fit", str(tmp_path / "s.bag"), "--mag", "/w.mag", "-o", str(tmp_path / "o2")])
    assert res.exit_code == 2                                      # a usage error: the id is not in the log
    assert "/d.a.b" in res.output and "/w.mag_field" in res.output


@pytest.fixture
def zoo(realdata: Path) -> Path:
    """../shared/realdata/zoo, or a skip naming it."""
    folder = realdata / "zoo"
    if not all((folder / name).exists() for name in ZOO):
        pytest.skip(f"the zoo VectorNav logs are not at {folder}")
    return folder


@pytest.mark.parametrize("name", ZOO)
def test_zoo_vectornav_inspect_lists_the_nested_streams(zoo: Path, name: str) -> None:
    """`magcal inspect` on the real VectorNav bags (ROS 1 and ROS 2 MCAP) lists /imu.imu and /imu.mag_field."""
    res = CliRunner().invoke(cli, ["inspect", str(zoo / name), "--json"])
    assert res.exit_code == 0, res.output
    streams = {(s["id"], s["kind"]) for s in json.loads(res.output)["streams"]}
    assert {("/imu.imu", "accelerometer"), ("/imu.imu", "gyroscope"), ("/imu.mag_field", "magnetometer")} <= streams
    rec: Recording = open_recording(zoo / name)
    mag = rec.select(Kind.MAGNETOMETER, "/imu.mag_field")
    assert mag.native_unit == ("gauss" if name.endswith(".bag") else "tesla")
    assert 20e-6 < float(np.median(np.linalg.norm(mag.values, axis=1))) < 70e-6      # the Earth's field, in SI


@pytest.mark.parametrize("name", ZOO)
def test_zoo_vectornav_fit_reads_the_streams(zoo: Path, tmp_path: Path, name: str) -> None:
    """`magcal fit` reads the nested streams of the real VectorNav logs: it calibrates /imu.mag_field or names it
    when the motion (a car on flat ground) is too poor, but never says a stream is missing. As measured at this
    commit: the ROS 1 circle and the ROS 2 bag are calibrated (exit 0), the ROS 1 square is refused (exit 1)."""
    res = CliRunner().invoke(cli, ["fit", str(zoo / name), "-o", str(tmp_path / "out"), "-q"])
    assert "no accelerometer stream" not in res.output and "no magnetometer stream" not in res.output
    if res.exit_code == 0:
        doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
        ids = [m["id"] for m in doc["magnetometers"]] + [r["id"] if isinstance(r, dict) else r for r in doc["refused"]]
        assert "/imu.mag_field" in ids
        assert doc["imu"]["id"] == "/imu.imu"
    else:
        assert res.exit_code == 1, res.output
        assert "/imu.mag_field" in res.output
