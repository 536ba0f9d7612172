"""Run the concealed-effect suite: simulate each (case, seed) log, fit it, store one JSON record per run.

    python benchmarks/concealed/run.py --seeds 20 --jobs 2 --out out/concealed [--cases a,b] [--effects-arg auto]

`--effects-arg explicit` (the default until the diagnosis lands) fits each case's candidate list
(`Case.candidates`); `auto` or a literal `ID[,ID]` is passed to `magcal fit --effects` as is. Runs whose record
exists are skipped, so an interrupted run resumes. The generator is magcal's simulator (independent physics,
synth_inject.py); nothing here imports the estimator.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cases import CASES, Case, select  # noqa: E402
from truth_score import heading_errors, z_scores  # noqa: E402


def sim_seed(case: Case, seed: int) -> int:
    """The simulator seed of run `seed` of `case`: distinct per case so that negative controls are independent."""
    return (zlib.crc32(case.name.encode()) % 100_000) * 1000 + seed


def effects_value(case: Case, effects_arg: str) -> str:
    """The `magcal fit --effects` value: the case's candidates for "explicit", else `effects_arg` itself."""
    return ",".join(case.candidates) if effects_arg == "explicit" else effects_arg


def record_path(out: Path, case: Case, seed: int) -> Path:
    """Where the record of one run lives."""
    return out / "runs" / case.name / f"{seed:03d}.json"


def concealment(sim: Any) -> dict[str, dict[str, float]]:
    """Per injected effect with an additive term: per-sample visibility v = RMS(term) / noise std (per axis), the
    same after removing the term's mean (which the offset or bias absorbs), and that offset absorption."""
    out: dict[str, dict[str, float]] = {}
    for e in sim.effects:
        term = e.signals.get("term")
        if term is None:
            continue
        noise = sim.truth.noise_std["magnetometer" if e.sensor == "magnetometer" else "accelerometer"]
        raw = float(np.sqrt(np.mean(term**2)) / noise)
        centred = float(np.sqrt(np.mean((term - term.mean(axis=0)) ** 2)) / noise)
        out[e.id] = {"v": round(raw, 4), "v_centred": round(centred, 4),
                     "offset_absorption": round(1.0 - (centred / raw) ** 2, 4) if raw > 0 else 0.0}
    return out


def generate(case: Case, seed: int, log: Path) -> dict[str, Any]:
    """Write the case's log for `seed` (its format: `log`'s suffix) and return its truth document (the reader's ids
    and magnetometer unit) with the concealment figures under "concealment"."""
    from magcal_cli import __version__
    from magcal_cli.calibration.document import dumps_json
    from magcal_cli.readers import open_recording
    from magcal_cli.synth.effects import parse_effect
    from magcal_cli.synth.logs import imu_sampling, write_log
    from magcal_cli.synth.simulate import simulate, truth_calibration

    st = case.settings(seed)
    specs = tuple(parse_effect(e) for e in st.effects)
    sim = simulate(case.scenario, sim_seed(case, seed), st.rate, st.mag_rate, case.duration, effects=specs,
                   power_profile=case.power_profile, imu_sampling=imu_sampling(log), mag_phase_s=st.mag_phase_s,
                   **dict(case.simulate))
    if case.firmware == "stale":
        from magcal_cli.synth.firmware import STALE_CURRENT_COMPENSATION

        sim = replace(sim, previous=STALE_CURRENT_COMPENSATION)
    write_log(sim, log)
    doc = dumps_json(truth_calibration(sim, open_recording(log), __version__, "1970-01-01T00:00:00Z"))
    truth: dict[str, Any] = json.loads(doc)
    truth["concealment"] = concealment(sim)
    return truth


def run_one(case: Case, seed: int, out: Path, effects_arg: str, keep_logs: bool = False) -> dict[str, Any]:
    """Simulate, fit with `magcal fit --effects ...`, write and return the record of one run."""
    work = out / "work" / f"{case.name}-{seed:03d}"
    work.mkdir(parents=True, exist_ok=True)
    st = case.settings(seed)
    log = work / f"log{st.suffix}"
    t0 = time.perf_counter()
    truth = generate(case, seed, log)
    t_sim = time.perf_counter() - t0
    value = effects_value(case, effects_arg)
    cmd = [sys.executable, "-m", "magcal_cli", "fit", str(log), "-o", str(work / "fit"), "--effects", value,
           "--outputs", "json", "--force", "-q"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    t_fit = time.perf_counter() - t0
    effects: list[dict[str, Any]] | None = None
    z: list[list[Any]] | None = None
    heading: dict[str, float] | None = None
    cal = work / "fit" / "calibration.json"
    if proc.returncode in (0, 3) and cal.exists():
        fitted = json.loads(cal.read_text())
        effects = fitted.get("effects", [])
        z = [[s.sensor, s.name, round(s.z, 4)] for s in z_scores(fitted, truth)]
        heading = heading_errors(fitted, truth)
    rec = {"case": case.name, "tier": case.tier, "seed": seed, "sim_seed": sim_seed(case, seed),
           "effects_arg": value, "truth": truth.get("effects", []), "concealment": truth["concealment"],
           "effects": effects, "z": z, "heading_error_deg": heading,
           "settings": {"rate_hz": st.rate, "mag_rate_hz": st.mag_rate, "mag_phase_s": st.mag_phase_s,
                        "format": st.suffix, "imu_sampling": st.convention, "effects": list(st.effects)},
           "exit_code": proc.returncode, "stderr": proc.stderr[-2000:], "runtime_sim_s": round(t_sim, 3),
           "runtime_fit_s": round(t_fit, 3)}
    path = record_path(out, case, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".part")
    tmp.write_text(json.dumps(rec, indent=1))
    tmp.replace(path)
    if not keep_logs:
        shutil.rmtree(work, ignore_errors=True)
    return rec


def _task(args: tuple[str, int, str, str, bool]) -> tuple[str, int, int, float]:
    """One run in a worker process: (case, seed, exit code, fit seconds)."""
    name, seed, out, effects_arg, keep = args
    rec = run_one(CASES[name], seed, Path(out), effects_arg, keep)
    return name, seed, int(rec["exit_code"]), float(rec["runtime_fit_s"])


def run_suite(out: Path, seeds: int, jobs: int, cases: list[Case], effects_arg: str,
              keep_logs: bool = False, first_seed: int = 0) -> int:
    """Run every missing (case, seed); return the number of runs done now."""
    todo = [(c.name, s, str(out), effects_arg, keep_logs) for c in cases
            for s in range(first_seed, first_seed + seeds) if not record_path(out, c, s).exists()]
    t0 = time.perf_counter()
    if jobs <= 1:
        done = map(_task, todo)
        for name, seed, rc, dt in done:
            print(f"{name} seed {seed}: exit {rc}, fit {dt:.1f} s", flush=True)
    else:
        with ProcessPoolExecutor(jobs) as pool:
            for name, seed, rc, dt in pool.map(_task, todo):
                print(f"{name} seed {seed}: exit {rc}, fit {dt:.1f} s", flush=True)
    print(f"{len(todo)} runs in {time.perf_counter() - t0:.0f} s on {jobs} process(es)", flush=True)
    return len(todo)


def main(argv: list[str] | None = None) -> None:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/concealed"))
    ap.add_argument("--cases", default="", help="comma-separated case names or tiers [default: all]")
    ap.add_argument("--effects-arg", default="explicit", help="explicit (each case's candidates), auto, or ID[,ID]")
    ap.add_argument("--keep-logs", action="store_true")
    a = ap.parse_args(argv)
    run_suite(a.out, a.seeds, a.jobs, select(a.cases), a.effects_arg, a.keep_logs, a.first_seed)


if __name__ == "__main__":
    main()
