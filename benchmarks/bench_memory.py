"""Peak memory of reading a gigantic DataFlash log (issue 6): bounded windows versus the whole file at once.

    python benchmarks/bench_memory.py [--size-gb 1.0] [--filler 0.75] [--compare-mb 200] [--log PATH] [--keep]

Writes a synthetic ArduPilot `.bin` of at least --size-gb by tiling a simulated handheld log (times shifted so
the result is one long, valid recording) with --filler of its bytes in a record type magcal does not read (as
EKF, PID and RC records fill real logs), then runs each measurement in its own subprocess and prints wall
time and peak RSS above the interpreter's baseline after imports:

- `read`: the DataFlash reader (`open_recording`), windowed parse plus streams in SI units;
- `parse`: the windowed parser alone (decoded wanted records);
- `whole`: the same parse over the whole file held in memory (the reader before issue 6), on a --compare-mb
  log only, because on the big one it needs several times the file size.

The streams' own size (times and values, float64) is printed too: that much memory is needed whatever the
reader does. Not a test: the 1 GB run takes a few minutes. The big file is deleted unless --keep.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

#: the metadata records written once at the start (not tiled)
META = frozenset({"FMT", "UNIT", "MULT", "FMTU", "PARM", "VER", "MSG"})
#: the filler record type: TimeUS and fourteen floats (67 bytes with the header), like XKF1/PIDR records
FILL_ID, FILL_NAME, FILL_FORMAT, FILL_LENGTH = 250, "FILL", "Q" + "f" * 14, 67


def rss_mb() -> float:
    """Peak resident set size of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_rss_mb() -> float:
    """Resident set size now (MB), from /proc."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return float(line.split()[1]) / 1024.0
    return rss_mb()


def _gather_u64(buf: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Byte indices (N, 8) of little-endian uint64 fields at `offsets` and their values."""
    idx = offsets[:, None] + np.arange(8)
    return idx, buf[idx].copy().view("<u8")[:, 0]


def make_log(path: Path, size_gb: float, filler: float, seed: int) -> dict[str, Any]:
    """Tile a simulated log (shifting TimeUS and MAG.S per tile) until the file holds `size_gb`."""
    from magcal_cli.readers.dataflash.binary import parse_buffer
    from magcal_cli.readers.dataflash.format import FMT_ID, FMT_LENGTH, HEAD1, HEAD2
    from magcal_cli.synth.logs.dataflash import build
    from magcal_cli.synth.simulate import simulate

    base = build(simulate("handheld", seed, rate=200.0, mag_rate=100.0))
    raw = parse_buffer(base)
    first = min(int(t.pos[0]) for n, t in raw.tables.items() if n not in META and len(t))
    head, data = base[:first], base[first:]
    time_at, s_at, t_max = [], [], 0
    for name, table in raw.tables.items():
        f = table.fmt
        if name in META or not len(table) or f.columns[0] != "TimeUS" or f.format[0] != "Q":
            continue
        time_at.append(table.pos - first + 3)
        t_max = max(t_max, int(table.num("TimeUS").max()))
        if name == "MAG" and "S" in f.columns:
            s_at.append(table.pos - first + 3 + f.dtype().fields["S"][1])
    t_at, s_offs = np.concatenate(time_at), np.concatenate(s_at) if s_at else np.zeros(0, np.int64)
    t0 = int(_gather_u64(data, t_at)[1].min())
    span = t_max - t0 + 10_000
    n_fill = int(filler / (1.0 - filler) * data.size / FILL_LENGTH) if filler > 0 else 0
    fmt_rec = np.zeros(FMT_LENGTH, np.uint8)
    fmt_rec[:5] = [HEAD1, HEAD2, FMT_ID, FILL_ID, FILL_LENGTH]
    fmt_rec[5:9] = np.frombuffer(FILL_NAME.encode(), np.uint8)
    fmt_rec[9:9 + len(FILL_FORMAT)] = np.frombuffer(FILL_FORMAT.encode(), np.uint8)
    cols = ",".join(["TimeUS"] + [f"V{i}" for i in range(14)]).encode()
    fmt_rec[25:25 + len(cols)] = np.frombuffer(cols, np.uint8)
    fill = np.zeros((n_fill, FILL_LENGTH), np.uint8)
    fill[:, :3] = [HEAD1, HEAD2, FILL_ID]
    fill[:, 11:] = np.random.default_rng(seed).random((n_fill, 14), np.float32).view(np.uint8)
    fill_t = t0 + np.linspace(0, span - 10_000, n_fill).astype(np.uint64)
    tile_bytes = data.size + fill.size
    tiles = int(np.ceil((size_gb * 1e9 - head.size) / tile_bytes))
    t_idx, t_vals = _gather_u64(data, t_at)
    s_idx = s_offs[:, None] + np.arange(4)
    s_vals = data[s_idx].copy().view("<u4")[:, 0].astype(np.uint64)
    with path.open("wb") as fh:
        fh.write(head.tobytes())
        if n_fill:
            fh.write(fmt_rec.tobytes())
        for k in range(tiles):
            tile = data.copy()
            shift = np.uint64(k * span)
            tile[t_idx] = (t_vals + shift).view(np.uint8).reshape(-1, 8)
            tile[s_idx] = ((s_vals + shift) % np.uint64(1 << 32)).astype("<u4").view(np.uint8).reshape(-1, 4)
            fh.write(tile.tobytes())
            if n_fill:
                fill[:, 3:11] = (fill_t + shift).view(np.uint8).reshape(-1, 8)
                fh.write(fill.tobytes())
    return {"tiles": tiles, "hours": tiles * span / 3.6e9, "filler_share": filler}


def run(kind: str, path: Path) -> dict[str, Any]:
    """One measurement (in its own process): wall time, peak RSS above the post-import baseline, stream bytes."""
    from magcal_cli.readers import ReadOptions, open_recording
    from magcal_cli.readers.dataflash.binary import parse_binary, parse_buffer
    from magcal_cli.readers.dataflash.load import WANTED

    base = current_rss_mb()
    t = time.perf_counter()
    out: dict[str, Any] = {}
    if kind == "read":
        rec = open_recording(path, "dataflash", ReadOptions())
        out["stream_mb"] = sum(s.t.nbytes + s.values.nbytes for s in rec.streams) / 1e6
        out["samples"] = {f"{s.id} {s.kind.value}": len(s) for s in rec.streams if s.kind.value in
                          ("magnetometer", "accelerometer")}
    elif kind == "parse":
        raw = parse_binary(path, WANTED)
        out["decoded_mb"] = sum(sum(c.nbytes for c in t.columns.values()) + t.pos.nbytes
                                for t in raw.tables.values()) / 1e6
    else:
        raw = parse_buffer(np.fromfile(path, dtype=np.uint8), WANTED)
    out["wall_s"] = time.perf_counter() - t
    out["peak_rss_mb"] = rss_mb() - base
    return out


def measure(kind: str, path: Path) -> dict[str, Any]:
    """Run one measurement in a subprocess and return its JSON."""
    proc = subprocess.run([sys.executable, __file__, "--run", kind, "--log", str(path)], check=True,
                          capture_output=True, text=True)
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def main() -> int:
    """Write the logs, measure, print."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size-gb", type=float, default=1.0)
    ap.add_argument("--filler", type=float, default=0.75, help="share of the bytes in a type magcal does not read")
    ap.add_argument("--compare-mb", type=float, default=200.0, help="size of the log for the whole-file comparison")
    ap.add_argument("--log", type=Path, default=None, help="measure this .bin instead of writing one")
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--run", choices=["read", "parse", "whole"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.run:
        print(json.dumps(run(args.run, args.log)))
        return 0
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        small = Path(tmp) / "compare.bin"
        info = make_log(small, args.compare_mb / 1e3, args.filler, args.seed)
        rows = [(small, "whole", info), (small, "parse", info), (small, "read", info)]
        big = args.log
        if big is None:
            big = Path(tmp) / "big.bin" if not args.keep else Path.cwd() / "bench_memory_big.bin"
            t = time.perf_counter()
            info = make_log(big, args.size_gb, args.filler, args.seed)
            print(f"wrote {big} ({big.stat().st_size / 1e9:.2f} GB, {info['hours']:.0f} h of flight, "
                  f"{100 * args.filler:.0f} % filler) in {time.perf_counter() - t:.0f} s", file=sys.stderr)
        rows += [(big, "parse", info), (big, "read", info)]
        print(f"{'log':>9s} {'what':6s} {'wall s':>7s} {'MB/s':>6s} {'peak RSS MB':>12s} {'x file':>7s} "
              f"{'streams MB':>11s}")
        for path, kind, _ in rows:
            r = measure(kind, path)
            size = path.stat().st_size / 1e6
            extra = f"{r['stream_mb']:11.0f}" if "stream_mb" in r else f"{r.get('decoded_mb', float('nan')):11.0f}"
            print(f"{size:7.0f}MB {kind:6s} {r['wall_s']:7.1f} {size / r['wall_s']:6.0f} {r['peak_rss_mb']:12.0f} "
                  f"{r['peak_rss_mb'] / size:7.2f} {extra}", flush=True)
            if kind == "read" and "samples" in r:
                print("          " + ", ".join(f"{k}: {v}" for k, v in r["samples"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
