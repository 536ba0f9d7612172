"""Are the fit's files the same, byte for byte, from two checkouts? (issue 26: a redesign changes no result)

Runs `magcal fit LOG` (default options, every output but the report's prose and plots) on every sample log and
every real log that `flight_logs.py` runs, once with each package, and compares `calibration.json` (its
timestamps and run time aside) and the firmware parameter files byte for byte. Where they differ (issue 27: a
solver that converges in fewer steps reaches the same optimum within its tolerance), it says how far each
magnetometer's D, o and dip moved in their own reported std, how far the effects' parameters moved in theirs,
and whether every effect's verdict is the same.

    git worktree add /tmp/before REV
    python benchmarks/same_outputs.py --before /tmp/before [--after .] [--realdata ../shared/realdata]

`--save DIR` keeps each package's outputs (DIR/before, DIR/after); `--only before|after` runs one side into
DIR and `--compare DIR` compares two saved sides without running anything.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from flight_logs import LOG_GLOBS  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
#: what changes from run to run and is not a result
VOLATILE = re.compile(r'"(created_utc|created|generated|timestamp|run_seconds|seconds|elapsed_s|magcal_version)": [^,\n}]*')
OUTPUTS = "json,ardupilot,px4"


def logs(realdata: Path) -> list[Path]:
    """The sample logs (this checkout's, so both sides read the same paths, which the outputs record) and the
    real logs, sorted by name within each."""
    samples = sorted(p for p in (ROOT / "sample_logs").iterdir() if not p.name.endswith(".json"))
    real = sorted(p for g in LOG_GLOBS for p in realdata.glob(g)) if realdata.is_dir() else []
    return samples + real


def run_side(package: Path, log: Path, out: Path) -> dict[str, object]:
    """One `magcal fit` with `package` first on the path; the exit code and the files it wrote."""
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(package.resolve()))
    cmd = [sys.executable, "-m", "magcal_cli", "fit", str(log.resolve()), "-o", str(out), "--force", "-q",
           "--outputs", OUTPUTS]
    t0 = time.perf_counter()
    # cwd outside both trees: `python -m` puts the cwd ahead of PYTHONPATH
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=out, check=False)
    err = [ln for ln in proc.stderr.splitlines() if ln.startswith("Error")]
    (out / "exit.txt").write_text(f"{proc.returncode}\n{err[0] if err else ''}\n")
    return {"exit": proc.returncode, "seconds": time.perf_counter() - t0}


def digest(folder: Path) -> dict[str, str]:
    """File name -> sha256 of its bytes, with the volatile fields of JSON files blanked."""
    out: dict[str, str] = {}
    for f in sorted(folder.iterdir()):
        data = f.read_bytes()
        if f.suffix == ".json":
            data = VOLATILE.sub(lambda m: f'"{m.group(1)}": _', data.decode()).encode()
        out[f.name] = hashlib.sha256(data).hexdigest()[:16]
    return out


def key(log: Path) -> str:
    """A folder name for one log."""
    return log.parent.name + "__" + log.name


def shifts(before: Path, after: Path) -> tuple[float, float, bool]:
    """For two calibration.json files: the largest change of any magnetometer's D, o or dip in its own reported
    std, the largest change of an effect's parameter in its own std (95 % interval / 3.92), and whether every
    effect's verdict (id, sensor, status) is the same."""
    a, b = (json.loads(p.read_text()) for p in (before, after))
    cal = 0.0
    for ma, mb in zip(a.get("magnetometers", []), b.get("magnetometers", []), strict=False):
        for k in ("D", "o", "dip_deg"):
            std = np.asarray(ma["std"][k], float)
            d = np.abs(np.asarray(ma[k], float) - np.asarray(mb[k], float))
            cal = max(cal, float(np.max(np.where(std > 0, d / np.where(std > 0, std, 1.0), 0.0))))
    eb = {(e["id"], e["sensor"]): e for e in b.get("effects", [])}
    eff = 0.0
    for e in a.get("effects", []):
        f = eb.get((e["id"], e["sensor"]))
        if f is None:
            continue
        for name, ci in (e.get("ci95") or {}).items():
            v, w = e["params"].get(name), f.get("params", {}).get(name)
            if v is None or w is None or isinstance(v, str):
                continue
            half = np.diff(np.asarray(ci, float).reshape(-1, 2), axis=1)[:, 0] / 3.92
            d = np.abs(np.atleast_1d(np.asarray(v, float)) - np.atleast_1d(np.asarray(w, float)))
            eff = max(eff, float(np.max(np.where(half > 0, d / np.where(half > 0, half, 1.0), 0.0))))
    same = sorted((e["id"], e["sensor"], e["status"]) for e in a.get("effects", [])) == \
        sorted((e["id"], e["sensor"], e["status"]) for e in b.get("effects", []))
    return cal, eff, same


def compare(save: Path, names: list[str]) -> int:
    """Print one row per log and return the number that differ (for those, how far the calibration moved in its
    own std, and whether the effects' verdicts are the same)."""
    bad = 0
    for name in names:
        a, b = digest(save / "before" / name), digest(save / "after" / name)
        same = a == b
        bad += not same
        diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        how = ""
        cal_a, cal_b = save / "before" / name / "calibration.json", save / "after" / name / "calibration.json"
        if not same and cal_a.exists() and cal_b.exists():
            cal, eff, verdicts = shifts(cal_a, cal_b)
            how = (f"; D/o/dip moved <= {cal:.3f} std, effect parameters <= {eff:.3f} std, verdicts "
                   f"{'the same' if verdicts else 'DIFFERENT'}")
        print(f"{'same' if same else 'DIFF':4}  {name:60} {len(a)} files" + ("" if same else f"  differ: {diff}{how}"))
    return bad


def main(argv: list[str] | None = None) -> int:
    """Run both sides (or one) and compare."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path)
    ap.add_argument("--after", type=Path, default=ROOT)
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--save", type=Path, default=Path("/tmp/same_outputs"))
    ap.add_argument("--only", choices=("before", "after"))
    ap.add_argument("--compare", action="store_true", help="compare saved sides only")
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    all_logs = logs(args.realdata)
    names = [key(p) for p in all_logs]
    sides = [args.only] if args.only else ["before", "after"]
    if not args.compare:
        for side in sides:
            package = args.before if side == "before" else args.after
            if package is None:
                ap.error("--before DIR is needed to run the before side")
            outs = [args.save / side / key(p) for p in all_logs]
            with ThreadPoolExecutor(args.jobs) as pool:
                runs = list(pool.map(run_side, [package] * len(all_logs), all_logs, outs))
            total = sum(float(r["seconds"]) for r in runs)  # type: ignore[arg-type]
            print(f"{side}: {len(runs)} fits, {total:.0f} s of fitting", file=sys.stderr)
        if args.only:
            return 0
    bad = compare(args.save, names)
    print(json.dumps({"logs": len(names), "differ": bad}))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
