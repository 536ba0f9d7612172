"""Joint MAP on real BROAD trials (../shared/realdata/broad): a factory-calibrated magnetometer stays near
identity; a magnet fixed to the board is calibrated away (norm and mocap heading).

Modules it covers (the mirrored test file aside): magcal_cli.models.epochs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.pipeline import calibrate
from magcal_cli.streams import Kind


def _heading_std_deg(m_b: np.ndarray, t: np.ndarray, att_t: np.ndarray, att_q: np.ndarray) -> float:
    """Circular std (deg) of the magnetic heading with the mocap attitude."""
    idx = np.searchsorted(att_t, t)
    ok = (idx < att_t.size) & (np.abs(att_t[np.minimum(idx, att_t.size - 1)] - t) < 1e-6)
    m_n = np.einsum("nij,nj->ni", so3.from_quat(att_q[idx[ok]]), m_b[ok])
    r = np.abs(np.mean(np.exp(1j * np.arctan2(m_n[:, 1], m_n[:, 0]))))
    return float(np.degrees(np.sqrt(-2.0 * np.log(r))))


def test_undisturbed_trial_finds_no_hard_iron(realdata: Path) -> None:
    """Trial 02 (slow rotations, factory-calibrated sensor): |b| components < 1 uT, shape within 5 % of I."""
    res = calibrate(realdata / "broad" / "02_undisturbed_slow_rotation_B.hdf5", Config(method="map"))
    mag = res.calibration.magnetometers[0]
    assert np.all(np.abs(mag.b) < 1.0)                                   # microtesla
    assert np.abs(mag.soft_iron - np.eye(3)).max() < 0.05
    assert 60.0 < mag.dip_deg < 75.0                                     # Berlin lab, ~70 deg


def test_attached_magnet_is_calibrated_away(realdata: Path) -> None:
    """Trial 32 (magnet 1 cm from the IMU), magnet window 45-90 s: calibrated norm within 2 % RMS, mocap
    heading at least 5x steadier than with the raw readings."""
    res = calibrate(realdata / "broad" / "32_disturbed_attached_magnet_1cm.hdf5",
                    Config(method="map", start_s=45.0, end_s=90.0))
    mag = res.calibration.magnetometers[0]
    series = res.series[mag.id]
    norm = np.linalg.norm(series.calibrated, axis=1)
    assert 100.0 * np.std(norm) / np.mean(norm) < 2.0
    att = res.recording.select(Kind.ATTITUDE)
    before = _heading_std_deg(series.raw, series.t, att.t, att.values)
    after = _heading_std_deg(series.calibrated, series.t, att.t, att.values)
    assert after < before / 5.0
    assert np.linalg.norm(mag.b) > 20.0                                  # the magnet's hard iron, uT
