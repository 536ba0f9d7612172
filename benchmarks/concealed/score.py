"""Score the concealed-effect suite's run records against the issue-11 thresholds.

    python benchmarks/concealed/score.py --out out/concealed [--results docs/results]

Reads `OUT/runs/<case>/<seed>.json` (run.py) and writes `RESULTS/concealed.md` and `RESULTS/concealed.json`.
Scored fields of each `effects[]` entry: `id`, `status`, `ci95` (coverage of the truth's params, same unit),
`confounded_with` (ids or {"id": ...}) of `ambiguous` entries, and `evidence` (`heldout_gain_ci95` or
`heldout_rms_before/after`) for the held-out improvement. A run without a parseable report is a failure.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cases import CASES, TIERS, Case  # noqa: E402

#: the parameters whose 95 % intervals are checked against the truth (others are references or not estimated)
COVERED = {"current_interference": ("c",), "throttle_interference": ("c", "p"), "temperature_drift": ("k",),
           "time_offset": ("tau_s",), "gyro_scale": ("s",), "accel_scale": ("s",), "lever_arm": ("r_m",)}
#: thresholds: issue 11 ("Must show"), and the design's (mismatch.md 7.6) where the issue names none
NEG_MAX, CLEAR_MIN, WRONG_MAX, COVER = 0.05, 0.90, 0.05, (0.88, 0.99)
HELDOUT_MIN, AMBIG_MIN, SEPARABLE_MIN, STRONG_MIN = 0.90, 0.80, 0.90, 0.98
#: coverage is judged from this many intervals of one effect on (design 7.6: >= 40 accepted runs)
MIN_INTERVALS = 40
#: issue 25: time_offset accepted on the timing grid's negative controls; the lag tier's mean error (s); the base
#: parameters' |z| <= 1.96 share pooled over the good logs, and the largest |z| any log may have
TIMING_MAX, LAG_BIAS_MAX, Z_SHARE, Z_MAX = 0.05, 0.5e-3, (0.85, 0.99), 5.0

Record = dict[str, Any]


def load(out: Path) -> list[Record]:
    """Every run record under OUT/runs, sorted by case and seed."""
    recs = [json.loads(p.read_text()) for p in sorted((out / "runs").glob("*/*.json"))]
    return sorted(recs, key=lambda r: (r["case"], r["seed"]))


def accepted(rec: Record) -> set[str]:
    """Ids with status accepted."""
    return {e["id"] for e in rec.get("effects") or [] if e.get("status") == "accepted"}


def _ids(items: list[Any]) -> set[str]:
    """confounded_with entries (ids or dicts with "id") as ids."""
    return {i["id"] if isinstance(i, dict) else str(i) for i in items}


def ambiguous_names(rec: Record) -> set[str]:
    """Ids named by ambiguous entries: their own and their confounded_with rivals."""
    out: set[str] = set()
    for e in rec.get("effects") or []:
        if e.get("status") == "ambiguous":
            out |= {e["id"]} | _ids(e.get("confounded_with") or [])
    return out


def _flat(x: Any) -> list[Any]:
    """A number or (nested) list as a flat list of its leaves, pairs kept whole when `x` is a list of pairs."""
    if isinstance(x, list) and x and isinstance(x[0], list):
        return [v for item in x for v in _flat(item)]
    return list(x) if isinstance(x, list) else [x]


def _pairs(ci: Any) -> list[list[float]]:
    """[lo, hi] or [[lo, hi], ...] as a list of [lo, hi]."""
    if isinstance(ci, list) and len(ci) == 2 and not isinstance(ci[0], list):
        return [ci]
    return [p for item in ci for p in _pairs(item)]


def coverage(rec: Record, eid: str) -> list[bool]:
    """For the accepted `eid`: is each truth component inside its 95 % interval (one bool per component)."""
    truth = next((t for t in rec.get("truth") or [] if t["id"] == eid), None)
    fit = next((e for e in rec.get("effects") or [] if e["id"] == eid and e.get("status") == "accepted"), None)
    if truth is None or fit is None:
        return []
    out: list[bool] = []
    for name in COVERED.get(eid, ()):
        if name not in truth["params"] or name not in (fit.get("ci95") or {}):
            continue
        values, cis = _flat(truth["params"][name]), _pairs(fit["ci95"][name])
        out += [lo <= v <= hi for v, (lo, hi) in zip(values, cis, strict=False)]
    return out


def heldout(rec: Record, eid: str) -> bool | None:
    """Did the accepted `eid` improve held-out data (evidence field), None when the entry reports nothing."""
    fit = next((e for e in rec.get("effects") or [] if e["id"] == eid and e.get("status") == "accepted"), None)
    ev = (fit or {}).get("evidence") or {}
    if ev.get("heldout_gain_ci95") is not None:
        return float(ev["heldout_gain_ci95"][0]) > 0.0
    if ev.get("heldout_rms_before") is not None and ev.get("heldout_rms_after") is not None:
        return float(ev["heldout_rms_after"]) < float(ev["heldout_rms_before"])
    return None


def wald(rec: Record, eid: str) -> float | None:
    """The test statistic reported for `eid` (explicit fits: Wald chi^2), None when absent."""
    e = next((e for e in rec.get("effects") or [] if e["id"] == eid), None)
    stat = ((e or {}).get("test") or {}).get("statistic")
    return None if stat is None else float(stat)


def run_outcome(rec: Record, case: Case) -> dict[str, Any]:
    """One run's outcome against its case."""
    ok = rec.get("effects") is not None
    acc, expected = accepted(rec), set(case.expected)
    pair = set(case.ambiguous)
    cover = [c for eid in sorted(expected & acc) for c in coverage(rec, eid)]
    held = [h for eid in sorted(expected & acc) if (h := heldout(rec, eid)) is not None]
    return {"ok": ok, "accepted": sorted(acc),
            "correct": ok and bool(expected) and expected <= acc,
            "exact": ok and acc == expected,
            "wrong_or_extra": ok and bool(acc - expected),
            "ambiguous_pair": ok and bool(pair) and pair <= ambiguous_names(rec),
            "wrong_pick": ok and bool(acc & (pair - expected)),
            "covered": sum(cover), "intervals": len(cover),
            "heldout_ok": sum(held), "heldout_n": len(held),
            "time_offset": "time_offset" in acc, "lag_error": lag_error(rec),
            "z": [float(z[2]) for z in rec.get("z") or []],
            "heading": list((rec.get("heading_error_deg") or {}).values())}


def lag_error(rec: Record) -> float | None:
    """Estimated minus true tau_s of an accepted time_offset that was injected, None otherwise."""
    truth = next((t for t in rec.get("truth") or [] if t["id"] == "time_offset"), None)
    fit = next((e for e in rec.get("effects") or [] if e["id"] == "time_offset" and e.get("status") == "accepted"),
               None)
    if truth is None or fit is None or "tau_s" not in (fit.get("params") or {}):
        return None
    return float(fit["params"]["tau_s"]) - float(truth["params"]["tau_s"])


def _rate(k: int, n: int) -> float | None:
    return k / n if n else None


def summarise(recs: list[Record]) -> dict[str, dict[str, Any]]:
    """Per case: runs, failures, rates (None where undefined), coverage and held-out counts, runtime."""
    by: dict[str, list[Record]] = defaultdict(list)
    for r in recs:
        if r["case"] in CASES:
            by[r["case"]].append(r)
    out: dict[str, dict[str, Any]] = {}
    for name, rs in by.items():
        case = CASES[name]
        oc = [run_outcome(r, case) for r in rs]
        n = len(oc)
        ok = sum(o["ok"] for o in oc)
        correct = sum(o["correct"] for o in oc)
        covered, intervals = sum(o["covered"] for o in oc), sum(o["intervals"] for o in oc)
        h_ok, h_n = sum(o["heldout_ok"] for o in oc), sum(o["heldout_n"] for o in oc)
        fit_s = sorted(float(r.get("runtime_fit_s", 0.0)) for r in rs)
        stats = sorted(w for r in rs for eid in case.expected[:1] if (w := wald(r, eid)) is not None)
        out[name] = {
            "tier": case.tier, "runs": n, "failed": n - ok, "expected": list(case.expected),
            "accept_rate": _rate(correct, n) if case.expected else None,
            "exact_rate": _rate(sum(o["exact"] for o in oc), n),
            "wrong_or_extra_rate": _rate(sum(o["wrong_or_extra"] for o in oc), n),
            "false_accept_rate": _rate(sum(o["wrong_or_extra"] for o in oc), n) if not case.expected else None,
            "covered": covered, "intervals": intervals, "coverage": _rate(covered, intervals),
            "heldout_ok": h_ok, "heldout_n": h_n, "heldout_rate": _rate(h_ok, h_n),
            "ambiguous_rate": _rate(sum(o["ambiguous_pair"] for o in oc), n) if case.ambiguous else None,
            "wrong_pick_rate": _rate(sum(o["wrong_pick"] for o in oc), n) if case.ambiguous else None,
            "median_fit_s": fit_s[len(fit_s) // 2] if fit_s else None,
            "statistic_min_median": [round(stats[0], 1), round(stats[len(stats) // 2], 1)] if stats else None,
            "effects_arg": sorted({str(r.get("effects_arg")) for r in rs}),
            "time_offset_rate": _rate(sum(o["time_offset"] for o in oc), n),
            "lag_errors": [o["lag_error"] for o in oc if o["lag_error"] is not None],
            "z_within": sum(int(abs(z) <= 1.96) for o in oc for z in o["z"]),
            "z_count": sum(len(o["z"]) for o in oc),
            "z_max": [round(max(map(abs, o["z"])), 2) for o in oc if o["z"]],
            "heading_deg": sorted(h for o in oc for h in o["heading"]),
        }
    return out


def _verdict(value: float | None, ok: bool) -> str:
    return "n/a" if value is None else ("PASS" if ok else "FAIL")


def checks(summary: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The pass/fail criteria: issue 11's, plus the design's for strong and separable cases."""
    rows: list[dict[str, Any]] = []

    def add(what: str, threshold: str, value: float | None, ok: bool, detail: str = "") -> None:
        rows.append({"criterion": what, "threshold": threshold, "value": value, "verdict": _verdict(value, ok),
                     "detail": detail})

    def tier(t: str) -> dict[str, dict[str, Any]]:
        return {k: v for k, v in summary.items() if v["tier"] == t}

    fails = sum(v["failed"] for v in summary.values())
    add("runs with a parseable report", "all", 1.0 - fails / max(1, sum(v["runs"] for v in summary.values())),
        fails == 0, f"{fails} failed")
    neg = tier("negative")
    n_neg = sum(v["runs"] for v in neg.values())
    fa = sum(round(v["false_accept_rate"] * v["runs"]) for v in neg.values()) if n_neg else 0
    add("negative controls: any effect accepted", f"<= {NEG_MAX:.0%}", _rate(fa, n_neg),
        n_neg > 0 and fa / n_neg <= NEG_MAX, f"{fa}/{n_neg}")
    for name, v in tier("timing").items():
        add(f"{name}: time_offset accepted (issue 25)", f"<= {TIMING_MAX:.0%}", v["time_offset_rate"],
            (v["time_offset_rate"] or 0.0) <= TIMING_MAX, f"of {v['runs']} runs")
        add(f"{name}: wrong or extra", f"<= {WRONG_MAX:.0%}", v["wrong_or_extra_rate"],
            (v["wrong_or_extra_rate"] or 0.0) <= WRONG_MAX)
    for name, v in tier("lag").items():
        errs = v["lag_errors"]
        mean = sum(errs) / len(errs) if errs else None
        add(f"{name}: accepted", f">= {CLEAR_MIN:.0%}", v["accept_rate"], (v["accept_rate"] or 0.0) >= CLEAR_MIN)
        rows.append({"criterion": f"{name}: |mean error| of tau (issue 25)", "threshold": "<= 0.5 ms",
                     "value": None if mean is None else abs(mean), "unit": "ms",
                     "verdict": "n/a" if mean is None else ("PASS" if abs(mean) <= LAG_BIAS_MAX else "FAIL"),
                     "detail": f"{len(errs)} runs" if mean is None else
                     f"mean {1e3 * mean:+.3f} ms, RMS {1e3 * (sum(e * e for e in errs) / len(errs)) ** 0.5:.3f} ms, "
                     f"{len(errs)} runs"})
        cov = v["coverage"]
        add(f"{name}: 95 % interval coverage (issue 25)", f"{COVER[0]:.0%}-{COVER[1]:.0%}", cov,
            cov is not None and COVER[0] <= cov <= COVER[1], f"{v['covered']}/{v['intervals']}")
    within, count = sum(v["z_within"] for v in summary.values()), sum(v["z_count"] for v in summary.values())
    add("base parameters |z| <= 1.96, pooled (issue 25)", f"{Z_SHARE[0]:.0%}-{Z_SHARE[1]:.0%}", _rate(within, count),
        count > 0 and Z_SHARE[0] <= within / count <= Z_SHARE[1], f"{within}/{count} estimates of D, o, dip, biases")
    logs = [m for v in summary.values() for m in v["z_max"]]
    over = sum(m > Z_MAX for m in logs)
    add("logs with max |z| <= 5 (issue 25)", "all", _rate(len(logs) - over, len(logs)), bool(logs) and over == 0,
        f"{over} of {len(logs)} logs over; largest {max(logs) if logs else 'n/a'}")
    for name, v in tier("clear").items():
        add(f"clear {name.removeprefix('clear_')}: accepted", f">= {CLEAR_MIN:.0%}", v["accept_rate"],
            (v["accept_rate"] or 0.0) >= CLEAR_MIN)
        add(f"clear {name.removeprefix('clear_')}: wrong or extra", f"<= {WRONG_MAX:.0%}", v["wrong_or_extra_rate"],
            (v["wrong_or_extra_rate"] or 0.0) <= WRONG_MAX)
    for name, v in tier("strong").items():
        add(f"strong {name.removeprefix('strong_')}: accepted (design)", f">= {STRONG_MIN:.0%}", v["accept_rate"],
            (v["accept_rate"] or 0.0) >= STRONG_MIN)
    per_effect: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for v in summary.values():
        if len(v["expected"]) == 1 and v["intervals"]:
            per_effect[v["expected"][0]][0] += v["covered"]
            per_effect[v["expected"][0]][1] += v["intervals"]
    for eid, (k, n) in sorted(per_effect.items()):
        add(f"CI coverage {eid}", f"{COVER[0]:.0%}-{COVER[1]:.0%}", k / n, COVER[0] <= k / n <= COVER[1],
            f"{k}/{n} intervals")
        if n < MIN_INTERVALS:
            rows[-1]["verdict"] = f"too few (< {MIN_INTERVALS})"
    h_ok = sum(v["heldout_ok"] for v in summary.values())
    h_n = sum(v["heldout_n"] for v in summary.values())
    add("held-out improvement of correct accepts", f">= {HELDOUT_MIN:.0%}", _rate(h_ok, h_n),
        h_n > 0 and h_ok / h_n >= HELDOUT_MIN, f"{h_ok}/{h_n} with evidence")
    for name, v in tier("separable").items():
        add(f"{name}: exact attribution (design)", f">= {SEPARABLE_MIN:.0%}", v["exact_rate"],
            (v["exact_rate"] or 0.0) >= SEPARABLE_MIN)
    for name, v in tier("inseparable").items():
        add(f"{name}: ambiguous with the pair", f">= {AMBIG_MIN:.0%}", v["ambiguous_rate"],
            (v["ambiguous_rate"] or 0.0) >= AMBIG_MIN)
        add(f"{name}: confident wrong pick", "never", v["wrong_pick_rate"], v["wrong_pick_rate"] == 0.0)
    return rows


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.0f} %"


def _spread(values: list[float]) -> str:
    """'median / max' of a list, n/a when empty."""
    if not values:
        return "n/a"
    v = sorted(values)
    return f"{v[len(v) // 2]:.2f} / {v[-1]:.2f}"


def _shown(row: dict[str, Any]) -> str:
    """A criterion's value as the table prints it: a share in per cent, a time in milliseconds."""
    if row.get("unit") == "ms":
        return "n/a" if row["value"] is None else f"{1e3 * row['value']:.3f} ms"
    return _pct(row["value"])


def markdown(summary: dict[str, dict[str, Any]], rows: list[dict[str, Any]], load_note: str) -> str:
    """The report: per-case table, then the criteria."""
    lines = ["# Concealed-effect suite (issue 11)", "", load_note, "",
             "The `--effects` column is what `magcal fit` was given (`auto`: the default diagnosis; `explicit`: "
             "each case's candidate list); issue 11 asks for >= 20 runs per case with `auto`. Produced by "
             "`benchmarks/concealed/score.py` (cases and calibration: `benchmarks/concealed/README.md`).", "",
             "| case | tier | --effects | runs | failed | accepted (correct) | wrong/extra | CI coverage "
             "| held-out | ambiguous pair | wrong pick | test stat min / median | max abs z median / max "
             "| level-turn heading error deg median / max | fit s |", "|" + "---|" * 15]
    order = sorted(summary, key=lambda k: (TIERS.index(summary[k]["tier"]), k))
    for k in order:
        v = summary[k]
        cov = f"{_pct(v['coverage'])} ({v['covered']}/{v['intervals']})" if v["intervals"] else "n/a"
        held = f"{_pct(v['heldout_rate'])} ({v['heldout_ok']}/{v['heldout_n']})" if v["heldout_n"] else "n/a"
        lines.append(f"| {k} | {v['tier']} | {', '.join(v['effects_arg'])} | {v['runs']} | {v['failed']} "
                     f"| {_pct(v['accept_rate'])} | {_pct(v['wrong_or_extra_rate'])} | {cov} | {held} "
                     f"| {_pct(v['ambiguous_rate'])} | {_pct(v['wrong_pick_rate'])} "
                     f"| {' / '.join(map(str, v['statistic_min_median'] or ['n/a']))} | {_spread(v['z_max'])} "
                     f"| {_spread(v['heading_deg'])} | {v['median_fit_s']} |")
    lines += ["", "| criterion | threshold | value | verdict | detail |", "|---|---|---|---|---|"]
    lines += [f"| {r['criterion']} | {r['threshold']} | {_shown(r)} | {r['verdict']} | {r['detail']} |" for r in rows]
    return "\n".join(lines) + "\n"


def score(out: Path, results: Path | None) -> tuple[dict[str, dict[str, Any]], list[dict[str, Any]]]:
    """Summarise OUT's records, print the report and write it under `results` (None: print only)."""
    recs = load(out)
    summary = summarise(recs)
    rows = checks(summary)
    seeds = sorted({r["seed"] for r in recs})
    total = sum(float(r.get("runtime_sim_s", 0.0)) + float(r.get("runtime_fit_s", 0.0)) for r in recs)
    note = (f"{len(recs)} runs, {len(summary)} cases, seeds {seeds[0] if seeds else '-'}-"
            f"{seeds[-1] if seeds else '-'}; load: {total:.0f} s of simulate + fit in total "
            f"({total / max(1, len(recs)):.1f} s per run, one process each).")
    text = markdown(summary, rows, note)
    print(text)
    if results is not None:
        results.mkdir(parents=True, exist_ok=True)
        (results / "concealed.md").write_text(text)
        (results / "concealed.json").write_text(json.dumps({"note": note, "cases": summary, "criteria": rows},
                                                           indent=1) + "\n")
    return summary, rows


def main(argv: list[str] | None = None) -> None:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/concealed"))
    ap.add_argument("--results", type=Path, default=Path(__file__).resolve().parents[2] / "docs" / "results")
    a = ap.parse_args(argv)
    score(a.out, a.results)


if __name__ == "__main__":
    main()
