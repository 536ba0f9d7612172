"""report.txt and the numbers report.html shares with it, as a person reads them once (issue 30 item 4): no unit
after a dimensionless estimate, no p printed as 0, each effect explained once, and the files the run wrote."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from magcal_cli import effects as registry
from magcal_cli.calibration.run import RunResult
from magcal_cli.config import Config
from magcal_cli.pipeline import calibrate_recording
from magcal_cli.synth.simulate import Simulation
from magcal_cli.writers import write_outputs
from magcal_cli.writers.report.html import render_html
from magcal_cli.writers.report.text import render

MAGS = ("MAG[0]", "MAG[1]", "MAG[2]")


@pytest.fixture(scope="module")
def result(sim: Simulation) -> RunResult:
    """The base-model fit of the shared hand-held simulation."""
    return calibrate_recording(sim.recording, Config(method="map"))


def _throttle(sensor: str, p: float) -> dict[str, Any]:
    """log171's throttle interference entry: an estimate with a dimensionless exponent, a Wald p far below 1e-16."""
    return {"id": "throttle_interference", "sensor": sensor, "status": "ambiguous",
            "params": {"c": [163.7, -260.6, 406.5], "p": 1.13}, "std": {"c": [9.1, 22.0, 14.0], "p": 0.099},
            "units": {"c": "milligauss", "p": "1"}, "test": {"kind": "wald", "p_value": p},
            "confounded_with": ["current_interference"],
            "reason": "cannot be told apart from current_interference in this log",
            "physics_left_out": f"{registry.get('throttle_interference').physics_left_out} This log cannot tell it "
                                "apart from current_interference; to separate them, record throttle steps."}


@pytest.fixture(scope="module")
def with_effects(result: RunResult) -> RunResult:
    """The fit with log171's throttle entries for three compasses (p 1.5e-183 and 0.0 among them) and a diagnosis
    whose simulation check went from 2.12e-175 to 0."""
    effects = tuple(_throttle(m, p) for m, p in zip(MAGS, (1.5e-183, 0.0, 0.00021), strict=True))
    block = {"sensor": "MAG[0]", "ppc": {"global_p": 2.12e-175, "top": []}, "ppc_after": {"global_p": 0.0},
             "located": {}, "summary": "MAG[0]: the recording disagrees."}
    return replace(result, calibration=replace(result.calibration, effects=effects, diagnosis={**block,
                                                                                             "sensors": [block]}))


def test_a_dimensionless_estimate_has_no_unit(with_effects: RunResult) -> None:
    """Issue 30: the report printed a stray unit '1' after dimensionless estimates ('p = 1.13 +- 0.099 1')."""
    text, page = render(with_effects), render_html(with_effects)
    assert "p = 1.13 +- 0.099;" in text and "0.099 1" not in text
    assert "p = 1.13 +- 0.099<" in page and "0.099 1" not in page


def test_no_p_value_prints_as_zero(with_effects: RunResult) -> None:
    """Issue 30: the Diagnosis table showed p going from '2.12e-175 → 0'; every p below 1e-16 prints '< 1e-16', in
    the text report's effects, the page's effects and its Diagnosis table alike."""
    text, page = render(with_effects), render_html(with_effects)
    assert text.count("Wald test p < 1e-16") == 2 and "Wald test p = 0.00021" in text
    assert "p = 0." not in text.replace("p = 0.00021", "")
    diagnosis = page[page.index("<section id='diagnosis'"):page.index("</section>", page.index("id='diagnosis'"))]
    assert "<td>&lt; 1e-16 &rarr; &lt; 1e-16</td>" in diagnosis
    effects = page[page.index("<section id='effects'"):page.index("<section id='diagnosis'")]
    assert effects.count("<td>&lt; 1e-16</td>") == 2 and "<td>0</td>" not in effects


def test_each_effect_is_explained_once(with_effects: RunResult) -> None:
    """Issue 30: one sentence for all magnetometers: the physics of an effect tested on three compasses, and the
    recording that separates it from its rival, are said once, then one line per compass."""
    text = render(with_effects)
    words = " ".join(text.split())                     # report.txt wraps its paragraphs at 100 characters
    physics = registry.get("throttle_interference").physics_left_out
    assert words.count(physics) == 1 and words.count("battery charge levels") == 1
    assert all(f"    - {m}: ambiguous, Wald test" in text for m in MAGS)
    page = render_html(with_effects)
    assert page[page.index("<section id='effects'"):page.index("<section id='diagnosis'")].count(physics) == 1


def test_provenance_lists_every_file_the_run_wrote(result: RunResult, tmp_path: Path) -> None:
    """Issue 30: provenance left out ardupilot.param (and report.html): both reports list every file written."""
    paths = write_outputs(result, tmp_path, ["json", "yaml", "report", "plots", "ardupilot"])
    names = [p.name for p in paths]
    assert names == ["calibration.json", "calibration.yaml", "report.txt", "report.html", "ardupilot.param"]
    page = (tmp_path / "report.html").read_text(encoding="utf-8")
    provenance = page[page.index("<section id='provenance'"):]
    assert ", ".join(names) in provenance
    assert f"Files:   {', '.join(names)}" in (tmp_path / "report.txt").read_text(encoding="utf-8")
