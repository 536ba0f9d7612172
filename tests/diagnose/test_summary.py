"""The diagnosis in plain words (issue 30 item 4): one level of brackets, each explanation said once for all the
magnetometers, p-values printed alike everywhere."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import effects as registry
from magcal_cli.diagnose import summary
from magcal_cli.diagnose.ppc import Check
from magcal_cli.diagnose.select import Selection
from magcal_cli.models.result import EffectFit
from tests.wording import depth

MAGS = ("MAG[0]", "MAG[1]", "MAG[2]")


def _paragraph(sensor: str) -> str:
    """log171's case: current and throttle the log cannot tell apart, a lever arm it cannot test."""
    verdicts = (
        EffectFit("current_interference", sensor, "ambiguous", reason="cannot be told apart from throttle_interference "
                  "in this log", confounded_with=("throttle_interference",)),
        EffectFit("throttle_interference", sensor, "ambiguous", reason="cannot be told apart from "
                  "current_interference in this log", confounded_with=("current_interference",)),
        EffectFit("lever_arm", "IMU[0]", "not_testable", reason="in flight the vehicle's acceleration comes from its "
                  "position fixes (GPS[0]), which miss the fast part a lever arm would be confused with"))
    check = Check(("gyro NIS",), np.array([108.5]), 4.3e-82, 19, ())
    return summary.paragraph(sensor, Selection(None, verdicts, None, ()), check, check, "milligauss")  # type: ignore[arg-type]


def test_an_ambiguous_pair_is_said_without_brackets_in_brackets() -> None:
    """Issue 30: '(cannot be told apart ...; to separate them, record throttle steps at several battery charge levels
    (or a bench run with a payload), so ...)' nested the experiment's brackets in the reason's."""
    text = _paragraph("MAG[0]")
    assert depth(text) <= 1, text
    assert "This log cannot tell throttle_interference apart from current_interference; to separate them, record " \
           f"{registry.get('throttle_interference').separating_experiment}." in text


def test_each_explanation_is_said_once_for_all_magnetometers() -> None:
    """Issue 30: log171's report repeated the physics of current and throttle, the recordings that separate them
    and the lever arm's untestable reason for each of its three compasses; now the first paragraph says them and
    the others keep only what is their own."""
    first, second, third = summary.fold([_paragraph(m) for m in ("MAG[0]", "MAG[1]", "MAG[2]")])
    physics = registry.get("current_interference").physics_left_out
    for text in (second, third):
        assert physics not in text and "to separate them" not in text and "not testable" not in text
        assert "This log cannot tell current_interference apart from throttle_interference." in text
    assert physics in first and first.count("to separate them") == 2 and "lever_arm is not testable" in first


@pytest.mark.parametrize(("p", "cell", "sentence"), [
    (0.0, "< 1e-16", "p < 1e-16"), (2.12e-175, "< 1e-16", "p < 1e-16"), (0.032, "0.032", "p = 0.032"),
    (float("nan"), "n/a", "p n/a"), (None, "n/a", "p n/a")])
def test_p_values_print_alike_and_never_as_zero(p: float | None, cell: str, sentence: str) -> None:
    """Issue 30: the Diagnosis table showed p going from '2.12e-175 → 0'; a p below 1e-16 is '< 1e-16' everywhere."""
    assert summary.p_text(p) == cell and summary.p_is(p) == sentence


def test_a_dimensionless_unit_is_not_printed() -> None:
    """Issue 30: 'p = 1.13 +- 0.099 1' printed the unit '1' of a dimensionless estimate."""
    assert summary.unit_suffix("1") == "" and summary.unit_suffix(None) == "" and summary.unit_suffix("s") == " s"


def test_the_document_s_summary_says_each_explanation_once() -> None:
    """The document's top-level `diagnosis.summary` (all magnetometers) folds the same way; each magnetometer's own
    block keeps its whole paragraph (`magcal diagnose` prints it alone)."""
    from types import SimpleNamespace

    from magcal_cli.calibration.assemble import diagnosis_block

    blocks = tuple({"sensor": m, "ppc": {"global_p": 1e-3}, "summary": _paragraph(m)} for m in MAGS)
    doc = diagnosis_block(blocks, {m: SimpleNamespace(native_unit="milligauss") for m in MAGS})  # type: ignore[misc]
    physics = registry.get("throttle_interference").physics_left_out
    assert doc["summary"].count(physics) == 1 and doc["summary"].count("lever_arm is not testable") == 1
    assert all(b["summary"].count(physics) == 1 for b in doc["sensors"])
