"""Accuracy and honesty of a method on N seeds of the `handheld` scenario (issue 2's acceptance numbers).

Prints the median and max of: relative Frobenius error of D, |o - o_true| / |field|, misalignment angle
error (deg), dip error (deg); and the share of scalar parameters (D, o, dip) within 3 reported std.

    python benchmarks/handheld_accuracy.py [--seeds 20] [--method kok2012]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.methods.table import METHODS
from magcal_cli.pipeline import select_problem
from magcal_cli.registry import resolve
from magcal_cli.synth.simulate import simulate


def main() -> None:
    """Run the study and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--method", default="kok2012", choices=sorted(METHODS))
    ap.add_argument("--scenario", default="handheld")
    args = ap.parse_args()
    run = resolve(METHODS[args.method].run, f"the {args.method} method")
    rows, inside, total, times = [], 0, 0, []
    for seed in range(args.seeds):
        sim = simulate(args.scenario, seed)
        tr = sim.truth
        cfg = Config(method=args.method)
        t0 = time.perf_counter()
        fit = run(select_problem(sim.recording, cfg), cfg).mags[0]
        times.append(time.perf_counter() - t0)
        est = np.concatenate([fit.D.ravel(order="F"), fit.o, [fit.dip]])
        true = np.concatenate([tr.D.ravel(order="F"), tr.o, [tr.dip]])
        z = (est - true) / np.sqrt(np.diag(fit.cov)[:13])
        inside += int(np.sum(np.abs(z) <= 3.0))
        total += z.size
        rows.append([np.linalg.norm(fit.D - tr.D) / np.linalg.norm(tr.D),
                     np.linalg.norm(fit.o - tr.o) / tr.field_strength,
                     np.rad2deg(so3.angle(so3.polar(fit.D)[0].T @ so3.polar(tr.D)[0])),
                     abs(np.rad2deg(fit.dip - tr.dip))])
    a = np.array(rows)
    print(f"{args.method} on {args.seeds} seeds of '{args.scenario}' "
          f"(median fit time {np.median(times) * 1e3:.0f} ms)")
    print(f"{'metric':<34}{'median':>12}{'max':>12}")
    names = ["relative Frobenius error of D", "|o - o_true| / |field|", "misalignment angle error [deg]",
             "dip error [deg]"]
    for name, col in zip(names, a.T, strict=True):
        print(f"{name:<34}{np.median(col):>12.4g}{col.max():>12.4g}")
    print(f"scalar parameters within 3 reported std: {inside}/{total} = {100 * inside / total:.1f} %")


if __name__ == "__main__":
    main()
