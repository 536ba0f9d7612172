"""The vehicle's attitude and the WMM as the reference (`--method attitude`, issue 12 item 2): truth-based on a
simulated ArduPilot flight whose ATT is the true attitude, with its stated uncertainty; current interference; and
the automatic use when the log's own motion cannot determine the calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal_cli import pipeline
from magcal_cli.config import Config
from magcal_cli.errors import InsufficientDataError
from magcal_cli.methods.table import METHODS
from magcal_cli.readers import open_recording
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.logs import write_log
from magcal_cli.synth.simulate import simulate


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    """A simulated multirotor flight written as DataFlash (ATT = the true attitude, GPS at HOME) with 3 mG/A of
    current interference."""
    sim = simulate("multirotor", 2, duration=150.0,
                   effects=(EffectSpec("current_interference", {"c": (3e-7, -2e-7, 1e-7)}),))
    path = tmp_path_factory.mktemp("att") / "flight.bin"
    write_log(sim, path)
    return path, sim


def test_attitude_reference_recovers_the_truth_within_its_uncertainty(flight: tuple[Path, object]) -> None:
    """D and o within 4 stated std of the truth (mG), the dip is the WMM's, the current interference is found,
    and the document says which reference the result used."""
    path, sim = flight
    res = pipeline.calibrate(path, Config(method="attitude"))
    mag = res.calibration.magnetometers[0]
    truth = sim.truth                                            # type: ignore[attr-defined]
    f = 1e7                                                       # tesla -> milligauss
    assert mag.reference == "vehicle attitude (ATT) + WMM-2025"
    assert mag.dip_deg == pytest.approx(np.rad2deg(truth.dip), abs=0.1)        # WMM at the flown position
    z_d = (mag.D - truth.D * f) / mag.std_of("D")
    z_o = (mag.o - truth.o * f) / mag.std_of("o")
    free = [h["parameter"] for h in mag.held]
    assert np.abs(z_o).max() < 4.0, (z_o, free)
    assert np.abs(z_d).max() < 4.0, (z_d, free)
    (cur,) = [e for e in res.calibration.effects if e["id"] == "current_interference"]
    assert cur["status"] == "accepted"
    np.testing.assert_allclose(cur["params"]["c"], [3.0, -2.0, 1.0], atol=0.3)
    assert res.calibration.method == "attitude"


def test_auto_uses_the_attitude_where_the_motion_cannot_decide(flight: tuple[Path, object],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """When the joint MAP refuses the log, --method auto calibrates against the attitude and says so; an explicit
    --method map still refuses."""
    path, _ = flight

    def refuse(problem: object, cfg: object) -> object:
        msg = "flight.bin: MAG[0]: too little tilt"
        raise InsufficientDataError(msg)

    monkeypatch.setitem(METHODS, "map", METHODS["map"]._replace(run=refuse))
    res = pipeline.calibrate(path, Config(effects=()))
    assert res.calibration.method == "attitude"
    assert any(f.code == "attitude_reference" and "too little tilt" in f.message for f in res.findings)
    with pytest.raises(InsufficientDataError, match="too little tilt"):
        pipeline.calibrate(path, Config(method="map", effects=()))


def test_a_log_without_a_ned_attitude_is_refused_with_the_reason(tmp_path: Path) -> None:
    """A ROS bag has no autopilot attitude: --method attitude says what it needs."""
    sim = simulate("handheld", 1, duration=60.0)
    path = tmp_path / "h.mcap"
    write_log(sim, path)
    rec = open_recording(path)
    with pytest.raises(InsufficientDataError, match=r"needs the autopilot's attitude estimate \(ArduPilot ATT, PX4 "
                                                    r"vehicle_attitude\)"):
        pipeline.calibrate_recording(rec, Config(method="attitude", location=(47.0, 8.0, 400.0)))
