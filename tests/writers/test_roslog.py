"""`magcal apply CAL LOG -o OUT.mcap|OUT.bag|DIR` (issue 40): the log copied with a calibrated MagneticField
topic; read back with mcap-ros2-support and rosbags, originals byte-identical, the topic equal to apply's CSV.

Modules it covers (the mirrored test file aside): magcal_cli.writers.roslog.bags, magcal_cli.writers.roslog.mcapfile,
magcal_cli.writers.roslog.series, magcal_cli.calibration.fieldcov.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import units
from magcal_cli.calibration.apply import apply_rows
from magcal_cli.calibration.document import load
from magcal_cli.calibration.fieldcov import field_covariance, field_jacobian
from magcal_cli.calibration.types import Calibration, ImuCalibration
from magcal_cli.cli.main import cli
from magcal_cli.errors import OutputError
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind, Recording
from magcal_cli.writers.roslog import apply_to_log
from magcal_cli.writers.roslog.series import out_topic, split_id

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ROOT / "sample_logs"
MF = "sensor_msgs/msg/MagneticField"


def with_cov(cal: Calibration, seed: int = 0) -> Calibration:
    """`cal` with a random positive-definite covariance on every magnetometer (the truth documents carry none)."""
    rng = np.random.default_rng(seed)
    mags = []
    for m in cal.magnetometers:
        scale = np.r_[np.full(9, 1e-3 * m.field_strength), np.full(3, 1e-2 * m.field_strength), 0.1]
        g = rng.normal(size=(13, 13))
        mags.append(replace(m, cov=(g @ g.T / 13 + np.eye(13)) * np.outer(scale, scale)))
    return replace(cal, magnetometers=tuple(mags))


def made_for(rec: Recording) -> Calibration:
    """A calibration of every magnetometer of `rec` (a mild soft iron and offset in its own unit), against its
    first IMU: for the real logs, which ship no calibration."""
    base = load(SAMPLES / "handheld.mcap.truth.json")
    mags = []
    for s in rec.of_kind(Kind.MAGNETOMETER):
        unit = units.canonical(s.native_unit)
        f = float(np.median(np.linalg.norm(s.xyz, axis=1))) * units.from_si(unit)
        d = f * np.array([[1.05, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.01]])
        mags.append(replace(base.magnetometers[0], id=s.id, unit=unit, D=d, o=np.array([0.1, -0.05, 0.02]) * f,
                            field_strength=f))
    imu = rec.of_kind(Kind.ACCELEROMETER)
    return with_cov(replace(base, magnetometers=tuple(mags), effects=(), refused=(),
                            imu=ImuCalibration(id=imu[0].id if imu else "imu")))


def read_back(out: Path) -> tuple[dict[str, list[bytes]], dict[str, list[Any]], dict[str, str]]:
    """(raw payloads per topic, decoded MagneticField messages per topic, type per topic) with the libraries' own
    readers: mcap + mcap-ros2-support for an MCAP file, rosbags for a bag."""
    raw: dict[str, list[bytes]] = defaultdict(list)
    dec: dict[str, list[Any]] = defaultdict(list)
    types: dict[str, str] = {}
    if out.suffix == ".mcap":
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        with out.open("rb") as fh:
            for schema, ch, msg, d in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
                raw[ch.topic].append(msg.data)
                types[ch.topic] = schema.name
                if schema.name == MF:
                    dec[ch.topic].append(d)
        return raw, dec, types
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as reader:
        for conn, _, data in reader.messages():
            raw[conn.topic].append(bytes(data))
            types[conn.topic] = conn.msgtype
            if conn.msgtype == MF:
                dec[conn.topic].append(reader.deserialize(data, conn.msgtype))
    return raw, dec, types


def check_copy(log: Path, out: Path, cal: Calibration, replace_: bool = False) -> dict[str, Any]:
    """Apply, read back, and check: originals byte-identical, one message per reading, field = apply's rows to
    1e-12 relative, covariance = the propagated one, frame = the IMU's. Returns the decoded calibrated topics."""
    rec = open_recording(log)
    done = apply_to_log(cal, log, out, replace=replace_)
    before, _, _ = read_back(log)
    after, dec, types = read_back(out)
    new = set(done.topics)
    for topic, payloads in before.items():
        if topic not in new:
            assert after[topic] == payloads, f"{topic}: payloads changed"
    rows, _, _ = apply_rows(cal, rec)
    for m in cal.magnetometers:
        mine = [(t, v) for t, i, v in rows if i == m.id]
        topic = out_topic(m.id, None, replace_)
        assert types[topic] == MF
        got = dec[topic]
        assert len(got) == len(mine) == done.topics[topic]
        field = np.array([[g.magnetic_field.x, g.magnetic_field.y, g.magnetic_field.z] for g in got])
        want = np.array([v for _, v in mine]) * units.to_si(m.unit)
        np.testing.assert_allclose(field, want, rtol=1e-12, atol=0)
        cov = np.array([np.asarray(g.magnetic_field_covariance) for g in got]).reshape(-1, 3, 3)
        ref = field_covariance(m, np.array([v for _, v in mine])) * units.to_si(m.unit) ** 2
        np.testing.assert_allclose(cov, ref, rtol=1e-12, atol=1e-30)
        stamps = np.array([g.header.stamp.sec * 10**9 + g.header.stamp.nanosec for g in got])
        np.testing.assert_allclose((stamps - stamps[0]) * 1e-9, np.array([t for t, _ in mine]) - mine[0][0],
                                   atol=2e-9)
        if m.id in dec and not replace_:          # a MagneticField source: the stamps are its own, to the ns
            own = {g.header.stamp.sec * 10**9 + g.header.stamp.nanosec for g in dec[m.id]}
            assert set(stamps.tolist()) <= own
    return dec


def test_field_jacobian_matches_finite_differences() -> None:
    """dm/d(vec D, o) of m = F A (y - o), the formula written once in calibration/fieldcov.py, against central
    differences; and the covariance is J cov J^T with the dip's rows left out."""
    cal = with_cov(load(SAMPLES / "handheld.mcap.truth.json"))
    mag = cal.magnetometers[0]
    rng = np.random.default_rng(3)
    y = mag.distort(rng.normal(size=(4, 3))) + rng.normal(size=(4, 3)) * 1e-7
    m = mag.field_strength * mag.apply(y)
    theta = np.r_[mag.D.ravel(order="F"), mag.o]

    def field(th: np.ndarray) -> np.ndarray:
        d, o = th[:9].reshape(3, 3, order="F"), th[9:]
        return mag.field_strength * (y - o) @ np.linalg.inv(d).T

    fd = np.zeros((4, 3, 12))
    for k in range(12):
        h = 1e-6 * max(abs(theta[k]), mag.field_strength)
        e = np.zeros(12)
        e[k] = h
        fd[:, :, k] = (field(theta + e) - field(theta - e)) / (2 * h)
    j = field_jacobian(mag, m)
    np.testing.assert_allclose(j, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())
    c = mag.cov[:12, :12]
    np.testing.assert_allclose(field_covariance(mag, m), np.einsum("nip,pq,njq->nij", fd, c, fd), rtol=1e-5)


@pytest.mark.parametrize("name", ["handheld.mcap", "handheld.bag", "handheld_ros2"])
def test_sample_logs_copied_with_the_calibrated_topic(tmp_path: Path, name: str) -> None:
    """The shipped MCAP sample and the simulated ROS 1 bag and ROS 2 bag folder: each copy reads back, its
    originals are byte-identical, and the new topic is apply's field, one message per reading, in the IMU's frame."""
    log = SAMPLES / name
    cal = with_cov(load(SAMPLES / f"{name}.truth.json"))
    out = tmp_path / ("out" + (log.suffix or ""))
    dec = check_copy(log, out, cal)
    assert {g.header.frame_id for g in dec["/imu/mag/calibrated"]} == {"imu_link"}


REAL = ["ros/ardrone_imu.bag", "ros/phidgets_imu_upside_down.bag", "ros/phidgets_imu_upside_down_legacy_Vector3Stamped.bag",
        "ros/phidgets_imu_upside_down_mcap", "ros/sparkfun_razor.bag", "ros/sparkfun_razor_sqlite3",
        "zoo/vectornav-ros1/calibration_circle.bag", "zoo/vectornav-ros2/going_in_circles1"]


@pytest.mark.parametrize("name", REAL)
def test_real_bags_copied_with_the_calibrated_topic(tmp_path: Path, realdata: Path, name: str) -> None:
    """The real ROS 1 and ROS 2 bags of ../shared/realdata (legacy Vector3Stamped, VectorNav wrappers whose field
    is `/imu.mag_field`: topic `/imu/mag_field/calibrated`) copied and checked as the samples are."""
    log = realdata / name
    if not log.exists():
        pytest.skip(f"{log} not available")
    cal = made_for(open_recording(log))
    check_copy(log, tmp_path / ("out" + log.suffix), cal)


def test_csv_and_topic_agree(tmp_path: Path) -> None:
    """`apply -o OUT.csv` and `apply -o OUT.mcap` give the same field: the topic printed as the CSV prints it (7
    significant digits, in the document's unit) is the CSV, row for row (the unrounded rows agree to 1e-12 relative
    in check_copy)."""
    cal_path = tmp_path / "cal.json"
    cal_path.write_text((SAMPLES / "handheld.mcap.truth.json").read_text())
    log = SAMPLES / "handheld.mcap"
    runner = CliRunner()
    for out in ("a.csv", "a.mcap"):
        res = runner.invoke(cli, ["apply", str(cal_path), str(log), "-o", str(tmp_path / out)])
        assert res.exit_code == 0, res.output
    csv = [ln.split(",")[2:5] for ln in (tmp_path / "a.csv").read_text().splitlines()[1:]]
    _, dec, _ = read_back(tmp_path / "a.mcap")
    per_t = units.from_si(load(cal_path).magnetometers[0].unit)
    topic = np.array([[g.magnetic_field.x, g.magnetic_field.y, g.magnetic_field.z]
                      for g in dec["/imu/mag/calibrated"]]) * per_t
    printed = np.array(csv, dtype=float)
    assert topic.shape == printed.shape
    assert np.max(np.abs(topic - printed)) <= 1e-12 * np.max(np.abs(printed))


def test_rosbags_converts_the_outputs(tmp_path: Path) -> None:
    """rosbags' converter takes the ROS 1 copy to ROS 2 and the ROS 2 copy to ROS 1, calibrated topic included."""
    from rosbags.convert import convert
    from rosbags.typesys import Stores, get_typestore

    cal = with_cov(load(SAMPLES / "handheld.bag.truth.json"))
    apply_to_log(cal, SAMPLES / "handheld.bag", tmp_path / "a.bag")
    apply_to_log(cal, SAMPLES / "handheld_ros2", tmp_path / "b")
    store = get_typestore(Stores.ROS2_HUMBLE)
    for src, dst in ((tmp_path / "a.bag", tmp_path / "a2"), (tmp_path / "b", tmp_path / "b1.bag")):
        convert([src], dst, "mcap" if dst.suffix != ".bag" else "", 9, None, "none", store, None, [], [], [], [])
        _, dec, _ = read_back(dst)
        assert len(dec["/imu/mag/calibrated"]) == 2402


def test_dataflash_becomes_a_ros2_mcap(tmp_path: Path) -> None:
    """A DataFlash log: -o OUT.mcap writes its IMU (sensor_msgs/Imu) and its magnetometer as logged and calibrated,
    read back by mcap-ros2-support; --replace leaves only the calibrated one, under the compass's own name."""
    cal = with_cov(load(SAMPLES / "handheld.bin.truth.json"))
    done = apply_to_log(cal, SAMPLES / "handheld.bin", tmp_path / "a.mcap")
    raw, dec, types = read_back(tmp_path / "a.mcap")
    assert types == {"/IMU0": "sensor_msgs/msg/Imu", "/MAG0": MF, "/MAG0/calibrated": MF}
    assert len(dec["/MAG0/calibrated"]) == len(dec["/MAG0"]) == done.topics["/MAG0/calibrated"]
    apply_to_log(cal, SAMPLES / "handheld.bin", tmp_path / "b.mcap", replace=True)
    _, dec2, types2 = read_back(tmp_path / "b.mcap")
    assert set(types2) == {"/IMU0", "/MAG0"}
    assert [g.magnetic_field.x for g in dec2["/MAG0"]] == [g.magnetic_field.x for g in dec["/MAG0/calibrated"]]


def test_replace_and_topic(tmp_path: Path) -> None:
    """--replace puts the calibrated field on the magnetometer's own topic; --topic renames it."""
    cal = with_cov(load(SAMPLES / "handheld.bag.truth.json"))
    apply_to_log(cal, SAMPLES / "handheld.bag", tmp_path / "r.bag", replace=True)
    apply_to_log(cal, SAMPLES / "handheld.bag", tmp_path / "t.bag", topic="/mag_cal")
    _, dec_r, types_r = read_back(tmp_path / "r.bag")
    _, dec_t, types_t = read_back(tmp_path / "t.bag")
    assert set(types_r) == {"/imu/data", "/imu/mag"}
    assert set(types_t) == {"/imu/data", "/imu/mag", "/mag_cal"}
    assert [g.magnetic_field.y for g in dec_r["/imu/mag"]] == [g.magnetic_field.y for g in dec_t["/mag_cal"]]


def test_bad_requests_leave_nothing(tmp_path: Path) -> None:
    """One-line errors, exit 1 (an output the log cannot become, a topic the log has) or 2 (--topic with
    --replace, an existing output), and no output or temporary file left."""
    cal_path = tmp_path / "cal.json"
    cal_path.write_text((SAMPLES / "handheld.bag.truth.json").read_text())
    runner = CliRunner()
    cases = [(["-o", str(tmp_path / "x.mcap")], 1, "a MCAP file (.mcap) output for a rosbag log"),
             (["-o", str(tmp_path / "x.bag"), "--topic", "/imu/data"], 1, "the log has this topic already"),
             (["-o", str(tmp_path / "x.bag"), "--topic", "/a", "--replace"], 2, "give one"),
             (["-o", str(tmp_path / "x.csv"), "--replace"], 2, "name a topic of a log output")]
    for args, code, text in cases:
        res = runner.invoke(cli, ["apply", str(cal_path), str(SAMPLES / "handheld.bag"), *args])
        assert res.exit_code == code, res.output
        assert text in res.output
        assert len([ln for ln in res.output.splitlines() if ln.startswith("Error")]) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json"]
    (tmp_path / "y.bag").write_bytes(b"old")
    res = runner.invoke(cli, ["apply", str(cal_path), str(SAMPLES / "handheld.bag"), "-o", str(tmp_path / "y.bag")])
    assert res.exit_code == 2
    assert (tmp_path / "y.bag").read_bytes() == b"old"


def test_replace_refuses_a_nested_field(tmp_path: Path) -> None:
    """A VectorNav-style `/imu.mag_field` lives inside a message that holds more: --replace is refused."""
    rec = open_recording(SAMPLES / "handheld.bag")
    cal = made_for(rec)
    nested = replace(cal, magnetometers=(replace(cal.magnetometers[0], id="/imu.mag_field"),))
    assert split_id("/imu.mag_field", {"/imu"}) == ("/imu", ("mag_field",))
    assert out_topic("/imu.mag_field", None, False) == "/imu/mag_field/calibrated"
    with pytest.raises(Exception, match="none of the calibration's magnetometers"):
        apply_to_log(nested, SAMPLES / "handheld.bag", tmp_path / "o.bag", replace=True)
    with pytest.raises(OutputError, match="ROS 2 bag folder"):
        apply_to_log(cal, SAMPLES / "handheld.bag", tmp_path / "o")


def test_stamps_snap_to_the_logged_ones() -> None:
    """t0 + t misses a logged integer-ns stamp by up to ~120 ns (rec.t0 is a float of ~1.7e9 s): the one shift
    under 1 us that lands the stamps on the source's times is applied; a larger miss is left alone."""
    from magcal_cli.writers.roslog.series import snapped

    logged = 1_700_000_000_123_456_789 + np.arange(0, 10**9, 10**7, dtype=np.int64)
    assert np.array_equal(snapped(logged[::3] - 97, logged), logged[::3])
    assert np.array_equal(snapped(logged[::3] + 5000, logged), logged[::3] + 5000)


def test_a_new_mcap_is_written_in_time_order_as_one_stable_sort_of_every_message(tmp_path: Path) -> None:
    """The new MCAP's messages are merged from the streams as they are written (issue 39: a list of every message's
    dict held 3.7 GB for a 60-min, 400 Hz log): log times never go back, sequences count up from 0, and messages
    with equal stamps keep the sources' order (IMU, the compass as logged, then calibrated), as one stable sort of
    every message did."""
    from mcap.reader import make_reader

    cal = with_cov(load(SAMPLES / "handheld.bin.truth.json"))
    apply_to_log(cal, SAMPLES / "handheld.bin", tmp_path / "a.mcap")
    with (tmp_path / "a.mcap").open("rb") as fh:
        got = [(m.log_time, c.topic, m.sequence) for _, c, m in make_reader(fh).iter_messages(log_time_order=False)]
    rank = {"/IMU0": 0, "/MAG0": 1, "/MAG0/calibrated": 2}
    assert [s for _, _, s in got] == list(range(len(got)))
    assert got == sorted(got, key=lambda e: (e[0], rank[e[1]]))
    tied = {t for (t, _, _), (u, _, _) in zip(got[:-1], got[1:], strict=True) if t == u}
    assert tied                         # the sample's IMU and compass share stamps: the ties are tested
