"""Huang et al. 2025, Sec. IV-A reproduced: kok2012, map, ekf-ml and ekf-aug on the paper's simulation protocol.

Two experiments (methods.md section 5): the sampling rate (10/20/40/80 Hz, magnetometer at the IMU rate) and the
magnetometer-to-IMU rate ratio (1/2/4/8 at 80 Hz); dataset i is `synth.simulate.simulate("paper", seed=i, ...)`
in every configuration. Per method and configuration: the RMSE over the datasets of b_a, b_g, o and D (root of
the mean squared error norm, the authors' compute_stat.m), the computation time per dataset, and the
Cramer-Rao bound (the inverse Fisher information of the joint MAP model at the truth with the true noise
levels). Methods run as a user's `magcal fit` would: from the log alone (kok2012 with quasi-static verticals,
as the protocol has no still segment). ekf-ml and ekf-aug run all datasets of a configuration in one batched
filter loop; their time per dataset is the batch's time divided by the number of datasets.

Writes paper_study.md (tables, the published values, the checks), paper_study.json and paper_study_{rate,ratio}.png.

    python benchmarks/paper_study.py                    # the full study: 10 datasets of 5.4 min
    python benchmarks/paper_study.py --quick            # 1 dataset of 60 s per configuration
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magcal_cli.config import Config
from magcal_cli.methods.table import METHODS
from magcal_cli.models.ekf import aug as ekf_aug
from magcal_cli.models.ekf import core as ekf
from magcal_cli.models.ekf import ml as ekf_ml
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MethodResult
from magcal_cli.pipeline import select_problem
from magcal_cli.registry import resolve
from magcal_cli.synth.simulate import Simulation, simulate

ROOT = Path(__file__).resolve().parents[1]
PUBLISHED = ROOT.parent / "shared" / "realdata" / "huang2025-results" / "computation_results"
ORDER = ("kok2012", "map", "ekf-ml", "ekf-aug")
#: parameter groups of theta = (b_a, b_g, vec D, o, dip): slice, display factor and unit (the paper's figures)
GROUPS = {"b_a": (slice(0, 3), 1.0, "m/s^2"), "b_g": (slice(3, 6), 1.0, "rad/s"),
          "o": (slice(15, 18), 1e6, "uT"), "D": (slice(6, 15), 1e6, "uT")}
#: the published statistics' names for our methods (the authors' EKF is Wu et al., their ML is Kok & Schoen)
PUBLISHED_NAMES = {"map": "statMAP", "ekf-aug": "statEKF", "ekf-ml": "statML"}
PUBLISHED_TIMES = {"map": "jointmap_times", "ekf-aug": "ekf_times", "ekf-ml": "ML_times"}
PUBLISHED_FIELDS = {"b_a": "acc_bias_err", "b_g": "gyro_bias_err", "o": "mag_bias_err", "D": "D_err"}
#: batched fits: all datasets of a configuration in one filter loop
BATCHED: dict[str, Callable[[list[ekf.Prepared]], list[ekf.Estimate]]] = {
    "ekf-ml": ekf_ml.fit_batch, "ekf-aug": ekf_aug.fit_batch}


@dataclass
class Cell:
    """One method on one configuration: per-dataset errors (n, 19) (NaN where not estimated) and time (s)."""

    errors: list[list[float]] = field(default_factory=list)
    seconds: float = 0.0

    def rmse(self, group: str) -> float:
        """RMSE of a parameter group over the datasets (NaN when the method does not estimate it)."""
        e = np.array(self.errors)[:, GROUPS[group][0]]
        return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


@dataclass(frozen=True)
class Setup:
    """One configuration: experiment name, x value, IMU and magnetometer rates (Hz)."""

    experiment: str
    x: float
    rate: float
    mag_rate: float


def truth_theta(sim: Simulation) -> np.ndarray:
    """theta of the simulation's truth (SI)."""
    return sim.truth.theta


def result_theta(res: MethodResult) -> np.ndarray:
    """theta (SI) of a method's result; NaN where it estimates nothing (kok2012's biases)."""
    fit, imu = res.mags[0], res.imu
    nan3 = np.full(3, np.nan)
    return np.concatenate([nan3 if imu.accel_bias is None else imu.accel_bias,
                           nan3 if imu.gyro_bias is None else imu.gyro_bias, fit.D.ravel(order="F"), fit.o, [fit.dip]])


def crlb(sim: Simulation, problem: Problem) -> np.ndarray | None:
    """Inverse Fisher information (19, 19) of the joint MAP model at the truth, or None without `map`."""
    try:
        from magcal_cli.models.epochs import Noise, epochs_for
        from magcal_cli.models.map import fit as mapm
    except ImportError:
        return None
    info_at = getattr(mapm, "information_at", None)
    if info_at is None:
        return None
    sd = sim.truth.noise_std
    noise = Noise(np.full(3, sd["accelerometer"]), np.full(3, sd["gyroscope"]), np.full(3, sd["magnetometer"]))
    mag = problem.mags[0]
    step = int(round(problem.acc.rate_hz / mag.rate_hz))
    k = epochs_for(problem, mag, 1.0).t.size
    return np.asarray(info_at(problem, mag, sim.rotations[::step][:k], truth_theta(sim), noise))


def run_setup(setup: Setup, datasets: int, duration: float | None, methods: Sequence[str],
              sims: dict[tuple[float, float, int], Simulation]) -> tuple[dict[str, Cell], Cell, float]:
    """All methods on one configuration: their cells, the CRLB's standard deviations (as 'errors') and the
    recording length (s)."""
    cells = {m: Cell() for m in methods}
    bound = Cell()
    problems, truths, cur = [], [], []
    for i in range(datasets):
        key = (setup.rate, setup.mag_rate, i)
        if key not in sims:
            sims[key] = simulate("paper", i, setup.rate, setup.mag_rate, duration)
        cur.append(sims[key])
        problems.append(select_problem(sims[key].recording, Config()))
        truths.append(truth_theta(sims[key]))
    for m in methods:
        t0 = time.perf_counter()
        if m in BATCHED:
            preps = [ekf.prepare(p, p.mags[0]) for p in problems]
            thetas = [e.theta for e in BATCHED[m](preps)]
        else:
            run = resolve(METHODS[m].run, f"the {m} method")
            thetas = [result_theta(run(p, Config(method=m))) for p in problems]
        cells[m].seconds = (time.perf_counter() - t0) / datasets
        cells[m].errors = [(th - tr).tolist() for th, tr in zip(thetas, truths, strict=True)]
    for sim, p in zip(cur, problems, strict=True):
        c = crlb(sim, p)
        if c is not None:
            bound.errors.append(np.sqrt(np.clip(np.diag(c), 0.0, None)).tolist())
    return cells, bound, float(cur[0].recording.streams[0].t[-1])


def load_published() -> dict[str, dict] | None:
    """The authors' statistics (results_freq.mat, results_ratio.mat), or None when the files are absent."""
    if not (PUBLISHED / "results_freq.mat").is_file():
        return None
    from scipy.io import loadmat

    out = {}
    for exp, name, xs in (("rate", "results_freq.mat", "sample_freq"), ("ratio", "results_ratio.mat",
                                                                          "downsample_rates")):
        d = loadmat(PUBLISHED / name, squeeze_me=True, struct_as_record=False)
        n = 10                                                     # config.json: num_datasets
        rows = {}
        for m, stat in PUBLISHED_NAMES.items():
            s = d[stat]
            # the authors' magnetometer unit is uT; their times are for all 10 datasets
            rows[m] = {g: [float(getattr(x, f)) * (1e-6 if g in ("o", "D") else 1.0) for x in s]
                       for g, f in PUBLISHED_FIELDS.items()}
            rows[m]["time"] = [float(t) / n for t in np.atleast_1d(d[PUBLISHED_TIMES[m]])]
        out[exp] = {"x": [float(x) for x in np.atleast_1d(d[xs])], "methods": rows}
    return out


def _fmt(x: float, factor: float) -> str:
    return "—" if not np.isfinite(x) else f"{x * factor:.3g}"


def markdown(results: dict, published: dict | None, args: argparse.Namespace, wall: float,
             load: tuple[float, float]) -> str:
    """The report: per-experiment tables, the published values, the ordering, flatness and time checks."""
    methods = results["methods"]
    lines = [f"# Huang et al. 2025 simulation study, reproduced ({args.datasets} datasets per configuration)", "",
             f"Generated by `python benchmarks/paper_study.py{' ' + ' '.join(args.argv) if args.argv else ''}` in "
             f"{wall / 60:.1f} min (load average {load[0]:.1f} before, {load[1]:.1f} after, 2 cores shared with "
             "other work). RMSE over the datasets of the error norm of each group; o and D in uT (field 27 uT); "
             "time per dataset in seconds (ekf-ml and ekf-aug: one batched filter loop over the datasets, time "
             "divided by their number). CRLB: root of the mean trace of the inverse Fisher information of the joint "
             "MAP model at the truth. kok2012 (Kok et al. 2012, quasi-static verticals) estimates neither b_a nor "
             "b_g (—).", ""]
    for exp, title in (("rate", "Sampling rate (Hz), magnetometer at the IMU rate"),
                       ("ratio", "Magnetometer-to-IMU rate ratio, IMU at 80 Hz")):
        block = results[exp]
        lines += [f"## {title}", "", "| x | method | b_a [m/s²] | b_g [rad/s] | o [uT] | D [uT] | time [s] |",
                  "|---|---|---|---|---|---|---|"]
        for j, x in enumerate(block["x"]):
            for m in methods + ["crlb"]:
                c = block["cells"][m][j]
                vals = " | ".join(_fmt(c["rmse"][g], GROUPS[g][1]) for g in GROUPS)
                t = "" if m == "crlb" else f"{c['seconds']:.2f}"
                lines.append(f"| {x:g} | {m} | {vals} | {t} |")
        if published is not None:
            pub = published[exp]
            lines += ["", f"Published (computation_results/results_{'freq' if exp == 'rate' else 'ratio'}.mat; "
                      "the authors' ML used 20 cores for its numerical gradients):", "",
                      "| x | method | b_a [m/s²] | b_g [rad/s] | o [uT] | D [uT] | time [s] |",
                      "|---|---|---|---|---|---|---|"]
            for j, x in enumerate(pub["x"]):
                for m, row in pub["methods"].items():
                    vals = " | ".join(_fmt(row[g][j], GROUPS[g][1]) for g in GROUPS)
                    lines.append(f"| {x:g} | {m} | {vals} | {row['time'][j]:.2f} |")
        lines.append("")
    lines += ["## Checks", ""] + checks(results)
    return "\n".join(lines) + "\n"


def checks(results: dict) -> list[str]:
    """The paper's claims, measured: who has the lowest o and D, flatness in the rate, time versus samples."""
    out = []
    methods = results["methods"]
    for g in ("o", "D"):
        wins, total = {m: 0 for m in methods}, 0
        for exp in ("rate", "ratio"):
            for j in range(len(results[exp]["x"])):
                vals = {m: results[exp]["cells"][m][j]["rmse"][g] for m in methods}
                best = min(vals, key=lambda m: vals[m] if np.isfinite(vals[m]) else np.inf)
                wins[best] += 1
                total += 1
        out.append(f"- lowest RMSE in {g}: " + ", ".join(f"{m} {n}/{total}" for m, n in wins.items()) + " configurations")
    if "map" in methods and "ekf-ml" in methods:           # are the two efficient estimators the same estimate?
        for g in ("o", "D"):
            sl = GROUPS[g][0]
            parts = []
            for exp in ("rate", "ratio"):
                cells = results[exp]["cells"]
                for j, x in enumerate(results[exp]["x"]):
                    diff = np.array(cells["map"][j]["errors"])[:, sl] - np.array(cells["ekf-ml"][j]["errors"])[:, sl]
                    ratio = float(np.sqrt(np.mean(np.sum(diff**2, axis=1)))) / cells["crlb"][j]["rmse"][g]
                    parts.append(f"{exp} {x:g}: {ratio:.2f}")
            out.append(f"- map - ekf-ml, RMS over the datasets of the difference of their {g} estimates, in units "
                       f"of the CRLB: {'; '.join(parts)}")
    rate = results["rate"]
    for m in methods:
        spread = []
        for g in GROUPS:
            v = np.array([c["rmse"][g] for c in rate["cells"][m]])
            if np.all(np.isfinite(v)):
                spread.append(f"{g} {v.max() / v.min():.2f}")
        samples = np.array(rate["x"]) * results["duration_s"]
        secs = np.array([c["seconds"] for c in rate["cells"][m]])
        slope = float(np.polyfit(np.log(samples), np.log(secs), 1)[0])
        out.append(f"- {m}: max/min RMSE over the sampling rates: {', '.join(spread)}; time ~ samples^{slope:.2f}")
    return out


def plot(results: dict, published: dict | None, outdir: Path) -> list[Path]:
    """Two figures in the paper's layout (Figs. 3 and 4): time, o, D, b_a and b_g against the rate or ratio."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"kok2012": "tab:purple", "map": "tab:blue", "ekf-ml": "tab:green", "ekf-aug": "tab:orange"}
    paths = []
    for exp, xlabel in (("rate", "sampling rate [Hz]"), ("ratio", "magnetometer-to-IMU rate ratio")):
        block = results[exp]
        fig, axes = plt.subplots(1, 5, figsize=(20, 4))
        panels = [("time", "time per dataset [s]", 1.0)] + [(g, f"RMSE {g} [{GROUPS[g][2]}]", GROUPS[g][1])
                                                           for g in ("o", "D", "b_a", "b_g")]
        for ax, (key, label, f) in zip(axes, panels, strict=True):
            for m in results["methods"]:
                ys = [c["seconds"] if key == "time" else c["rmse"][key] for c in block["cells"][m]]
                if np.all(np.isfinite(ys)):
                    ax.plot(block["x"], np.array(ys) * f, "o-", color=colours.get(m), label=m)
                if published is not None and m in published[exp]["methods"]:
                    pub = published[exp]
                    ax.plot(pub["x"], np.array(pub["methods"][m][key]) * f, "x:", color=colours.get(m),
                            label=f"{m} (published)")
            if key != "time":
                ys = [c["rmse"][key] for c in block["cells"]["crlb"]]
                if np.all(np.isfinite(ys)):
                    ax.plot(block["x"], np.array(ys) * f, "k--", label="CRLB")
            ax.set_yscale("log")
            ax.set_xscale("log", base=2)
            ax.set_xticks(block["x"], [f"{x:g}" for x in block["x"]])
            ax.set_xlabel(xlabel)
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
        handles = {lab: h for ax in axes for h, lab in zip(*ax.get_legend_handles_labels(), strict=True)}
        fig.legend(list(handles.values()), list(handles), loc="upper center", ncol=len(handles), fontsize=8)
        fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.9))
        path = outdir / f"paper_study_{exp}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def main(argv: Sequence[str] | None = None) -> Path:
    """Run the study and write the report, the raw numbers and the plots; returns the Markdown path."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", type=int, default=10, help="datasets per configuration")
    ap.add_argument("--duration", type=float, default=None, help="trajectory length (s) [default: the paper's]")
    ap.add_argument("--quick", action="store_true", help="1 dataset of 60 s per configuration")
    ap.add_argument("--rates", default="10,20,40,80", help="IMU sampling rates (Hz)")
    ap.add_argument("--ratios", default="1,2,4,8", help="magnetometer-to-IMU rate ratios at the top rate")
    ap.add_argument("--methods", default=",".join(m for m in ORDER if m in METHODS),
                    help="methods to compare (registered in methods.table.METHODS)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results", help="output directory")
    args = ap.parse_args(argv)
    args.argv = list(argv) if argv is not None else list(os.sys.argv[1:])
    if importlib.util.find_spec("matplotlib") is None:   # before the hours of fitting, not after them
        sys.exit("paper_study.py draws its figures with matplotlib, an extra: pip install 'magcal-cli[bench]'")
    if args.quick:
        args.datasets, args.duration = 1, args.duration or 60.0
    methods = [m for m in args.methods.split(",") if m in METHODS]
    rates = [float(x) for x in args.rates.split(",")]
    ratios = [float(x) for x in args.ratios.split(",")]
    top = max(rates)
    setups = [Setup("rate", r, r, r) for r in rates] + [Setup("ratio", q, top, top / q) for q in ratios]
    load0 = os.getloadavg()[0]
    start = time.perf_counter()
    sims: dict[tuple[float, float, int], Simulation] = {}
    done: dict[tuple[float, float], tuple[dict[str, Cell], Cell, float]] = {}
    results: dict = {"methods": methods, "datasets": args.datasets, "rate": {"x": [], "cells": {}},
                     "ratio": {"x": [], "cells": {}}}
    for s in setups:
        key = (s.rate, s.mag_rate)
        if key not in done:                       # ratio 1 at the top rate is the top sampling rate: run once
            t0 = time.perf_counter()
            done[key] = run_setup(s, args.datasets, args.duration, methods, sims)
            print(f"{s.experiment} {s.x:g}: " + ", ".join(f"{m} {c.seconds:.2f} s" for m, c in done[key][0].items())
                  + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
        cells, bound, results["duration_s"] = done[key]
        block = results[s.experiment]
        block["x"].append(s.x)
        for m, c in list(cells.items()) + [("crlb", bound)]:
            rmse = {g: (c.rmse(g) if c.errors else float("nan")) for g in GROUPS}
            block["cells"].setdefault(m, []).append({"rmse": rmse, "seconds": c.seconds, "errors": c.errors})
        for k in [k for k in sims if k[:2] == key]:
            del sims[k]
    wall = time.perf_counter() - start
    published = load_published()
    args.out.mkdir(parents=True, exist_ok=True)
    md = args.out / "paper_study.md"
    md.write_text(markdown(results, published, args, wall, (load0, os.getloadavg()[0])))
    (args.out / "paper_study.json").write_text(json.dumps(results, indent=1))
    plot(results, published, args.out)
    print(f"wrote {md} ({wall / 60:.1f} min)")
    return md


if __name__ == "__main__":
    main()
