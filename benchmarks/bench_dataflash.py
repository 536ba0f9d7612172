"""Read speed of the DataFlash reader against a plain pymavlink recv_match loop, on a >= 50 MB simulated log.

    python benchmarks/bench_dataflash.py [--size-mb 55] [--log PATH] [--keep]

Writes a synthetic ArduPilot `.bin` (magcal's writer, handheld scenario, long duration) unless --log names an
existing one, then runs each reader in its own subprocess (so peak RSS is per reader) and prints wall time,
MB/s, the speed ratio and peak memory (RSS high-water mark above the interpreter's baseline after imports;
tracemalloc peak of Python-visible allocations for magcal's reader). Both extract the same messages: MAG,
IMU, ATT, BAT, CTUN, GPS and PARM with the fields magcal uses. Not a test: it takes about a minute.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections import defaultdict
from pathlib import Path
from typing import Any

#: message -> fields, the same for both readers (magcal's reader decodes these and more)
FIELDS: dict[str, tuple[str, ...]] = {
    "MAG": ("TimeUS", "I", "MagX", "MagY", "MagZ", "OfsX", "OfsY", "OfsZ", "MOX", "MOY", "MOZ", "Health",
            "S"),
    "IMU": ("TimeUS", "I", "GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ", "T"),
    "ATT": ("TimeUS", "Roll", "Pitch", "Yaw"),
    "BAT": ("TimeUS", "Inst", "Volt", "Curr"),
    "CTUN": ("TimeUS", "ThO"),
    "GPS": ("TimeUS", "Status", "Lat", "Lng", "Alt"),
    "PARM": ("TimeUS", "Name", "Value"),
}


def rss_mb() -> float:
    """This process's peak resident set size so far, in MB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_rss_mb() -> float:
    """This process's resident set size now, in MB (Linux /proc; the peak where unavailable)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return rss_mb()


def run_magcal(path: Path) -> dict[str, Any]:
    """Time magcal's reader (streams, raw field reconstruction, notes) on `path`."""
    from magcal_cli.readers import ReadOptions
    from magcal_cli.readers.dataflash.reader import DataflashReader

    base = current_rss_mb()
    t = time.perf_counter()
    rec = DataflashReader().read(path, ReadOptions())
    wall = time.perf_counter() - t
    peak_rss = rss_mb() - base
    del rec
    tracemalloc.start()
    rec = DataflashReader().read(path, ReadOptions())
    traced = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    counts = {s.id + ":" + s.kind.value: len(s) for s in rec.streams}
    return {"wall_s": wall, "peak_rss_mb": peak_rss, "tracemalloc_peak_mb": traced, "counts": counts}


def run_pymavlink(path: Path) -> dict[str, Any]:
    """Time a plain DFReader recv_match loop collecting the same fields into numpy arrays."""
    import numpy as np
    from pymavlink import DFReader

    base = current_rss_mb()
    t = time.perf_counter()
    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    rows: dict[str, list[list[Any]]] = defaultdict(list)
    types = list(FIELDS)
    while True:
        msg = reader.recv_match(type=types)
        if msg is None:
            break
        name = msg.get_type()
        rows[name].append([getattr(msg, f) for f in FIELDS[name]])
    arrays = {k: np.array(v, dtype=object if k == "PARM" else np.float64) for k, v in rows.items()}
    wall = time.perf_counter() - t
    return {"wall_s": wall, "peak_rss_mb": rss_mb() - base, "counts": {k: len(v) for k, v in arrays.items()}}


def make_log(path: Path, size_mb: float, seed: int) -> None:
    """Simulate a handheld recording long enough for `size_mb` and write it with magcal's DataFlash writer."""
    from magcal_cli.synth.logs.dataflash import build
    from magcal_cli.synth.simulate import simulate

    per_second = 8_350.0        # bytes per second: IMU 100 Hz, MAG 50 Hz, ATT/BAT/CTUN 10 Hz, GPS 5 Hz
    sim = simulate("handheld", seed, duration=size_mb * 1e6 / per_second)
    build(sim).tofile(path)


def main() -> int:
    """Write (or reuse) the log, run both readers in subprocesses and print the comparison."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size-mb", type=float, default=55.0, help="size of the simulated log (MB)")
    ap.add_argument("--log", type=Path, default=None, help="use this .bin instead of simulating one")
    ap.add_argument("--keep", action="store_true", help="keep the simulated log (path printed)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--run", choices=["magcal", "pymavlink"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.run:
        result = (run_magcal if args.run == "magcal" else run_pymavlink)(args.log)
        print(json.dumps(result))
        return 0
    tmpdir = None
    path = args.log
    if path is None:
        tmpdir = tempfile.TemporaryDirectory(prefix="bench_dataflash_")
        path = Path(tmpdir.name) / "bench.bin"
        t = time.perf_counter()
        make_log(path, args.size_mb, args.seed)
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t:.1f} s",
              file=sys.stderr)
    size_mb = path.stat().st_size / 1e6
    results = {}
    for name in ("magcal", "pymavlink"):
        out = subprocess.run([sys.executable, __file__, "--run", name, "--log", str(path)], check=True,
                             capture_output=True, text=True).stdout
        results[name] = json.loads(out.strip().splitlines()[-1])
    ours, theirs = results["magcal"], results["pymavlink"]
    print(f"log: {size_mb:.1f} MB")
    for name, r in results.items():
        extra = f", tracemalloc peak {r['tracemalloc_peak_mb']:.0f} MB" if "tracemalloc_peak_mb" in r else ""
        print(f"{name:10s} {r['wall_s']:7.2f} s  {size_mb / r['wall_s']:7.1f} MB/s  "
              f"peak RSS +{r['peak_rss_mb']:.0f} MB{extra}")
    print(f"ratio (pymavlink / magcal wall time): {theirs['wall_s'] / ours['wall_s']:.1f}x")
    print(f"messages: magcal MAG[0] {ours['counts'].get('MAG[0]:magnetometer')}, IMU[0] "
          f"{ours['counts'].get('IMU[0]:accelerometer')}; pymavlink MAG {theirs['counts'].get('MAG')}, "
          f"IMU {theirs['counts'].get('IMU')}")
    if args.keep and tmpdir is not None:
        kept = Path(tempfile.gettempdir()) / "bench_dataflash.bin"
        path.replace(kept)
        print(f"kept {kept}", file=sys.stderr)
    if tmpdir is not None:
        tmpdir.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
