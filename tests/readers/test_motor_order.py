"""ArduPilot 3.5 added COMPASS_MOT's motor offsets before the iron matrix, 3.6 and newer after it: the reader undoes
the order the log's firmware used, read from its MSG banner when the log has no VER record (3.x logs have none).

The same simulated flight written by firmware 3.5.5 and 4.6.2 (tests/firmware/flightsim.py, MAG[2] flown with
DIA3 = BAD_DIA and COMPASS_MOT3 x current) logs different fields but must read back as the same raw field.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magcal_cli.readers import open_recording
from magcal_cli.readers.dataflash.compass import Correction, apply_correction, undo_correction
from magcal_cli.streams import Kind

from ..firmware.flightsim import BAD_DIA, three_compass_flight


def test_the_reader_undoes_each_firmwares_motor_order(tmp_path: Path) -> None:
    """Raw fields agree to a count whichever order the firmware used; the logged fields differ by far more."""
    old, _ = three_compass_flight(tmp_path, seed=2, duration=95.0, drift_mg=0.0, dia3=BAD_DIA, firmware=(3, 5, 5))
    new, _ = three_compass_flight(tmp_path, seed=2, duration=95.0, drift_mg=0.0, dia3=BAD_DIA, firmware=(4, 6, 2))
    a, b = (open_recording(p).select(Kind.MAGNETOMETER, "MAG[2]") for p in (old, new))
    assert np.array_equal(a.t, b.t)
    # mG: each log truncates to int16 counts, which the undone DIA3_Z = 0.63 stretches to 1.6 mG along z
    assert np.max(np.abs(a.values - b.values)) * 1e7 < 3.0
    assert any("before the iron matrix, where firmware 3.5" in n for n in open_recording(old).notes)


def test_the_order_matters_for_a_bad_iron_matrix() -> None:
    """The two orders differ by (M - I) MO: tens of mG with DIA3 = BAD_DIA, so the test above can tell them apart."""
    n = 4
    raw, mo = np.tile([300.0, -200.0, 400.0], (n, 1)), np.tile([30.0, 20.0, 40.0], (n, 1))
    m = np.tile(np.diag(BAD_DIA), (n, 1, 1))
    before = Correction(np.zeros((n, 3)), m, np.ones(n), mo, motor_after_matrix=False)
    logged = apply_correction(raw, before)
    assert np.allclose(undo_correction(logged, before), raw)
    after = Correction(np.zeros((n, 3)), m, np.ones(n), mo, motor_after_matrix=True)
    assert np.max(np.abs(undo_correction(logged, after) - raw)) > 10.0
