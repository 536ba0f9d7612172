"""The concealed-effect suite (benchmarks/concealed): a fast end-to-end subset and the scorer's arithmetic."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks" / "concealed"))

import cases  # noqa: E402
import run  # noqa: E402
import score  # noqa: E402

#: what `magcal fit --effects` gets: the default diagnosis
EFFECTS_ARG = "auto"
#: two short cases: a clear concealed current effect and a decoy-rich negative control
SUBSET = ("clear_current_interference", "neg_decoys_flight")


@pytest.mark.parametrize("effects_arg", [EFFECTS_ARG])
def test_subset_end_to_end(tmp_path: Path, effects_arg: str) -> None:
    chosen = [cases.CASES[n] for n in SUBSET]
    assert run.run_suite(tmp_path, 1, 2, chosen, effects_arg) == 2
    assert run.run_suite(tmp_path, 1, 2, chosen, effects_arg) == 0          # resumable: nothing left to do
    rec = json.loads(run.record_path(tmp_path, chosen[0], 0).read_text())
    assert rec["exit_code"] == 0 and rec["truth"][0]["units"]["c"] == "milligauss/ampere"
    summary, rows = score.score(tmp_path, tmp_path / "results")
    assert summary["clear_current_interference"]["accept_rate"] == 1.0
    assert summary["clear_current_interference"]["wrong_or_extra_rate"] == 0.0
    assert summary["neg_decoys_flight"]["false_accept_rate"] == 0.0
    assert (tmp_path / "results" / "concealed.md").exists()
    assert {r["criterion"] for r in rows} >= {"negative controls: any effect accepted"}


def _entry(eid: str, status: str, **kw: Any) -> dict[str, Any]:
    return {"id": eid, "sensor": "MAG[0]", "status": status, "params": kw.pop("params", {}),
            "ci95": kw.pop("ci95", {}), "confounded_with": kw.pop("confounded_with", []), **kw}


def _rec(case: str, seed: int, effects: list[dict[str, Any]] | None, truth: list[dict[str, Any]]) -> dict[str, Any]:
    return {"case": case, "tier": cases.CASES[case].tier, "seed": seed, "effects": effects, "truth": truth,
            "effects_arg": "auto", "exit_code": 0 if effects is not None else 1, "runtime_fit_s": 1.0}


CUR_TRUTH = [{"id": "current_interference", "params": {"c": [0.1, -0.2, 0.3]}},
             {"id": "temperature_drift", "params": {"k": [0.0, 0.0, 0.0], "T0": 25.0}}]


def test_scorer_counts_wrong_extra_and_coverage() -> None:
    good_ci = {"c": [[0.05, 0.15], [-0.25, -0.15], [0.0, 0.2]]}             # third misses 0.3
    recs = [
        _rec("clear_current_interference", 0, [_entry("current_interference", "accepted", ci95=good_ci,
                                                      evidence={"heldout_gain_ci95": [0.1, 0.3]})], CUR_TRUTH),
        _rec("clear_current_interference", 1, [_entry("current_interference", "accepted", ci95=good_ci,
                                                      evidence={"heldout_rms_before": 2.0, "heldout_rms_after": 2.5}),
                                               _entry("temperature_drift", "accepted")], CUR_TRUTH),
        _rec("clear_current_interference", 2, [_entry("current_interference", "rejected")], CUR_TRUTH),
        _rec("clear_current_interference", 3, None, CUR_TRUTH),
    ]
    v = score.summarise(recs)["clear_current_interference"]
    assert (v["runs"], v["failed"]) == (4, 1)
    assert v["accept_rate"] == 0.5 and v["wrong_or_extra_rate"] == 0.25 and v["exact_rate"] == 0.25
    assert (v["covered"], v["intervals"]) == (4, 6)
    assert (v["heldout_ok"], v["heldout_n"]) == (1, 2)


def test_scorer_negative_and_inseparable() -> None:
    neg = [_rec("neg_decoys_flight", s, [_entry("current_interference", "accepted" if s == 0 else "rejected")], [])
           for s in range(4)]
    amb = [_entry("current_interference", "ambiguous", confounded_with=[{"id": "temperature_drift"}]),
           _entry("temperature_drift", "ambiguous", confounded_with=["current_interference"])]
    insep = [_rec("insep_current_vs_temperature", 0, amb, CUR_TRUTH),
             _rec("insep_current_vs_temperature", 1, [_entry("temperature_drift", "accepted")], CUR_TRUTH),
             _rec("insep_current_vs_temperature", 2, [_entry("current_interference", "accepted")], CUR_TRUTH),
             _rec("insep_current_vs_temperature", 3, [_entry("current_interference", "rejected")], CUR_TRUTH)]
    summary = score.summarise(neg + insep)
    assert summary["neg_decoys_flight"]["false_accept_rate"] == 0.25
    v = summary["insep_current_vs_temperature"]
    assert v["ambiguous_rate"] == 0.25 and v["wrong_pick_rate"] == 0.25
    verdicts = {r["criterion"]: r["verdict"] for r in score.checks(summary)}
    assert verdicts["negative controls: any effect accepted"] == "FAIL"
    assert verdicts["insep_current_vs_temperature: confident wrong pick"] == "FAIL"
    assert verdicts["held-out improvement of correct accepts"] == "n/a"


def test_scalar_interval_and_case_matrix() -> None:
    truth = [{"id": "time_offset", "params": {"tau_s": 0.0007}}]
    rec = _rec("clear_time_offset", 0, [_entry("time_offset", "accepted", ci95={"tau_s": [0.0005, 0.0009]})], truth)
    assert score.coverage(rec, "time_offset") == [True]
    tiers = {c.tier for c in cases.CASES.values()}
    assert tiers == set(cases.TIERS)
    for c in cases.CASES.values():
        assert set(c.expected) <= set(c.candidates) and set(c.ambiguous) <= set(c.candidates)
    assert run.effects_value(cases.CASES["sep_current_vs_throttle"], "explicit") == \
        "current_interference,throttle_interference"
    assert run.effects_value(cases.CASES["sep_current_vs_throttle"], "auto") == "auto"


def test_scorer_timing_lag_and_z_criteria() -> None:
    """Issue 25's rows: time_offset on the timing grid, the lag tier's mean error and coverage, pooled |z|."""
    lag = [{"id": "time_offset", "params": {"tau_s": 0.020}}]
    recs = [_rec("timing_handheld", s, [_entry("time_offset", "accepted" if s == 0 else "rejected")], [])
            for s in range(20)]
    recs += [_rec("lag_handheld", s, [_entry("time_offset", "accepted", params={"tau_s": 0.0203},
                                             ci95={"tau_s": [0.0199, 0.0207] if s else [0.0201, 0.0207]})], lag)
             for s in range(10)]
    for r in recs:
        r["z"] = [["MAG[0]", "o.x", 0.5], ["MAG[0]", "o.y", -2.5]] if r["seed"] != 3 else [["MAG[0]", "o.x", 5.5]]
    summary = score.summarise(recs)
    assert summary["timing_handheld"]["time_offset_rate"] == 0.05
    assert summary["lag_handheld"]["lag_errors"] == pytest.approx([0.0003] * 10)
    rows = {r["criterion"]: r for r in score.checks(summary)}
    assert rows["timing_handheld: time_offset accepted (issue 25)"]["verdict"] == "PASS"
    assert rows["lag_handheld: |mean error| of tau (issue 25)"]["value"] == pytest.approx(0.0003)
    assert rows["lag_handheld: 95 % interval coverage (issue 25)"]["value"] == 0.9
    assert rows["base parameters |z| <= 1.96, pooled (issue 25)"]["value"] == pytest.approx(28 / 58)      # seed 3 of both cases: one z
    assert rows["logs with max |z| <= 5 (issue 25)"]["verdict"] == "FAIL"


def test_a_drifting_offset_is_compared_at_the_fits_reference_temperature() -> None:
    """The fit reports o at its T0 (the log's mean temperature), the simulator's truth at 25 degC: the truth's
    offset moves by k (T0_fit - T0_true) before the two are compared."""
    from truth_score import z_scores  # run.py put benchmarks/ on the path

    truth = {"magnetometers": [{"id": "MAG[0]", "D": np.eye(3).tolist(), "o": [10.0, 0.0, 0.0], "dip_deg": 60.0}],
             "effects": [{"id": "temperature_drift", "sensor": "MAG[0]", "params": {"k": [0.5, 0.0, 0.0], "T0": 25.0}}]}
    doc = {"magnetometers": [{"id": "MAG[0]", "D": np.eye(3).tolist(), "o": [14.0, 0.0, 0.0], "dip_deg": 60.0,
                              "std": {"D": np.full((3, 3), 0.1).tolist(), "o": [0.1] * 3, "dip_deg": 0.1}}],
           "effects": [{"id": "temperature_drift", "sensor": "MAG[0]", "status": "accepted",
                        "params": {"k": [0.5, 0.0, 0.0], "T0": 33.0}}]}
    assert max(abs(z.z) for z in z_scores(doc, truth)) < 1e-9
