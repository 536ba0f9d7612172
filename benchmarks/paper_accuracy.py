"""Huang et al. 2025 simulation protocol (methods.md section 5): joint MAP versus Kok 2012 in magcal.

For each seed: `synth.simulate.simulate("paper", seed)`, both methods on the same Problem (Kok 2012 uses
quasi-static verticals: the protocol has no still segment). Prints per parameter group
  - RMSE over the seeds (Kok 2012 does not estimate b_a and b_g: its error there is the bias itself),
  - mean NEES of the MAP estimate with its 95 % chi-square band (consistency of the reported covariance),
  - RMSE^2 / CRLB, the CRLB from the Fisher information at the truth (true trajectory, truth, true noise).

    python benchmarks/paper_accuracy.py [--seeds 20] [--duration S] [--rate HZ] [--mag-rate HZ]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
from scipy import stats

from magcal_cli.config import Config
from magcal_cli.models import kok2012
from magcal_cli.models.epochs import Noise
from magcal_cli.models.map import fit as mapm
from magcal_cli.pipeline import select_problem
from magcal_cli.synth.simulate import Simulation, simulate

#: parameter groups of theta = (b_a, b_g, vec D, o, dip) and the unit they are printed in
GROUPS = {"b_a": (slice(0, 3), 1.0, "m/s^2"), "b_g": (slice(3, 6), 1.0, "rad/s"),
          "D": (slice(6, 15), 1e6, "uT"), "o": (slice(15, 18), 1e6, "uT"), "dip": (slice(18, 19), 1.0, "rad")}


@dataclass
class SeedResult:
    """Errors of both methods and the MAP covariance and CRLB for one seed."""

    seed: int
    err_map: np.ndarray
    err_kok: np.ndarray
    cov_map: np.ndarray
    crlb: np.ndarray
    time_map: float
    time_kok: float


def truth_vector(sim: Simulation) -> np.ndarray:
    """theta of the simulation's truth (SI)."""
    return sim.truth.theta


def run_seed(seed: int, duration: float | None = None, rate: float | None = None,
             mag_rate: float | None = None) -> SeedResult:
    """Both methods and the Cramer-Rao bound on one simulated recording."""
    sim = simulate("paper", seed, rate, mag_rate, duration)
    problem = select_problem(sim.recording, Config())
    mag = problem.mags[0]
    truth = truth_vector(sim)
    t0 = time.perf_counter()
    est = mapm.fit_map(problem, mag)
    t1 = time.perf_counter()
    kok = kok2012.run(problem, Config(method="kok2012"))
    t2 = time.perf_counter()
    fit = kok.mags[0]
    kok_theta = np.concatenate([np.zeros(3) if kok.imu.accel_bias is None else kok.imu.accel_bias,
                                np.zeros(3) if kok.imu.gyro_bias is None else kok.imu.gyro_bias,
                                fit.D.ravel(order="F"), fit.o, [fit.dip]])
    sd = sim.truth.noise_std
    noise = Noise(np.full(3, sd["accelerometer"]), np.full(3, sd["gyroscope"]),
                       np.full(3, sd["magnetometer"]))
    step = int(round(sim.recording.streams[0].rate_hz / mag.rate_hz))
    states = sim.rotations[::step][: est.epochs.size]
    crlb = mapm.information_at(problem, mag, states, truth, noise)
    return SeedResult(seed, est.theta - truth, kok_theta - truth, est.cov, crlb, t1 - t0, t2 - t1)


def table(results: list[SeedResult]) -> str:
    """The comparison table: RMSE (MAP, Kok), mean NEES with its band, RMSE^2/CRLB with a 95 % interval."""
    n = len(results)
    lines = [f"{n} seeds; RMSE is the root of the mean (over seeds) of the squared error norm of the group; "
             "95% CI: where RMSE^2/CRLB of an efficient estimator falls; std/CRLB: reported std over CRLB "
             "std "
             "(geometric mean over seeds and entries)",
             f"{'group':6} {'RMSE map':>12} {'RMSE kok2012':>13} {'unit':6} {'map<=kok':>8} "
             f"{'mean NEES':>10} {'95% band':>15} {'RMSE^2/CRLB':>12} {'95% CI':>14} {'std/CRLB':>10}"]
    for name, (sl, f, unit) in GROUPS.items():
        dim = sl.stop - sl.start
        e_map = np.array([r.err_map[sl] for r in results])
        e_kok = np.array([r.err_kok[sl] for r in results])
        rmse_map = float(np.sqrt(np.mean(np.sum(e_map**2, axis=1))))
        rmse_kok = float(np.sqrt(np.mean(np.sum(e_kok**2, axis=1))))
        nees = np.array([r.err_map[sl] @ np.linalg.solve(r.cov_map[sl, sl], r.err_map[sl]) for r in results])
        lo, hi = stats.chi2.ppf([0.025, 0.975], n * dim) / n
        crlb = float(np.mean([np.trace(r.crlb[sl, sl]) for r in results]))
        ratio = rmse_map**2 / crlb
        # for an efficient estimator sum |e|^2 = sum of lambda_i chi2_1 over the CRLB eigenvalues of every
        # seed: Satterthwaite's chi-square with dof (sum lambda)^2 / sum lambda^2 gives its 95 % interval
        lam = np.concatenate([np.linalg.eigvalsh(r.crlb[sl, sl]) for r in results])
        dof = float(lam.sum() ** 2 / np.sum(lam**2))
        c_lo, c_hi = stats.chi2.ppf([0.025, 0.975], dof) / dof
        eff = float(np.exp(np.mean([np.log(np.sqrt(np.diag(r.cov_map[sl, sl]) / np.diag(r.crlb[sl, sl])))
                                    for r in results])))
        lines.append(f"{name:6} {rmse_map * f:12.4g} {rmse_kok * f:13.4g} {unit:6} "
                     f"{'yes' if rmse_map <= rmse_kok else 'NO':>8} {nees.mean():10.2f} "
                     f"[{lo:5.2f}, {hi:5.2f}] {ratio:12.3f} [{c_lo:5.2f}, {c_hi:5.2f}] {eff:10.3f}")
    nees_all = np.array([r.err_map @ np.linalg.solve(r.cov_map, r.err_map) for r in results])
    lo, hi = stats.chi2.ppf([0.025, 0.975], n * 19) / n
    lines.append(f"all 19 parameters: mean NEES {nees_all.mean():.2f} (95 % band [{lo:.2f}, {hi:.2f}])")
    lines.append(f"time per fit: map {np.median([r.time_map for r in results]):.2f} s, "
                 f"kok2012 {np.median([r.time_kok for r in results]):.2f} s (median)")
    return "\n".join(lines)


def main() -> None:
    """Run the study and print the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--rate", type=float, default=None)
    ap.add_argument("--mag-rate", type=float, default=None)
    ap.add_argument("--seed0", type=int, default=0, help="first seed")
    ap.add_argument("--save", default=None, help="also save the per-seed errors and covariances (.npz)")
    args = ap.parse_args()
    results = []
    for seed in range(args.seed0, args.seed0 + args.seeds):
        results.append(run_seed(seed, args.duration, args.rate, args.mag_rate))
        r = results[-1]
        print(f"seed {seed:2d}: map {r.time_map:.2f} s, kok2012 {r.time_kok:.2f} s", flush=True)
    if args.save:
        np.savez(args.save, **{f"{k}_{r.seed}": getattr(r, k) for r in results
                               for k in ("err_map", "err_kok", "cov_map", "crlb")})
    print(table(results))


if __name__ == "__main__":
    main()
