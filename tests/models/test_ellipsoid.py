"""The algebraic ellipsoid fit (Kok 2012, Sec. IV-A).

Modules it covers (the mirrored test file aside): magcal_cli.ellipsoid.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal_cli.ellipsoid import fit_ellipsoid
from magcal_cli.errors import InsufficientDataError


def _sphere(n: int, rng: np.random.Generator) -> np.ndarray:
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 100_000), st.floats(1e-7, 1e3), st.floats(0.0, 0.5))
def test_exact_on_noiseless_data_for_any_spd_soft_iron(seed: int, scale: float, distortion: float) -> None:
    """D0 D0^T = D D^T and o0 = o for any well-conditioned D at any scale (tesla to milligauss)."""
    rng = np.random.default_rng(seed)
    d = scale * (np.eye(3) + distortion * rng.uniform(-1, 1, size=(3, 3)))
    if np.linalg.cond(d) > 5:
        return
    o = scale * rng.uniform(-2, 2, size=3)
    y = _sphere(300, rng) @ d.T + o
    ell = fit_ellipsoid(y)
    np.testing.assert_allclose(ell.o0, o, atol=1e-8 * scale)
    np.testing.assert_allclose(ell.D0 @ ell.D0.T, d @ d.T, atol=1e-8 * scale**2)
    assert ell.residual_rms < 1e-9


def test_planar_data_is_refused_with_advice() -> None:
    """Readings from a yaw-only rotation lie on an ellipse, not an ellipsoid: the fit must say so."""
    a = np.linspace(0, 2 * np.pi, 200)
    y = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1) * 30.0 + 5.0
    with pytest.raises(InsufficientDataError, match="do not lie on an ellipsoid.*rotate the sensor"):
        fit_ellipsoid(y, "flat.mcap")


def test_too_few_samples() -> None:
    """Nine parameters need at least nine readings."""
    with pytest.raises(InsufficientDataError, match="at least 9 three-axis samples, got 4"):
        fit_ellipsoid(np.ones((4, 3)))
