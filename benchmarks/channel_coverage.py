"""Effect coverage when the effect's channel is logged at other instants than the magnetometer (issue 38 item 8).

The hand-held logs of ../shared/independent (a simulator that shares nothing with magcal) get an injected term:
current interference c I(t) with a flight's current (magcal's power model, a random profile per seed, c 2 % of the
field at 20 A in a random direction), or a temperature drift k (T(t) - 25 degC) of a warm-up with random start,
end and time constant. The field is added at the readings' own stamps; the channel is logged at `--rate` Hz
(0: at the readings' stamps, as magcal's own simulations log it) with 0.05 A or 0.05 degC of noise. Each seed is
fitted with `--effects ID` (or the default diagnosis, --auto) and z = (fitted - true) / std per component.

    python benchmarks/channel_coverage.py LOGDIR EFFECT RATE SEEDS [--auto] [--out PREFIX]
    PYTHONPATH=/tmp/before python benchmarks/channel_coverage.py ...    # an older checkout's package
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.config import Config
from magcal_cli.pipeline import calibrate_recording
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind, Stream
from magcal_cli.synth import physics as phys


def one(rec0: Any, kind: str, rate: float, seed: int, auto: bool) -> dict[str, Any]:
    """Inject, fit and score one seed."""
    rng = np.random.default_rng(seed)
    mag = next(s for s in rec0.streams if s.kind is Kind.MAGNETOMETER)
    dur = float(mag.t[-1]) + 2.0
    field = float(np.median(np.linalg.norm(mag.values, axis=1)))
    c = rng.normal(0.0, 1.0, 3)
    c *= 0.02 * field / (np.linalg.norm(c) * 20.0)
    if kind == "current_interference":
        signal, chan, unit, name, ref = phys.power(rng, dur).current, Kind.BATTERY_CURRENT, "A", "c", 0.0
    else:
        signal = phys.temperature(dur, rng.uniform(15, 30), rng.uniform(35, 50), rng.uniform(30, 300))
        chan, unit, name, ref = Kind.TEMPERATURE, "degC", "k", 25.0
    t_aux = mag.t if rate <= 0 else np.arange(0.0, dur - 1.0, 1.0 / rate)
    y = mag.values + (signal(mag.t) - ref)[:, None] * c[None, :]
    aux = Stream(chan, "/aux", t_aux, (signal(t_aux) + 0.05 * rng.standard_normal(t_aux.size))[:, None],
                 "inject#/aux", unit)
    streams = tuple(Stream(s.kind, s.id, s.t, y, s.source, s.native_unit) if s is mag else s for s in rec0.streams)
    res = calibrate_recording(replace(rec0, streams=(*streams, aux)),
                              Config(diagnose=auto, effects=() if auto else (kind,)))
    found = [e for e in res.calibration.effects if e["id"] == kind and e["status"] in ("accepted", "ambiguous")]
    if not found:
        return {"seed": seed, "z": None}
    f = found[0]
    true = c * units.from_si(units.canonical(mag.native_unit))
    z = (np.asarray(f["params"][name], dtype=float) - true) / np.asarray(f["std"][name], dtype=float)
    return {"seed": seed, "z": [float(v) for v in z]}


def main() -> None:
    """Run the seeds, print each z and the coverage."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logdir", type=Path)
    ap.add_argument("effect", choices=("current_interference", "temperature_drift"))
    ap.add_argument("rate", type=float)
    ap.add_argument("seeds", type=int)
    ap.add_argument("--auto", action="store_true")
    ap.add_argument("--out", type=Path, default=None, help="a .json file for the rows")
    args = ap.parse_args()
    rec0 = open_recording(next(p for p in args.logdir.iterdir() if p.name.startswith("log")))
    rows = []
    for seed in range(args.seeds):
        rows.append(one(rec0, args.effect, args.rate, seed, args.auto))
        print(rows[-1], flush=True)
    z = np.abs(np.array([v for r in rows if r["z"] for v in r["z"]]))
    summary = {"log": args.logdir.name, "effect": args.effect, "rate_hz": args.rate, "auto": args.auto,
               "components": int(z.size), "covered": float(np.mean(z <= 1.96)) if z.size else None,
               "max_abs_z": float(z.max()) if z.size else None, "not_found": sum(r["z"] is None for r in rows)}
    print(summary)
    if args.out is not None:
        args.out.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
