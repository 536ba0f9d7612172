"""Speed of the joint MAP with effect terms against the base model, same log, same process.

The paper protocol, 5 minutes at 62.5 Hz with the magnetometer every 3rd sample (6,250 epochs), with current
interference, temperature drift and a gyro scale injected (a time offset is not testable on this protocol: its
rotation rates are constant, so a delay is a mounting rotation); fitted with no effects and with those three terms.
Target (issue 10): no effects as fast as before (<= 0.5 s per magnetometer), three effects <= 2x that.

    python benchmarks/bench_effects.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from magcal_cli.config import Config
from magcal_cli.models.map import fit as mapm
from magcal_cli.pipeline import select_problem
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.simulate import simulate

RATE, DECIMATE = 62.5, 3
THREE = ("current_interference", "temperature_drift", "gyro_scale")


def main() -> None:
    """Median wall time of fit_map without and with three effects."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    sim = simulate("paper", 0, RATE, RATE / DECIMATE, 300.0, effects=tuple(EffectSpec(e) for e in THREE))
    clean = select_problem(simulate("paper", 0, RATE, RATE / DECIMATE, 300.0).recording, Config())
    problem = select_problem(sim.recording, Config())
    out = {}
    for label, effects in (("clean", ()), ("none", ()), ("three", THREE)):
        prob = clean if label == "clean" else problem
        mag = prob.mags[0]
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            est = mapm.fit_map(prob, mag, effects=effects)
            times.append(time.perf_counter() - t0)
        out[label] = float(np.median(times))
        status = ", ".join(f"{e.id} {e.status}" for e in est.effects) or "base model"
        print(f"{label:>5}: median {out[label]:.3f} s over {args.repeats} runs ({mag.t.size} epochs; {status})")
    print("clean: the same log without the injected effects; none: with them, base model only")
    print(f"ratio three effects / clean base model: {out['three'] / out['clean']:.2f}x (target <= 2x; "
          "base model target <= 0.5 s)")


if __name__ == "__main__":
    main()
