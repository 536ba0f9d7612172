"""Messages a person reads once (issue 30 item 4): one sentence each, no brackets within brackets, a folded warning
that says what to do, and no warning that fires on every real log without changing what the user should do."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.cli.common import BRIEF, warning_lines
from magcal_cli.config import Config
from magcal_cli.errors import InsufficientDataError, MagcalError
from magcal_cli.findings import Finding, Severity
from magcal_cli.models import partial
from magcal_cli.models.map import fit as mapm
from magcal_cli.params import BASE
from magcal_cli.pipeline import calibrate, calibrate_recording
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.synth.simulate import simulate
from magcal_cli.writers.report.html import render_html
from magcal_cli.writers.report.text import render
from tests.models.mapsim import record
from tests.wording import depth

PACKAGE = Path(__file__).resolve().parents[2] / "magcal_cli"
#: words that say what to do (or that there is nothing to do)
ACTION = re.compile(r"to fix|record again|rotate|turn the vehicle|log the raw|check the|find the|do not use|"
                    r"nothing to do|-v prints|calibrate from")


def _drifted() -> Recording:
    """A hand-held recording whose field carries a 0.3 uT random-walk disturbance (tests/models/test_widening.py):
    its residuals are correlated in time, as on every real log."""
    rec = simulate("handheld", 0).recording
    mag = rec.select(Kind.MAGNETOMETER)
    walk = np.cumsum(np.random.default_rng(100).normal(size=(len(mag), 3)), axis=0)
    walk *= 0.3e-6 / np.abs(walk).max()
    return replace(rec, streams=tuple(Stream(s.kind, s.id, s.t, s.values + walk, s.source, s.native_unit)
                                      if s.kind is Kind.MAGNETOMETER else s for s in rec.streams))


def test_correlated_residuals_are_a_finding_with_its_number_not_a_warning() -> None:
    """Issue 30: every real log warned 'residuals correlated in time beyond the noise model (uncertainty widened up
    to N x)', which changes nothing the user should do (the stds include it; the verdict judges them). It is now a
    note, and each magnetometer's 'How good' in both reports gives the factor."""
    result = calibrate_recording(_drifted(), Config(method="map"))
    (note,) = [f for f in result.findings if f.code == "correlated_residuals"]
    mag = result.calibration.magnetometers[0]
    assert note.severity is Severity.INFO and note.evidence["sensor"] == mag.id
    factor = float(note.evidence["max_factor"])
    assert factor > 1.0 and depth(note.message) <= 1
    assert not any("correlated" in line for line in warning_lines(result.findings, [mag.id], verbose=False))
    assert f"uncertainty        widened up to {factor:.1f}x" in render(result)
    assert f"widened up to {factor:.1f}x" in render_html(result).split("<section id='effects'")[0]


def test_a_folded_warning_says_what_to_do() -> None:
    """Issue 30: without -v the summary folded log 01_07_59's warnings to 'MAG[0]: attitude reference' and
    'MAG[0], MAG[1]: low coverage', which say nothing; a folded line now says what happened and what to do."""
    advice = "tilt the vehicle through large pitch and roll angles"
    found = (
        Finding(Severity.WARNING, "attitude_reference", "the log's own motion cannot determine the calibration "
                "(01_07_59.px4log: MAG[0]: the motion in this log determines no part of the calibration. To fix: "
                "rotate the vehicle about all three axes); it was calibrated against the vehicle's attitude "
                "estimate (ATT) and the World Magnetic Model instead, so it inherits the errors of that estimate " * 2),
        *(Finding(Severity.WARNING, "low_coverage", f"{m}: the field directions cover only {c:.0f} % of the sphere; "
                  "rotate the vehicle about all three axes (roll it over, pitch it up and down).",
                  {"coverage_pct": c}) for m, c in (("MAG[0]", 8.2), ("MAG[1]", 10.4))),
        *(Finding(Severity.WARNING, "poorly_observable", f"log: {m}: this log leaves the accelerometer bias poorly "
                  f"determined: std {'x' * 200}. To fix: {advice}.") for m in ("MAG[0]", "MAG[1]")))
    lines = warning_lines(found, ["MAG[0]", "MAG[1]"], verbose=False)
    assert lines == [
        "MAG[0]: calibrated against the vehicle's attitude estimate and the World Magnetic Model, as the log's own "
        "motion determines too little, so it inherits that estimate's heading errors; for a calibration of its own, "
        "record again turning the vehicle about all three axes",
        "MAG[0], MAG[1]: the field directions cover only 8-10 % of the sphere; record again, rolling and pitching "
        "the vehicle through all orientations",
        f"MAG[0], MAG[1]: accelerometer bias poorly determined by the motion in this log; to fix: {advice}"]
    assert warning_lines(found, ["MAG[0]", "MAG[1]"], verbose=True) == [f.message for f in found]


def test_every_warning_a_run_raises_folds_to_a_line_that_says_what_to_do() -> None:
    """Each warning code the package can raise has its folded line, and each names what to do (a kind without one
    would fold to its bare title, as 'attitude reference' did)."""
    codes = {m.group(1) for p in PACKAGE.rglob("*.py")
             for m in re.finditer(r'Severity\.WARNING,\s*"([a-z_]+)"', p.read_text(encoding="utf-8"))}
    assert {"attitude_reference", "low_coverage", "poorly_observable", "not_calibrated"} <= codes
    assert codes - {"correlated_residuals"} <= set(BRIEF), sorted(codes - set(BRIEF))
    # a line with {fix} quotes its messages' 'To fix:' advice (or points to -v and the recording guide)
    silent = [c for c in codes - {"correlated_residuals"} if "{fix}" not in BRIEF[c] and not ACTION.search(BRIEF[c])]
    assert not silent
    lines = warning_lines(tuple(Finding(Severity.WARNING, c, f"{m}: {c} " + "x" * 300) for c in sorted(codes)
                                for m in ("MAG[0]", "MAG[1]")), ["MAG[0]", "MAG[1]"], verbose=False)
    # a refused magnetometer is named on a line of its own, with its own reason and advice (issue 38)
    assert len(lines) == len(codes) + 1 and all(ACTION.search(line) or "recording-guide" in line for line in lines)


def _still(yaw_deg: float, rate: float = 50.0, duration: float = 30.0) -> np.ndarray:
    """30 s of yaw swings of `yaw_deg` with 0.1 deg of tilt: a vehicle that hardly moved."""
    t = np.arange(int(duration * rate) + 1) / rate
    yaw = np.deg2rad(yaw_deg) * np.sin(3 * np.pi * t / duration) + 0.4
    a = np.deg2rad(0.1)
    return so3.exp(np.stack([0 * t, 0 * t, yaw], 1)) @ so3.exp(
        np.stack([a * np.sin(0.9 * t), a * np.cos(0.53 * t), 0 * t], 1))


def test_a_refusal_is_one_sentence_without_brackets_in_brackets() -> None:
    """Issue 30: 'the motion in this log determines no part ... with D held at the calibration the vehicle flew with
    (as logged (firmware-corrected) in the log's parameters (px4log)) (the field directions ... (that needs ...))
    (...)': now one sentence with one level of brackets, then what to do; the prior sources it quotes (the
    document's held[].source) nest no deeper either."""
    problem, truths, _ = record(_still(0.3), 50.0, 0, mag_step=5)
    y = problem.mags[0].xyz
    flown = partial.flown_prior(y, y / np.cbrt(np.linalg.det(truths[0].D)), 1.0,
                                "CAL_MAG0_* in the log's parameters (ulog)")   # what the pipeline passes for a .ulg
    assert flown is not None
    held = partial.prior_of(BASE, BASE.zeros(), replace(flown, spread=np.deg2rad([2.0, 1.0, 0.1])),
                            1.0, None)
    assert max(depth(s) for s in held.prior_sources) <= 1
    with pytest.raises(InsufficientDataError) as info:
        mapm.fit_map(replace(problem, priors={problem.mags[0].id: flown}), problem.mags[0], dip_prior=truths[0].dip)
    message = str(info.value)
    assert depth(message) <= 1 and message.count("To fix:") == 1 and "\n" not in message
    what = message.split(" To fix:")[0]
    assert what.startswith(f"{problem.where}: {problem.mags[0].id}: the motion in this log determines no part")
    assert not re.search(r"\. [A-Z]", what) and "held at the calibration the vehicle flew with, as the field directions" in what


def test_the_px4log_refusal_reads_as_one_sentence(realdata: Path) -> None:
    """The issue's example, on the log itself: whatever the method does with it, what it says nests one level."""
    try:
        result = calibrate(realdata / "px4" / "01_07_59.px4log", Config(method="map"))
    except MagcalError as exc:
        assert depth(str(exc)) <= 1 and "firmware-corrected" not in str(exc), str(exc)
        return
    held = [str(h["source"]) for m in result.calibration.magnetometers for h in m.held]
    assert all(depth(s) <= 1 for s in held), held
