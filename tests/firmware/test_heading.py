"""Never silently worse (issue 38 item 6): heading against the vehicle's attitude, magcal's vs the flown calibration.

A simulated ArduPilot flight (flightsim: full turns, +-20 deg of tilt, an ATT stream) flown with a known
calibration; magcal's document is the truth or the truth perturbed, so which is better for heading is known.
Also the report's view of it: magcal_cli.writers.report.sections.heading and report.txt's lines.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.calibration.document import from_dict, to_dict
from magcal_cli.calibration.types import Calibration
from magcal_cli.config import Config
from magcal_cli.firmware.heading import heading_checks
from magcal_cli.pipeline import calibrate_recording
from magcal_cli.writers import get_writer
from magcal_cli.writers.report.html import render_html
from magcal_cli.writers.report.sections.heading import render as heading_section
from magcal_cli.writers.report.text import heading_lines
from magcal_cli.writers.report.text import render as render_text

from .flightsim import flight

#: magcal's hard iron moved by this much (mG; the horizontal field is 550 cos 65 deg = 232 mG): about 20 deg of
#: heading error at the worst heading
PERTURB_MG = (90.0, -60.0, 0.0)


def _perturbed(cal: Calibration) -> Calibration:
    """The truth with its hard iron off by PERTURB_MG."""
    m = cal.magnetometers[0]
    return replace(cal, magnetometers=(replace(m, o=m.o + np.asarray(PERTURB_MG)),))


def _param_file(cal: Calibration, rec: object, tmp_path: Path) -> str:
    """ardupilot.param as `fit` writes it for this document and recording."""
    result = SimpleNamespace(calibration=cal, recording=rec)
    (path,) = get_writer("ardupilot").write(result, tmp_path)  # type: ignore[arg-type]
    return path.read_text()


def test_worse_than_flown_is_said_and_left_out(tmp_path: Path) -> None:
    """Flown = truth, magcal's hard iron 108 mG off: verdict worse, a warning that says the flown calibration is
    better for heading, and MAG[0] absent from ardupilot.param, whose header names it and says why."""
    fl = flight(0, ofs_miss=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0), tilt_deg=(0.0, 0.0))
    cal, found = heading_checks(fl.recording, _perturbed(fl.truth()), [], None)
    block = cal.magnetometers[0].heading_check
    assert block is not None and block["verdict"] == "worse" and block["exported"] is False
    assert block["rms_deg"]["magcal"] > block["rms_deg"]["flown"] + 5.0
    assert block["difference_deg"] > 1.96 * block["difference_std_deg"]
    assert [f.code for f in found] == ["flown_calibration_better"]
    assert "the calibration the vehicle flew with is better for heading" in found[0].message
    assert "left out of the firmware parameter file" in found[0].message
    text = _param_file(cal, fl.recording, tmp_path)
    assert "COMPASS_OFS_X" not in text and "COMPASS_DIA_X" not in text
    assert "# left out: MAG[0]" in text and "worse by more than the comparison's uncertainty" in text
    again = from_dict(to_dict(cal))                        # the block survives the document's round trip
    assert again.magnetometers[0].heading_check == block


def test_export_worse_writes_it_anyway(tmp_path: Path) -> None:
    """--export-worse (Config.export_worse): the same verdict and warning, and MAG[0] is in ardupilot.param."""
    fl = flight(0, ofs_miss=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0), tilt_deg=(0.0, 0.0))
    cal, found = heading_checks(fl.recording, _perturbed(fl.truth()), [], None, export_worse=True)
    block = cal.magnetometers[0].heading_check
    assert block is not None and block["verdict"] == "worse" and block["exported"] is True
    assert "written to the firmware parameter file anyway (--export-worse)" in found[0].message
    text = _param_file(cal, fl.recording, tmp_path)
    assert "COMPASS_OFS_X," in text and "left out" not in text


def test_better_than_a_bad_flown_calibration_is_exported(tmp_path: Path) -> None:
    """Flown offsets 100 mG off, magcal's = truth: verdict better, no warning, MAG[0] exported."""
    fl = flight(1, ofs_miss=(80.0, -60.0, 30.0), c=(0.0, 0.0, 0.0), tilt_deg=(0.0, 0.0))
    cal, found = heading_checks(fl.recording, fl.truth(), [], None)
    block = cal.magnetometers[0].heading_check
    assert block is not None and block["verdict"] == "better" and block["exported"] is True
    assert block["rms_deg"]["magcal"] < 1.0 < 5.0 < block["rms_deg"]["flown"]
    assert found == []
    text = _param_file(cal, fl.recording, tmp_path)
    assert "COMPASS_OFS_X," in text and "left out" not in text


def test_no_attitude_no_block() -> None:
    """Without an attitude stream nothing is measured and the document is unchanged (no new key)."""
    fl = flight(0)
    rec = replace(fl.recording, streams=tuple(s for s in fl.recording.streams if s.id != "ATT"))
    cal, found = heading_checks(rec, fl.truth(), [], None)
    assert cal.magnetometers[0].heading_check is None and found == []
    assert "heading_check" not in to_dict(cal)["magnetometers"][0]


def test_fit_attaches_the_heading_check() -> None:
    """calibrate_recording runs the check: a flight whose flown offsets are 100 mG off gets a block saying
    magcal's calibration is better, shown in report.txt and report.html."""
    fl = flight(1, ofs_miss=(80.0, -60.0, 30.0), c=(0.0, 0.0, 0.0), tilt_deg=(0.0, 0.0))
    result = calibrate_recording(fl.recording, Config())
    block = result.calibration.magnetometers[0].heading_check
    assert block is not None and block["verdict"] == "better", block
    text = render_text(result)
    assert "Heading against the vehicle's attitude" in text and "time folds: better" in text
    page = render_html(result)
    assert "<section id='heading'>" in page and "badge good'>better" in page


def test_report_says_what_was_left_out() -> None:
    """report.txt's lines for a compass left out name the reason and --export-worse; the HTML row says so."""
    fl = flight(0, ofs_miss=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0), tilt_deg=(0.0, 0.0))
    cal, _ = heading_checks(fl.recording, _perturbed(fl.truth()), [], None)
    lines = " ".join(heading_lines(cal.magnetometers[0]))
    assert "time folds: worse" in lines and "left out of the firmware parameter file" in lines
    assert "--export-worse" in lines
    ctx = SimpleNamespace(result=SimpleNamespace(calibration=cal, recording=fl.recording), anchor="heading")
    page = heading_section(ctx)  # type: ignore[arg-type]
    assert "left out (the vehicle keeps its own)" in page
    assert "Heading error against the vehicle&#x27;s attitude" in page and "data:image/svg+xml;base64," in page


def test_ardupilot_trim_levels_the_board() -> None:
    """ATT is the vehicle's attitude, the board's less AHRS_TRIM_X/Y (as magfit_WMM reads it): with the trim
    added back the true calibration's heading error vanishes; read without it, 3 deg of pitch trim at dip 65 deg
    would show as several degrees of heading error."""
    fl = flight(0, ofs_miss=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0), tilt_deg=(0.0, 0.0))
    trim = (0.02, 0.05)
    att = next(s for s in fl.recording.streams if s.id == "ATT")
    rpy = so3.as_rpy(so3.from_quat(att.values)) - np.array([*trim, 0.0])
    vehicle = replace(att, values=so3.as_quat(so3.from_rpy(rpy)))
    streams = tuple(vehicle if s.id == "ATT" else s for s in fl.recording.streams)
    rec = replace(fl.recording, streams=streams, params={**fl.recording.params, "AHRS_TRIM_X": trim[0],
                                                          "AHRS_TRIM_Y": trim[1]})
    cal, _ = heading_checks(rec, fl.truth(), [], None)
    block = cal.magnetometers[0].heading_check
    assert block is not None, "no heading check"
    assert block["rms_deg"]["magcal"] < 0.5, block["rms_deg"]
    untrimmed, _ = heading_checks(replace(rec, params=fl.recording.params), fl.truth(), [], None)
    assert untrimmed.magnetometers[0].heading_check["rms_deg"]["magcal"] > 2.0  # type: ignore[index]


@pytest.mark.parametrize(("flag", "expected"), [((), False), (("--export-worse",), True)])
def test_fit_option_reaches_the_pipeline(flag: tuple[str, ...], expected: bool, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """`magcal fit --export-worse` sets Config.export_worse (default off), which heading_checks reads."""
    from click.testing import CliRunner

    from magcal_cli import pipeline
    from magcal_cli.cli.main import cli
    from magcal_cli.errors import MagcalError

    seen: list[Config] = []

    def stop(path: Path, cfg: Config, *args: object) -> None:
        seen.append(cfg)
        raise MagcalError("stopped by the test")

    monkeypatch.setattr(pipeline, "calibrate", stop)
    log = Path(__file__).resolve().parents[2] / "sample_logs" / "handheld.bin"
    out = CliRunner().invoke(cli, ["fit", str(log), "-o", str(tmp_path / "out"), *flag])
    assert out.exit_code == 1 and [c.export_worse for c in seen] == [expected], out.output


def test_two_compasses_only_the_worse_is_left_out(tmp_path: Path) -> None:
    """Two compasses reading the same field with the same flown calibration: MAG[0] magcal's = truth (not worse),
    MAG[1] perturbed (worse). ardupilot.param keeps COMPASS_OFS_* for MAG[0] and leaves COMPASS_OFS2_* out,
    its header naming MAG[1]."""
    fl = flight(0, ofs_miss=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0), tilt_deg=(0.0, 0.0))
    rec = fl.recording
    mag0 = next(s for s in rec.streams if s.id == "MAG[0]")
    second = {k.replace("COMPASS_OFS_", "COMPASS_OFS2_").replace("COMPASS_DIA_", "COMPASS_DIA2_")
              .replace("COMPASS_ODI_", "COMPASS_ODI2_").replace("COMPASS_USE", "COMPASS_USE2")
              .replace("COMPASS_EXTERNAL", "COMPASS_EXTERN2").replace("COMPASS_ORIENT", "COMPASS_ORIENT2"): v
              for k, v in rec.params.items() if k.startswith(("COMPASS_OFS_", "COMPASS_DIA_", "COMPASS_ODI_"))
              or k in ("COMPASS_USE", "COMPASS_EXTERNAL", "COMPASS_ORIENT")}
    rec = replace(rec, streams=(*rec.streams, replace(mag0, id="MAG[1]")), params={**rec.params, **second})
    truth = fl.truth()
    m1 = _perturbed(truth).magnetometers[0]
    cal, found = heading_checks(rec, replace(truth, magnetometers=(*truth.magnetometers, replace(m1, id="MAG[1]"))),
                                [], None)
    verdicts = {m.id: (m.heading_check or {}).get("verdict") for m in cal.magnetometers}
    assert verdicts["MAG[1]"] == "worse" and verdicts["MAG[0]"] in ("same", "better"), verdicts
    assert [f.evidence["sensor"] for f in found] == ["MAG[1]"]
    text = _param_file(cal, rec, tmp_path)
    assert "COMPASS_OFS_X," in text and "COMPASS_OFS2_X" not in text and "# left out: MAG[1]" in text
    assert "left out: MAG[0]" not in text
