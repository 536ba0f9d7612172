"""Speed of the joint MAP calibration (`--method map`) on the paper's real-data setting, simulated.

1. One magnetometer, 5 minutes at 62.5 Hz with the magnetometer decimated x3 (6,250 epochs): median wall time
   of the whole fit (initial values, noise re-estimation rounds, covariance) over repeated runs.
2. 30 magnetometers on one IMU (the paper's real setup): total time of `map_run.run`.
3. The identical problem and start (noise levels fixed) solved by `scipy.optimize.least_squares` (trf, sparse
   analytic Jacobian, states as a chart R0 Exp(phi)): time until it reaches magcal's final cost.
4. Runtime against duration (1, 5, 20 minutes).

    python benchmarks/bench_map.py [--repeats 7] [--skip-scipy]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magcal_cli import so3  # noqa: E402
from magcal_cli.config import Config  # noqa: E402
from magcal_cli.methods import map_run  # noqa: E402
from magcal_cli.models.epochs import epochs_for, initial_noise  # noqa: E402
from magcal_cli.models.factor import Factor  # noqa: E402
from magcal_cli.models.map import fit as mapm  # noqa: E402
from magcal_cli.models.map import init as map_init  # noqa: E402
from magcal_cli.models.map.cost import make_linearize  # noqa: E402
from magcal_cli.models.map.start import FitSettings, initial_state  # noqa: E402
from magcal_cli.models.solve import Options, solve  # noqa: E402
from magcal_cli.pipeline import select_problem  # noqa: E402
from magcal_cli.synth.simulate import paper_trajectory, simulate  # noqa: E402
from tests.models.mapsim import record  # noqa: E402

RATE, DECIMATE = 62.5, 3


def paper_problem(minutes: float, seed: int = 0):  # noqa: ANN201
    """The paper protocol at 62.5 Hz, magnetometer every 3rd sample, `minutes` long."""
    sim = simulate("paper", seed, RATE, RATE / DECIMATE, minutes * 60.0)
    return select_problem(sim.recording, Config())


def timed(fn, repeats: int) -> tuple[float, list[float], float]:  # noqa: ANN001
    """Median and all wall times (s) of fn(), and the median CPU time of this process (s)."""
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(times)), times, float(np.median(cpu))


def sparse_jacobian(factors: list[Factor], n: int, p: int, phi: np.ndarray) -> sparse.csr_matrix:
    """d r / d (phi, dtheta) for states R0 Exp(phi): the right-perturbation blocks times J_r(phi_k)."""
    jr = so3.right_jacobian(phi)
    rows, cols, vals = [], [], []
    offset = 0
    for f in factors:
        m, k = f.r.shape
        row = offset + np.arange(m)[:, None] * k + np.arange(k)[None, :]            # (m, k)
        for jx, idx in ((f.J_x, f.idx), (f.J_next, None if f.idx is None else f.idx + 1)):
            if jx is None or idx is None:
                continue
            block = jx @ jr[idx]                                                   # (m, k, 3)
            rows.append(np.broadcast_to(row[:, :, None], block.shape).ravel())
            cols.append(np.broadcast_to((3 * idx)[:, None, None] + np.arange(3), block.shape).ravel())
            vals.append(block.ravel())
        if f.J_theta is not None:
            tc = np.arange(p) if f.theta_cols is None else f.theta_cols
            block = f.J_theta
            rows.append(np.broadcast_to(row[:, :, None], block.shape).ravel())
            cols.append(np.broadcast_to(3 * n + tc[None, None, :], block.shape).ravel())
            vals.append(block.ravel())
        offset += m * k
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(offset, 3 * n + p))


def scipy_comparison(problem) -> dict[str, float]:  # noqa: ANN001
    """magcal's solver and scipy's trf on the same fixed-noise problem from the same start."""
    mag = problem.mags[0]
    intr = map_init.intrinsic_fit(mag.xyz, "bench")
    ep = epochs_for(problem, mag, intr.scale)
    noise = initial_noise(problem, mag, intr.scale, intr.residual_rms)
    states0, theta0, pre, _ = initial_state(problem, ep, intr, noise, FitSettings(), {})
    lin = make_linearize(ep, pre, noise)
    n, p = states0.shape[0], theta0.size
    t0 = time.perf_counter()
    sol = solve(lin, states0, theta0, Options(max_iterations=100))
    t_magcal = time.perf_counter() - t0
    target = sol.cost
    trace: list[tuple[float, float]] = []
    start = time.perf_counter()

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        phi = x[:3 * n].reshape(n, 3)
        return states0 @ so3.exp(phi), theta0 + x[3 * n:], phi

    def fun(x: np.ndarray) -> np.ndarray:
        s, th, _ = unpack(x)
        r = np.concatenate([f.r.ravel() for f in lin(s, th, False)])
        trace.append((time.perf_counter() - start, 0.5 * float(r @ r)))
        return r

    def jac(x: np.ndarray) -> sparse.csr_matrix:
        s, th, phi = unpack(x)
        return sparse_jacobian(list(lin(s, th, True)), n, p, phi)

    res = least_squares(fun, np.zeros(3 * n + p), jac=jac, method="trf", tr_solver="lsmr", x_scale="jac",
                        ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=300)
    t_total = time.perf_counter() - start
    reached = [t for t, c in trace if c <= target * (1.0 + 1e-6)]
    return {"epochs": float(n), "magcal_s": t_magcal, "magcal_cost": target,
            "magcal_iterations": sol.iterations, "scipy_s_to_cost": reached[0] if reached else float("nan"),
            "scipy_total_s": t_total, "scipy_final_cost": float(res.cost), "scipy_nfev": float(res.nfev)}


def thirty_magnetometers(minutes: float = 5.0, n_mags: int = 30) -> tuple[float, int]:
    """Total time of map_run.run for n_mags magnetometers (different D, o) on one simulated IMU."""
    rng = np.random.default_rng(7)
    rot = paper_trajectory(rng, RATE, minutes * 60.0)
    problem, _, _ = record(rot, RATE, 7, mag_step=DECIMATE, n_mags=n_mags)
    t0 = time.perf_counter()
    result = map_run.run(problem, Config(method="map"))
    return time.perf_counter() - t0, len(result.mags)


def main() -> None:
    """Print every number."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--skip-scipy", action="store_true")
    args = ap.parse_args()
    load = os.getloadavg()
    print(f"machine: {os.cpu_count()} cores, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} "
          "(1/5/15 min)")
    problem = paper_problem(5.0)
    mag = problem.mags[0]
    mapm.fit_map(problem, mag)                                                     # warm-up (imports, caches)
    med, times, cpu = timed(lambda: mapm.fit_map(problem, mag), args.repeats)
    print(f"1 magnetometer, 5 min at 62.5 Hz / 3 ({mag.t.size} epochs): median wall {med:.3f} s over "
          f"{args.repeats} runs (min {min(times):.3f}, max {max(times):.3f}; CPU {cpu:.3f} s); "
          "target <= 0.5 s")
    c0 = time.process_time()
    total, count = thirty_magnetometers()
    print(f"{count} magnetometers on one IMU, 5 min each: total wall {total:.2f} s "
          f"({total / count:.3f} s each; CPU {time.process_time() - c0:.2f} s); target <= 15 s")
    if not args.skip_scipy:
        c = scipy_comparison(problem)
        n_unknowns = 3 * int(c["epochs"]) + 19
        print(f"same problem and start, noise fixed ({int(c['epochs'])} epochs, {n_unknowns} unknowns): "
              f"magcal solve {c['magcal_s']:.3f} s ({int(c['magcal_iterations'])} iterations, cost "
              f"{c['magcal_cost']:.6f})")
        if np.isfinite(c["scipy_s_to_cost"]):
            print(f"  scipy least_squares trf/lsmr reached that cost after {c['scipy_s_to_cost']:.2f} s: "
                  f"magcal {c['scipy_s_to_cost'] / c['magcal_s']:.1f}x faster; target >= 5x")
        else:
            print(f"  scipy least_squares trf/lsmr never reached it: {int(c['scipy_nfev'])} evaluations in "
                  f"{c['scipy_total_s']:.1f} s ended at cost {c['scipy_final_cost']:.6f}; magcal > "
                  f"{c['scipy_total_s'] / c['magcal_s']:.0f}x faster; target >= 5x")
    print("duration  epochs  wall s   CPU s  CPU ms per 1000 epochs  iterations")
    for minutes in (1.0, 5.0, 20.0):
        prob = paper_problem(minutes)
        its: list[int] = []
        med, _, cpu = timed(lambda p=prob, out=its: out.append(mapm.fit_map(p, p.mags[0]).iterations), 3)
        k = prob.mags[0].t.size
        print(f"{minutes:5.0f} min  {k:6d}  {med:6.3f}  {cpu:6.3f}  {1e6 * cpu / k:22.1f}  {its[-1]:10d}")


if __name__ == "__main__":
    main()
