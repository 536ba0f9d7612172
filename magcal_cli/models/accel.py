"""Accelerometer residuals: the biased specific force (joint MAP) and the unit vertical (Kok 2012)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.models.factor import Factor
from magcal_cli.models.gyro import Within
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

#: standard gravity, m/s^2 (NED: g_n = [0, 0, G]); the specific force at rest is -R^T g_n (points up)
G = 9.80665
#: the vertical "up" in NED: what a normalised accelerometer reading at rest points to
UP_N = np.array([0.0, 0.0, -1.0])


def accel_factor(rot: FloatArray, y: FloatArray, l_inv: FloatArray, theta: FloatArray, bias_at: int,
                 idx: IntArray | None, gravity: float = G, jacobians: bool = True,
                 compact: bool = False, within: Within | None = None) -> Factor:
    """Whitened r = L^-1 (y + R^T g_n - b_a) (Huang et al. 2025, methods.md section 3 item 1).

    dr/dphi = L^-1 [R^T g_n]x, dr/db_a = -L^-1. `compact`: J_theta holds only the b_a columns (theta_cols).
    `within` (gyro.Within): y is a group's mean, predicted -N g_b + b_a with g_b = R^T g_n and N = A + M(db),
    db = theta[bias_at+3:bias_at+6] (the gyro bias follows b_a in every layout); dr/dphi = L^-1 N [g_b]x,
    dr/ddb = L^-1 sum_a g_b,a B_a.
    """
    g_b = gravity * rot[:, 2, :]                                  # R^T [0, 0, g]
    gyro_at = bias_at + 3
    n = None if within is None else within.mixed(theta[gyro_at:gyro_at + 3])
    mean = g_b if n is None else np.einsum("mij,mj->mi", n, g_b)
    r = (y + mean - theta[bias_at:bias_at + 3]) @ l_inv.T
    if not jacobians:
        return Factor("accel", r)
    jx = so3.times_hat(l_inv, g_b) if n is None else l_inv @ (n @ so3.hat(g_b))
    if compact and within is None:
        jt = np.broadcast_to(-l_inv, (y.shape[0], 3, 3))
        return Factor("accel", r, idx, jx, None, jt, np.arange(bias_at, bias_at + 3))
    at = 0 if compact else bias_at
    jt = np.zeros((y.shape[0], 3, 6 if compact else theta.size))
    jt[:, :, at:at + 3] = -l_inv
    if within is not None:
        jt[:, :, at + 3:at + 6] = l_inv @ within.by_bias(g_b)
    return Factor("accel", r, idx, jx, None, jt, np.arange(bias_at, bias_at + 6) if compact else None)


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
