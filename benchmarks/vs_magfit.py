"""magcal against pymavlink's magfit_WMM.py on the same logs, side by side in one run (issue 12's "must show").

Simulated ArduPilot flights with known truth (`magcal simulate --scenario multirotor`, some seeds with
current_interference): heading error over a level 360-degree turn and parameter errors (offsets, correction
matrix, current coefficient). Real ArduPilot logs (log171.bin and the 2015-10-11 text logs, skipped when absent):
field-norm spread after calibration and the yaw residual against the ATT attitude (tilt-compensated heading with
the WMM declination). Wall-clock time for both tools, every fit on one core, --jobs fits at a time.

magfit_WMM runs as a subprocess (`--elliptical --cmot`, one run per compass, Agg backend); when it crashes on a
log's missing parameters the crash is recorded and it is rerun with `--att-source ATT`, and on simulated logs,
which carry no AHRS_TRIM_*, on a copy with AHRS_TRIM_X/Y/Z = 0 appended. magcal runs in-process with
`--effects auto` (default) and `--effects none`.

    python benchmarks/vs_magfit.py [--seeds 0,1,2,3] [--current-seeds 1,3] [--reduce 10] [--jobs 2]
                                   [--realdata ../shared/realdata] [--out docs/results/vs_magfit] [--render]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import multiprocessing
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from effects_accuracy import heading_error_deg  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL_LOGS = ("log171.bin", "2015-10-11_19-53-46.log", "2015-10-11_19-59-09.log", "2015-10-11_20-17-22.log")
MAGFIT_ARGS = ("--elliptical", "--cmot")
#: one core per fit (both tools), no display for magfit_WMM's plot
SINGLE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MAGCAL_JOBS": "1",
                 "MPLBACKEND": "Agg"}
#: magfit_WMM with its scale bound widened (one simulated seed): how much of its error is the 1.5 bound
WIDENED = ("--max-scale", "2.0")
TRIMS = ("AHRS_TRIM_X", "AHRS_TRIM_Y", "AHRS_TRIM_Z")
GPS_EPOCH = dt.datetime(1980, 1, 6)


def magfit_script() -> Path:
    """pymavlink's tools/magfit_WMM.py (the installed module's copy, else the script on PATH)."""
    import pymavlink

    path = Path(pymavlink.__file__).parent / "tools" / "magfit_WMM.py"
    return path if path.exists() else Path(sys.executable).parent / "magfit_WMM.py"


def simulate_log(folder: Path, seed: int, current: bool) -> dict[str, Any]:
    """`magcal simulate OUT.bin --scenario multirotor --seed N [--effect current_interference]`."""
    out = folder / f"multirotor_seed{seed}{'_current' if current else ''}.bin"
    cmd = [sys.executable, "-m", "magcal_cli", "simulate", str(out), "--scenario", "multirotor", "--seed",
           str(seed), "-q", "--force"] + (["--effect", "current_interference"] if current else [])
    subprocess.run(cmd, check=True, capture_output=True)
    return {"log": str(out), "name": out.name, "kind": "simulated", "seed": seed, "current": current,
            "truth": str(out) + ".truth.json"}


def append_params(src: Path, dst: Path, values: dict[str, float]) -> None:
    """Copy a DataFlash .bin and append PARM records (the file's own PARM format) for `values`."""
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(src))
    last = 0
    while (msg := log.recv_match(type=["PARM", "IMU"])) is not None:
        last = max(last, int(getattr(msg, "TimeUS", 0)))
    fmt = next(f for f in log.formats.values() if f.name == "PARM")
    data = src.read_bytes()
    for name, value in values.items():
        fields = {"TimeUS": last, "TimeMS": last // 1000, "Name": name.encode(), "Value": value}
        row = [fields.get(c, 0.0 if ch == "f" else 0) for c, ch in zip(fmt.columns, fmt.format, strict=True)]
        data += bytes([0xA3, 0x95, fmt.type]) + struct.pack(fmt.msg_struct, *row)
    dst.write_bytes(data)


def parse_magfit(stdout: str) -> dict[str, Any]:
    """The COMPASS_* lines magfit_WMM prints (one compass), its attitude source and earth field."""
    params = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(COMPASS\w+) (-?[\d.]+)$", stdout, re.M)}
    out: dict[str, Any] = {"params": params}
    for stem in ("OFS", "DIA", "ODI", "MOT"):
        keys = sorted(k for k in params if re.fullmatch(rf"COMPASS\d?_{stem}\d?_[XYZ]", k))
        out[stem] = [params[k] for k in keys] if len(keys) == 3 else None
    scale = [v for k, v in params.items() if re.fullmatch(r"COMPASS\d?_SCALE\d?", k)]
    out["SCALE"] = scale[0] if scale else 1.0
    for key, pattern in (("att_source", r"^Attitude source (\S+)"), ("points", r"^Extracted (\d+) points"),
                         ("wmm_strength_mG", r"strength (\d+)"), ("iterations", r"Iterations: (\d+)")):
        m = re.search(pattern, stdout, re.M)
        out[key] = m.group(1) if m else None
    return out


def magfit_once(log: Path, mag: int, extra: list[str], timeout: float) -> dict[str, Any]:
    """One magfit_WMM run: exit code, seconds, parsed parameters or the error line."""
    cmd = [sys.executable, str(magfit_script()), *MAGFIT_ARGS, "--mag", str(mag), *extra, str(log)]
    env = {**os.environ, **SINGLE_THREAD}
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, check=False)
    except subprocess.TimeoutExpired:
        return {"args": extra, "exit": None, "seconds": timeout, "error": f"timed out after {timeout:.0f} s"}
    seconds = time.perf_counter() - t0
    res: dict[str, Any] = {"args": [*MAGFIT_ARGS, "--mag", str(mag), *extra], "exit": proc.returncode,
                           "seconds": seconds}
    parsed = parse_magfit(proc.stdout)
    if proc.returncode == 0 and parsed["OFS"] is not None:
        res.update(parsed)
    else:
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()] or \
            [ln for ln in proc.stdout.splitlines() if ln.strip()]
        res["error"] = lines[-1] if lines else f"exit {proc.returncode}, no output"
    return res


def run_magfit(log: str, mag: int, reduce: int, timeout: float, more: tuple[str, ...] = ()) -> dict[str, Any]:
    """magfit_WMM as a user would try it: plain, then --att-source ATT, then (simulated .bin) with AHRS_TRIM_*."""
    path, extra = Path(log), (["--reduce", str(reduce)] if reduce > 1 else []) + list(more)
    attempts = [magfit_once(path, mag, extra, timeout)]
    if "error" in attempts[-1]:
        attempts.append(magfit_once(path, mag, [*extra, "--att-source", "ATT"], timeout))
    if "error" in attempts[-1] and "AHRS_TRIM" in attempts[-1]["error"] and path.suffix == ".bin":
        patched = path.with_name(f"{path.stem}_trim_{os.getpid()}.bin")
        append_params(path, patched, dict.fromkeys(TRIMS, 0.0))
        attempts.append(magfit_once(patched, mag, [*extra, "--att-source", "ATT"], timeout))
        attempts[-1]["patched"] = "AHRS_TRIM_X/Y/Z = 0 appended as PARM records"
    tool = " ".join(["magfit_WMM", *more])
    return {"tool": tool, "log": log, "mag": mag, "attempts": attempts, "result": attempts[-1]}


def run_magcal(log: str, effects: str) -> dict[str, Any]:
    """magcal's fit of every compass (Python API, as `magcal fit LOG --effects auto|none` or, for "attitude",
    `--method attitude`: the same reference as magfit_WMM), timed."""
    from magcal_cli.config import Config
    from magcal_cli.errors import MagcalError
    from magcal_cli.pipeline import calibrate

    cfg = Config(allow_truncated=True, diagnose=effects == "auto",
                 method="attitude" if effects == "attitude" else "auto")
    t0 = time.perf_counter()
    try:
        res = calibrate(Path(log), cfg)
    except MagcalError as exc:
        return {"tool": f"magcal {effects}", "log": log, "seconds": time.perf_counter() - t0, "error": str(exc)}
    seconds = time.perf_counter() - t0
    mags = {}
    for m in res.calibration.magnetometers:
        eff = [e for e in res.calibration.effects if e.get("sensor") == m.id
               and e.get("status") in ("accepted", "ambiguous")]
        ser = res.series[m.id]
        mags[m.id] = {"D": m.D.tolist(), "o": m.o.tolist(), "dip_deg": m.dip_deg,
                      "held": [h["parameter"] for h in m.held],
                      "effects": {e["id"]: {"status": e["status"], "params": e["params"]} for e in eff},
                      "t": ser.t, "field": ser.calibrated}
    failed = {f.evidence.get("sensor"): f.message for f in res.findings if f.code == "not_calibrated"}
    return {"tool": f"magcal {effects}", "log": log, "seconds": seconds, "mags": mags, "failed": failed,
            "reference": [n for n in res.calibration.notes if "WMM" in n or "attitude" in n.lower()][:3]}


def log_context(log: Path) -> dict[str, Any]:
    """The log's first GPS fix date (UTC) and magfit_WMM's own raw field per compass (its remove_offsets)."""
    from pymavlink import mavutil

    mlog = mavutil.mavlink_connection(str(log))
    params: dict[str, float] = {}
    mags: dict[str, list[tuple[float, ...]]] = {}
    date = None
    while (msg := mlog.recv_match(type=["PARM", "GPS", "MAG", "MAG2", "MAG3"])) is not None:
        kind = msg.get_type()
        if kind == "PARM":
            params[msg.Name] = float(msg.Value)
        elif kind == "GPS":
            week, ms = getattr(msg, "GWk", getattr(msg, "Week", 0)), getattr(msg, "GMS", getattr(msg, "TimeMS", 0))
            if date is None and msg.Status >= 3 and week > 0:
                date = (GPS_EPOCH + dt.timedelta(weeks=week, milliseconds=ms)).date()
        else:
            t = getattr(msg, "TimeUS", None)
            t = t / 1e6 if t is not None else msg.TimeMS / 1e3
            mags.setdefault(kind, []).append((t, msg.MagX, msg.MagY, msg.MagZ, msg.OfsX, msg.OfsY, msg.OfsZ))
    return {"date": date, "params": params, "mag": {k: np.array(v) for k, v in mags.items()}}


def magfit_raw(ctx: dict[str, Any], mag: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(t, raw mG) as magfit_WMM's remove_offsets computes it (no motor term: MOT is 0 on these logs)."""
    from magcal_cli.readers.dataflash.compass import iron_matrix

    rows = ctx["mag"].get("MAG" if mag == 1 else f"MAG{mag}")
    if rows is None:
        return None
    p = ctx["params"]
    sfx = "" if mag == 1 else str(mag)
    dia = np.array([[p.get(f"COMPASS_DIA{sfx}_{a}", 1.0) for a in "XYZ"]])
    odi = np.array([[p.get(f"COMPASS_ODI{sfx}_{a}", 0.0) for a in "XYZ"]])
    scale = p.get(f"COMPASS_SCALE{sfx}", 1.0)
    scale = 1.0 if scale < 0.1 else scale
    field = rows[:, 1:4] @ np.linalg.inv(iron_matrix(dia, odi)[0]).T / scale - rows[:, 4:7]
    return rows[:, 0], np.trunc(field)


def field_metrics(rec: Any, t: np.ndarray, field: np.ndarray, decl: float) -> dict[str, float]:
    """Norm spread (std/mean %) and the yaw residual (deg) against the ATT attitude (AHRS_TRIM added back, as
    magfit_WMM does): tilt-compensated heading with the WMM declination minus ATT yaw, wrapped."""
    from magcal_cli import so3
    from magcal_cli.align import onto
    from magcal_cli.streams import Kind

    ok = np.all(np.isfinite(field), axis=1)
    norm = np.linalg.norm(field[ok], axis=1)
    out = {"norm_spread_pct": float(100 * np.std(norm) / np.mean(norm))}
    att = [s for s in rec.of_kind(Kind.ATTITUDE) if s.id == "ATT"]
    if not att:
        return out
    mask, q = onto(att[0], t, max_gap_s=1.0)
    rpy = so3.as_rpy(so3.from_quat(q)) + np.array([rec.params.get(k, 0.0) for k in TRIMS])
    m_n = np.einsum("nij,nj->ni", so3.from_rpy(rpy), field[mask])
    keep = ok[mask]
    err = np.degrees(np.angle(np.exp(1j * (decl - np.arctan2(m_n[keep, 1], m_n[keep, 0])))))
    out.update({"yaw_rms_deg": float(np.sqrt(np.mean(err**2))),
                "yaw_p95_deg": float(np.percentile(np.abs(err), 95)), "yaw_mean_deg": float(np.mean(err)),
                "yaw_samples": int(err.size)})
    return out


def magfit_field(rec: Any, mag_id: str, fit: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The field magfit_WMM's correct() gives for the reader's raw readings: SCALE M (raw + OFS) + MOT I."""
    from magcal_cli import units
    from magcal_cli.firmware.flown import signal_at
    from magcal_cli.readers.dataflash.compass import iron_matrix
    from magcal_cli.streams import Kind

    s = rec.select(Kind.MAGNETOMETER, mag_id)
    raw = s.xyz * units.from_si("milligauss")
    m = fit["SCALE"] * iron_matrix(np.array([fit["DIA"]]), np.array([fit["ODI"]]))[0]
    field = (raw + np.array(fit["OFS"])) @ m.T
    current = signal_at(rec, Kind.BATTERY_CURRENT, s.t)
    if current is not None and fit["MOT"] is not None:
        field = field + current[:, None] * np.array(fit["MOT"])
    return s.t, field


def as_d_o_c(fit: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """magfit_WMM's field = S M (y + OFS) + MOT I as magcal's y = D m + o + c I: D ~ (S M)^-1, o = -OFS,
    c = -(S M)^-1 MOT (D up to scale, which the heading and the scale-free matrix error ignore)."""
    from magcal_cli.readers.dataflash.compass import iron_matrix

    m_inv = np.linalg.inv(fit["SCALE"] * iron_matrix(np.array([fit["DIA"]]), np.array([fit["ODI"]]))[0])
    mot = np.array(fit["MOT"] or [0.0, 0.0, 0.0])
    return m_inv, -np.array(fit["OFS"]), -m_inv @ mot


def truth_errors(d: np.ndarray, o: np.ndarray, c: np.ndarray | None, truth: dict[str, Any]) -> dict[str, float]:
    """Heading error (deg, level turn), offsets error (mG), scale-free correction-matrix error (%), c error."""
    def unit_det(a: np.ndarray) -> np.ndarray:
        return a / np.cbrt(np.linalg.det(a))

    a_fit, a_true = unit_det(np.linalg.inv(d)), unit_det(np.linalg.inv(truth["D"]))
    out = {"heading_err_deg": heading_error_deg(d, o, truth["D"], truth["o"], truth["dip"]),
           "o_err_mG": float(np.linalg.norm(o - truth["o"])),
           "A_err_pct": float(100 * np.linalg.norm(a_fit - a_true) / np.linalg.norm(a_true))}
    if truth["c"] is not None:
        out["c_err_mG_per_A"] = float(np.linalg.norm((np.zeros(3) if c is None else c) - truth["c"]))
    return out


def load_truth(path: str) -> dict[str, Any]:
    """D, o (mG), dip (rad) of MAG[0] from the truth document, the current coefficient (mG/A) and the heading
    error of the truth without its rotation (left polar factor P of D = P U), what a symmetric matrix drops."""
    from magcal_cli import so3

    doc = json.loads(Path(path).read_text())
    m = doc["magnetometers"][0]
    d, o = np.array(m["D"]), np.array(m["o"])
    cur = [e for e in doc["effects"] if e["id"] == "current_interference"]
    u, p = so3.polar(d)
    dip = float(np.radians(m["dip_deg"]))
    return {"D": d, "o": o, "dip": dip, "c": np.array(cur[0]["params"]["c"]) if cur else None,
            "field_mG": m["field_strength"], "dip_deg": m["dip_deg"], "misalignment_deg": m["misalignment"]["angle_deg"],
            "no_rotation_deg": heading_error_deg(u @ p @ u.T, o, d, o, dip)}


def evaluate(spec: dict[str, Any], runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per compass and tool for a log: field metrics, truth errors (simulated), time, failures."""
    from magcal_cli import units
    from magcal_cli.firmware.flown import flown_fields
    from magcal_cli.readers import ReadOptions, open_recording
    from magcal_cli.streams import Kind
    from magcal_cli.wmm import reference_field

    log = Path(spec["log"])
    rec = open_recording(log, None, ReadOptions(allow_truncated=True))
    ctx = log_context(log)
    pos = rec.select(Kind.POSITION).values
    lat, lon, alt = np.median(pos[np.all(np.isfinite(pos), axis=1) & (np.abs(pos[:, 0]) > 0)], axis=0)
    ref = reference_field(lat, lon, alt, ctx["date"] or dt.date.today())
    spec.update({"date": str(ctx["date"]), "wmm": {"model": ref.model, "dip_deg": ref.dip_deg,
                                                   "strength_mG": ref.intensity * 1e7,
                                                   "declination_deg": float(np.degrees(ref.declination))}})
    truth = load_truth(spec["truth"]) if "truth" in spec else None
    if truth is not None:
        spec["truth_summary"] = {k: truth[k] for k in ("field_mG", "dip_deg", "misalignment_deg",
                                                      "no_rotation_deg")}
    # the simulator's field is the WMM's at its GPS position and date, declination included
    # (synth.truth.at_home)
    decl = ref.declination
    spec["yaw_declination_deg"] = float(np.degrees(decl))
    rows = []
    for i, mag_id in enumerate(rec.ids(Kind.MAGNETOMETER)):
        base = {"log": log.name, "mag": mag_id}
        s = rec.select(Kind.MAGNETOMETER, mag_id)
        check = magfit_raw(ctx, i + 1)
        if check is not None and len(check[0]) == len(s):
            diff = np.abs(check[1] - s.xyz * units.from_si("milligauss"))
            base["raw_vs_magfit_mG"] = {"median": float(np.median(diff)), "max": float(np.max(diff))}
        try:
            flown = flown_fields(rec, [mag_id], None, None)[0][0]
            rows.append({**base, "tool": "flown (log's COMPASS_*)",
                         **field_metrics(rec, flown.t, flown.field, decl)})
        except Exception as exc:  # noqa: BLE001 - a baseline, reported and skipped
            rows.append({**base, "tool": "flown (log's COMPASS_*)", "error": f"{type(exc).__name__}: {exc}"})
        for run in runs:
            row = {**base, "tool": run["tool"]}
            if run["tool"].startswith("magfit_WMM"):
                if run["mag"] != i + 1:
                    continue
                res = run["result"]
                row.update(seconds=res["seconds"], attempts=[{k: a.get(k) for k in ("args", "exit", "seconds",
                                                                                     "error", "patched")}
                                                             for a in run["attempts"]])
                if "error" in res:
                    rows.append({**row, "error": res["error"]})
                    continue
                row["params"] = {k: res[k] for k in ("OFS", "DIA", "ODI", "MOT", "SCALE")}
                row.update(att_source=res["att_source"], points=res["points"], iterations=res["iterations"])
                row.update(field_metrics(rec, *magfit_field(rec, mag_id, res), decl))
                if truth is not None and i == 0:
                    row.update(truth_errors(*as_d_o_c(res), truth))
            else:
                row["seconds_all_mags"] = run["seconds"]
                if "error" in run or mag_id not in run["mags"]:
                    error = run.get("error") or run.get("failed", {}).get(mag_id, f"{mag_id} not calibrated")
                    rows.append({**row, "error": error})
                    continue
                m = run["mags"][mag_id]
                row.update(dip_deg=m["dip_deg"], held=m["held"], effects=m["effects"])
                row.update(field_metrics(rec, m["t"], m["field"], decl))
                if truth is not None and i == 0:
                    cur = m["effects"].get("current_interference")
                    c = np.array(cur["params"]["c"]) if cur else None
                    row.update(truth_errors(np.array(m["D"]), np.array(m["o"]), c, truth))
            rows.append(row)
    return rows


def fmt(v: Any, spec: str = ".2f") -> str:
    """A number for the table, or a dash."""
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def tables(specs: list[dict[str, Any]], rows: list[dict[str, Any]]) -> str:
    """The accuracy table (one row per log, compass, tool), the timing table and the simulated summary."""
    lines = ["| log | mag | tool | norm spread % | yaw RMS / p95 / mean deg | heading err deg | o err mG | "
             "A err % | c err mG/A | fit s | notes |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        note = r.get("error", "")
        if not note and "dip_deg" in r:
            note = "; ".join(filter(None, [f"dip {r['dip_deg']:.1f}",
                                           r.get("held") and f"held {', '.join(r['held'])}",
                                           r.get("effects") and f"effects {', '.join(r['effects'])}"]))
        if len(r.get("attempts", [])) > 1:
            note = "; ".join(filter(None, [note, f"{len(r['attempts']) - 1} crash(es) first: "
                                           + " | ".join(str(a["error"]) for a in r["attempts"][:-1])]))
        secs = r.get("seconds", r.get("seconds_all_mags"))
        yaw = "-" if "yaw_rms_deg" not in r else \
            f"{r['yaw_rms_deg']:.2f} / {r['yaw_p95_deg']:.2f} / {r['yaw_mean_deg']:+.2f}"
        lines.append(f"| {r['log']} | {r['mag']} | {r['tool']} | {fmt(r.get('norm_spread_pct'))} | {yaw} | "
                     f"{fmt(r.get('heading_err_deg'))} | {fmt(r.get('o_err_mG'), '.1f')} | "
                     f"{fmt(r.get('A_err_pct'))} | {fmt(r.get('c_err_mG_per_A'), '.3f')} | "
                     f"{fmt(secs, '.1f')}{' (all mags)' if 'seconds_all_mags' in r else ''} | {note} |")
    lines += ["", "| log | compasses | magcal auto s | magcal attitude s | magcal none s | magfit_WMM s (sum of "
              "per-compass runs) | magfit / magcal auto | magfit / magcal attitude | magfit / magcal none |",
              "|---|---|---|---|---|---|---|---|---|"]
    for spec in specs:
        rs = [r for r in rows if r["log"] == Path(spec["log"]).name]
        mags = sorted({r["mag"] for r in rs})

        def secs(tool: str, rs: list[dict[str, Any]] = rs) -> tuple[float | None, str]:
            """The run's time and, when some compasses failed, how many it calibrated."""
            mine = [r for r in rs if r["tool"] == tool]
            ok = sum("error" not in r for r in mine)
            t = mine[0]["seconds_all_mags"] if mine else None
            return t, "" if ok == len(mine) else f" ({ok} of {len(mine)} calibrated)"

        (auto, auto_note), (none, none_note) = secs("magcal auto"), secs("magcal none")
        att, att_note = secs("magcal attitude")
        mf = [r["seconds"] for r in rs if r["tool"] == "magfit_WMM" and "error" not in r]
        total = float(sum(mf)) if len(mf) == len(mags) else None
        lines.append(f"| {Path(spec['log']).name} | {len(mags)} | {fmt(auto, '.1f')}{auto_note} | "
                     f"{fmt(att, '.1f')}{att_note} | {fmt(none, '.1f')}{none_note} | {fmt(total, '.1f')} | "
                     f"{fmt(total / auto if total and auto else None, '.1f')}x | "
                     f"{fmt(total / att if total and att else None, '.1f')}x | "
                     f"{fmt(total / none if total and none else None, '.1f')}x |")
    sim = [r for r in rows if r["log"].startswith("multirotor") and "heading_err_deg" in r]
    if sim:
        lines += ["", "Simulated flights, median (max) over seeds:", "",
                  "| tool | heading err deg | o err mG | A err % | seeds |", "|---|---|---|---|---|"]
        for tool in dict.fromkeys(r["tool"] for r in sim):
            rs = [r for r in sim if r["tool"] == tool]
            if rs:
                cells = [f"{np.median([r[k] for r in rs]):.2f} ({np.max([r[k] for r in rs]):.2f})"
                         for k in ("heading_err_deg", "o_err_mG", "A_err_pct")]
                lines.append(f"| {tool} | {' | '.join(cells)} | {len(rs)} |")
        floors = [s["truth_summary"]["no_rotation_deg"] for s in specs if "truth_summary" in s]
        lines.append(f"| (truth without its rotation: left polar factor) | {np.median(floors):.2f} "
                     f"({np.max(floors):.2f}) "
                     f"| 0 | - | {len(floors)} |")
    return "\n".join(lines)


def pin_magcal() -> None:
    """Import every magcal_cli module now, so that edits other engineers make during the run cannot mix versions
    (modules are otherwise imported on first use, minutes later)."""
    import importlib
    import pkgutil
    import warnings

    import magcal_cli

    for mod in pkgutil.walk_packages(magcal_cli.__path__, "magcal_cli."):
        if mod.name.endswith("__main__"):        # runs the CLI
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                importlib.import_module(mod.name)
            except ImportError:                  # an optional extra that is not installed
                continue


def git_state() -> dict[str, Any]:
    """The commit and the magcal_cli files modified in the work tree (other engineers edit it meanwhile)."""
    def git(*cmd: str) -> str:
        return subprocess.run(["git", *cmd], cwd=ROOT, capture_output=True, text=True, check=False).stdout.strip()

    return {"commit": git("rev-parse", "HEAD"), "modified": git("status", "--porcelain", "magcal_cli").splitlines()}


def notes(specs: list[dict[str, Any]], rows: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    """What was run, what each number means and what went wrong, with the measured facts filled in."""
    sims = [s for s in specs if s["kind"] == "simulated"]
    out = ["## What was run", "",
           f"- magfit_WMM: `{meta['magfit_script']}` (pymavlink {meta['pymavlink']}), "
           f"`{' '.join(meta['magfit_args'])} --mag N` once per compass, MPLBACKEND=Agg (its plot is drawn "
           "and discarded), stdout parsed for the COMPASS_* lines it prints. "
           "When it crashed, the crash is kept (notes column) and it was rerun with `--att-source ATT`; on "
           "simulated logs, which have no AHRS_TRIM_*, a copy with AHRS_TRIM_X/Y/Z = 0 appended as PARM "
           f"records was used. Simulated logs with `--reduce {meta['reduce_simulated']}` (50 Hz -> "
           f"{50 / meta['reduce_simulated']:g} Hz) to fit the time budget; real logs at full rate (10 Hz).",
           *([f"- Also on seed {meta['widened']['seed']}: magfit_WMM `{' '.join(meta['widened']['args'])}`, to "
              "see how much of its simulated error comes from its default scale bound (1.5)."]
             if meta["widened"]["seed"] in meta["seeds"] else []),
           "- magcal: `calibrate(LOG, Config(...))` in-process, i.e. `magcal fit LOG --effects auto`, "
           "`--method attitude` (the vehicle's attitude and the WMM, magfit_WMM's own reference) and "
           "`--effects none`; all compasses of a log in one fit.",
           f"- Simulated: `magcal simulate --scenario multirotor --seed N` for seeds {meta['seeds']}, with "
           f"`--effect current_interference` (default 0.2/-0.1/0.3 mG/A) on seeds {meta['current_seeds']}.",
           f"- Every fit on one core (OMP/OpenBLAS/MKL threads = 1, MAGCAL_JOBS=1), {meta['jobs']} fits at a "
           f"time on {meta['cpu_count']} cores; magcal's diagnosis would use 2 threads by default. Times are wall "
           "clock: magfit's include its interpreter start, log parsing and plot; magcal's include reading the log "
           "but not importing magcal (done once per worker).",
           f"- magcal tree: {meta['git']['commit'][:10]}"
           + (f", with uncommitted changes by other engineers in {', '.join(meta['git']['modified'])}"
              if meta["git"]["modified"] else "")
           + ("" if meta.get("git_end") in (None, meta["git"]) else
              f" (it changed to {meta['git_end']['commit'][:10]} during the run; every magcal_cli module was "
              "imported at the start, so the fits used the starting version)") + ".", "",
           "## What the numbers mean", "",
           "- **heading err** (simulated, MAG[0]): the largest heading error over a level 360-degree turn at the "
           "truth's dip, when the fitted calibration corrects readings made with the true one "
           "(effects_accuracy.heading_error_deg).",
           "- **o err**: |o_fit - o_true| in mG; magfit's o is -COMPASS_OFS (ArduPilot: field = M (raw + OFS)).",
           "- **A err**: relative error (Frobenius) of the correction matrix A = D^-1, both scaled to unit "
           "determinant (the field strength is not compared); magfit's A is SCALE * M(DIA, ODI).",
           "- **c err**: |c_fit - c_true| of the current coefficient (raw mG/A); magfit's c = -(SCALE M)^-1 MOT; "
           "a tool that did not fit it counts as c = 0.",
           "- **norm spread**: std/mean of |calibrated field| over every reading, in %.",
           "- **yaw RMS / p95 / mean**: heading from the calibrated field, tilt-compensated with the ATT roll and "
           "pitch (AHRS_TRIM added back, as magfit_WMM does), plus the declination, minus ATT yaw, wrapped to "
           "+-180 deg, with the WMM declination at the median GPS position on the GPS date (the simulator's "
           "field has it too). On real logs ATT yaw is the autopilot's estimate, which "
           "used the compass with the calibration it flew with (the `flown` row), so it is a reference, not "
           "truth.",
           "- **flown**: the log's own COMPASS_* calibration applied to the same raw readings (the baseline).",
           "- **fit s**: magfit per compass; magcal per log (all compasses). On simulated logs magfit_WMM "
           f"read only every {meta['reduce_simulated']}th reading, so its time there is about "
           f"1/{meta['reduce_simulated']} of a full-rate run (its cost is linear in the readings). The machine is "
           "shared: absolute times moved by up to 2x between runs while this benchmark was written; compare the "
           "ratios within one run.", ""]
    out += ["## Against the target (magcal at least as accurate, >= 10x faster)", ""]
    for tool in ("magcal auto", "magcal attitude", "magcal none"):
        pairs = [(r, m) for r in rows if r["tool"] == tool for m in rows
                 if m["tool"] == "magfit_WMM" and m["log"] == r["log"] and m["mag"] == r["mag"]]
        both = [(r, m) for r, m in pairs if "error" not in r and "error" not in m]
        failed = sum("error" in r for r, _ in pairs)
        line = f"- {tool}: {failed} of {len(pairs)} compass fits failed where magfit_WMM produced a result" \
            if failed else f"- {tool}: every compass calibrated"
        for key, label in (("heading_err_deg", "heading error vs truth"), ("yaw_rms_deg", "yaw RMS vs ATT"),
                           ("norm_spread_pct", "norm spread")):
            cmp = [(r[key], m[key]) for r, m in both if key in r and key in m]
            if cmp:
                line += f"; {label} <= magfit_WMM's on {sum(a <= b for a, b in cmp)} of {len(cmp)}"
        full, reduced = [], []            # magfit_WMM on every reading (real logs); on every n-th (simulated)
        for spec in specs:
            name = Path(spec["log"]).name
            mine = [r for r in rows if r["log"] == name and r["tool"] == tool]
            mf = [r["seconds"] for r in rows if r["log"] == name and r["tool"] == "magfit_WMM" and "error" not in r]
            if mine and mf and len(mf) == len(mine) and all("error" not in r for r in mine):
                ratio = sum(mf) / mine[0]["seconds_all_mags"]
                (full if spec["kind"] != "simulated" else reduced).append(ratio)
        if full:
            line += (f"; >= 10x faster on {sum(x >= 10 for x in full)} of {len(full)} real logs, both at full rate "
                     f"(ratio {min(full):.1f}x to {max(full):.1f}x)")
        if reduced:
            k = meta["reduce_simulated"]
            line += (f"; on the simulated logs, where magfit_WMM read every {k}th reading and magcal all of them, "
                     f"{min(reduced):.1f}x to {max(reduced):.1f}x as measured ({k * min(reduced):.0f}x to "
                     f"{k * max(reduced):.0f}x per reading)")
        out.append(line + ".")
    out += ["", "## Observations (measured in this run)", ""]
    checks = [r["raw_vs_magfit_mG"] for r in rows if "raw_vs_magfit_mG" in r and r["tool"].startswith("flown")]
    if checks:
        out.append(f"- Same raw field: magfit_WMM's `remove_offsets` (replicated from the log with pymavlink) and "
                   f"magcal's reader agree within {max(c['max'] for c in checks):.1f} mG (median "
                   f"{np.median([c['median'] for c in checks]):.1f} mG) on every compass of every log: magfit "
                   "truncates to int and uses the logged integer OfsX.., magcal adds back half a count and uses "
                   "the PARM offsets. Both fit the same raw field; both are evaluated here on magcal's.")
    for s in sims:
        t, w = s.get("truth_summary", {}), s.get("wmm", {})
        if t:
            out.append(f"- {s['name']}: truth |B| {t['field_mG']:.0f} mG, dip {t['dip_deg']:.1f} deg, "
                       f"misalignment {t['misalignment_deg']:.1f} deg; the WMM at the log's GPS position says "
                       f"{w['strength_mG']:.0f} mG, dip {w['dip_deg']:.1f} deg, declination "
                       f"{w['declination_deg']:.1f} deg. ArduPilot's DIA/ODI matrix is symmetric and cannot hold "
                       f"the rotation: the truth with its rotation dropped (left polar factor) has a heading "
                       f"error of {t['no_rotation_deg']:.1f} deg (not a bound: another symmetric matrix may "
                       "do better on a level turn).")
    for s in specs:
        if s["kind"] == "real" and "wmm" in s:
            dips = [f"{r['mag']} {r['dip_deg']:.1f} ({r['tool'].split()[1]})" for r in rows
                    if r["log"] == s["name"] and r["tool"].startswith("magcal") and "dip_deg" in r]
            out.append(f"- {s['name']} (GPS date {s['date']}): WMM dip {s['wmm']['dip_deg']:.1f} deg, "
                       f"declination {s['wmm']['declination_deg']:.1f} deg; magcal fitted dip "
                       f"{', '.join(dips) or '-'} deg (magfit_WMM takes the dip from its own WMM table).")
    bound = [r for r in rows if r["tool"] == "magfit_WMM" and r.get("params") and
             (r["params"]["SCALE"] >= 1.5 or max(r["params"]["DIA"]) >= 1.2 or min(r["params"]["DIA"]) <= 0.8)]
    if bound:
        out.append(f"- magfit_WMM ended on a bound (SCALE 1.5 or DIA 0.8/1.2) for {len(bound)} compass fits: "
                   + ", ".join(f"{r['log']} {r['mag']} (SCALE {r['params']['SCALE']:g}, DIA "
                               f"{'/'.join(f'{v:g}' for v in r['params']['DIA'])})" for r in bound) + ".")
    no_mot = [f"{r['log']} {r['mag']}" for r in rows if r["tool"] == "magfit_WMM" and r.get("params")
              and not any(r["params"]["MOT"] or []) and not r["log"].startswith("multirotor")]
    if no_mot:
        out.append("- magfit_WMM's `--cmot` reads the current from BAT messages; these logs (Copter 3.3/3.4) log it "
                   f"in CURR, so COMPASS_MOT stayed 0 on {', '.join(no_mot)}. On simulated logs, which log BAT, it "
                   "also fitted MOT where no current interference was injected (seeds without it).")
    failed = [r for r in rows if r.get("error")]
    crashed = [r for r in rows if len(r.get("attempts", [])) > 1]
    for r in crashed:
        out.append(f"- magfit_WMM crashed on {r['log']} {r['mag']} before succeeding: "
                   + "; ".join(f"`{' '.join(a['args'])}` -> {a['error']}" for a in r["attempts"][:-1]))
    for r in failed:
        out.append(f"- {r['tool']} failed on {r['log']} {r['mag']}: {r['error']}")
    if meta["skipped"]:
        out.append(f"- Skipped (not found): {', '.join(meta['skipped'])}")
    return "\n".join(out)


def main() -> None:
    """Simulate, run both tools on every log (--jobs at a time), evaluate, print and write the results."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3", help="simulated multirotor seeds ('' for none)")
    ap.add_argument("--current-seeds", default="1,3", help="seeds simulated with current_interference")
    ap.add_argument("--reduce", type=int, default=10, help="magfit_WMM --reduce on the simulated 50 Hz logs")
    ap.add_argument("--widened-seed", type=int, default=0,
                    help="also run magfit_WMM --max-scale 2 on this seed (-1: no)")
    ap.add_argument("--logs", default=",".join(REAL_LOGS), help="real logs (names in REALDATA/ardupilot)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=1500.0, help="seconds per magfit_WMM run")
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--no-effects-none", action="store_true", help="skip magcal --effects none")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "vs_magfit")
    ap.add_argument("--render", action="store_true", help="only rewrite OUT.md (and print) from OUT.json")
    args = ap.parse_args()
    if args.render:
        render(args.out)
        return
    os.environ.update(SINGLE_THREAD)         # spawned workers import numpy with one BLAS thread
    # both tools' bytecode cached, as installed packages have it (a PYTHONDONTWRITEBYTECODE=1 shell would make
    # every magcal run compile its ~200 modules: 0.1 s of a 1 s fit)
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    import compileall

    compileall.compile_dir(str(ROOT / "magcal_cli"), quiet=1)
    start = time.perf_counter()
    pin_magcal()
    git_start = git_state()
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    current = {int(s) for s in args.current_seeds.split(",") if s.strip()}
    tmp = Path(tempfile.mkdtemp(prefix="vs_magfit_"))
    specs = [simulate_log(tmp, s, s in current) for s in seeds]
    skipped = []
    for name in filter(None, args.logs.split(",")):
        path = args.realdata / "ardupilot" / name
        if path.exists():
            specs.append({"log": str(path), "name": name, "kind": "real"})
        else:
            skipped.append(str(path))
            print(f"skipping {path}: not found (the real logs are not shipped with magcal)", file=sys.stderr)
    from magcal_cli.readers import ReadOptions, open_recording
    from magcal_cli.streams import Kind

    tasks: list[tuple[Any, ...]] = []
    for spec in specs:
        n = len(open_recording(Path(spec["log"]), None, ReadOptions(allow_truncated=True)).ids(Kind.MAGNETOMETER))
        reduce = args.reduce if spec["kind"] == "simulated" else 1
        tasks += [(run_magfit, spec["log"], k, reduce, args.timeout) for k in range(1, n + 1)]
        if spec.get("seed") == args.widened_seed:
            tasks.append((run_magfit, spec["log"], 1, reduce, args.timeout, WIDENED))
        tasks += [(run_magcal, spec["log"], e) for e in ("auto", "attitude", "none")[: 2 if args.no_effects_none
                                                                                       else 3]]
    tasks.sort(key=lambda t: (t[0] is not run_magfit, "log171" not in t[1]))    # longest first
    print(f"{len(tasks)} fits, {args.jobs} at a time ...", file=sys.stderr)
    with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn"),
                             initializer=pin_magcal) as pool:
        futures = [pool.submit(t[0], *t[1:]) for t in tasks]
        runs = [f.result() for f in futures]
    rows = []
    for spec in specs:
        rows += evaluate(spec, [r for r in runs if r["log"] == spec["log"]])
    shutil.rmtree(tmp, ignore_errors=True)
    elapsed = time.perf_counter() - start
    import pymavlink

    meta = {"elapsed_s": elapsed, "jobs": args.jobs, "magfit_script": str(magfit_script()),
            "pymavlink": pymavlink.__version__, "magfit_args": list(MAGFIT_ARGS), "reduce_simulated": args.reduce,
            "widened": {"seed": args.widened_seed, "args": list(WIDENED)}, "seeds": seeds,
            "current_seeds": sorted(current), "skipped": skipped, "cpu_count": os.cpu_count(), "git": git_start,
            "git_end": git_state(),
            "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"meta": meta, "logs": specs, "rows": rows}, indent=1,
                                                        default=str) + "\n")
    render(args.out)


def render(out: Path) -> None:
    """Print the tables of OUT.json and write OUT.md from it."""
    doc = json.loads(out.with_suffix(".json").read_text())
    meta, specs, rows = doc["meta"], doc["logs"], doc["rows"]
    text = tables(specs, rows)
    print(text)
    print(f"\n{meta['elapsed_s']:.0f} s in all", file=sys.stderr)
    out.with_suffix(".md").write_text(
        f"# magcal against pymavlink magfit_WMM.py\n\nGenerated by `python benchmarks/vs_magfit.py` on "
        f"{meta['date_utc']} UTC: {meta['elapsed_s']:.0f} s in all, {meta['jobs']} fits at a time.\n\n"
        f"{notes(specs, rows, meta)}\n\n## Results\n\n{text}\n")


if __name__ == "__main__":
    main()
