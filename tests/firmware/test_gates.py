"""The --fail-on expression language: grammar, semantics, every message."""

from __future__ import annotations

import pytest

from magcal_cli.firmware.gates import Condition, GateSyntaxError, failures, parse

KNOWN = {"heading_error_deg": "", "field_norm_rms_pct": "", "coverage_pct": ""}


def test_parse_conditions() -> None:
    got = parse(" heading_error_deg>5 , field_norm_rms_pct >= 2.5,coverage_pct<1e2", KNOWN)
    assert got == (Condition("heading_error_deg", ">", 5.0), Condition("field_norm_rms_pct", ">=", 2.5),
                   Condition("coverage_pct", "<", 100.0))
    assert [str(c) for c in got] == ["heading_error_deg>5", "field_norm_rms_pct>=2.5", "coverage_pct<100"]


def test_each_operator() -> None:
    assert Condition("m", ">", 5).holds(5.1) and not Condition("m", ">", 5).holds(5.0)
    assert Condition("m", ">=", 5).holds(5.0) and Condition("m", "<", 5).holds(4.9)
    assert Condition("m", "<=", 5).holds(5.0) and not Condition("m", "<=", 5).holds(5.01)


def test_failures_report_values_and_unmeasured_metrics() -> None:
    conds = parse("heading_error_deg>5,coverage_pct<50", KNOWN)
    assert failures(conds, {"heading_error_deg": 4.0, "coverage_pct": 80.0}) == []
    assert failures(conds, {"heading_error_deg": 7.25, "coverage_pct": None}, {"coverage_pct": "no data"}) == [
        "heading_error_deg>5 (measured 7.25)", "coverage_pct<50 (not measured: no data)"]
    assert failures(conds, {}) == ["heading_error_deg>5 (not measured: not measured)",
                                   "coverage_pct<50 (not measured: not measured)"]


@pytest.mark.parametrize("text", ["heading_error_deg=>5", "heading_error_deg>five", "__import__('os')>1",
                                  "heading_error_deg>5 or 1", "heading_error_deg>nan", "5>heading_error_deg"])
def test_anything_else_is_a_syntax_error(text: str) -> None:
    """No eval: only METRIC OP NUMBER passes."""
    with pytest.raises(GateSyntaxError, match=r"--fail-on: .* is not METRIC OP NUMBER \(OP one of >, >=, <, <=\), "
                                              r"e.g. heading_error_deg>5"):
        parse(text, KNOWN)


def test_empty_and_unknown() -> None:
    with pytest.raises(GateSyntaxError, match=r"--fail-on 'a>1,': empty condition; write METRIC OP NUMBER"):
        parse("a>1,", KNOWN)
    with pytest.raises(GateSyntaxError, match=r"--fail-on: unknown metric 'heading_eror_deg'; this command measures "
                                              r"coverage_pct, field_norm_rms_pct, heading_error_deg"):
        parse("heading_eror_deg>5", KNOWN)
