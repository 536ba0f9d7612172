"""A small fleet recorded with `magcal fit --history` and read with `magcal fleet` (issue 29): the stepped vehicle
is found at the right flight and the steady ones stay steady; text, --json, --fail-on, the HTML report in
headless Chromium (screenshot in docs/images/fleet-report.png), and the vehicle file of `magcal simulate`.

Modules it covers: magcal_cli.history.fleet, magcal_cli.history.entry, magcal_cli.history.identity,
magcal_cli.cli.fleet, magcal_cli.writers.fleet, magcal_cli.synth.vehicle.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.history import fleet as model
from magcal_cli.history.store import load
from magcal_cli.synth.vehicle import VehicleFileError
from magcal_cli.synth.vehicle import load as load_vehicle
from tests.history.conftest import STEP_AT
from tests.test_report_browser import IMAGES, check_in_browser


@pytest.fixture(scope="module")
def store(fleet_logs: list[Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Every log fitted once with --history (one of them twice, under another name: nothing changes)."""
    out = tmp_path_factory.mktemp("fleet-store")
    db = out / "fleet.db"
    runner = CliRunner()
    for k, log in enumerate(fleet_logs):
        run = runner.invoke(cli, ["fit", str(log), "-o", str(out / f"fit{k}"), "--effects", "none", "--outputs",
                                  "json", "--history", str(db)])
        assert run.exit_code == 0, run.output
    copy = out / "copy.bin"
    copy.write_bytes(fleet_logs[0].read_bytes())
    again = runner.invoke(cli, ["fit", str(copy), "-o", str(out / "again"), "--effects", "none", "--outputs", "json",
                                "--history", str(db)])
    assert again.exit_code == 0 and "0 of 1 results new" in again.output, again.output
    return db


def test_store_holds_each_flight_once_with_identity(store: Path) -> None:
    """15 entries keyed by SYSID_THISMAV and COMPASS_DEV_ID, in log-time order, hard iron within 3 std of the truth."""
    entries = load(store)
    assert len(entries) == 15
    assert {e["vehicle"] for e in entries} == {"sysid 1", "sysid 2", "sysid 3"}
    assert {e["sensor"] for e in entries} == {"MAG[0] dev 97539"}
    assert all(e["vehicle_source"] == "SYSID_THISMAV" for e in entries)
    first = next(e for e in entries if e["vehicle"] == "sysid 1")
    value, std = first["params"]["hard_iron.x"]
    assert first["unit"] == "milligauss" and abs(value - 30.0) < 3 * std + 0.5      # 2 + 1 uT = 30 mG
    assert set(first["quality"]) >= {"field_norm_rms_pct", "heading_std_deg"}
    assert first["covariance"]["std_o"] == pytest.approx([s for _, s in
                                                          (first["params"][f"hard_iron.{a}"] for a in "xyz")])


def test_fleet_finds_the_step_and_nothing_else(store: Path) -> None:
    """Vehicle 2 alarms in hard iron at the step's flight; vehicles 1 and 3 stay steady."""
    fleet = model.build(load(store))
    states = {c.vehicle: c.state for c in fleet.compasses}
    assert states == {"sysid 1": "steady", "sysid 2": "settled", "sysid 3": "steady"}
    (stepped,) = [c for c in fleet.compasses if c.vehicle == "sysid 2"]
    starts = {ch.start for ch in stepped.changes if ch.category == "hard_iron"}
    assert starts == {STEP_AT} and min(ch.at for ch in stepped.changes) <= STEP_AT + 1
    x = next(ch for ch in stepped.changes if ch.param == "hard_iron.x")
    assert x.step == pytest.approx(15.0, abs=1.0)


def test_fleet_command_text_json_and_fail_on(store: Path, fleet_logs: list[Path], tmp_path: Path) -> None:
    """Text and --json agree; --fail-on changed exits 3 only when the latest flight changed."""
    runner = CliRunner()
    text = runner.invoke(cli, ["fleet", str(store)])
    assert text.exit_code == 0 and "3 compasses on 3 vehicles: 0 changed, 1 settled, 0 new, 2 steady" in text.output
    doc = json.loads(runner.invoke(cli, ["fleet", str(store), "--json"]).output)
    assert doc["counts"] == {"changed": 0, "settled": 1, "new": 0, "steady": 2}
    assert runner.invoke(cli, ["fleet", str(store), "--fail-on", "changed"]).exit_code == 0
    settled = runner.invoke(cli, ["fleet", str(store), "--fail-on", "changed,settled"])
    assert settled.exit_code == 3 and "Error: fleet --fail-on: 1 compass changed/settled (sysid 2" in settled.output
    bad = runner.invoke(cli, ["fleet", str(store), "--fail-on", "moved"])
    assert bad.exit_code == 2 and "expected states among changed, settled, new" in bad.output
    # the step's second flight alone: the compass changed at its latest flight
    db = tmp_path / "short.db"
    for k, log in enumerate(fleet_logs[5:5 + STEP_AT + 1]):
        run = runner.invoke(cli, ["fit", str(log), "-o", str(tmp_path / f"f{k}"), "--effects", "none", "--outputs",
                                  "json", "--history", str(db), "--vehicle", "uav-2"])
        assert run.exit_code == 0, run.output
    changed = runner.invoke(cli, ["fleet", str(db), "--fail-on", "changed"])
    assert changed.exit_code == 3 and "uav-2 MAG[0] dev 97539" in changed.output, changed.output


def test_fleet_report_in_a_browser(store: Path, tmp_path: Path) -> None:
    """The HTML report: a table row per compass and a trend figure each, clean in headless Chromium."""
    page = tmp_path / "fleet.html"
    run = CliRunner().invoke(cli, ["fleet", str(store), "-o", str(page)])
    assert run.exit_code == 0, run.output
    html = page.read_text(encoding="utf-8")
    assert html.count("<tr style=") == 3 and html.count("<img ") == 3 and "settled" in html
    refused = CliRunner().invoke(cli, ["fleet", str(store), "-o", str(page)])
    assert refused.exit_code == 2 and "exists already" in refused.output
    piped = CliRunner().invoke(cli, ["fleet", str(store), "-o", "-"])      # the page on stdout, the summary on stderr
    assert piped.stdout.startswith("<!DOCTYPE html>") and "3 compasses on 3 vehicles" in piped.stderr
    probe = check_in_browser(page, IMAGES / "fleet-report.png")
    assert probe["images"] == 3


def test_vehicle_file_errors(tmp_path: Path) -> None:
    """A vehicle file's mistakes name the key; a good one round-trips into SI."""
    bad = tmp_path / "bad.json"
    for doc, message in (({"sysid": 0}, "sysid must be an integer 1..255"),
                         ({"soft_iron": [[1, 2, 0], [0, 1, 0], [0, 0, 1]]}, "symmetric positive definite"),
                         ({"hard_iron": [1, 2, 3]}, "unknown key 'hard_iron'"),
                         ({"orientation_deg": [1, 2]}, "orientation_deg must be a list of 3 numbers")):
        bad.write_text(json.dumps(doc), encoding="utf-8")
        with pytest.raises(VehicleFileError, match=message):
            load_vehicle(bad)
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"hard_iron_uT": [1, 2, 3], "orientation_deg": [0, 0, 90]}), encoding="utf-8")
    v = load_vehicle(good)
    assert np.allclose(v.hard_iron_t, [1e-6, 2e-6, 3e-6]) and np.isclose(v.orientation_rad[2], np.pi / 2)
