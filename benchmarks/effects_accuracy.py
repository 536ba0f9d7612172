"""Effect plug-ins on simulated logs with known truth: coverage of each effect's parameters, and what leaving the
effect out costs (D, o, dip, heading errors with the term versus without it).

For each effect and seed: the handheld scenario without the effect fitted with the base model (the no-effect
level), the same log with the effect injected fitted with --effects none (the bias it causes) and with
--effects ID (the term). The injection is independent physics (synth/inject.py), not the estimator's term.
`--method` fits with another method (the EKFs carry the additive magnetometer effects); `--skip-none` leaves out
the --effects none fits (the bias an effect causes is the MAP table's, and ekf-ml costs ~40 s a fit).

    python benchmarks/effects_accuracy.py [--seeds 20] [--jobs 2] [--out docs/results/effects_accuracy]
    python benchmarks/effects_accuracy.py --method ekf-aug --effects current_interference,temperature_drift
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.effects import EFFECTS, get
from magcal_cli.effects.base import Target
from magcal_cli.pipeline import calibrate_recording
from magcal_cli.streams import Kind
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.simulate import simulate

#: the truth value of each fitted parameter (SI), by effect: name -> callable(injected params) -> value
TRUTH = {
    "current_interference": {"c": lambda p: p["c"]},
    "throttle_interference": {"c": lambda p: p["c"], "p": lambda p: p["p"]},
    "temperature_drift": {"k": lambda p: p["k"]},
    "time_offset": {"tau_s": lambda p: p["tau_s"]},
    "gyro_scale": {"s": lambda p: p["s"]},
    "accel_scale": {"s": lambda p: p["s"]},
    "lever_arm": {"r_m": lambda p: p["r_m"]},
    "nongravity_acceleration": {"kappa": lambda p: 1.0, "delay_s": lambda p: p.get("delay_s", 0.0)},
    "transient_disturbance": {},
}


def heading_error_deg(d_fit: np.ndarray, o_fit: np.ndarray, d_true: np.ndarray, o_true: np.ndarray,
                      dip: float) -> float:
    """Largest heading error (deg) over a level 360-degree turn when the fitted calibration corrects readings
    made with the true one."""
    psi = np.deg2rad(np.arange(360.0))
    rot = so3.exp(np.stack([np.zeros_like(psi), np.zeros_like(psi), psi], axis=1))
    m_n = np.array([np.cos(dip), 0.0, np.sin(dip)])
    m_b = np.einsum("nji,j->ni", rot, m_n)
    y = m_b @ d_true.T + o_true
    m_hat = (y - o_fit) @ np.linalg.inv(d_fit).T
    h = np.einsum("nij,nj->ni", rot, m_hat)
    return float(np.degrees(np.max(np.abs(np.arctan2(h[:, 1], h[:, 0])))))


def _errors_of(d: np.ndarray, o: np.ndarray, dip_deg: float, sim: Any, o_shift: np.ndarray) -> dict[str, float]:
    """D relative error (%), o error (% of the field), dip error (deg), heading error (deg) of D, o (tesla)."""
    tr = sim.truth
    field = float(np.cbrt(np.linalg.det(tr.D)))
    o_true = tr.o + o_shift
    return {"D_pct": float(100 * np.linalg.norm(d - tr.D) / np.linalg.norm(tr.D)),
            "o_pct": float(100 * np.linalg.norm(o - o_true) / field),
            "dip_deg": float(dip_deg - np.rad2deg(tr.dip)),
            "heading_deg": heading_error_deg(d, o, tr.D, o_true, tr.dip)}


def _errors(res: Any, sim: Any, o_shift: np.ndarray) -> dict[str, float]:
    """`_errors_of` the first magnetometer of a pipeline result (simulated logs are in tesla)."""
    m = res.calibration.magnetometers[0]
    return _errors_of(np.asarray(m.D), np.asarray(m.o), float(m.dip_deg), sim, o_shift)


def _coverage(effect: str, injected: dict[str, Any], value: Any, std: Any) -> tuple[list[bool], list[float]]:
    """Which truth entries lie within the 95 % interval, and the z-scores; value/std: param name -> estimate."""
    cover, z = [], []
    for name, truth in TRUTH[effect].items():
        v, s = np.atleast_1d(value(name)), np.atleast_1d(std(name))
        t = np.atleast_1d(np.asarray(truth(injected), dtype=float))
        cover.extend((np.abs(v - t) <= 1.959963984540054 * s).tolist())
        z.extend(((v - t) / s).tolist())
    return cover, z


NAN_ERRORS = {"D_pct": float("nan"), "o_pct": float("nan"), "dip_deg": float("nan"), "heading_deg": float("nan")}


def ekf_batched(effect: str | None, method: str, seeds: list[int], none: bool) -> list[dict[str, Any]]:
    """All seeds through one batched filter loop per model (as paper_study.py runs the EKFs; the method's own
    `fit_batch` on `prepare_all`, what `magcal fit` runs per log): with the effect (or clean logs when effect is
    None), and with --effects none unless not `none`."""
    from magcal_cli.models.ekf import aug as ekf_aug
    from magcal_cli.models.ekf import core as ekf
    from magcal_cli.models.ekf import ml as ekf_ml
    from magcal_cli.params import BASE
    from magcal_cli.pipeline import select_problem

    fit_batch = {"ekf-ml": ekf_ml.fit_batch, "ekf-aug": ekf_aug.fit_batch}[method]

    def run(sims: list[Any], ids: tuple[str, ...]) -> tuple[list[Any], float]:
        cfg = Config(method=method, effects=ids)
        preps = [ekf.prepare_all(select_problem(s.recording, cfg), cfg, method)[0] for s in sims]
        t0 = time.perf_counter()
        return fit_batch(preps), (time.perf_counter() - t0) / len(sims)

    def errors(est: Any, sim: Any, shift: np.ndarray) -> dict[str, float]:
        return _errors_of(BASE.value(est.theta, "D"), BASE.get(est.theta, "o"),
                          float(np.rad2deg(BASE.get(est.theta, "dip")[0])), sim, shift)

    if effect is None:
        sims = [simulate("handheld", s) for s in seeds]
        ests, secs = run(sims, ())
        return [{"seed": s, "clean": errors(e, sim, np.zeros(3)), "seconds": secs}
                for s, e, sim in zip(seeds, ests, sims, strict=True)]
    sims = [simulate("handheld", s, effects=(EffectSpec(effect),)) for s in seeds]
    base, t_none = run(sims, ()) if none else ([None] * len(sims), float("nan"))
    withs, t_with = run(sims, (effect,))
    rows = []
    for seed, sim, b, w in zip(seeds, sims, base, withs, strict=True):
        injected = sim.effects[0].params
        fit = next(f for f in w.effects if f.id == effect)
        shift = np.zeros(3)
        if effect == "temperature_drift" and "T0" in fit.constants:
            shift = np.asarray(injected["k"]) * (float(fit.constants["T0"]) - float(injected["T0"]))
        cover, z = ([], []) if fit.estimate is None else \
            _coverage(effect, injected, lambda n, f=fit: f.estimate[n], lambda n, f=fit: f.estimate.std(n))
        rows.append({"effect": effect, "seed": seed, "method": method, "status": fit.status, "covered": cover,
                     "z": z, "none": NAN_ERRORS if b is None else errors(b, sim, np.zeros(3)),
                     "with": errors(w, sim, shift), "seconds": {"none": t_none, "with": t_with}})
    return rows


def _operating_offsets(sim: Any, base: Any, with_term: Any) -> tuple[float, float]:
    """The error (% of the field) of the offset at the log's mean operating point, o plus the mean of the
    magnetometer term, without and with the term fitted: what the calibration subtracts on average in this log.

    An interference term's o is the offset at zero current, extrapolated from the log's 2-27 A: its std is an
    intercept's, not a mean's. This is the figure comparable with the clean fit's o.
    """
    from magcal_cli.effects.correct import remove

    inj = sim.effects[0]
    tr = sim.truth
    field = float(np.cbrt(np.linalg.det(tr.D)))
    mag = sim.recording.select(Kind.MAGNETOMETER)                  # simulated logs are in tesla
    term = inj.signals.get("term") if get(inj.id).target is Target.MAG else None   # the lever arm's is an acceleration
    truth = tr.o + (np.zeros(3) if term is None else np.mean(term, axis=0))

    def err(res: Any) -> float:
        if res is None:
            return float("nan")
        m = res.calibration.magnetometers[0]
        _, y, _ = remove(res.calibration.effects, m.id, sim.recording, mag.t, mag.xyz, ("accepted", "ambiguous"))
        return float(100 * np.linalg.norm(np.asarray(m.o) + np.nanmean(mag.xyz - y, axis=0) - truth) / field)

    return err(base), err(with_term)


def clean_fit(seed: int, method: str) -> dict[str, Any]:
    """The base model on the seed's log without any effect: the no-effect level (the same for every effect)."""
    clean = simulate("handheld", seed)
    t0 = time.perf_counter()
    res = calibrate_recording(clean.recording, Config(method=method))
    return {"seed": seed, "clean": _errors(res, clean, np.zeros(3)), "seconds": time.perf_counter() - t0}


def one(effect: str, seed: int, method: str = "map", none: bool = True) -> dict[str, Any]:
    """The fits of one seed with the effect injected: base model (unless not `none`) and with the term."""
    sim = simulate("handheld", seed, effects=(EffectSpec(effect),))
    injected = sim.effects[0].params
    t1 = time.perf_counter()
    base = calibrate_recording(sim.recording, Config(method=method)) if none else None
    t2 = time.perf_counter()
    with_term = calibrate_recording(sim.recording, Config(method=method, effects=(effect,)))
    t3 = time.perf_counter()
    entry = next(e for e in with_term.calibration.effects if e["id"] == effect)
    operating = _operating_offsets(sim, base, with_term)
    shift = np.zeros(3)
    if effect == "temperature_drift" and "T0" in entry["params"]:
        # the fit's o is the offset at the log's mean temperature; the truth's at its own T0
        shift = np.asarray(injected["k"]) * (float(entry["params"]["T0"]) - float(injected["T0"]))
    cover, z = ([], []) if entry["status"] == "not_testable" else \
        _coverage(effect, injected, lambda n: entry["params"][n], lambda n: entry["std"][n])
    return {"effect": effect, "seed": seed, "method": method, "status": entry["status"], "covered": cover, "z": z,
            "none": NAN_ERRORS if base is None else {**_errors(base, sim, np.zeros(3)), "o_op_pct": operating[0]},
            "with": {**_errors(with_term, sim, shift), "o_op_pct": operating[1]},
            "seconds": {"none": t2 - t1 if none else float("nan"), "with": t3 - t2}}


def main() -> None:
    """Run every effect over the seeds and print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--effects", default=",".join(EFFECTS))
    ap.add_argument("--method", default="map", help="map (default), ekf-ml or ekf-aug")
    ap.add_argument("--skip-none", action="store_true", help="leave out the --effects none fits")
    ap.add_argument("--batched", action="store_true",
                    help="EKF methods: all seeds of an effect in one batched filter loop (fit s: per log)")
    ap.add_argument("--out", type=Path, default=None, help="write OUT.json and OUT.md")
    args = ap.parse_args()
    effects = args.effects.split(",")
    seeds = list(range(args.seeds))
    tasks = [(e, s, args.method, not args.skip_none) for e in effects for s in seeds]
    start = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as pool:
        if args.batched:
            jobs = [None, *effects]
            parts = list(pool.map(ekf_batched, jobs, [args.method] * len(jobs), [seeds] * len(jobs),
                                  [not args.skip_none] * len(jobs)))
            cleans, rows = parts[0], [r for part in parts[1:] for r in part]
        else:
            cleans = list(pool.map(clean_fit, seeds, [args.method] * len(seeds)))
            rows = list(pool.map(one, *zip(*tasks, strict=True)))
        clean_of = {c["seed"]: c for c in cleans}
    for r in rows:
        r["clean"] = clean_of[r["seed"]]["clean"]
        r["seconds"]["clean"] = clean_of[r["seed"]]["seconds"]
    lines = [f"`python benchmarks/effects_accuracy.py --method {args.method} --seeds {args.seeds} --effects "
             f"{','.join(effects)}{' --skip-none' if args.skip_none else ''}{' --batched' if args.batched else ''}`",
             "",
             f"{len(tasks)} runs ({args.seeds} seeds x {len(effects)} effects, handheld, method {args.method}) and "
             f"{len(seeds)} clean fits, {time.perf_counter() - start:.0f} s on {args.jobs} processes", "",
             "| effect | accepted | coverage 95 % | median \\|z\\| | D err % clean / none / with | "
             "o err % of field clean / none / with | o at the operating point, err % clean / none / with | "
             "dip err deg none / with | heading err deg clean / none / with | fit s none / with |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for e in effects:
        rs = [r for r in rows if r["effect"] == e]
        cov = [c for r in rs for c in r["covered"]]
        z = [abs(v) for r in rs for v in r["z"]]

        def med(key: str, which: str, rs: list[dict[str, Any]] = rs) -> float:
            return float(np.median([abs(r[which].get(key, np.nan)) for r in rs]))

        def secs(which: str, rs: list[dict[str, Any]] = rs) -> float:
            return float(np.median([r["seconds"][which] for r in rs]))

        acc = sum(r["status"] == "accepted" for r in rs)
        lines.append(
            f"| {e} | {acc}/{len(rs)} | {100 * np.mean(cov) if cov else float('nan'):.1f} % ({len(cov)}) | "
            f"{np.median(z) if z else float('nan'):.2f} | "
            f"{med('D_pct', 'clean'):.3f} / {med('D_pct', 'none'):.3f} / {med('D_pct', 'with'):.3f} | "
            f"{med('o_pct', 'clean'):.3f} / {med('o_pct', 'none'):.3f} / {med('o_pct', 'with'):.3f} | "
            f"{med('o_pct', 'clean'):.3f} / {med('o_op_pct', 'none'):.3f} / {med('o_op_pct', 'with'):.3f} | "
            f"{med('dip_deg', 'none'):.3f} / {med('dip_deg', 'with'):.3f} | "
            f"{med('heading_deg', 'clean'):.2f} / {med('heading_deg', 'none'):.2f} / "
            f"{med('heading_deg', 'with'):.2f} | "
            f"{secs('none'):.2f} / {secs('with'):.2f} |")
    lines.append("")
    lines.append("Errors are medians over seeds of |error|; clean = the same seed without the effect, base model. "
                 "The operating point's offset is o plus the mean magnetometer term over the log (the interference "
                 "effects' o is at zero current, extrapolated; temperature's is at the log's mean temperature).")
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
        title = "# Effects on simulated logs" + ("" if args.method == "map" else f" ({args.method})")
        args.out.with_suffix(".md").write_text(title + "\n\n" + text + "\n")


if __name__ == "__main__":
    main()
