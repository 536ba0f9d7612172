"""Every real log through a default `magcal fit`, and the fate of every magnetometer in it (issue 38's "must show").

For each log in ../shared/realdata/ (ArduPilot, PX4, ROS, CSV, BROAD and zoo/): `magcal fit LOG --json -o TMP`
with nothing else (so `--effects auto`, `--method auto`) in a subprocess, its exit code and wall time, and for each
magnetometer `magcal inspect LOG --json` lists, its fate:
- calibrated: the method (the magnetometer's own `method` key, else the document's), the field-norm spread after
  calibration (`quality.field_norm_rms_pct`) and what was held at a prior;
- refused: listed in the document's `refused[]` with its reason (or named by the error line of a whole-log refusal);
- only in the notes: neither calibrated nor in `refused[]`, but a note of the document names it with a reason;
- VANISHED: in inspect's list, but neither calibrated nor refused nor named anywhere. None may vanish.

    python benchmarks/real_logs.py [--realdata ../shared/realdata] [--out docs/results/real_logs] [--jobs 1]
                                   [--timeout 900]
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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from flight_logs import LOG_GLOBS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: the zoo's logs (zoo/README.md): any ArduPilot, PX4 or ROS 1 file, and ROS 2 bag folders (found by metadata.yaml)
ZOO_GLOBS = ("zoo/*/*.bin", "zoo/*/*.BIN", "zoo/*/*.log", "zoo/*/*.ulg", "zoo/*/*.px4log", "zoo/*/*.bag",
             "zoo/*/*.mcap", "zoo/*/*.csv")
#: a magnetometer id as the readers name them (MAG[1], sensor_mag[0], /imu/mag, /imu.mag_field)
CALIBRATED, REFUSED, NOTES, VANISHED = "calibrated", "refused", "only in notes", "VANISHED"


def find_logs(realdata: Path) -> list[Path]:
    """Every log of the realdata folder a reader opens: flight_logs.py's globs, the zoo's, ROS 2 bag folders."""
    found = {p for g in (*LOG_GLOBS, *ZOO_GLOBS) for p in realdata.glob(g)}
    found |= {m.parent for m in realdata.glob("zoo/*/*/metadata.yaml")}
    return sorted(found)


def run_command(cmd: list[str], cwd: str, timeout: float) -> tuple[subprocess.CompletedProcess[str] | None, float]:
    """A magcal command on one core (the machine is shared), its wall time; None when it timed out."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "MPLBACKEND": "Agg"}
    t0 = time.perf_counter()
    try:
        # cwd outside the work tree: `python -m` puts the cwd first on the path
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout, check=False, cwd=cwd)
    except subprocess.TimeoutExpired:
        return None, timeout
    return proc, time.perf_counter() - t0


def inspect_mags(log: Path, timeout: float) -> tuple[list[str], str | None]:
    """The magnetometer ids `magcal inspect LOG --json` lists, and its error line when it failed."""
    with tempfile.TemporaryDirectory() as cwd:
        proc, _ = run_command([sys.executable, "-m", "magcal_cli", "inspect", str(log.resolve()), "--json"], cwd, timeout)
    if proc is None:
        return [], f"inspect timed out after {timeout:.0f} s"
    try:
        doc = json.loads(proc.stdout)
    except json.JSONDecodeError:
        return [], _error_line(proc.stderr) or f"inspect exit {proc.returncode}, no JSON"
    streams = doc.get("streams", []) if isinstance(doc, dict) else []
    ids = [s["id"] for s in streams if s.get("kind") == "magnetometer"]
    return list(dict.fromkeys(ids)), None


def _error_line(stderr: str) -> str | None:
    """The `Error: ...` line of a magcal command's stderr (its last non-empty line when there is none)."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("Error:")]
    return errors[0] if errors else (lines[-1] if lines else None)


def fit_default(log: Path, timeout: float, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """`magcal fit LOG --json -o TMP` (defaults otherwise, plus `extra`): exit code, seconds, document, error line,
    stderr."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        proc, seconds = run_command([sys.executable, "-m", "magcal_cli", "fit", str(log.resolve()), "--json", "-o", str(out),
                                     *extra],
                             tmp, timeout)
        if proc is None:
            return {"exit": None, "seconds": seconds, "error": f"timed out after {timeout:.0f} s", "document": None,
                    "stderr": ""}
        doc = None
        for text in (proc.stdout, (out / "calibration.json").read_text() if (out / "calibration.json").exists()
                     else ""):
            try:
                doc = json.loads(text)
                break
            except json.JSONDecodeError:
                continue
    return {"exit": proc.returncode, "seconds": seconds, "document": doc if isinstance(doc, dict) else None,
            "error": _error_line(proc.stderr) if proc.returncode != 0 else None, "stderr": proc.stderr}


def _names(text: str, mag_id: str) -> bool:
    """Whether `text` names the magnetometer `mag_id` (not as a prefix of a longer id: MAG[1] is not MAG[10])."""
    return re.search(re.escape(mag_id) + r"(?![\w\[\].])", text) is not None


def fate(mag_id: str, res: dict[str, Any]) -> dict[str, Any]:
    """What became of one magnetometer in one default fit."""
    doc = res["document"] or {}
    stderr = res.get("stderr", "")
    named = _names(stderr, mag_id)
    m = next((m for m in doc.get("magnetometers", []) if m.get("id") == mag_id), None)
    if m is not None:
        held = [str(h.get("parameter")) for h in m.get("held", [])]
        sources = list(dict.fromkeys(str(h["source"]) for h in m.get("held", []) if h.get("source")))
        q = m.get("quality") or {}
        return {"id": mag_id, "fate": CALIBRATED, "method": m.get("method") or doc.get("method"),
                "reference": m.get("reference"), "spread_pct": q.get("field_norm_rms_pct"), "held": held,
                "held_sources": sources,
                "heading_check": m.get("heading_check")}
    ref = next((r for r in doc.get("refused", []) or [] if r.get("id") == mag_id), None)
    if ref is not None:
        return {"id": mag_id, "fate": REFUSED, "reason": ref.get("reason"), "advice": ref.get("advice"),
                "source": "refused[]", "stderr_names_it": named}
    if res["exit"] != 0 and res.get("error") and (_names(res["error"], mag_id) or not _any_mag(res["error"])):
        return {"id": mag_id, "fate": REFUSED, "reason": _about(res["error"], mag_id),
                "source": "error line (whole log)", "error": res["error"], "stderr_names_it": named}
    notes = [n for n in doc.get("notes", []) if _names(n, mag_id) and re.search(
        r"not calibrated|no calibration|does not explain|dropped|refus|dead|stuck|unusable", n)]
    if notes:
        return {"id": mag_id, "fate": NOTES, "reason": notes[0], "source": "notes", "stderr_names_it": named}
    return {"id": mag_id, "fate": VANISHED, "reason": None, "stderr_names_it": named}


def _about(error: str, mag_id: str) -> str:
    """The part of a whole-log error line about one magnetometer: from its first mention within a parenthesised
    list of reasons ("none of the 2 magnetometers can be used (MAG[0]: ...; MAG[1]: ...)", or ": MAG[0], ...;
    MAG[1], ..."), else the whole line."""
    m = re.search(r"[(;:,]\s*" + re.escape(mag_id) + r"(?![\w\[\].])\s*[:,]", error)
    return f"whole log refused; {error[m.start() + 1:].strip()}" if m else error


def _any_mag(text: str) -> bool:
    """Whether an error line names some magnetometer (then it is about that one, not the whole log)."""
    return re.search(r"MAG\[\d\]|sensor_mag\[\d\]|vehicle_magnetometer|mag_field|/mag\b|magnetic_field", text) \
        is not None


def run_log(log: Path, realdata: Path, timeout: float) -> dict[str, Any]:
    """inspect and default fit of one log, and each magnetometer's fate."""
    mags, inspect_error = inspect_mags(log, timeout)
    res = fit_default(log, timeout)
    doc = res["document"] or {}
    in_doc = [m.get("id") for m in doc.get("magnetometers", [])]
    fates = [fate(m, res) for m in mags]
    # a calibrated magnetometer inspect did not list (a nested stream named differently) is shown too
    fates += [fate(m, res) | {"not_in_inspect": True} for m in in_doc if m not in mags]
    name = str(log.relative_to(realdata))
    print(f"{name}: exit {res['exit']} in {res['seconds']:.1f} s, "
          + ", ".join(f"{f['id']} {f['fate']}" for f in fates), flush=True)
    return {"log": name, "exit": res["exit"], "seconds": round(res["seconds"], 1), "error": res["error"],
            "method": doc.get("method"), "inspect_error": inspect_error, "mags": fates,
            "refused_key": "refused" in doc}


def _cell(text: Any, limit: int = 160) -> str:
    """Text fit for a markdown cell: one line, pipes escaped, cut at `limit`."""
    s = " ".join(str(text).split()).replace("|", "\\|")
    return s if len(s) <= limit else s[: limit - 1] + "…"


def counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    """How many logs, magnetometers and of each fate."""
    fates = [f["fate"] for r in rows for f in r["mags"]]
    out = {"logs": len(rows), "magnetometers": len(fates), "exit_0": sum(r["exit"] == 0 for r in rows)}
    out |= {k: fates.count(k) for k in (CALIBRATED, REFUSED, NOTES, VANISHED)}
    out["no_magnetometer_listed"] = sum(not r["mags"] for r in rows)
    return out


def markdown(rows: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    """The page: header with the counts, then one line per magnetometer."""
    c = counts(rows)
    head = (f"# Every real log through a default `magcal fit`\n\n"
            f"Made by `{meta['command']}` on {meta['date']} at {meta['commit']}{meta['dirty']}; {meta['seconds']:.0f} s "
            f"in all, {meta['jobs']} log(s) at a time, each command on one core.\n\n"
            f"**{c[VANISHED]} of {c['magnetometers']} magnetometers VANISHED** (listed by `magcal inspect`, neither "
            f"calibrated nor refused nor named by the run). {c[CALIBRATED]} calibrated, {c[REFUSED]} refused by name, "
            f"{c[NOTES]} refused only in the document's notes (not in `refused[]`); {c['logs']} logs, {c['exit_0']} "
            f"exited 0; {c['no_magnetometer_listed']} log(s) where inspect lists no magnetometer.\n\n"
            "Command per log: `magcal fit LOG --json -o TMP` (defaults: `--effects auto`, `--method auto`); the "
            "magnetometers are those `magcal inspect LOG --json` lists with kind magnetometer. Method: the "
            "magnetometer's own `method` key, else the document's. Spread: `quality.field_norm_rms_pct`. Held: the "
            "parameters held at a prior (their source). Reason: the document's `refused[]` entry, else the error line "
            "of a whole-log refusal, else the note that names the compass. Named on stderr: whether the terminal "
            "output names the compass at all.\n\n")
    lines = ["| log | exit | s | magnetometer | fate | method / reason | spread % | held | named on stderr |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        first = f"| {r['log']} | {r['exit']} | {r['seconds']} "
        if not r["mags"]:
            why = r["inspect_error"] or r["error"] or "inspect lists no magnetometer"
            lines.append(first + f"| — | — | {_cell(why)} | | | |")
        for i, f in enumerate(r["mags"]):
            lead = first if i == 0 else "| | | "
            extra = " (not in inspect's list)" if f.get("not_in_inspect") else ""
            if f["fate"] == CALIBRATED:
                how = f"{f['method']}" + (f" ({f['reference']})" if f.get("reference") not in (None, "motion") else "")
                spread = "—" if f["spread_pct"] is None else f"{f['spread_pct']:.2f}"
                lines.append(lead + f"| {f['id']}{extra} | calibrated | {_cell(how)} | {spread} | "
                             f"{_cell(held_text(f), 200)} | |")
            else:
                fate_txt = f"**{f['fate']}**" if f["fate"] == VANISHED else f["fate"]
                lines.append(lead + f"| {f['id']}{extra} | {fate_txt} | {_cell(f.get('reason') or '—', 220)} | | | "
                             f"{'yes' if f.get('stderr_names_it') else 'no'} |")
    return head + "\n".join(lines) + "\n"


def held_text(f: dict[str, Any]) -> str:
    """The held parameters compactly (a whole D as `D`), then where the first prior came from."""
    held = f["held"]
    if not held:
        return "nothing"
    names = ["D" if all(f"D[{i}][{j}]" in held for i in range(3) for j in range(3)) else ""]
    names += [h for h in held if not (names[0] and h.startswith("D["))]
    src = f.get("held_sources") or []
    return ", ".join(n for n in names if n) + (f" ({src[0].split(';')[0]})" if src else "")


def git_meta() -> dict[str, str]:
    """The work tree's commit and whether it has uncommitted changes."""
    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True, check=False).stdout.strip()
    return {"commit": git("rev-parse", "--short=10", "HEAD"),
            "dirty": " (with uncommitted changes)" if git("status", "--porcelain", "--untracked-files=no") else ""}


def main() -> None:
    """Run every log, print and save the table (OUT.md, OUT.json)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "real_logs",
                    help="writes OUT.md and OUT.json")
    ap.add_argument("--jobs", type=int, default=1, help="logs at a time (the machine has 2 cores)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per magcal command")
    ap.add_argument("--only", default="", help="comma-separated substrings: run only the logs whose path has one")
    ap.add_argument("--render", action="store_true", help="only rewrite OUT.md (and print it) from OUT.json")
    args = ap.parse_args()
    if args.render:
        saved = json.loads(args.out.with_suffix(".json").read_text())
        args.out.with_suffix(".md").write_text(page := markdown(saved["logs"], saved["meta"]))
        print(page)
        return
    if not args.realdata.is_dir():
        print(f"{args.realdata}: no real logs here; nothing to measure")
        return
    logs = find_logs(args.realdata)
    if args.only:
        logs = [p for p in logs if any(s in str(p) for s in args.only.split(","))]
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        rows = list(pool.map(lambda p: run_log(p, args.realdata, args.timeout), logs))
    meta = {"command": "python benchmarks/real_logs.py " + " ".join(sys.argv[1:]),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "seconds": time.perf_counter() - t0,
            "jobs": args.jobs, **git_meta()}
    page = markdown(rows, meta)
    print(page)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"meta": meta, "counts": counts(rows), "logs": rows},
                                                        indent=1, default=str) + "\n")
    args.out.with_suffix(".md").write_text(page)


if __name__ == "__main__":
    main()
