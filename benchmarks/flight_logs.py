"""Every real log in ../shared/realdata/ through `magcal fit`, before and after a change (issue 12's table).

For each log: the exit code and first error line of `fit --effects none`, and per magnetometer what was
calibrated and what was held at a prior (partial calibration), the field-norm spread of the raw readings and
after calibration, and the heading change against the calibration the vehicle flew with (largest difference
over a level 360-degree turn at the fitted dip, where the log's parameters give one).

`--before DIR` also runs an older checkout's package (its folder holding `magcal_cli/`, e.g. made with
`git worktree add /tmp/before REV`) on the same logs, in the same run.

    python benchmarks/flight_logs.py [--realdata ../shared/realdata] [--before /tmp/before]
                                     [--out docs/results/flight_logs]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

#: the log files of ../shared/realdata/ that a reader opens (licences and result folders are not logs)
LOG_GLOBS = ("ardupilot/*.bin", "ardupilot/*.log", "px4/*.ulg", "px4/*.px4log", "ros/*.bag", "ros/*_mcap",
             "ros/*_sqlite3", "csv/*.csv", "broad/*.mat", "broad/*.hdf5")


def fit(log: Path, package: Path | None, timeout: float = 900.0, extra: tuple[str, ...] = ("--effects", "none")
        ) -> dict[str, Any]:
    """`magcal fit LOG --json` plus `extra` options in a subprocess (with `package` first on the path when given)."""
    env = dict(os.environ)
    if package is not None:
        env["PYTHONPATH"] = str(package)
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "magcal_cli", "fit", str(log.resolve()), "-o", out, "--outputs", "json", "--json",
               *extra]
        t0 = time.perf_counter()
        try:
            # cwd outside the work tree: `python -m` puts the cwd first on the path, ahead of PYTHONPATH
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout, check=False,
                                  cwd=out)
        except subprocess.TimeoutExpired:
            return {"exit": None, "error": f"timed out after {timeout:.0f} s", "seconds": timeout}
        seconds = time.perf_counter() - t0
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("Error:")]
    out_doc = json.loads(proc.stdout) if proc.returncode == 0 and proc.stdout.strip() else None
    return {"exit": proc.returncode, "error": errors[0] if errors else None, "seconds": seconds,
            "document": out_doc}


def heading_change_deg(doc: dict[str, Any], log: Path) -> dict[str, float | None]:
    """Per magnetometer: the largest heading difference over a level turn between the calibration the vehicle
    flew with (the log's parameters: the affine map raw -> field the firmware applied, `partial.flown_prior`) and
    the fitted one, None when the log has no firmware calibration."""
    from magcal_cli import units
    from magcal_cli.calibration.document import from_dict
    from magcal_cli.errors import MagcalError
    from magcal_cli.firmware.flown import flown_fields
    from magcal_cli.models.partial import flown_prior
    from magcal_cli.readers import open_recording

    cal = from_dict(doc)
    out: dict[str, float | None] = {m.id: None for m in cal.magnetometers}
    try:
        rec = open_recording(log)
        flown, _ = flown_fields(rec, [m.id for m in cal.magnetometers], None, None)
    except MagcalError:
        return out
    psi = np.deg2rad(np.arange(0.0, 360.0, 1.0))
    for f in flown:
        m = cal.magnetometer(f.id)
        dip = np.deg2rad(m.dip_deg)
        m_b = np.stack([np.cos(dip) * np.cos(psi), -np.cos(dip) * np.sin(psi), np.full_like(psi, np.sin(dip))], 1)
        raw = m.distort(m_b) * units.to_si(m.unit) * units.from_si(f.unit)   # what the sensor reads, flown unit
        flown = flown_prior(f.raw, f.field, 1.0, f.slot)              # the firmware's map, as y = D m_b + o
        if flown is None:
            continue
        field = (raw - flown.o) @ np.linalg.inv(flown.D).T
        h_flown = np.degrees(np.arctan2(-field[:, 1], field[:, 0]))
        h_fit = np.degrees(psi)
        out[f.id] = float(np.max(np.abs((h_flown - h_fit + 180.0) % 360.0 - 180.0)))
    return out


def _kind() -> Any:
    from magcal_cli.streams import Kind

    return Kind.MAGNETOMETER


def summary(res: dict[str, Any], log: Path) -> dict[str, Any]:
    """The table's fields of one fit."""
    doc = res.get("document")
    row: dict[str, Any] = {"exit": res["exit"], "error": res["error"], "seconds": round(res["seconds"], 1)}
    if doc is None:
        return row
    change = heading_change_deg(doc, log)
    wmm = [float(x) for n in doc.get("notes", []) for x in re.findall(r"from the WMM\S* at the log's position "
                                                                        r"\((-?[\d.]+) deg\)", n)]
    row["method"] = doc.get("method")
    timing = (doc.get("source") or {}).get("timing") or {}
    row["timing"] = timing.get("imu", "following (magcal 0.1: every gyro)")
    row["mags"] = [{
        "time_offset": time_offset(doc, m["id"]),
        "id": m["id"], "held": [h["parameter"] for h in m.get("held", [])], "reference": m.get("reference", "motion"),
        "wmm_dip_deg": wmm[0] if wmm else None,
        "held_source": sorted({h["source"] for h in m.get("held", [])}),
        "norm_rms_pct": m["quality"]["field_norm_rms_pct"], "dip_deg": m["dip_deg"],
        "coverage_pct": m["quality"]["coverage_pct"], "heading_change_deg": change.get(m["id"])}
        for m in doc["magnetometers"]]
    row["not_calibrated"] = [n for n in doc.get("notes", []) if "was not calibrated" in n]
    return row


def time_offset(doc: dict[str, Any], mag_id: str) -> str:
    """The document's time_offset verdict for one magnetometer: status, and tau with its 95 % interval (ms)."""
    e = next((e for e in doc.get("effects", []) if e["id"] == "time_offset" and e.get("sensor") == mag_id), None)
    if e is None:
        return "not run"
    tau, ci = (e.get("params") or {}).get("tau_s"), (e.get("ci95") or {}).get("tau_s")
    if tau is None:
        return e["status"]
    interval = f" [{1e3 * ci[0]:.1f}, {1e3 * ci[1]:.1f}]" if ci else ""
    return f"{e['status']} {1e3 * tau:.1f}{interval}"


def raw_spread(log: Path) -> dict[str, float]:
    """Field-norm spread of each magnetometer's raw readings (std / mean of |y|, %)."""
    from magcal_cli.errors import MagcalError
    from magcal_cli.readers import open_recording

    try:
        rec = open_recording(log)
    except MagcalError:
        return {}
    out = {}
    for s in rec.of_kind(_kind()):
        r = np.linalg.norm(s.xyz, axis=1)
        out[s.id] = float(100.0 * np.std(r) / np.mean(r)) if len(r) else float("nan")
    return out


def markdown(rows: list[dict[str, Any]], before: bool) -> str:
    """The results table."""
    head = "| log | " + ("before | " if before else "") + "after | magnetometer | held at a prior | raw spread % | " \
        "calibrated spread % | dip deg (WMM) | heading change deg | time offset ms (IMU samples) | s |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        b = r.get("before")
        before_txt = (f"exit {b['exit']}: {(b['error'] or 'ok')[:90]} | " if b else "— | ") if before else ""
        a = r["after"]
        if not a.get("mags"):
            lines.append(f"| {r['log']} | {before_txt}exit {a['exit']}: {(a['error'] or '')[:300]} | | | | | | | | "
                         f"{a['seconds']} |")
            continue
        for i, m in enumerate(a["mags"]):
            held = ", ".join(m["held"]) or "nothing"
            hc = m["heading_change_deg"]
            wmm = m.get("wmm_dip_deg")
            how = f"{a.get('method')}" + (f" ({m['reference']})" if m.get("reference", "motion") != "motion" else "")
            lines.append(
                f"| {r['log'] if i == 0 else ''} | {before_txt if i == 0 else ('| ' if before else '')}"
                f"{'calibrated: ' + how if i == 0 else ''} | {m['id']} | {held} | "
                f"{r['raw'].get(m['id'], float('nan')):.2f} | {m['norm_rms_pct']:.2f} | {m['dip_deg']:.1f}"
                f"{'' if wmm is None else f' ({wmm:.1f})'} | {'—' if hc is None else f'{hc:.1f}'} | "
                f"{m['time_offset']} ({a['timing']}) | {a['seconds'] if i == 0 else ''} |")
        for n in a.get("not_calibrated", []):
            lines.append(f"| | {'| ' if before else ''}| {n[:300]} | | | | | | | |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Run every log, print and save the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--realdata", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "realdata")
    ap.add_argument("--before", type=Path, default=None, help="an older checkout (folder holding magcal_cli/)")
    ap.add_argument("--out", type=Path, default=Path("docs/results/flight_logs"))
    ap.add_argument("--fit", default="", help="options for `magcal fit` [default: none, i.e. fit's defaults]")
    args = ap.parse_args()
    extra = tuple(args.fit.split())
    if not args.realdata.is_dir():
        print(f"{args.realdata}: no real logs here; nothing to measure")
        return
    logs = sorted({p for g in LOG_GLOBS for p in args.realdata.glob(g)})
    rows = []
    for log in logs:
        name = str(log.relative_to(args.realdata))
        print(f"{name} ...", flush=True)
        row: dict[str, Any] = {"log": name, "raw": raw_spread(log), "after": summary(fit(log, None, extra=extra), log)}
        if args.before is not None:
            row["before"] = summary(fit(log, args.before, extra=extra), log)
        rows.append(row)
    table = markdown(rows, args.before is not None)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1, default=str) + "\n")
    args.out.with_suffix(".md").write_text(
        f"# Every real log through `{' '.join(('magcal fit', args.fit)).strip()}`\n\n"
        "Made by `python benchmarks/flight_logs.py" + (f" --before {args.before}" if args.before else "") +
        (f" --fit '{args.fit}'" if args.fit else "") + "`. "
        "Raw spread: std/mean of |raw reading|; calibrated spread: the document's field_norm_rms_pct; heading "
        "change: largest difference over a level turn between the calibration the vehicle flew with and the "
        "fitted one.\n\n" + table)


if __name__ == "__main__":
    main()
