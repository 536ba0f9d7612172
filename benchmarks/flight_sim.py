"""Simulated flights with known truth: is `magcal fit` honest in flight (issue 12)?

For each scenario (multirotor: tilt within about 22 deg, the accelerometer senses thrust, GPS logged; rover:
tilt within 5 deg) and seed, the DataFlash log `magcal simulate` writes is fitted with the base model and with
`--effects nongravity_acceleration`. Printed per fit: the largest |error / reported std| over D, o, dip and the
IMU biases (issue 12 asks for <= 5 on every parameter), the D and o errors, the dip error, what was held at a
prior, and the fit time.

    python benchmarks/flight_sim.py [--seeds 5] [--out docs/results/flight_sim]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli import __version__
from magcal_cli.calibration.document import dumps_json, load
from magcal_cli.config import Config
from magcal_cli.errors import MagcalError
from magcal_cli.pipeline import calibrate
from magcal_cli.readers import open_recording
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.simulate import simulate, truth_calibration

SCENARIOS = ("multirotor", "rover")
#: the fits compared: name -> Config; "auto" (magcal fit's default, with the diagnosis) only with --auto
VARIANTS: dict[str, Config] = {"none": Config(effects=()),
                               "nongravity_acceleration": Config(effects=("nongravity_acceleration",)),
                               "attitude": Config(method="attitude"),
                               "auto": Config(diagnose=True)}


def one(scenario: str, seed: int, variant: str, folder: Path) -> dict[str, Any]:
    """Simulate (once per scenario and seed), fit, and score against the truth."""
    log = folder / f"{scenario}-{seed}.bin"
    if not log.exists():
        sim = simulate(scenario, seed)
        write_log(sim, log)
        truth_doc = truth_calibration(sim, open_recording(log), __version__, "")
        Path(f"{log}.truth.json").write_text(dumps_json(truth_doc))
    truth = load(Path(f"{log}.truth.json"))
    t0 = time.perf_counter()
    try:
        res = calibrate(log, VARIANTS[variant])
    except MagcalError as exc:
        return {"scenario": scenario, "seed": seed, "variant": variant, "error": str(exc),
                "seconds": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    m, tm = res.calibration.magnetometers[0], truth.magnetometers[0]
    z = {"D": np.abs((m.D - tm.D) / m.std_of("D")).max(), "o": np.abs((m.o - tm.o) / m.std_of("o")).max(),
         "dip": abs(m.dip_deg - tm.dip_deg) / float(m.std_of("dip"))}
    imu, ti = res.calibration.imu, truth.imu
    for k in ("accelerometer_bias", "gyroscope_bias"):
        est, std, tv = getattr(imu, k), getattr(imu, f"{k}_std"), getattr(ti, k)
        if est is not None and std is not None and tv is not None:
            z[k] = float(np.abs((np.asarray(est) - tv) / std).max())
    return {"scenario": scenario, "seed": seed, "variant": variant, "seconds": seconds,
            "max_abs_z": {k: float(v) for k, v in z.items()},
            "D_err_pct": float(100 * np.linalg.norm(m.D - tm.D) / np.linalg.norm(tm.D)),
            "o_err_pct": float(100 * np.linalg.norm(m.o - tm.o) / tm.field_strength),
            "dip_err_deg": float(m.dip_deg - tm.dip_deg), "held": [h["parameter"] for h in m.held]}


def markdown(rows: list[dict[str, Any]]) -> str:
    """One line per fit and a summary per scenario and effect set."""
    lines = ["| scenario | seed | fit | max abs z (D, o, dip, b_a, b_g) | D err % | o err % | dip err deg | "
             "held | s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scenario']} | {r['seed']} | {r['variant']} | refused: "
                         f"{r['error'][:150]} | | | | | {r['seconds']:.1f} |")
            continue
        z = r["max_abs_z"]
        lines.append(f"| {r['scenario']} | {r['seed']} | {r['variant']} | "
                     + ", ".join(f"{z.get(k, float('nan')):.1f}" for k in
                                 ("D", "o", "dip", "accelerometer_bias", "gyroscope_bias"))
                     + f" | {r['D_err_pct']:.3f} | {r['o_err_pct']:.3f} | {r['dip_err_deg']:+.2f} | "
                       f"{', '.join(r['held']) or '-'} | {r['seconds']:.1f} |")
    lines += ["", "| scenario | fit | fits with every abs z <= 5 (D, o, dip; and IMU biases where estimated) | "
              "worst abs z |", "|---|---|---|---|"]
    for sc in SCENARIOS:
        for var in VARIANTS:
            sel = [r for r in rows if r["scenario"] == sc and r["variant"] == var]
            if sel:
                worst = [max(r["max_abs_z"].values()) if "max_abs_z" in r else float("inf") for r in sel]
                lines.append(f"| {sc} | {var} | {sum(w <= 5 for w in worst)}/{len(sel)} | {max(worst):.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Run the seeds, print and save."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path("docs/results/flight_sim"))
    ap.add_argument("--auto", action="store_true", help="also magcal fit's default (--effects auto: slow)")
    args = ap.parse_args()
    variants = [v for v in VARIANTS if v != "auto" or args.auto]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for sc in SCENARIOS:
            for seed in range(args.seeds):
                for var in variants:
                    rows.append(one(sc, seed, var, Path(tmp)))
                    print(rows[-1], flush=True)
    table = markdown(rows)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
    args.out.with_suffix(".md").write_text(
        f"# Simulated flights: honest in flight?\n\n`python benchmarks/flight_sim.py --seeds {args.seeds}"
        f"{' --auto' if args.auto else ''}`: DataFlash logs from `magcal simulate --scenario multirotor|rover`, "
        "fitted with the base model (`none`), with `nongravity_acceleration` (GPS-differentiated acceleration), "
        "against the vehicle's attitude and the WMM (`attitude`; the simulated ATT is the true attitude)"
        f"{' and with the default `--effects auto`' if args.auto else ''}. max abs z: the largest |error / "
        "reported std| within each block (the attitude method estimates no IMU biases).\n\n" + table)


if __name__ == "__main__":
    main()
