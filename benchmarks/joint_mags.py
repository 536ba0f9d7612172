"""One joint fit for 30 magnetometers on one IMU against 30 separate fits (issue 14 item 3), side by side.

Huang et al. 2025's board: 30 magnetometers on one IMU, simulated with the paper protocol for 5 minutes at
62.5 Hz with the magnetometers every 3rd sample (6,250 epochs, as benchmarks/bench_map.py), every magnetometer
with its own D and o (synth.array.simulate_array). For each seed, in one process and one after the other:
- separate: `map.fit.fit_map` per magnetometer, later ones starting from the first one's IMU noise levels and
  sharing its preintegration (what `map_run.run` did before the joint fit: today's cost);
- joint: `map_run.run` with `--method map` (the joint fit, the consistency check and the assembly).
Printed: wall and CPU time of each, and per method the RMS error against the truth of D, o (uT) and dip (deg)
over the 30 magnetometers, the mean NEES of (vec D, o, dip) (13 for an honest covariance) and the share of
magnetometers inside the 95 % ellipsoid, and the IMU bias errors in units of their std.

    python benchmarks/joint_mags.py [--seeds 2] [--mags 30] [--minutes 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magcal_cli.config import Config  # noqa: E402
from magcal_cli.methods import map_run  # noqa: E402
from magcal_cli.models.map.fit import fit_map  # noqa: E402
from magcal_cli.models.result import MagFit  # noqa: E402
from magcal_cli.pipeline import select_problem  # noqa: E402
from magcal_cli.synth.array import simulate_array  # noqa: E402
from magcal_cli.synth.simulate import Truth  # noqa: E402

RATE, DECIMATE = 62.5, 3


def separate(problem) -> tuple[list[MagFit], np.ndarray, np.ndarray]:  # noqa: ANN001
    """Today's path: one fit_map per magnetometer (IMU levels and preintegration from the first)."""
    ests, cache = [], {}
    for m in problem.mags:
        ests.append(fit_map(problem, m, imu_start=ests[0].noise if ests else None, cache=cache))
    best = min(ests, key=lambda e: float(np.sum(e.std_of("gyroscope_bias"))))
    fits = [map_run.to_fits(e, s) for e, s in zip(ests, problem.mags, strict=True)]
    return fits, np.concatenate([best.value("accelerometer_bias"), best.value("gyroscope_bias")]), \
        np.concatenate([best.std_of("accelerometer_bias"), best.std_of("gyroscope_bias")])


def scores(fits: list[MagFit], truths: tuple[Truth, ...]) -> dict[str, float]:
    """RMS errors of D, o (uT), dip (deg) over all magnetometers, mean NEES and 95 % coverage of (D, o, dip)."""
    ed, eo, edip, nees = [], [], [], []
    for f, t in zip(fits, truths, strict=True):
        e = np.concatenate([(f.D - t.D).ravel(order="F"), f.o - t.o, [f.dip - t.dip]])
        ed.append(e[:9])
        eo.append(e[9:12])
        edip.append(e[12])
        nees.append(float(e @ np.linalg.solve(f.cov, e)))
    nees_a = np.array(nees)
    return {"D_uT": 1e6 * float(np.sqrt(np.mean(np.square(ed)))), "o_uT": 1e6 * float(np.sqrt(np.mean(np.square(eo)))),
            "dip_deg": float(np.degrees(np.sqrt(np.mean(np.square(edip))))), "nees": float(nees_a.mean()),
            "inside95": float(np.mean(nees_a < stats.chi2.ppf(0.95, 13)))}


def timed(fn):  # noqa: ANN001, ANN201
    """fn(), its wall and CPU time (s)."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def line(name: str, s: dict[str, float], imu_z: np.ndarray, wall: float, cpu: float) -> str:
    """One printed row."""
    return (f"  {name:8s} wall {wall:6.2f} s  CPU {cpu:6.2f} s | RMS error D {s['D_uT']:.5f} uT  o {s['o_uT']:.6f} uT  "
            f"dip {s['dip_deg']:.5f} deg | mean NEES {s['nees']:5.2f} (13)  inside 95 %: {100 * s['inside95']:3.0f} % | "
            f"IMU bias |error|/std max {float(np.max(np.abs(imu_z))):.2f}")


def main() -> None:
    """Print every number."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--mags", type=int, default=30)
    ap.add_argument("--minutes", type=float, default=5.0)
    args = ap.parse_args()
    load = os.getloadavg()
    print(f"machine: {os.cpu_count()} cores, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (1/5/15 min)")
    warm = simulate_array("paper", 99, 2, RATE, RATE / DECIMATE, 30.0)
    map_run.run(select_problem(warm.recording, Config()), Config(method="map"))          # imports, caches
    totals: dict[str, list[float]] = {"separate": [], "joint": []}
    ratios: dict[str, list[float]] = {"D_uT": [], "o_uT": [], "dip_deg": []}
    for seed in range(args.seeds):
        sim = simulate_array("paper", seed, args.mags, RATE, RATE / DECIMATE, 60.0 * args.minutes)
        problem = select_problem(sim.recording, Config())
        truth = sim.truths[0]
        bias_true = np.concatenate([truth.accel_bias, truth.gyro_bias])
        print(f"seed {seed}: {args.mags} magnetometers, {args.minutes:g} min at {RATE} Hz / {DECIMATE} "
              f"({problem.mags[0].t.size} epochs each)")
        (fits_s, bias_s, std_s), wall_s, cpu_s = timed(lambda p=problem: separate(p))
        result, wall_j, cpu_j = timed(lambda p=problem: map_run.run(p, Config(method="map")))
        imu = result.imu
        assert imu.accel_bias is not None and imu.gyro_bias is not None
        assert imu.accel_bias_std is not None and imu.gyro_bias_std is not None
        bias_j = np.concatenate([imu.accel_bias, imu.gyro_bias])
        std_j = np.concatenate([imu.accel_bias_std, imu.gyro_bias_std])
        sc_s, sc_j = scores(fits_s, sim.truths), scores(list(result.mags), sim.truths)
        print(line("separate", sc_s, (bias_s - bias_true) / std_s, wall_s, cpu_s))
        print(line("joint", sc_j, (bias_j - bias_true) / std_j, wall_j, cpu_j))
        joint_notes = [n for n in result.notes if "joint" in n]
        print(f"  joint: {'; '.join(joint_notes)}")
        print(f"  ratio joint/separate: time {wall_j / wall_s:.2f} (CPU {cpu_j / cpu_s:.2f}); error D "
              f"{sc_j['D_uT'] / sc_s['D_uT']:.2f}, o {sc_j['o_uT'] / sc_s['o_uT']:.2f}, dip "
              f"{sc_j['dip_deg'] / sc_s['dip_deg']:.2f}")
        cons = [f.message for f in result.findings if f.code.startswith("magnetometer_")]
        print(f"  consistency: {cons[0] if cons else 'none'}")
        totals["separate"].append(wall_s)
        totals["joint"].append(wall_j)
        for k in ratios:
            ratios[k].append(sc_j[k] / sc_s[k])
    load = os.getloadavg()
    print(f"median wall: separate {np.median(totals['separate']):.2f} s, joint {np.median(totals['joint']):.2f} s "
          f"(target <= 5 s); median error ratio joint/separate: D {np.median(ratios['D_uT']):.2f}, "
          f"o {np.median(ratios['o_uT']):.2f}, dip {np.median(ratios['dip_deg']):.2f} (target <= 1)")
    print(f"load average at the end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
