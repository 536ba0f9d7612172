"""report.html's cost from a finished fit (issue 27: "the report and its plots, for a log of any length: <= 0.4 s").

Each log is fitted once per code version (default settings, as `magcal fit`), and its RunResult pickled with the
names of the modules the fit imported; then every timed run is a fresh process that loads the RunResult and
times the import of the HTML writer plus `render_html` (matplotlib's import included, where a version uses it):
"in fit" after importing what the fit had imported (what `magcal fit` pays for its report), "cold" with nothing
preloaded. Versions alternate run by run, and the medians and their ratio are printed.

    python benchmarks/bench_report.py [--before /tmp/before27] [--runs 5] [LOG ...]

Without LOG: sample_logs/handheld.mcap and ../shared/realdata/ardupilot/log171.bin (when present).
"""

from __future__ import annotations

import argparse
import copyreg
import importlib
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOGS = [ROOT / "sample_logs" / "handheld.mcap", ROOT.parent / "shared" / "realdata" / "ardupilot" / "log171.bin"]


def proxy(d: dict[str, object]) -> types.MappingProxyType[str, object]:
    """Rebuild a read-only mapping (a Recording's streams) when unpickling."""
    return types.MappingProxyType(d)


copyreg.pickle(types.MappingProxyType, lambda m: (proxy, (dict(m),)))


def child(mode: str, log: str, pkl: str) -> None:
    """In a fresh process: 'fit' pickles the RunResult of `log` and the modules loaded; 'render' (after loading
    those modules) and 'cold' print the seconds report.html takes."""
    if mode == "fit":
        from magcal_cli.config import Config
        from magcal_cli.pipeline import calibrate

        Path(pkl).write_bytes(pickle.dumps(calibrate(Path(log), Config(diagnose=True))))
        Path(pkl).with_suffix(".modules").write_text("\n".join(sorted(sys.modules)))
        return
    result = pickle.loads(Path(pkl).read_bytes())  # noqa: S301 - our own file, written by this script
    if mode == "render":
        for name in Path(pkl).with_suffix(".modules").read_text().split():
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001, S112 - a module that imports only inside its package; not timed
                continue
    t0 = time.perf_counter()
    from magcal_cli.writers.report.html import render_html

    page = render_html(result)
    print(f"{time.perf_counter() - t0:.4f} {page.count('<img ')} {len(page)}")


def run(code: Path, *args: str) -> str:
    """This script as a child process with `code` first on the path."""
    env = dict(os.environ, PYTHONPATH=str(code))
    out = subprocess.run([sys.executable, __file__, "--child", *args], env=env, capture_output=True, text=True,
                         check=True, cwd=tempfile.gettempdir())
    return out.stdout.strip()


def main() -> None:
    """Fit each log with each version, then time alternating renders and print medians and ratios."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path)
    ap.add_argument("--before", type=Path, default=Path("/tmp/before27"), help="a copy of the code to compare")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(*a.child)
        return
    versions = {"after": ROOT} | ({"before": a.before} if a.before.is_dir() else {})
    print(f"{'log':<16} {'version':<7} {'in fit: median s':>16} {'min s':>6} {'cold: median s':>14} {'images':>6} "
          f"{'page MB':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        for log in a.logs or [p for p in LOGS if p.exists()]:
            pkls = {v: str(Path(tmp) / f"{log.stem}-{v}.pkl") for v in versions}
            for v, code in versions.items():
                run(code, "fit", str(log), pkls[v])
            times: dict[tuple[str, str], list[float]] = {(v, m): [] for v in versions for m in ("render", "cold")}
            shape: dict[str, tuple[int, float]] = {}
            for _ in range(a.runs):
                for v, code in versions.items():
                    for m in ("render", "cold"):
                        secs, images, size = run(code, m, str(log), pkls[v]).split()
                        times[v, m].append(float(secs))
                        shape[v] = (int(images), int(size) / 1e6)
            med = {k: statistics.median(t) for k, t in times.items()}
            for v in versions:
                print(f"{log.name:<16} {v:<7} {med[v, 'render']:16.3f} {min(times[v, 'render']):6.3f} "
                      f"{med[v, 'cold']:14.3f} {shape[v][0]:6d} {shape[v][1]:8.2f}")
            if "before" in versions:
                print(f"{log.name:<16} ratio before/after: in fit {med['before', 'render'] / med['after', 'render']:.1f}x,"
                      f" cold {med['before', 'cold'] / med['after', 'cold']:.1f}x")


if __name__ == "__main__":
    main()
