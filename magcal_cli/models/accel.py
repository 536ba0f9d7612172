"""Accelerometer residuals: the biased specific force (joint MAP) and the unit vertical (Kok 2012)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.models.factor import Factor
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

#: standard gravity, m/s^2 (NED: g_n = [0, 0, G]); the specific force at rest is -R^T g_n (points up)
G = 9.80665
#: the vertical "up" in NED: what a normalised accelerometer reading at rest points to
UP_N = np.array([0.0, 0.0, -1.0])


def accel_factor(rot: FloatArray, y: FloatArray, l_inv: FloatArray, theta: FloatArray, bias_at: int,
                 idx: IntArray | None, gravity: float = G, jacobians: bool = True,
                 compact: bool = False) -> Factor:
    """Whitened r = L^-1 (y + R^T g_n - b_a) (Huang et al. 2025, methods.md section 3 item 1).

    dr/dphi = L^-1 [R^T g_n]x, dr/db_a = -L^-1. `compact`: J_theta holds only the b_a columns (theta_cols).
    """
    g_b = gravity * rot[:, 2, :]                                  # R^T [0, 0, g]
    r = (y + g_b - theta[bias_at:bias_at + 3]) @ l_inv.T
    if not jacobians:
        return Factor("accel", r)
    if compact:
        jt = np.broadcast_to(-l_inv, (y.shape[0], 3, 3))
        return Factor("accel", r, idx, so3.times_hat(l_inv, g_b), None, jt, np.arange(bias_at, bias_at + 3))
    jt = np.zeros((y.shape[0], 3, theta.size))
    jt[:, :, bias_at:bias_at + 3] = -l_inv
    return Factor("accel", r, idx, so3.times_hat(l_inv, g_b), None, jt)


def vertical_factor(rot: FloatArray, v: FloatArray, l_inv: FloatArray, idx: IntArray | None,
                    jacobians: bool = True) -> Factor:
    """Whitened r = L^-1 (v - R^T z_n) of unit verticals v (M, 3), z_n = up (Kok et al. 2012, eq. 9b).

    dr/dphi = -L^-1 [R^T z_n]x; theta does not enter.
    """
    z_b = np.einsum("mji,j->mi", rot, UP_N)
    r = (v - z_b) @ l_inv.T
    if not jacobians:
        return Factor("vertical", r)
    return Factor("vertical", r, idx, -l_inv @ so3.hat(z_b), None, None)
