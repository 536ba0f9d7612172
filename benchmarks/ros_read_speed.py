"""Read speed of magcal's MCAP and ROS bag readers against message-by-message decoding of the same files.

    python benchmarks/ros_read_speed.py [--size-mb 100] [--big-gb 1.0] [--formats mcap,ros2-mcap,...] [--out MD]

Writes, under a temporary folder (deleted at the end), one log per format of realistic rates (IMU 400 Hz, field
100 Hz, battery and temperature 10 Hz; Imu, MagneticField, BatteryState, Temperature) of about --size-mb:
an MCAP file (zstd chunks), ROS 2 bags with MCAP (zstd) and sqlite3 storage, and a ROS 1 bag (lz4). Each is
read in its own subprocess by magcal's reader and by the per-message baseline that extracts the same fields
(mcap_ros2's decoder for MCAP; rosbags' AnyReader with deserialize_cdr / deserialize_ros1 for bags), which
prints wall time, MB/s, the ratio and the peak RSS above the interpreter's after imports. Then magcal alone
reads a >= --big-gb ROS 2 bag (MCAP storage) for its peak memory. Results go to --out as a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

#: (topic, ROS 2 type, rate Hz)
TOPICS = (("/imu/data", "sensor_msgs/msg/Imu", 400.0), ("/imu/mag", "sensor_msgs/msg/MagneticField", 100.0),
          ("/battery", "sensor_msgs/msg/BatteryState", 10.0),
          ("/imu/temperature", "sensor_msgs/msg/Temperature", 10.0))
FORMATS = ("mcap", "ros2-mcap", "ros2-sqlite3", "ros1")
BASELINE = {"mcap": "mcap_ros2", "ros2-mcap": "rosbags", "ros2-sqlite3": "rosbags", "ros1": "rosbags"}
WINDOW_S = 60.0
T0_NS = 1_700_000_000_000_000_000


def rss_mb() -> float:
    """Peak resident set size of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def default(store: Any, msgtype: str, frame: str) -> Any:
    """A message of `msgtype` with zero/empty fields and header frame_id `frame`."""
    from rosbags.typesys.base import Nodetype

    fields = {}
    for name, (node, spec) in store.fielddefs[msgtype][1]:
        if node == Nodetype.NAME:
            fields[name] = default(store, spec, frame)
        elif node == Nodetype.BASE:
            prim = spec[0]
            fields[name] = (frame if name == "frame_id" else "") if prim == "string" else \
                (False if prim == "bool" else 0.0 if prim.startswith("float") else 0)
        elif node == Nodetype.ARRAY:
            fields[name] = np.zeros(spec[1], dtype=np.float64 if "float" in spec[0][1][0] else np.uint8)
        else:
            fields[name] = np.zeros(0, dtype=np.float32 if "float" in str(spec) else np.uint8)
    return store.types[msgtype](**fields)


def payloads(store: Any, msgtype: str, ros1: bool, t_ns: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(n, size) serialized messages with header stamps `t_ns` and the values magcal reads (numpy fill)."""
    from magcal_cli.readers.ros.vec import STAMP_PATHS, VALUE_PATHS, flatten, offsets

    msg = default(store, msgtype, "imu_link")
    raw = np.frombuffer(bytes(store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)),
                        dtype=np.uint8)
    offs = offsets(flatten(store.fielddefs, msgtype), ros1, 8 if ros1 else 9)
    assert offs is not None
    out = np.tile(raw, (t_ns.size, 1))
    cols = [t_ns // 1_000_000_000, t_ns % 1_000_000_000, *values.T]
    for path, col in zip(STAMP_PATHS + VALUE_PATHS[msgtype], cols, strict=True):
        at, dtype = offs[path]
        size = np.dtype(dtype).itemsize
        out[:, at:at + size] = np.asarray(col).astype(dtype).view(np.uint8).reshape(-1, size)
    return out


def signals(msgtype: str, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Plausible values: gravity and rotation with noise, a rotating field in tesla, battery, temperature."""
    n = t.size
    if msgtype.endswith("Imu"):
        yaw = 0.3 * t
        acc = np.column_stack([np.sin(yaw), np.cos(yaw), np.full(n, 9.4)]) + rng.normal(0, 0.05, (n, 3))
        return np.column_stack([acc, rng.normal(0, 0.01, (n, 3)) + 0.3 * np.array([0, 0, 1])])
    if msgtype.endswith("MagneticField"):
        yaw = 0.3 * t
        return np.column_stack([2e-5 * np.cos(yaw), -2e-5 * np.sin(yaw), np.full(n, 4.3e-5)]) + rng.normal(0, 1e-7,
                                                                                                         (n, 3))
    if msgtype.endswith("BatteryState"):
        return np.column_stack([-10 - 5 * np.sin(t) + rng.normal(0, 0.1, n), 15.8 - 0.001 * t])
    return (25 + 0.001 * t + rng.normal(0, 0.05, n))[:, None]


def messages(duration: float, ros1: bool, store: Any, seed: int = 1) -> Iterator[tuple[int, int, bytes]]:
    """(topic index, receive time ns, serialized message) of every message in time order, a window at a time."""
    rng = np.random.default_rng(seed)
    for w0 in np.arange(0.0, duration, WINDOW_S):
        parts = []
        for k, (_, msgtype, rate) in enumerate(TOPICS):
            t = np.arange(np.ceil(w0 * rate), np.ceil(min(w0 + WINDOW_S, duration) * rate)) / rate
            ns = T0_NS + np.round(t * 1e9).astype(np.int64)
            parts.append((k, ns, payloads(store, msgtype, ros1, ns, signals(msgtype, t, rng))))
        order = np.argsort(np.concatenate([p[1] for p in parts]), kind="stable")
        ks = np.concatenate([np.full(p[1].size, p[0]) for p in parts])[order]
        ii = np.concatenate([np.arange(p[1].size) for p in parts])[order]
        for k, i in zip(ks.tolist(), ii.tolist(), strict=True):
            yield k, int(parts[k][1][i]), parts[k][2][i].tobytes()


def write(fmt: str, path: Path, duration: float) -> Path:
    """Write the log of `fmt` covering `duration` s at `path` (a file, or a bag directory); the path to read."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = fmt == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if fmt == "mcap":
        from mcap.writer import CompressionType, Writer

        with path.open("wb") as fh:
            w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=1 << 20)
            w.start(profile="ros2", library="ros_read_speed")
            chans = []
            for topic, msgtype, _ in TOPICS:
                sid = w.register_schema(msgtype, "ros2msg", store.generate_msgdef(msgtype, ros_version=2)[0].encode())
                chans.append(w.register_channel(topic, "cdr", sid))
            for k, ns, data in messages(duration, ros1, store):
                w.add_message(chans[k], log_time=ns, data=data, publish_time=ns)
            w.finish()  # type: ignore[no-untyped-call]
        return path
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        w1 = Writer1(path)
        w1.set_compression(Writer1.CompressionFormat.LZ4)
        with w1:
            conns = [w1.add_connection(t, m, typestore=store) for t, m, _ in TOPICS]
            for k, ns, data in messages(duration, ros1, store):
                w1.write(conns[k], ns, data)
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    plugin = StoragePlugin.MCAP if fmt == "ros2-mcap" else StoragePlugin.SQLITE3
    w2 = Writer(path, version=9, storage_plugin=plugin)
    if plugin is StoragePlugin.MCAP:
        w2.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with w2:
        conns = [w2.add_connection(t, m, typestore=store) for t, m, _ in TOPICS]
        for k, ns, data in messages(duration, ros1, store):
            w2.write(conns[k], ns, data)
    return path


def size_of(path: Path) -> int:
    """Bytes of a log file or bag directory."""
    return path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.iterdir())


def run_magcal(path: Path, fmt: str) -> dict[str, Any]:
    """magcal's reader: a Recording of every stream (cleaned, SI)."""
    from magcal_cli.readers import ReadOptions
    from magcal_cli.readers.ros.bag import RosbagReader
    from magcal_cli.readers.ros.mcap import McapReader
    from magcal_cli.readers.ros.msg import Collector

    reader = McapReader() if fmt == "mcap" else RosbagReader()
    decoded: list[float] = []
    recording = Collector.recording

    def timed(self: Collector, *args: Any) -> Any:      # the peak up to here is the decoding's (chunks, arrays)
        decoded.append(rss_mb())
        return recording(self, *args)

    Collector.recording = timed  # type: ignore[method-assign]
    base, t = rss_mb(), time.perf_counter()
    rec = reader.read(path, ReadOptions())
    wall = time.perf_counter() - t
    mag = next(s for s in rec.streams if s.kind.value == "magnetometer")
    counts = {s.id: len(s) for s in rec.streams}             # messages per topic (one stream of each)
    out_mb = sum(s.t.nbytes + s.values.nbytes for s in rec.streams) / 1e6
    return {"wall_s": wall, "peak_rss_mb": rss_mb() - base, "counts": counts, "mag_sum": float(mag.values.sum()),
            "output_mb": out_mb, "decoding_peak_mb": max(decoded, default=base) - base}


def run_baseline(path: Path, fmt: str) -> dict[str, Any]:
    """Per-message decoding of the same topics into arrays: mcap_ros2 for MCAP, rosbags for bags."""
    from magcal_cli.readers.ros.msg import ROS_TYPES, stamp_ns

    rows: dict[str, list[tuple[float, ...]]] = {t: [] for t, _, _ in TOPICS}
    stamps: dict[str, list[int]] = {t: [] for t, _, _ in TOPICS}
    types = {t: m for t, m, _ in TOPICS}
    base, t0 = rss_mb(), time.perf_counter()
    if fmt == "mcap":
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        with path.open("rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, channel, message, msg in reader.iter_decoded_messages(topics=list(types)):
                rows[channel.topic].append(ROS_TYPES[types[channel.topic]][2](msg))
                stamps[channel.topic].append(stamp_ns(msg))
                del message
    else:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as any_reader:
            conns = [c for c in any_reader.connections if c.topic in types]
            for conn, _, raw in any_reader.messages(connections=conns):
                msg = any_reader.deserialize(raw, conn.msgtype)
                rows[conn.topic].append(ROS_TYPES[types[conn.topic]][2](msg))
                stamps[conn.topic].append(stamp_ns(msg))
    arrays = {k: (np.array(stamps[k]), np.array(v, dtype=np.float64)) for k, v in rows.items()}
    wall = time.perf_counter() - t0
    mag = arrays["/imu/mag"][1]
    mag = mag[np.all(np.isfinite(mag), axis=1)]
    return {"wall_s": wall, "peak_rss_mb": rss_mb() - base, "counts": {k: len(v[0]) for k, v in arrays.items()},
            "mag_sum": float(mag.sum())}


def child(name: str, path: Path, fmt: str) -> dict[str, Any]:
    """Run one reader in a fresh interpreter (its own peak RSS) and return its JSON result."""
    out = subprocess.run([sys.executable, __file__, "--run", name, "--log", str(path), "--formats", fmt],
                         check=True, capture_output=True, text=True).stdout
    result: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    return result


def main() -> int:
    """Write the logs, time both readers on each, measure the big bag, print and save the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size-mb", type=float, default=100.0, help="size of each timed log (MB)")
    ap.add_argument("--big-gb", type=float, default=1.0, help="size of the peak-memory ROS 2 bag (GB; 0: skip)")
    ap.add_argument("--formats", default=",".join(FORMATS), help='timed formats ("" for the big bag only)')
    ap.add_argument("--out", type=Path, default=None, help="write the results as Markdown here")
    ap.add_argument("--tmp", type=Path, default=None, help="folder for the generated logs (default: system temp)")
    ap.add_argument("--run", choices=["magcal", "baseline"], help=argparse.SUPPRESS)
    ap.add_argument("--log", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.run:
        fn = run_magcal if args.run == "magcal" else run_baseline
        print(json.dumps(fn(args.log, args.formats)))
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="ros_read_speed_", dir=args.tmp))
    lines = ["| log | size (MB) | messages | magcal (s) | MB/s | baseline | baseline (s) | MB/s | ratio | "
             "peak RSS magcal / baseline (MB) |", "|---|---|---|---|---|---|---|---|---|---|"]
    try:
        for fmt in filter(None, args.formats.split(",")):
            probe = write(fmt, tmp / f"probe-{fmt}{'.mcap' if fmt == 'mcap' else '.bag' if fmt == 'ros1' else ''}",
                          WINDOW_S)
            duration = WINDOW_S * args.size_mb * 1e6 / size_of(probe)
            shutil.rmtree(probe) if probe.is_dir() else probe.unlink()
            t = time.perf_counter()
            path = write(fmt, tmp / f"{fmt}{'.mcap' if fmt == 'mcap' else '.bag' if fmt == 'ros1' else ''}",
                         duration)
            mb = size_of(path) / 1e6
            print(f"wrote {fmt}: {mb:.1f} MB, {duration / 3600:.2f} h of log in {time.perf_counter() - t:.0f} s",
                  file=sys.stderr)
            ours, theirs = child("magcal", path, fmt), child("baseline", path, fmt)
            n = sum(theirs["counts"].values())
            same = abs(ours["mag_sum"] - theirs["mag_sum"]) <= 1e-9 * abs(theirs["mag_sum"])
            line = (f"| {fmt} | {mb:.0f} | {n} | {ours['wall_s']:.2f} | {mb / ours['wall_s']:.1f} | "
                    f"{BASELINE[fmt]} | {theirs['wall_s']:.1f} | {mb / theirs['wall_s']:.2f} | "
                    f"**{theirs['wall_s'] / ours['wall_s']:.1f}x** | {ours['peak_rss_mb']:.0f} / "
                    f"{theirs['peak_rss_mb']:.0f} |")
            print(line + ("" if same else "  (MAGNETIC FIELD VALUES DIFFER)"))
            lines.append(line)
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        if args.big_gb > 0:
            probe = write("ros2-mcap", tmp / "probe-big", WINDOW_S)
            duration = WINDOW_S * args.big_gb * 1e9 / size_of(probe) * 1.02
            shutil.rmtree(probe)
            path = write("ros2-mcap", tmp / "big", duration)
            gb = size_of(path) / 1e9
            ours = child("magcal", path, "ros2-mcap")
            line = (f"magcal on a {gb:.2f} GB ROS 2 bag (MCAP storage, {sum(ours['counts'].values())} "
                    f"messages): {ours['wall_s']:.1f} s, {gb * 1e3 / ours['wall_s']:.0f} MB/s, peak RSS "
                    f"+{ours['peak_rss_mb']:.0f} MB for {ours['output_mb']:.0f} MB of output streams (+"
                    f"{ours['decoding_peak_mb']:.0f} MB at the end of decoding, before the streams are built)")
            print(line)
            lines += ["", line]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
