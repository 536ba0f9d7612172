"""Algebraic ellipsoid fit (Kok et al. 2012, Sec. IV-A, eqs. 15-23): the initial D~0 and o0."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from magcal_cli.errors import InsufficientDataError
from magcal_cli.streams import FloatArray


class Ellipsoid(NamedTuple):
    """|D0^-1 (y - o0)| = 1 with D0 = L^-T (lower-triangular Cholesky factor L of alpha A): defined up to a rotation."""

    D0: FloatArray
    o0: FloatArray
    residual_rms: float


def fit_ellipsoid(y: npt.ArrayLike, where: str = "magnetometer") -> Ellipsoid:
    """Least-squares ellipsoid y^T A y + b^T y + c = 0 through (N, 3) points (smallest right singular vector).

    The data are centred and scaled first (conditioning); A, b, c are mapped back before eq. 22-23.
    """
    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] != 3 or y.shape[0] < 9:
        msg = f"{where}: an ellipsoid fit needs at least 9 three-axis samples, got {y.shape[0]}"
        raise InsufficientDataError(msg)
    mu = y.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((y - mu) ** 2, axis=1)))) or 1.0
    x = (y - mu) / s
    cols = [x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2, 2 * x[:, 0] * x[:, 1], 2 * x[:, 0] * x[:, 2],
            2 * x[:, 1] * x[:, 2], x[:, 0], x[:, 1], x[:, 2], np.ones(len(x))]
    j = np.stack(cols, axis=1)
    _, _, vt = np.linalg.svd(j, full_matrices=False)
    eta = vt[-1]
    a_n = np.array([[eta[0], eta[3], eta[4]], [eta[3], eta[1], eta[5]], [eta[4], eta[5], eta[2]]])
    b_n, c_n = eta[6:9], eta[9]
    # back to the original coordinates: x = (y - mu)/s
    a = a_n / s**2
    b = b_n / s - 2.0 * a @ mu
    c = float(mu @ a @ mu - b_n @ mu / s + c_n)
    try:
        a_inv_b = np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        a_inv_b = np.full(3, np.nan)
    o0 = -0.5 * a_inv_b
    alpha = 1.0 / (0.25 * b @ a_inv_b - c)                     # eq. 22
    try:
        chol = np.linalg.cholesky(alpha * a)                      # eq. 23a: D0^-T D0^-1 = alpha A
    except np.linalg.LinAlgError:
        chol = None
    if chol is None or not np.all(np.isfinite(o0)):
        msg = (f"{where}: the readings do not lie on an ellipsoid (the fit is degenerate); "
               "rotate the sensor through more orientations, ideally about all three axes")
        raise InsufficientDataError(msg)
    d0 = np.linalg.inv(chol.T)                                    # D0^-1 = L^T
    h = (y - o0) @ chol
    rms = float(np.sqrt(np.mean((np.linalg.norm(h, axis=1) - 1.0) ** 2)))
    return Ellipsoid(d0, o0, rms)
