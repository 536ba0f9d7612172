"""`magcal apply`: the calibrated field over time as CSV, interference subtracted, messages.

Modules it covers (the mirrored test file aside): magcal_cli.cli.apply.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import so3
from magcal_cli.calibration.apply import apply_to_recording
from magcal_cli.cli.main import cli
from magcal_cli.errors import StreamError
from magcal_cli.streams import Kind

from ..firmware.flightsim import flight

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_logs" / "handheld.bin"


def rows(text: str) -> np.ndarray:
    """The numeric columns (t, mx, my, mz, norm) of the CSV."""
    lines = text.splitlines()[1:]
    return np.array([[float(v) for i, v in enumerate(ln.split(",")) if i != 1] for ln in lines])


def test_the_truth_gives_the_field_strength_and_the_true_direction() -> None:
    """Applying the truth (with its current term) to a simulated flight: |b| = F within the noise, and b is the
    Earth field seen at the true attitude (to 0.5 %)."""
    fl = flight(0, noise=0.5)
    effect = {"id": "current_interference", "sensor": "MAG[0]", "status": "accepted",
              "params": {"c": fl.c.tolist()}, "units": {"c": "milligauss/ampere"}}
    cal = replace(fl.truth(), effects=(effect,))
    text, notes = apply_to_recording(cal, fl.recording)
    assert text.splitlines()[0] == "t [s],id,mx [mG],my [mG],mz [mG],norm [mG]"
    assert notes == ["MAG[0]: current_interference removed"]
    data = rows(text)
    F = cal.magnetometers[0].field_strength
    assert np.abs(data[:, 4] / F - 1).max() < 0.005
    R = so3.from_quat(fl.recording.select(Kind.ATTITUDE).values)
    dip = np.deg2rad(fl.dip_deg)
    expected = F * np.einsum("nji,j->ni", R, [np.cos(dip), 0.0, np.sin(dip)])
    assert np.max(np.linalg.norm(data[:, 1:4] - expected, axis=1)) / F < 0.005
    without, _ = apply_to_recording(fl.truth(), fl.recording)
    assert np.max(np.linalg.norm(rows(without)[:, 1:4] - expected, axis=1)) / F > 0.02   # the term mattered


def test_an_ambiguous_term_the_fit_modelled_is_applied_and_exported_its_rival_not() -> None:
    """Current and throttle ambiguous (proportional in the log): the one the fit modelled carries c and is part
    of the calibration, in `apply` and in the ArduPilot export (with a note); the rival without c is neither.
    Dropped, D and o fitted with the term were wrong in flight (log171 MAG[1]: yaw RMS 26.5 against 11.4 deg)."""
    from magcal_cli.firmware.ardupilot import export_ardupilot

    fl = flight(0, noise=0.5)
    modelled = {"id": "current_interference", "sensor": "MAG[0]", "status": "ambiguous",
                "params": {"c": fl.c.tolist()}, "units": {"c": "milligauss/ampere"},
                "confounded_with": ["throttle_interference"]}
    rival = {"id": "throttle_interference", "sensor": "MAG[0]", "status": "ambiguous", "params": {},
             "confounded_with": ["current_interference"]}
    accepted = replace(fl.truth(), effects=({**modelled, "status": "accepted"},))
    cal = replace(fl.truth(), effects=(modelled, rival))
    text, notes = apply_to_recording(cal, fl.recording)
    assert notes == ["MAG[0]: current_interference removed"]
    assert text == apply_to_recording(accepted, fl.recording)[0]
    exp = export_ardupilot(cal, fl.recording.params)
    same = export_ardupilot(accepted, fl.recording.params)
    assert exp.params["COMPASS_MOTCT"] == 2 and all(
        exp.params[f"COMPASS_MOT_{a}"] == same.params[f"COMPASS_MOT_{a}"] != 0 for a in "XYZ")
    assert any("exported although the diagnosis found it ambiguous" in n for m in exp.mags for n in m.notes)
    only_rival = export_ardupilot(replace(fl.truth(), effects=(rival,)), fl.recording.params)
    assert "COMPASS_MOTCT" not in only_rival.params


def test_apply_cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "field.csv"
    truth = SAMPLE.with_name(SAMPLE.name + ".truth.json")
    result = CliRunner().invoke(cli, ["apply", str(truth), str(SAMPLE), "-o", str(out), "-q"])
    assert result.exit_code == 0 and result.stdout == f"wrote {out}\n"
    data = rows(out.read_text())
    strength = json.loads(truth.read_text())["magnetometers"][0]["field_strength"]
    assert np.median(data[:, 4]) == pytest.approx(strength, rel=0.01)
    again = CliRunner().invoke(cli, ["apply", str(truth), str(SAMPLE), "-o", str(out)])
    assert again.exit_code == 2 and "exists already. Pass --force to overwrite it" in again.stderr
    monkeypatch.chdir(tmp_path)
    piped = CliRunner().invoke(cli, ["apply", str(truth), str(SAMPLE), "-o", "-", "-q"])  # '-': standard output
    assert piped.exit_code == 0 and piped.stdout == out.read_text() and not Path("-").exists()


def test_apply_errors() -> None:
    fl = flight(0)
    other = replace(fl.truth(), magnetometers=(replace(fl.truth().magnetometers[0], id="/imu/mag"),))
    with pytest.raises(StreamError, match=r"sim.bin: none of the calibration's magnetometers \(/imu/mag\) is in "
                                          r"the log; it has MAG\[0\]"):
        apply_to_recording(other, fl.recording)
    two = replace(fl.truth(), magnetometers=(fl.truth().magnetometers[0],
                                             replace(fl.truth().magnetometers[0], id="MAG[1]", unit="tesla")))
    rec = replace(fl.recording, streams=(*fl.recording.streams,
                                         replace(fl.recording.select(Kind.MAGNETOMETER), id="MAG[1]")))
    with pytest.raises(StreamError, match=r"the magnetometers have different units \(T, mG\); use --mag"):
        apply_to_recording(two, rec)
    text, notes = apply_to_recording(replace(fl.truth(), effects=({"id": "throttle_interference", "sensor": "MAG[0]",
                                     "status": "accepted", "params": {"c": [1, 2, 3]}},)), fl.recording)
    assert notes == ["MAG[0]: the accepted throttle_interference is not removed (the log lacks its throttle channel)"]
