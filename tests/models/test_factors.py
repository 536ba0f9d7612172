"""Analytic Jacobians of the magnetometer, accelerometer and vertical factors against finite differences.

Modules it covers (the mirrored test file aside): magcal_cli.models.accel, magcal_cli.models.mag.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.models.accel import accel_factor, vertical_factor
from magcal_cli.models.factor import Factor
from magcal_cli.models.mag import MagLayout, mag_factor

EPS = 1e-6


def numeric_jacobians(fn, rot: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """Central differences of fn(rot, theta) -> r (M, m): w.r.t. the right perturbation of each rot and theta."""
    m = rot.shape[0]
    r0 = fn(rot, theta)
    jx = np.zeros(r0.shape + (3,))
    for i in range(3):
        d = np.zeros((m, 3))
        d[:, i] = EPS
        jx[..., i] = (fn(rot @ so3.exp(d), theta) - fn(rot @ so3.exp(-d), theta)) / (2 * EPS)
    jt = np.zeros(r0.shape + (theta.size,))
    for j in range(theta.size):
        d = np.zeros(theta.size)
        d[j] = EPS
        jt[..., j] = (fn(rot, theta + d) - fn(rot, theta - d)) / (2 * EPS)
    return jx, jt


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(42)


def _check(f: Factor, jx: np.ndarray, jt: np.ndarray | None) -> None:
    """Analytic blocks equal the numeric ones to 1e-7 (central differences with eps 1e-6 on O(1) functions)."""
    np.testing.assert_allclose(f.J_x, jx, atol=1e-7)
    if jt is not None:
        np.testing.assert_allclose(f.J_theta, jt, atol=1e-7)


def test_mag_factor_jacobians(rng: np.random.Generator) -> None:
    """dr/dphi, dr/dvec(D), dr/do, dr/ddip of the magnetometer residual (methods.md section 3)."""
    m = 7
    rot = so3.exp(rng.normal(size=(m, 3)))
    layout = MagLayout.packed(2)                          # not at 0: the layout offsets are exercised too
    theta = np.concatenate([rng.normal(size=2), (np.eye(3) + 0.2 * rng.normal(size=(3, 3))).ravel(order="F"),
                            rng.normal(size=3) * 0.1, [1.2], rng.normal(size=1)])
    y = rng.normal(size=(m, 3))
    l_inv = np.linalg.inv(np.linalg.cholesky(np.diag([1.0, 2.0, 0.5]) + 0.1))
    f = mag_factor(rot, y, l_inv, theta, layout, np.arange(m))
    jx, jt = numeric_jacobians(lambda r, t: mag_factor(r, y, l_inv, t, layout, None, False).r, rot, theta)
    _check(f, jx, jt)


def test_accel_factor_jacobians(rng: np.random.Generator) -> None:
    """dr/dphi = L^-1 [R^T g]x and dr/db_a = -L^-1."""
    m = 5
    rot = so3.exp(rng.normal(size=(m, 3)))
    theta = rng.normal(size=6)
    y = rng.normal(size=(m, 3)) + [0, 0, 9.8]
    l_inv = np.eye(3) / 0.2
    f = accel_factor(rot, y, l_inv, theta, 3, np.arange(m))
    jx, jt = numeric_jacobians(lambda r, t: accel_factor(r, y, l_inv, t, 3, None, jacobians=False).r, rot, theta)
    _check(f, jx, jt)


def test_vertical_factor_jacobian(rng: np.random.Generator) -> None:
    """dr/dphi = -L^-1 [R^T z_n]x; theta does not enter."""
    m = 5
    rot = so3.exp(rng.normal(size=(m, 3)))
    v = rng.normal(size=(m, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    l_inv = np.eye(3) / 0.01
    f = vertical_factor(rot, v, l_inv, np.arange(m))
    jx, _ = numeric_jacobians(lambda r, t: vertical_factor(r, v, l_inv, None, False).r, rot, np.zeros(1))
    _check(f, jx * 1.0, None)
    assert f.J_theta is None
