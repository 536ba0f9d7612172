"""magcal against magfit_WMM on logs neither fitted: the three 2015-10-11 flights of one vehicle (issue 12).

`vs_magfit.py` scores each calibration on the log it was fitted to. The field-norm spread and the yaw residual
against ATT are then in-sample: a tool that fits directions the flight does not determine (magfit_WMM's DIA/ODI
on a +-24 deg flight, which end on its 0.8/1.2 bounds) lowers both without calibrating better. The three
2015-10-11 logs are one vehicle on one afternoon (same compasses, COMPASS_DEV_IDs, orientation and INS
calibration); each calibration fitted on one log is scored here on the other two, with the same metrics
(vs_magfit.field_metrics). magfit_WMM's parameters are the ones vs_magfit.py found (its JSON), magcal is refitted
(`fit --effects auto`, `--method attitude`, `--effects none`); a magcal calibration is applied as `apply` does
(its accepted magnetometer effects removed, then A (y - b)).

    python benchmarks/cross_log.py [--realdata ../shared/realdata] [--magfit docs/results/vs_magfit.json]
                                   [--out docs/results/cross_log]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vs_magfit import field_metrics, log_context, magfit_field  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LOGS = ("2015-10-11_19-53-46.log", "2015-10-11_19-59-09.log", "2015-10-11_20-17-22.log")
TOOLS = ("magcal auto", "magcal attitude", "magcal none")


def fit_magcal(path: Path, tool: str) -> tuple[dict[str, Any], float]:
    """magcal's calibration document of `path` (as a dict) for one of TOOLS, and its time (s)."""
    from magcal_cli.calibration.document import to_dict
    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate

    kind = tool.split()[1]
    cfg = Config(diagnose=kind == "auto", method="attitude" if kind == "attitude" else "auto")
    t0 = time.perf_counter()
    doc = to_dict(calibrate(path, cfg).calibration)
    return doc, time.perf_counter() - t0


def magcal_field(rec: Any, mag_id: str, doc: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(t, calibrated unit field) of `rec`'s compass under a calibration fitted on another log."""
    from magcal_cli import units
    from magcal_cli.effects.correct import remove
    from magcal_cli.streams import Kind

    m = next(x for x in doc["magnetometers"] if x["id"] == mag_id)
    s = rec.select(Kind.MAGNETOMETER, mag_id)
    t, y, _ = remove(doc["effects"], mag_id, rec, s.t, s.xyz * units.from_si(m["units"]))
    return t, (y - np.array(m["b"])) @ np.array(m["A"]).T


def context(path: Path) -> tuple[Any, float]:
    """The recording and the WMM declination (rad) at its median fix on its GPS date."""
    from magcal_cli.readers import open_recording
    from magcal_cli.streams import Kind
    from magcal_cli.wmm import reference_field

    rec = open_recording(path)
    pos = rec.select(Kind.POSITION).values
    lat, lon, alt = np.median(pos[np.all(np.isfinite(pos), axis=1) & (np.abs(pos[:, 0]) > 0)], axis=0)
    date = log_context(path)["date"] or dt.date.today()
    return rec, float(reference_field(lat, lon, alt, date).declination)


def main() -> None:
    """Fit on each log, score on the others, print and write the tables."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--magfit", type=Path, default=ROOT / "docs" / "results" / "vs_magfit.json")
    ap.add_argument("--out", type=Path, default=None, help="write OUT.json and OUT.md")
    args = ap.parse_args()
    start = time.perf_counter()
    paths = [args.realdata / "ardupilot" / name for name in LOGS]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        sys.exit(f"cross_log: missing {', '.join(missing)}; pass --realdata")
    magfit = {(r["log"], r["mag"]): r["params"] for r in json.loads(args.magfit.read_text())["rows"]
              if r["tool"] == "magfit_WMM" and "params" in r}
    ctx = {p.name: context(p) for p in paths}
    fits: dict[tuple[str, str], dict[str, Any]] = {}
    seconds: dict[tuple[str, str], float] = {}
    for p in paths:
        for tool in TOOLS:
            fits[p.name, tool], seconds[p.name, tool] = fit_magcal(p, tool)
            print(f"fitted {p.name} {tool} in {seconds[p.name, tool]:.1f} s", file=sys.stderr, flush=True)
    rows = []
    for fitted in LOGS:
        for scored in LOGS:
            rec, decl = ctx[scored]
            for mag_id in ("MAG[0]", "MAG[1]"):
                base = {"fitted_on": fitted, "scored_on": scored, "mag": mag_id, "in_sample": fitted == scored}
                params = magfit.get((fitted, mag_id))
                if params is not None:
                    rows.append({**base, "tool": "magfit_WMM",
                                 **field_metrics(rec, *magfit_field(rec, mag_id, params), decl)})
                for tool in TOOLS:
                    rows.append({**base, "tool": tool,
                                 **field_metrics(rec, *magcal_field(rec, mag_id, fits[fitted, tool]), decl)})
    md = markdown(rows, args.magfit, time.perf_counter() - start)
    print(md)
    if args.out:
        args.out.with_suffix(".json").write_text(json.dumps({"rows": rows, "magcal_seconds": {
            f"{k[0]} {k[1]}": v for k, v in seconds.items()}}, indent=1))
        args.out.with_suffix(".md").write_text(md)


def _wins(rows: list[dict[str, Any]], tool: str, key: str, in_sample: bool) -> tuple[int, int]:
    """How often `tool`'s `key` is <= magfit_WMM's, over (fitted, scored, compass) cells of one kind."""
    cells: dict[tuple[str, str, str], dict[str, float]] = {}
    for r in rows:
        if r["in_sample"] == in_sample and key in r:
            cells.setdefault((r["fitted_on"], r["scored_on"], r["mag"]), {})[r["tool"]] = r[key]
    both = [c for c in cells.values() if tool in c and "magfit_WMM" in c]
    return sum(c[tool] <= c["magfit_WMM"] for c in both), len(both)


def _median(rows: list[dict[str, Any]], tool: str, key: str, in_sample: bool) -> float:
    """Median of `key` over one tool's cells of one kind."""
    vals = [r[key] for r in rows if r["tool"] == tool and r["in_sample"] == in_sample and key in r]
    return float(np.median(vals)) if vals else float("nan")


def markdown(rows: list[dict[str, Any]], magfit_json: Path, seconds: float) -> str:
    """Summary (in-sample against out-of-sample) and the full table."""
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, check=False).stdout.strip()
    lines = ["# Calibrations scored on the logs they were not fitted to (issue 12)", "",
             f"Generated by `python benchmarks/cross_log.py` on {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC at "
             f"{commit}, {seconds:.0f} s. magfit_WMM's parameters from `{magfit_json.name}` (its run's "
             "`--elliptical --cmot` fits); magcal refitted. Yaw RMS: heading from the calibrated field, "
             "tilt-compensated with ATT (AHRS_TRIM added back), plus the WMM declination, minus ATT yaw "
             "(ATT used the compass with the calibration it flew with: a reference, not truth). Norm spread: "
             "std/mean of |field| in %.", "",
             "| tool | yaw RMS <= magfit_WMM (in-sample) | (other logs) | median yaw RMS deg in / out | "
             "norm spread <= magfit_WMM (in-sample) | (other logs) | median norm spread % in / out |",
             "|---|---|---|---|---|---|---|"]
    for tool in ("magfit_WMM", *TOOLS):
        cells = []
        for key in ("yaw_rms_deg", "norm_spread_pct"):
            if tool == "magfit_WMM":
                cells += ["-", "-"]
            else:
                cells += ["{}/{}".format(*_wins(rows, tool, key, True)), "{}/{}".format(*_wins(rows, tool, key, False))]
            cells.append(f"{_median(rows, tool, key, True):.2f} / {_median(rows, tool, key, False):.2f}")
        lines.append(f"| {tool} | " + " | ".join(cells[:3]) + " | " + " | ".join(cells[3:]) + " |")
    lines += ["", "| fitted on | scored on | compass | tool | yaw RMS deg | yaw p95 deg | norm spread % |",
              "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['fitted_on'][11:19]} | {r['scored_on'][11:19]}{' (same)' if r['in_sample'] else ''} | "
                     f"{r['mag']} | {r['tool']} | {r.get('yaw_rms_deg', float('nan')):.2f} | "
                     f"{r.get('yaw_p95_deg', float('nan')):.2f} | {r['norm_spread_pct']:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
