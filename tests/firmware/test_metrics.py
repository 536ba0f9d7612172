"""fit --fail-on's metrics: heading uncertainty from the covariance, interference, what the firmware loses."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Quality, Source
from magcal_cli.firmware.metrics import fit_metrics, heading_std_deg
from magcal_cli.streams import Kind, Recording, Stream

F = 500.0


def mag(cov: np.ndarray | None = None, D: np.ndarray | None = None) -> MagCalibration:
    return MagCalibration("MAG[0]", "milligauss", F * np.eye(3) if D is None else D, np.zeros(3), 60.0,
                          np.zeros((13, 13)) if cov is None else cov, F, "data", Quality(100, 1.0, 0.5, 80.0, True, 5))


def test_heading_std_from_offset_uncertainty() -> None:
    """Offset noise sigma on every axis: the heading std is sigma / (F cos dip) at every heading."""
    cov = np.zeros((13, 13))
    cov[9:12, 9:12] = np.eye(3) * 4.0 ** 2
    assert heading_std_deg(mag(cov)) == pytest.approx(np.rad2deg(4.0 / (F * np.cos(np.deg2rad(60.0)))), rel=1e-9)


def test_heading_std_from_a_matrix_element_matches_monte_carlo() -> None:
    """Uncertainty in D[1, 0] (x field leaking into y): first-order std against sampled headings."""
    cov = np.zeros((13, 13))
    cov[1, 1] = (0.01 * F) ** 2                          # vec(D) column-major: index 1 is D[1, 0]
    rng = np.random.default_rng(0)
    psi = np.deg2rad(np.arange(360.0))
    dip = np.deg2rad(60.0)
    mb = np.stack([np.cos(dip) * np.cos(psi), -np.cos(dip) * np.sin(psi), np.full_like(psi, np.sin(dip))], 1)
    errs = []
    for e in rng.normal(0.0, 0.01 * F, 4000):
        D = F * np.eye(3)
        D[1, 0] += e
        m = (mb @ (F * np.eye(3)).T) @ np.linalg.inv(D).T        # raw from the truth, corrected with the estimate
        errs.append(np.angle(np.exp(1j * (np.arctan2(-m[:, 1], m[:, 0]) - psi))))
    mc = np.rad2deg(np.std(np.array(errs), axis=0)).max()
    assert heading_std_deg(mag(cov)) == pytest.approx(mc, rel=0.05)


def test_unknown_covariance_is_none() -> None:
    assert heading_std_deg(mag(np.full((13, 13), np.nan))) is None


def result(effects: tuple[dict[str, Any], ...], fmt: str = "dataflash", D: np.ndarray | None = None) -> Any:
    cal = Calibration(Source("x.bin", fmt, "", 0, 1), "map", ImuCalibration("IMU[0]"), (mag(D=D),), "0", "t",
                      effects=effects)
    bat = Stream(Kind.BATTERY_CURRENT, "BAT[0]", np.arange(3.0), [2.0, 20.0, 5.0], "b", "A")
    return SimpleNamespace(calibration=cal, recording=Recording(Path("x.bin"), fmt, (bat,), 0.0,
                                                                {"COMPASS_EXTERNAL": 0.0}))


def test_fit_metrics_interference_and_export_loss() -> None:
    """Accepted current term: |A c| I_peak; rejected: 0; untested: not measured. An internal compass 2 deg off
    on an ArduPilot log loses 2 deg of misalignment."""
    acc = {"id": "current_interference", "sensor": "MAG[0]", "status": "accepted", "params": {"c": [3.0, 4.0, 0]}}
    m, why = fit_metrics(result((acc,)))["MAG[0]"]
    assert m["interference_pct"] == pytest.approx(100 * 5.0 / F * 20.0)
    assert m["field_norm_rms_pct"] == 0.5 and m["coverage_pct"] == 80.0 and m["heading_error_deg"] < 1e-9
    m, _ = fit_metrics(result(({**acc, "status": "rejected"},)))["MAG[0]"]
    assert m["interference_pct"] == 0.0
    m, why = fit_metrics(result(()))["MAG[0]"]
    assert m["interference_pct"] is None
    assert why["interference_pct"] == "the diagnosis did not test current or throttle interference"
    m, _ = fit_metrics(result((), D=F * so3.exp(np.deg2rad([0.0, 0.0, 2.0]))))["MAG[0]"]
    assert m["residual_misalignment_deg"] == pytest.approx(2.0, abs=1e-6) and m["heading_error_deg"] > 1.9
    m, _ = fit_metrics(result((), fmt="mcap", D=F * so3.exp(np.deg2rad([0.0, 0.0, 2.0]))))["MAG[0]"]
    assert m["heading_error_deg"] == 0.0                 # no firmware holds it: nothing is lost
