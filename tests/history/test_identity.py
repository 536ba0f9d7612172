"""Which vehicle a log comes from (issue 38, item 7): ArduPilot vehicles of one fleet share SYSID_THISMAV 1 and
BRD_SERIAL_NUM 0, so the board's unique id in its boot message keys them; `magcal fleet` says how each vehicle was
identified and warns where SYSID_THISMAV alone merges vehicles.

Modules it covers: magcal_cli.history.identity, magcal_cli.readers.dataflash.ardupilot (board_info),
magcal_cli.synth.vehicle (serial, board_id).
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.history.store import load
from magcal_cli.readers import open_recording
from magcal_cli.synth.vehicle import VehicleFileError
from magcal_cli.synth.vehicle import load as load_vehicle
from tests.history.conftest import BASE

#: two boards' boot messages, as ArduPilot logs them (the second from the issue)
BOARDS = ("fmuv3 002F001F 33375111 37353832", "PH4-mini 0043002B 34385109 39303535")
UIDS = ("uid 002F001F3337511137353832", "uid 0043002B3438510939303535")


def _flight(folder: Path, k: int, board: str | None) -> Path:
    """Vehicle k's one flight: SYSID_THISMAV 1, BRD_SERIAL_NUM 0, hard iron 5 uT apart per vehicle (a step
    of many stds were the two one vehicle), and the board's boot message when `board` is given."""
    doc = {**BASE, "hard_iron_uT": [2.0 + 5.0 * k, -1.0, 0.5], "sysid": 1, "serial": 0,
           "start_utc": 1_763_700_000.0 + 86_400.0 * k} | ({"board_id": board} if board else {})
    spec = folder / f"v{k}.vehicle.json"
    spec.write_text(json.dumps(doc), encoding="utf-8")
    log = folder / f"v{k}.bin"
    with contextlib.redirect_stdout(io.StringIO()):
        cli.main(["simulate", "-o", str(log), "--vehicle-file", str(spec), "--seed", str(40 + k), "--rate", "50",
                  "--mag-rate", "25", "-q"], standalone_mode=False)
    return log


def _store(tmp_path: Path, name: str, boards: tuple[str | None, ...]) -> Path:
    """The two vehicles' flights fitted with --history into one store."""
    folder = tmp_path / name
    folder.mkdir()
    db = folder / "fleet.db"
    for k, board in enumerate(boards):
        run = CliRunner().invoke(cli, ["fit", str(_flight(folder, k, board)), "-o", str(folder / f"fit{k}"),
                                       "--effects", "none", "--outputs", "json", "--history", str(db)])
        assert run.exit_code == 0, run.output
    return db


def test_same_sysid_different_boards_are_two_vehicles(tmp_path: Path) -> None:
    """Issue 38 item 7: two vehicles with SYSID_THISMAV 1 and BRD_SERIAL_NUM 0 but different board ids are two
    vehicles and no compass changed; without the boot messages they merge (SYSID only, said with a warning) and
    the second vehicle's compass reads as a change of the first's."""
    runner = CliRunner()
    apart = _store(tmp_path, "boards", BOARDS)
    entries = load(apart)
    assert sorted(e["vehicle"] for e in entries) == sorted(UIDS)
    assert {e["vehicle_source"] for e in entries} == {"board uid (fmuv3)", "board uid (PH4-mini)"}
    text = runner.invoke(cli, ["fleet", str(apart), "--std-scale", "1", "--fail-on", "changed"])
    assert text.exit_code == 0, text.output
    assert "2 compasses on 2 vehicles: 0 changed, 0 settled, 2 new" in text.output
    assert "board unique id (fmuv3)" in text.output and "warning" not in text.output
    assert "Vehicle identified by board unique id (PH4-mini)" in runner.invoke(cli, ["fleet", str(apart), "-o", "-"]).stdout
    doc = json.loads(runner.invoke(cli, ["fleet", str(apart), "--json"]).output)
    assert {c["identified_by"] for c in doc["compasses"]} == {"board unique id (fmuv3)", "board unique id (PH4-mini)"}

    merged = _store(tmp_path, "sysid", (None, None))
    assert {e["vehicle"] for e in load(merged)} == {"sysid 1"}
    text = runner.invoke(cli, ["fleet", str(merged), "--std-scale", "1", "--fail-on", "changed"])
    assert text.exit_code == 3, text.output
    assert "1 compasses on 1 vehicles: 1 changed" in text.output
    assert "sysid 1  SYSID only" in text.output
    assert "warning: sysid 1 is identified by SYSID_THISMAV only" in text.output
    doc = json.loads(runner.invoke(cli, ["fleet", str(merged), "--json"]).output)
    assert [(c["identified_by"], c["sysid_only"]) for c in doc["compasses"]] == [("SYSID only", True)]
    page = runner.invoke(cli, ["fleet", str(merged), "-o", "-"]).stdout          # the HTML report says it too
    assert "Warning: sysid 1 is identified by SYSID_THISMAV only" in page and "identified by SYSID only" in page


def test_board_info_reads_the_boot_message() -> None:
    """The board's name and its 24-digit id; other messages, and ids that were never read (all 0 or all F), are
    not one."""
    from magcal_cli.readers.dataflash.ardupilot import board_info

    assert board_info(["ArduCopter V3.6.7 (38b8af17)", "ChibiOS: d2030d88", BOARDS[0]]) == {
        "board": "fmuv3", "board_uid": "002F001F3337511137353832"}
    assert board_info(["px4v2 003a0027 34324708 31323533"])["board_uid"] == "003A00273432470831323533"
    for text in ("PX4: c3406165 NuttX: d48fa307", "u-blox 1 HW: 00080000 SW: EXT CORE 3.01 (d080e3)",
                 "fmuv3 00000000 00000000 00000000", "fmuv3 FFFFFFFF FFFFFFFF FFFFFFFF", "fmuv3 002F001F 33375111"):
        assert board_info([text]) == {}, text


def test_vehicle_file_serial_and_board_errors(tmp_path: Path) -> None:
    """A vehicle file's serial and board_id are checked; a good one writes BRD_SERIAL_NUM and the boot message."""
    bad = tmp_path / "bad.json"
    for doc, message in (({"serial": -1}, "serial must be an integer"),
                         ({"board_id": "fmuv3 12"}, "board_id must be a board's boot message")):
        bad.write_text(json.dumps(doc), encoding="utf-8")
        with pytest.raises(VehicleFileError, match=message):
            load_vehicle(bad)
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"serial": 42, "board_id": BOARDS[1]}), encoding="utf-8")
    v = load_vehicle(good)
    assert v.params() == {"BRD_SERIAL_NUM": 42.0} and v.board_id == BOARDS[1]


def test_real_logs_name_their_board(realdata: Path) -> None:
    """Real ArduPilot logs (both SYSID_THISMAV 1, BRD_SERIAL_NUM 0): a ChibiOS fmuv3 and a Pixhawk 4 are told
    apart by their boards' ids; a 2014 Linux board (PXF) logs none and stays SYSID only."""
    from magcal_cli.history.identity import vehicle_of

    expect = {"zoo/ardupilot/log_0041_mechanical_failure.bin": ("uid 002F001F3337511137353832", "board uid (fmuv3)"),
              "ardupilot/ap462_truncated_80k.bin": ("uid 0047002B3438510536363539", "board uid (Pixhawk4)"),
              "zoo/ardupilot/pxf_copter_5-12-2014_218.BIN": ("sysid 1", "SYSID_THISMAV")}
    for name, want in expect.items():
        if not (realdata / name).is_file():
            pytest.skip(f"{name} is absent from {realdata}")
        assert tuple(vehicle_of(open_recording(realdata / name))) == want, name
