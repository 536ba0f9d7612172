"""The mismatch diagnosis on real logs, blind (default `fit`, no hint): what it finds and the held-out numbers.

`python benchmarks/diagnose_realdata.py [--out docs/results/diagnose_realdata]` writes a Markdown table and the
raw JSON. Logs: `../shared/realdata/` (BROAD 06 fast rotation with optical motion capture; ArduPilot log171 with
motor current up to 27 A; the three 2015-10-11 ArduPilot logs with current 1-25 A). BROAD 06 is also scored
against the motion capture: heading RMS before (base fit) and after (the diagnosed fit, re-stamped by an accepted
time offset), as in effects_realdata.py.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from effects_realdata import Mocap, heading_stats  # noqa: E402

from magcal_cli.calibration.run import RunResult  # noqa: E402
from magcal_cli.config import Config  # noqa: E402
from magcal_cli.errors import MagcalError  # noqa: E402
from magcal_cli.pipeline import calibrate  # noqa: E402
from magcal_cli.streams import Kind  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "realdata"
LOGS = ("broad/06_undisturbed_fast_rotation_A.mat", "ardupilot/log171.bin", "ardupilot/2015-10-11_19-53-46.log",
        "ardupilot/2015-10-11_19-59-09.log", "ardupilot/2015-10-11_20-17-22.log")


def run(path: Path, diagnose: bool) -> tuple[RunResult | None, float, str]:
    """One fit (blind diagnosis or base model), its time and the error if it failed."""
    t = time.perf_counter()
    try:
        res = calibrate(path, Config(method="map", diagnose=diagnose))
    except MagcalError as exc:
        return None, time.perf_counter() - t, str(exc)
    return res, time.perf_counter() - t, ""


def mocap_heading(base: RunResult, auto: RunResult) -> dict[str, Any]:
    """BROAD: heading RMS against the motion capture, base fit and diagnosed fit."""
    rec = base.recording
    gyr = rec.select(Kind.GYROSCOPE)
    mocap = Mocap(rec.select(Kind.ATTITUDE, "opt_quat"), 1.0 / float(np.median(np.diff(gyr.t))), len(gyr))
    out = {}
    for label, res in (("before (base fit)", base), ("after (diagnosed fit)", auto)):
        mag = res.calibration.magnetometers[0]
        ser = res.series[mag.id]
        tau = 0.0
        for e in res.calibration.effects:
            if e["id"] == "time_offset" and e["status"] in ("accepted", "ambiguous") and e.get("params"):
                tau = float(e["params"]["tau_s"])
        rot, ok = mocap.at(ser.t - tau)
        out[label] = {"tau_ms": 1e3 * tau, **heading_stats(ser.calibrated * mag.field_strength, rot, ok)}
    return out


def one(rel: str) -> dict[str, Any]:
    """Base fit and blind diagnosis of one log."""
    path = DATA / rel
    base, t_base, err_base = run(path, False)
    auto, t_auto, err_auto = run(path, True)
    out: dict[str, Any] = {"log": rel, "seconds_base": t_base, "seconds_diagnosed": t_auto}
    if auto is None:
        out["error"] = err_auto or err_base
        return out
    diag = auto.calibration.diagnosis or {}
    out["not_diagnosed"] = [f.message for f in auto.findings if f.code == "diagnosis_failed"]
    out["sensors"] = []
    for block in diag.get("sensors", []):
        sid = block["sensor"]
        effects = [e for e in auto.calibration.effects if e.get("sensor") in (sid, auto.calibration.imu.id)]
        dip = {m.id: m.dip_deg for m in auto.calibration.magnetometers}
        dip0 = {m.id: m.dip_deg for m in base.calibration.magnetometers} if base is not None else {}
        out["sensors"].append({
            "sensor": sid, "dip_deg_base": dip0.get(sid), "dip_deg_diagnosed": dip.get(sid), "unit": block.get("unit"), "ppc_p": block["ppc"]["global_p"],
            "ppc_top": block["ppc"]["top"][:3], "ppc_after_p": block["ppc_after"]["global_p"],
            "located": block["located"], "heldout": block.get("heldout"), "summary": block["summary"],
            "effects": {e["id"]: {"status": e["status"], "params": e.get("params"), "ci95": e.get("ci95"),
                                  "reason": e.get("reason", ""), "evidence": e.get("evidence", {})}
                        for e in effects if e["status"] != "not_testable"},
            "not_testable": {e["id"]: e.get("reason", "") for e in effects if e["status"] == "not_testable"}})
    if base is not None and "broad" in rel:
        out["mocap"] = mocap_heading(base, auto)
    return out


def write_md(path: Path, results: list[dict[str, Any]]) -> None:
    """The Markdown summary."""
    lines = ["# Blind diagnosis of real logs", "",
             "`python benchmarks/diagnose_realdata.py`: `calibrate(path, Config(method='map', diagnose=True))`, "
             "i.e. what `magcal fit LOG` does by default; no effect named. Raw numbers in the JSON next to this file.",
             "", "| log | sensor | simulation check p (before / after) | accepted | ambiguous | held-out residual "
             "RMS before / after | dip deg base / diagnosed | base / diagnosed s |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['log']} | - | refused: {r['error'][:160]} | | | | | {r['seconds_base']:.1f} / "
                         f"{r['seconds_diagnosed']:.1f} |")
            continue
        for why in r.get("not_diagnosed", []):
            lines.append(f"| {r['log']} | - | not diagnosed: {why[:200]} | | | | | {r['seconds_base']:.1f} / "
                         f"{r['seconds_diagnosed']:.1f} |")
        for s in r["sensors"]:
            acc = ", ".join(k for k, v in s["effects"].items() if v["status"] == "accepted") or "none"
            amb = ", ".join(k for k, v in s["effects"].items() if v["status"] == "ambiguous") or "-"
            h = s["heldout"]
            held = f"{h['rms_before']:.3g} / {h['rms_after']:.3g} {s['unit']}" if h else "-"
            lines.append(f"| {r['log']} | {s['sensor']} | {s['ppc_p']:.2g} / {s['ppc_after_p']:.2g} | {acc} | "
                         f"{amb} | {held} | {s['dip_deg_base'] or float('nan'):.1f} / {s['dip_deg_diagnosed']:.1f} | "
                         f"{r['seconds_base']:.1f} / {r['seconds_diagnosed']:.1f} |")
    lines += ["", "## What the diagnosis said", ""]
    for r in results:
        for s in r.get("sensors", []):
            lines += [f"- **{r['log']} {s['sensor']}**: {s['summary']}"]
        if "mocap" in r:
            lines += ["", f"Heading against the motion capture ({r['log']}):", "",
                      "| fit | tau ms | heading RMS deg | heading p95 deg | field residual RMS uT |", "|---|---|---|---|---|"]
            for k, v in r["mocap"].items():
                lines.append(f"| {k} | {v['tau_ms']:.2f} | {v['heading_rms_deg']:.2f} | {v['heading_p95_deg']:.2f} | "
                             f"{v['field_residual_rms']:.3f} |")
            lines.append("")
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    """Run every log; write the Markdown and JSON."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "diagnose_realdata")
    ap.add_argument("--logs", default=",".join(LOGS))
    args = ap.parse_args()
    if not DATA.exists():
        print(f"skipped: {DATA} is absent")
        return 0
    results = []
    for rel in args.logs.split(","):
        print(f"{rel} ...", file=sys.stderr, flush=True)
        results.append(one(rel))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(results, indent=1, default=float))
    write_md(args.out.with_suffix(".md"), results)
    print(args.out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
