"""check's residual fit (firmware/residual.py): its heading-error std is widened only where the residuals are
correlated in time beyond white noise."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.firmware.residual import fit_residual
from magcal_cli.firmware.split import heading_error_deg

F, DIP_DEG = 500.0, 65.0
C0 = np.array([20.0, -10.0, 5.0])


def flight(seed: int, disturbance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(flown field, levelling rotations, times): 400 s, four slow turns, +-15/12 deg of roll and pitch, a
    residual offset C0, white noise of 0.5 % and a slowly wandering field of `disturbance` x F."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 400.0, 2000)
    zero = np.zeros_like(t)
    roll, pitch = np.deg2rad(15.0) * np.sin(2 * np.pi * t / 23), np.deg2rad(12.0) * np.sin(2 * np.pi * t / 31)
    lev = np.einsum("nij,njk->nik", so3.exp(np.c_[zero, pitch, zero]), so3.exp(np.c_[roll, zero, zero]))
    rot = np.einsum("nij,njk->nik", so3.exp(np.c_[zero, zero, 2 * np.pi * t / 100]), lev)
    dip = np.deg2rad(DIP_DEG)
    b = np.einsum("nji,j->ni", rot, F * np.array([np.cos(dip), 0.0, np.sin(dip)]))
    wander = disturbance * F * np.c_[np.sin(2 * np.pi * t / 70 + 1.0), np.cos(2 * np.pi * t / 55), zero]
    return b + C0 + rng.normal(0.0, 0.005 * F, b.shape) + wander, lev, t


@pytest.mark.parametrize("seed", [0, 1])
def test_white_noise_keeps_the_model_std_and_a_wandering_field_widens_it_to_cover_the_error(seed: int) -> None:
    """White noise: the times change nothing and the error is within 3 std. A field wandering by 4 % over a
    minute: the model std (0.14 deg) leaves the error at 2.5 std; widened (about 1.7 deg), it covers it."""
    truth = heading_error_deg(np.eye(3), C0 / F, DIP_DEG)
    c, lev, t = flight(seed, 0.0)
    plain, timed = fit_residual(c, lev), fit_residual(c, lev, None, t)
    assert timed.heading_error_std_deg == plain.heading_error_std_deg
    assert abs(plain.heading_error_deg - truth) < 3 * plain.heading_error_std_deg
    c, lev, t = flight(seed, 0.04)
    plain, timed = fit_residual(c, lev), fit_residual(c, lev, None, t)
    assert abs(plain.heading_error_deg - truth) > 2 * plain.heading_error_std_deg
    assert timed.heading_error_std_deg > 5 * plain.heading_error_std_deg
    assert abs(timed.heading_error_deg - truth) < timed.heading_error_std_deg
