"""report.html: its order, its self-containment, the grouped warnings and the numbers behind its plots.

Modules it covers (the mirrored test file aside): magcal_cli.findings, magcal_cli.writers.report.data,
magcal_cli.writers.report.html, magcal_cli.writers.report.sections.base,
magcal_cli.writers.report.sections.diagnosis, magcal_cli.writers.report.sections.effects,
magcal_cli.writers.report.sections.magnetometer, magcal_cli.writers.report.sections.markup,
magcal_cli.writers.report.sections.method, magcal_cli.writers.report.sections.notes,
magcal_cli.writers.report.sections.provenance, magcal_cli.writers.report.sections.summary,
magcal_cli.writers.report.text, magcal_cli.writers.report.verdict.
"""

from __future__ import annotations

import base64
import re
from dataclasses import replace
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest

from magcal_cli.calibration.run import RunResult
from magcal_cli.config import Config
from magcal_cli.findings import Finding, Severity
from magcal_cli.firmware.metrics import heading_std_curve_deg, heading_std_deg
from magcal_cli.pipeline import calibrate_recording
from magcal_cli.synth.simulate import Simulation
from magcal_cli.writers import get_writer
from magcal_cli.writers.report import verdict as rs
from magcal_cli.writers.report.data import heading_view, mag_view
from magcal_cli.writers.report.html import SECTIONS, render_html
from magcal_cli.writers.report.sections.base import Context, Section
from magcal_cli.writers.report.verdict import groups, verdicts


@pytest.fixture(scope="module")
def result(sim: Simulation) -> RunResult:
    """The base-model fit of the shared hand-held simulation."""
    return calibrate_recording(sim.recording, Config(method="map"))


@pytest.fixture(scope="module")
def page(result: RunResult) -> str:
    """The HTML report of that fit."""
    return render_html(result)


def test_sections_come_summary_first(page: str) -> None:
    """Summary (verdict, key numbers, next steps), then method, magnetometers, effects, diagnosis, warnings, provenance."""
    ids = re.findall(r"<section id='([^']+)'", page)
    assert ids[0] == "summary" and ids[1] == "method" and ids[2].startswith("mag-")
    assert ids[-4:] == ["effects", "diagnosis", "warnings", "provenance"]
    summary = page[page.index("id='summary'"):page.index("id='method'")]
    assert "What to do next" in summary and "field strength error" in summary


def test_navigation_and_body_follow_sections(page: str, result: RunResult) -> None:
    """The links and the sections both come from SECTIONS, in its order, and every in-page link has its target
    (issue 26: a section is its module and one SECTIONS line)."""
    cal = result.calibration
    ctx = Context(result, verdicts(result), groups(result.findings, [m.id for m in cal.magnetometers]))
    expected = [c.anchor for s in SECTIONS for c in s.contexts(ctx)]
    ids = re.findall(r"<section id='([^']+)'", page)
    nav = re.findall(r"<a href='#([^']+)'>", page[page.index("<nav>"):page.index("</nav>")])
    assert nav == ids == expected
    assert set(re.findall(r"href='#([^']+)'", page)) <= set(ids)


def test_a_section_is_one_line(result: RunResult, monkeypatch: pytest.MonkeyPatch) -> None:
    """A new SECTIONS line adds its link and its body; a section with nothing to show (None) adds neither."""
    from magcal_cli.writers.report import html

    extra = (Section("extra", "Extra", lambda c: f"<section id='{c.anchor}'><h2>Extra</h2></section>"),
             Section("empty", "Empty", lambda c: None))
    monkeypatch.setattr(html, "SECTIONS", (*html.SECTIONS, *extra))
    page = html.render_html(result)
    assert re.findall(r"<section id='([^']+)'", page)[-2:] == ["provenance", "extra"]
    assert "<a href='#extra'>Extra</a></nav>" in page and "'#empty'" not in page and "id='empty'" not in page


def test_page_is_self_contained_and_wraps(page: str) -> None:
    """No script, no external resource; every image an embedded SVG (issue 27: drawn without matplotlib) with no
    script or link of its own; long lines wrap (issue 13 item 1)."""
    assert "<script" not in page and "<link" not in page and not re.search(r"(src|href)=['\"](https?:|//)", page)
    images = re.findall(r"<img src='([^']*)'", page)
    assert len(images) >= 3 and all(i.startswith("data:image/svg+xml;base64,") for i in images)
    for uri in images:
        svg = base64.b64decode(uri.split(",", 1)[1]).decode("utf-8")
        root = ElementTree.fromstring(svg)            # well-formed
        assert root.tag == "{http://www.w3.org/2000/svg}svg"
        assert "<script" not in svg and "href" not in svg
    assert "overflow-wrap:anywhere" in page and "white-space:pre-wrap" in page


def test_plots_sit_beside_their_magnetometer(page: str, result: RunResult) -> None:
    """Each magnetometer's section holds its own text and its figures side by side."""
    for mag in result.calibration.magnetometers:
        start = page.index(f"<h2>Magnetometer {mag.id}")
        section = page[start:page.index("</section>", start)]
        assert "class='pair'" in section and "hard iron b" in section
        assert section.count("<img ") == 3 and "Field on the sphere" in section      # no modelled effect: 3


def test_writer_writes_report_html(result: RunResult, tmp_path: Path) -> None:
    """The `plots` output writes report.html."""
    (path,) = get_writer("plots").write(result, tmp_path)
    assert path.name == "report.html" and path.read_text(encoding="utf-8").startswith("<!doctype html>")


def test_verdict_follows_quality(result: RunResult) -> None:
    """A clean simulated fit is good; a field-strength spread above 5 % makes it not usable, with the reason."""
    (v,) = verdicts(result)
    assert v.level == "good" and v.reasons == ()
    mag = result.calibration.magnetometers[0]
    assert mag.quality is not None
    worse = replace(mag, quality=replace(mag.quality, field_norm_rms_pct=6.0))
    cal = replace(result.calibration, magnetometers=(worse,))
    (bad,) = verdicts(replace(result, calibration=cal))
    assert bad.level == "poor" and bad.reasons == ("the calibrated field strength still varies by 6.00 % RMS",)


def test_low_coverage_is_a_caveat_while_the_heading_is_determined(result: RunResult,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A flight covering 11 % of the sphere with heading sigma 0.75 deg is usable with caveats; at 6 deg it is not."""
    base = rs.fit_metrics(result)
    mid = result.calibration.magnetometers[0].id
    for heading, level in ((0.75, "check"), (6.0, "poor")):
        m = dict(base[mid][0]) | {"coverage_pct": 11.0, "heading_std_deg": heading}
        monkeypatch.setattr(rs, "fit_metrics", lambda _r, m=m: {mid: (m, *base[mid][1:])})
        (v,) = verdicts(result)
        assert v.level == level, (heading, v.reasons)
        assert "the log covers only 11 % of the field directions" in v.reasons


def test_warnings_grouped_in_full() -> None:
    """Findings group by code, warnings first, naming the sensors; every message is kept whole (issue 13 item 7)."""
    long = "MAG[1]: this log leaves the accelerometer bias poorly determined: " + "x" * 300
    fs = (Finding(Severity.INFO, "method_note", "MAG[0]: started from the gyro-integrated trajectory"),
          Finding(Severity.WARNING, "poorly_observable", "MAG[0]: this log leaves the bias poorly determined"),
          Finding(Severity.WARNING, "poorly_observable", long))
    gs = groups(fs, ["MAG[0]", "MAG[1]"])
    assert [g.code for g in gs] == ["poorly_observable", "method_note"]
    assert gs[0].sensors == ("MAG[0]", "MAG[1]") and gs[0].messages[1] == long
    assert gs[0].title == "Parameters the log determines poorly"


def test_heading_band_is_the_metric(result: RunResult) -> None:
    """The plotted 1-sigma band is the curve whose maximum is the heading_std_deg gate (one copy of the math)."""
    mag = result.calibration.magnetometers[0]
    curve = heading_std_curve_deg(mag)
    assert curve is not None and float(curve.max()) == heading_std_deg(mag)
    view = heading_view(result, mag)
    assert view.std is not None and np.array_equal(view.std, curve)
    assert view.raw.shape == view.headings.shape


def test_dip_view_recovers_the_fitted_dip(result: RunResult) -> None:
    """The accelerometer-referenced dip of the calibrated field scatters around the fitted dip."""
    mag = result.calibration.magnetometers[0]
    view = mag_view(result, mag)
    assert view is not None and view.dip_cal is not None
    assert np.nanmedian(view.dip_cal) == pytest.approx(mag.dip_deg, abs=1.0)
    assert np.sqrt(np.mean(view.norm_cal_pct ** 2)) < 1.0


def test_the_apply_step_names_the_terms_the_calibration_carries(result: RunResult) -> None:
    """A calibration that carries a magnetometer effect (here an ambiguous current term with its estimate) tells
    the reader to correct for it before A; its unmodelled rival and a calibration without terms do not."""
    from magcal_cli.writers.report.text import render

    mag = result.calibration.magnetometers[0]
    plain = render(result)
    assert "after correcting the readings for" not in plain
    fitted = {"id": "current_interference", "sensor": mag.id, "status": "ambiguous", "params": {"c": [1e-8, 0, 0]}}
    rival = {"id": "throttle_interference", "sensor": mag.id, "status": "ambiguous", "params": {}}
    carried = replace(result, calibration=replace(result.calibration, effects=(fitted, rival)))
    text = render(carried)
    assert f"after correcting the readings for current_interference (calibration.json: effects[] of {mag.id}" in text
    assert "throttle_interference (calibration.json" not in text
