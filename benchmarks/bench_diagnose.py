"""Speed of the default `magcal fit` (diagnosis included) on a 10-minute log, against `--effects none`.

Target (issue 11): a 10-minute log is diagnosed, fit included, in <= 60 s on this machine with default settings.
The log: the handheld scenario for 10 minutes (IMU 100 Hz, magnetometer 50 Hz: 30,000 epochs, a rate ArduPilot
and PX4 compasses log at) with current interference and a temperature drift injected, written as an ArduPilot
DataFlash log, so the diagnosis screens, refits, cross-validates and checks twice. Both commands run end to end in
a fresh process (reading, fitting, report, plots), one after the other; the machine's load average is printed,
since the numbers mean little on a busy machine.

    python benchmarks/bench_diagnose.py [--duration 600] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def timed(args: list[str]) -> float:
    """Wall time of one magcal command (which must succeed)."""
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "magcal_cli", *args], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def main() -> None:
    """Simulate, then time `fit --effects none` and the default `fit`."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--keep", type=Path, default=None)
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench-diagnose-"))
    work.mkdir(parents=True, exist_ok=True)
    log = work / "flight.bin"
    subprocess.run([sys.executable, "-m", "magcal_cli", "simulate", str(log), "--scenario", "handheld",
                    "--duration", str(args.duration), "--seed", "1", "--force",
                    "--effect", "current_interference:c_uT_per_A=0.01/-0.005/0.015",
                    "--effect", "temperature_drift"], check=True, stdout=subprocess.DEVNULL)
    load0 = os.getloadavg()[0]
    base = timed(["fit", str(log), "-o", str(work / "none"), "--force", "-q", "--effects", "none"])
    auto = timed(["fit", str(log), "-o", str(work / "auto"), "--force", "-q"])
    load1 = os.getloadavg()[0]
    print(f"log: handheld, {args.duration:.0f} s, IMU 100 Hz, magnetometer 50 Hz ({args.duration * 50:.0f} epochs), "
          f"{log.stat().st_size / 1e6:.1f} MB")
    print(f"load average (1 min) before / after: {load0:.2f} / {load1:.2f} on {os.cpu_count()} cores")
    print(f"magcal fit --effects none: {base:.1f} s")
    print(f"magcal fit (default --effects auto, diagnosis included): {auto:.1f} s  (target <= 60 s; "
          f"ratio to the base fit {auto / base:.1f}x)")


if __name__ == "__main__":
    main()
