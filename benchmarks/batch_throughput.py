"""magcal batch throughput (issue 14 item 2): 100 simulated handheld logs of 40-60 s in mixed formats, one of
them corrupt, fitted with 1 and 2 local workers and on a 2-worker local Dask cluster, side by side in one run.

Each configuration runs `magcal batch` as a user would (a subprocess, into its own output folder) and the
benchmark checks that the corrupt log is reported with exit 1 and every other log succeeds. The machine's load
average is recorded around each run: on a shared machine the numbers move with it, so the configurations run
in rounds, in turn and then in reverse order (ABC CBA), and each is summarised by its median.

    python benchmarks/batch_throughput.py [--logs 100] [--rounds 2] [--fit-args "--effects none --outputs json"]

Writes docs/results/batch_throughput.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
#: the log formats, in turn ("" is a ROS 2 bag directory)
FORMATS = (".bin", ".mcap", ".ulg", ".csv", ".bag", "")
CORRUPT = "corrupt.bin"


def make_logs(folder: Path, n: int, seed: int) -> dict[str, int]:
    """n-1 simulated handheld logs (40-60 s, formats in turn) and one corrupt DataFlash log; formats counted."""
    from magcal_cli.synth.logs import imu_sampling, write_log
    from magcal_cli.synth.simulate import simulate

    rng = np.random.default_rng(seed)
    counts: dict[str, int] = {}
    for i in range(n - 1):
        ext = FORMATS[i % len(FORMATS)]
        path = folder / f"log{i:03d}{ext}"
        # the IMU sampled as the format holds it; a CSV log has one row per IMU sample, so its field is on IMU stamps
        sim = simulate("handheld", seed + i, duration=float(rng.uniform(40.0, 60.0)), imu_sampling=imu_sampling(path),
                       mag_phase_s=0.0 if ext == ".csv" else None)
        write_log(sim, path)
        counts[ext or "ros2 bag dir"] = counts.get(ext or "ros2 bag dir", 0) + 1
    (folder / CORRUPT).write_bytes(rng.bytes(200_000))          # no record header anywhere: unusable
    counts["corrupt .bin"] = 1
    return counts


def run_batch(logs: Path, out: Path, how: list[str], fit_args: list[str]) -> dict[str, Any]:
    """One `magcal batch` run; its --json document, wall time, exit code and the load average around it."""
    cmd = [sys.executable, "-m", "magcal_cli", "batch", str(logs), "-o", str(out), *how, *fit_args, "--json", "-q"]
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()
    doc = json.loads(proc.stdout.replace(str(logs), "LOGS"))       # the temporary folder's name says nothing
    entries = doc["logs"]
    bad = [e for e in entries if e["status"] != "ok"]
    corrupt = [e for e in entries if Path(e["log"]).name == CORRUPT]
    return {"command": " ".join(["magcal", "batch", "LOGS", "-o", "OUT", *how, *fit_args, "--json", "-q"]),
            "exit_code": proc.returncode, "wall_s": wall, "batch_s": doc["seconds"],
            "logs_per_min": doc["logs_per_min"], "logs_per_min_wall": 60.0 * len(entries) / wall,
            "counts": doc["counts"], "workers": doc["runner"]["workers"],
            "corrupt": corrupt[0] if corrupt else None,
            "other_failures": [e for e in bad if Path(e["log"]).name != CORRUPT],
            "fit_s_median": float(np.median([e["seconds"] for e in entries if e["status"] == "ok"])),
            "load_before": load0, "load_after": load1, "stderr": proc.stderr[-2000:]}


def dask_run(logs: Path, out: Path, fit_args: list[str]) -> dict[str, Any]:
    """The batch on a local Dask cluster: a scheduler and two single-threaded worker processes on loopback."""
    import distributed

    t0 = time.perf_counter()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None, silence_logs=40) as cluster:
        start_s = time.perf_counter() - t0
        result = run_batch(logs, out, ["--scheduler", cluster.scheduler_address], fit_args)
    result["cluster_start_s"] = start_s
    return result


def median_rate(runs: list[dict[str, Any]]) -> float:
    """A configuration's median throughput over its rounds (logs/min)."""
    return float(np.median([r["logs_per_min"] for r in runs]))


def markdown(res: dict[str, Any]) -> str:
    """The results page."""
    rows = []
    for name, r in sorted(((n, r) for n, runs in res["runs"].items() for r in runs), key=lambda x: x[1]["order"]):
        c = r["corrupt"]
        rows.append(f"| {r['order'] + 1} | {name} | {r['logs_per_min']:.1f} | {r['logs_per_min_wall']:.1f} | "
                    f"{r['batch_s']:.0f} | {r['fit_s_median']:.2f} | {r['counts']['ok']} ok, "
                    f"{r['counts']['failed']} failed | {c['exit_code'] if c else '-'} | {r['exit_code']} | "
                    f"{r['load_before'][0]:.1f} → {r['load_after'][0]:.1f} |")
    medians = {name: median_rate(runs) for name, runs in res["runs"].items()}
    one = medians["1 local worker"]
    summary = "\n".join(f"| {name} | {m:.1f} | {m / one:.2f}× |" for name, m in medians.items())
    corrupt = res["runs"]["1 local worker"][0]["corrupt"]
    starts = ", ".join(f"{r['cluster_start_s']:.1f} s" for r in res["runs"]["2-worker Dask cluster"])
    formats = ", ".join(f"{k} {v}" for k, v in res["formats"].items())
    return f"""# `magcal batch` throughput

`python benchmarks/batch_throughput.py` ({res['date']}, magcal {res['version']}, {res['cores']} cores shared
with other work). {res['logs']} simulated handheld logs of 40–60 s (100 Hz IMU, 50 Hz field; {formats}), one
of them corrupt (200 kB of random bytes named `.bin`), fitted with `{' '.join(res['fit_args'])}` by each
configuration in {res['rounds']} rounds (in turn, then in reverse order), in one run, each into its own output
folder (nothing skipped).

| configuration | median logs/min | relative to 1 worker |
|---|---|---|
{summary}

Every run, in the order they ran:

| # | configuration | logs/min (batch) | logs/min (wall, with start-up) | batch s | median fit s | logs | corrupt log's exit | batch exit | load average (1 min) before → after |
|---|---|---|---|---|---|---|---|---|---|
{chr(10).join(rows)}

The Dask cluster took {starts} to start (not counted). "logs/min (batch)" is the batch's own count over its
own wall time (worker start-up included); "wall" adds the `magcal` process start.

The corrupt log is reported in every configuration with exit 1 and its error line, and every other log
succeeds (batch exit 1: a log could not be fitted):

    Error: {corrupt['error'] if corrupt else '-'}

The machine has {res['cores']} cores shared with other sessions: the load average column says how busy it was, and
two workers cannot reach 2× when other processes take a core. Per-log fit times ("median fit s") grow with the
load for the same reason. The local Dask cluster also runs its scheduler, two nannies and the client on the
same two cores, and each Dask worker imports magcal's modules on its first logs (a local worker is forked from
a server that imported them once); on a real cluster the scheduler and client sit elsewhere and the imports
are paid once per worker for the whole batch.
"""


def main() -> None:
    """Generate the logs, run the three configurations, write the results."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--logs", type=int, default=100)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--fit-args", default="--effects none --outputs json")
    ap.add_argument("--out", type=Path, default=RESULTS / "batch_throughput")
    args = ap.parse_args()
    from magcal_cli import __version__

    fit_args = shlex.split(args.fit_args)
    with tempfile.TemporaryDirectory(prefix="magcal-batch-bench-") as tmp:
        logs = Path(tmp) / "logs"
        logs.mkdir()
        t0 = time.perf_counter()
        formats = make_logs(logs, args.logs, args.seed)
        print(f"{args.logs} logs written in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        configs = ["1 local worker", "2 local workers", "2-worker Dask cluster"]
        runs: dict[str, list[dict[str, Any]]] = {name: [] for name in configs}
        order = 0
        for k in range(args.rounds):
            for name in configs if k % 2 == 0 else configs[::-1]:
                out = Path(tmp) / f"{name.replace(' ', '_')}-{k}"
                r = (dask_run(logs, out, fit_args) if "Dask" in name else
                     run_batch(logs, out, ["--jobs", name.split()[0]], fit_args))
                r["order"], r["round"] = order, k
                order += 1
                runs[name].append(r)
                print(f"{name}: {r['logs_per_min']:.1f} logs/min (load {r['load_before'][0]:.1f})", file=sys.stderr)
    res = {"date": time.strftime("%Y-%m-%d"), "version": __version__, "cores": os.cpu_count(), "logs": args.logs,
           "rounds": args.rounds, "formats": formats, "fit_args": fit_args, "runs": runs}
    for r in (r for rs in runs.values() for r in rs):
        ok = (r["corrupt"] is not None and r["corrupt"]["exit_code"] == 1 and not r["other_failures"]
              and r["counts"]["ok"] == args.logs - 1)
        r["corrupt_reported_rest_ok"] = ok
    args.out.with_suffix(".json").write_text(json.dumps(res, indent=2, default=float) + "\n")
    args.out.with_suffix(".md").write_text(markdown(res))
    print(markdown(res))
    if not all(r["corrupt_reported_rest_ok"] for rs in runs.values() for r in rs):
        sys.exit("a configuration did not report the corrupt log alone")


if __name__ == "__main__":
    main()
