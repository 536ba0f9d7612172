"""A small simulated fleet shared by the history tests: 3 vehicles x 5 flights, made with `magcal simulate
--vehicle-file` (handheld at 50/25 Hz, ArduPilot .bin); vehicle 2's hard iron steps by 1.5 uT from flight 3 on."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest

from magcal_cli.cli.main import cli

FLIGHTS, STEP_AT = 5, 3
BASE = {"hard_iron_uT": [2.0, -1.0, 0.5], "soft_iron": [[1.03, 0.01, 0.0], [0.01, 0.98, 0.0], [0.0, 0.0, 1.0]],
        "orientation_deg": [0.5, -1.0, 2.0]}


def vehicle_file(sysid: int, k: int) -> dict[str, object]:
    """Flight k of vehicle `sysid`: vehicle 2's hard iron x steps by 1.5 uT (15 mG) at flight STEP_AT."""
    step = 1.5 if sysid == 2 and k >= STEP_AT else 0.0
    hard = [BASE["hard_iron_uT"][0] + sysid + step, *BASE["hard_iron_uT"][1:]]   # type: ignore[index]
    return {**BASE, "hard_iron_uT": hard, "sysid": sysid, "start_utc": 1_763_700_000.0 + 86_400.0 * k}


def simulate(folder: Path, sysid: int, k: int) -> Path:
    """One flight with `magcal simulate --vehicle-file`."""
    spec = folder / f"v{sysid}-f{k}.vehicle.json"
    spec.write_text(json.dumps(vehicle_file(sysid, k)), encoding="utf-8")
    log = folder / f"v{sysid}-f{k}.bin"
    with contextlib.redirect_stdout(io.StringIO()):
        cli.main(["simulate", "-o", str(log), "--vehicle-file", str(spec), "--seed", str(10 * sysid + k), "--rate",
                  "50", "--mag-rate", "25", "-q"], standalone_mode=False)
    return log


@pytest.fixture(scope="session")
def fleet_logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """The 15 logs, vehicle by vehicle, in flight order."""
    folder = tmp_path_factory.mktemp("fleet-logs")
    return [simulate(folder, sysid, k) for sysid in (1, 2, 3) for k in range(FLIGHTS)]
