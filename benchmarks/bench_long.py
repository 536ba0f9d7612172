"""What long logs cost (issue 39): `simulate` and `fit` of 10- to 120-minute multirotor flights at 400 Hz.

For each length S (minutes): `magcal simulate --scenario multirotor --rate 400 --duration S*60 -o X.bin`, then
`magcal fit X.bin` default and `--effects none`. Each is one whole process: wall time, the largest process's
peak RSS (ru_maxrss from wait4) and the peak of the summed PSS of its process tree, forked diagnosis workers
included (bench_end_to_end.run_timed, sampled every 25 ms). Per-stage times of the fit come from one more
process that runs the stages through the public API: read (`open_recording`), select (`select_streams`:
still segments, timing), preintegrate (every `models.gyro.preintegrate` call, summed), fit (the method with
effects none), diagnose (the method's time default minus none), write (json, yaml, report.txt).

Results are kept in --json under a label (--label before / after), so a run of the starting commit (--package
/tmp/before39) and one of this tree make one page: --render writes docs/results/bench_long.md from the JSON,
with an inline SVG of time and memory against log length (no matplotlib).

    python benchmarks/bench_long.py --minutes 10,30 --label after [--package DIR] [--runs fit,fit_none,stages]
    python benchmarks/bench_long.py --render
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from contextlib import suppress
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_end_to_end import _compiled, _timed, run_json, run_timed  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
HERE = Path(__file__).resolve()
JSON = ROOT / "docs" / "results" / "bench_long.json"
PAGE = ROOT / "docs" / "results" / "bench_long.md"
#: what the numbers say, written by hand and kept when the page is rendered again
NOTES = ROOT / "docs" / "results" / "bench_long.notes.md"
STAGES = ("read", "select", "preintegrate", "fit", "diagnose", "write")
RUNS = ("simulate", "fit", "fit_none")


def _driver(log: Path, out: Path) -> None:
    """Time the stages of a fit of `log` in this interpreter and print them as JSON."""
    from magcal_cli import pipeline
    from magcal_cli.models import gyro
    from magcal_cli.readers import ReadOptions, open_recording
    from magcal_cli.writers import write_outputs

    stages: dict[str, float] = {}
    pre: dict[str, float] = {}
    original = gyro.preintegrate

    def timed_pre(*args: Any, **kwargs: Any) -> Any:
        with _timed(pre, "preintegrate"):
            return original(*args, **kwargs)

    gyro.preintegrate = timed_pre  # type: ignore[assignment]
    inner: dict[str, float] = {}
    for name, key in (("select_streams", "select"), ("run_method", "method")):
        fn = getattr(pipeline, name)

        def wrapped(*args: Any, _fn: Any = fn, _key: str = key, **kwargs: Any) -> Any:
            with _timed(inner, _key):
                return _fn(*args, **kwargs)

        setattr(pipeline, name, wrapped)
    with _timed(stages, "read"):
        rec = open_recording(log, None, ReadOptions(allow_truncated=True))
    method: dict[str, float] = {}
    result = None
    for label, effects in (("none", ()), ("default", None)):
        inner.clear()
        pre.clear()
        result = pipeline.calibrate_recording(rec, pipeline.command_config(effects=effects))
        method[label] = inner.get("method", float("nan"))
        if label == "none":
            stages["select"] = inner.get("select", float("nan"))
            stages["preintegrate"] = pre.get("preintegrate", 0.0)
    stages["fit"] = method["none"] - stages["preintegrate"]
    stages["diagnose"] = method["default"] - method["none"]
    with _timed(stages, "write"):
        write_outputs(result, out, ["json", "yaml", "report"])
    print(json.dumps(stages))


def measure(minutes: float, package: Path, work: Path, runs: set[str]) -> dict[str, Any]:
    """Simulate one flight of `minutes` and fit it: the whole-process runs and the stage times in `runs`."""
    py = sys.executable
    log = work / f"m{minutes:g}.bin"
    row: dict[str, Any] = {"minutes": minutes}
    row["simulate"] = run_timed([py, "-m", "magcal_cli", "simulate", "--scenario", "multirotor", "--rate", "400",
                                 "--duration", f"{minutes * 60:g}", "-o", str(log), "--force", "-q"],
                                package, work, pss=True)
    row["bin_mb"] = log.stat().st_size / 1e6 if log.exists() else float("nan")
    for key, extra in (("fit", ()), ("fit_none", ("--effects", "none"))):
        if key not in runs:
            continue
        row[key] = run_timed([py, "-m", "magcal_cli", "fit", str(log), "-o", str(work / key), "--force", "-q",
                              *extra], package, work, pss=True)
        print(f"{minutes:g} min {key}: {row[key]}", file=sys.stderr, flush=True)
    if "stages" in runs:
        with suppress(RuntimeError):
            row["stages"] = run_json([py, str(HERE), "--driver", str(log), str(work / "stages")], package, work)
    log.unlink(missing_ok=True)
    return row


def _svg(data: dict[str, list[dict[str, Any]]]) -> str:
    """Two small panels (wall s, peak MB) against log length (min), one line per label and run."""
    width, height, pad = 340, 220, 45
    colors = {"simulate": "#d62728", "fit": "#1f77b4", "fit_none": "#2ca02c"}
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{2 * width}" height="{height + 30}" '
           'font-family="sans-serif" font-size="11">']
    for panel, (key, title) in enumerate((("seconds", "wall (s)"), ("pss_mb", "peak memory, all processes (MB)"))):
        x0 = panel * width
        pts = [(r["minutes"], r[run][key]) for rows in data.values() for r in rows for run in RUNS if run in r]
        xmax = max(p[0] for p in pts) or 1.0
        ymax = max(p[1] for p in pts) or 1.0

        def fx(v: float, _x0: float = x0, _xmax: float = xmax) -> float:
            return _x0 + pad + (width - 1.5 * pad) * v / _xmax

        def fy(v: float, _ymax: float = ymax) -> float:
            return height - pad + 10 - (height - 1.5 * pad) * v / _ymax

        out.append(f'<text x="{x0 + width / 2}" y="14" text-anchor="middle">{title} vs log length (min)</text>')
        out.append(f'<line x1="{fx(0)}" y1="{fy(0)}" x2="{fx(xmax)}" y2="{fy(0)}" stroke="#000"/>')
        out.append(f'<line x1="{fx(0)}" y1="{fy(0)}" x2="{fx(0)}" y2="{fy(ymax)}" stroke="#000"/>')
        out.append(f'<text x="{fx(0) - 4}" y="{fy(ymax) + 4}" text-anchor="end">{ymax:.0f}</text>')
        out.append(f'<text x="{fx(xmax)}" y="{fy(0) + 14}" text-anchor="middle">{xmax:g}</text>')
        for label, rows in data.items():
            dash = ' stroke-dasharray="4 3"' if label == "before" else ""
            for run in RUNS:
                xy = [(fx(r["minutes"]), fy(r[run][key])) for r in rows if run in r]
                if xy:
                    d = " ".join(f"{x:.1f},{y:.1f}" for x, y in xy)
                    out.append(f'<polyline points="{d}" fill="none" stroke="{colors[run]}"{dash}/>')
    legend = "  ".join(f'<tspan fill="{c}">{r}</tspan>' for r, c in colors.items())
    out.append(f'<text x="{pad}" y="{height + 20}">{legend}  (dashed: before, solid: after)</text></svg>')
    return "\n".join(out)


def render(data: dict[str, list[dict[str, Any]]]) -> str:
    """The results page: a table per label and run, the stage table, the plot."""
    lines = ["# Long logs: time and memory against log length (issue 39)", "",
             "`python benchmarks/bench_long.py` (its docstring says how). Multirotor flights simulated at 400 Hz;",
             "wall time of one run on the shared 2-core machine (noisy), peak RSS of the largest process and peak",
             "summed PSS of the whole process tree (forked diagnosis workers included).", ""]
    for label, rows in data.items():
        lines += [f"## {label}", "", "| min | .bin MB | run | wall s | peak RSS MB | peak PSS all MB | exit |",
                  "|---|---|---|---|---|---|---|"]
        for r in sorted(rows, key=lambda r: r["minutes"]):
            for run in RUNS:
                if run in r:
                    m = r[run]
                    lines.append(f"| {r['minutes']:g} | {r['bin_mb']:.0f} | {run} | {m['seconds']:.1f} | "
                                 f"{m['peak_mb']:.0f} | {m['pss_mb']:.0f} | {m['exit']} |")
        staged = [r for r in rows if "stages" in r]
        if staged:
            lines += ["", "Stage times (s), one process running each stage once:", "",
                      "| min | " + " | ".join(STAGES) + " |", "|---" * (len(STAGES) + 1) + "|"]
            lines += [f"| {r['minutes']:g} | " + " | ".join(f"{r['stages'].get(s, float('nan')):.1f}" for s in STAGES)
                      + " |" for r in sorted(staged, key=lambda r: r["minutes"])]
        lines.append("")
    lines += ["## Plot", "", _svg(data), ""]
    if NOTES.exists():
        lines += [NOTES.read_text()]
    return "\n".join(lines)


def main() -> int:
    """Measure the lengths asked for and keep them under the label, or render the page."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", default="10,30")
    ap.add_argument("--label", default="after")
    ap.add_argument("--package", type=Path, default=ROOT, help="folder holding the magcal_cli to measure")
    ap.add_argument("--runs", default="fit,fit_none,stages",
                    help="what to measure after the simulation: fit, fit_none, stages (comma-separated)")
    ap.add_argument("--render", action="store_true")
    ap.add_argument("--driver", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.driver:
        _driver(*args.driver)
        return 0
    data: dict[str, list[dict[str, Any]]] = json.loads(JSON.read_text()) if JSON.exists() else {}
    if not args.render:
        _compiled(args.package)
        with tempfile.TemporaryDirectory(prefix="bench_long_") as tmp:
            for minutes in (float(m) for m in args.minutes.split(",")):
                t = time.perf_counter()
                row = measure(minutes, args.package, Path(tmp), set(args.runs.split(",")))
                if JSON.exists():                       # another label may have been measured meanwhile
                    data = json.loads(JSON.read_text())
                old = next((r for r in data.get(args.label, []) if r["minutes"] == minutes), {})
                rows = [r for r in data.get(args.label, []) if r["minutes"] != minutes]
                data[args.label] = [*rows, old | row]
                JSON.write_text(json.dumps(data, indent=1))
                print(f"{minutes:g} min done in {time.perf_counter() - t:.0f} s", file=sys.stderr, flush=True)
    PAGE.write_text(render(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
