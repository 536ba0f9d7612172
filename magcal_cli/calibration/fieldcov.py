"""The calibration's uncertainty propagated to a calibrated reading: first order, J cov J^T.

m = F A (y - o) with A = D^-1 and the field strength F held fixed. dA = -A dD A gives dm = -F A dD u with
u = A (y - o) = m / F, and dD u = (u^T kron I) vec(dD) for the column-major vec of the document's `cov`, so
    dm/dvec(D) = -(m^T kron A),    dm/do = -F A.
The dip does not enter m: its rows and columns of `cov` drop out. Both Jacobians are functions of the
calibrated reading m alone (after the effects are removed), so `apply`'s output is all they need.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from magcal_cli.calibration.types import MAG_PARAMS, MagCalibration
from magcal_cli.streams import FloatArray


def field_jacobian(mag: MagCalibration, m: npt.ArrayLike) -> FloatArray:
    """(N, 3, 12) Jacobian of the calibrated field m = F A (y - o) (N, 3, document unit) w.r.t. (vec D, o)."""
    m = np.atleast_2d(np.asarray(m, dtype=np.float64))
    a = mag.A
    jd = -np.einsum("nj,ik->nijk", m, a).reshape(len(m), 3, 9)    # column j of D: d m / d D[k, j] = -m_j A[i, k]
    jo = np.broadcast_to(-mag.field_strength * a, (len(m), 3, 3))
    return np.concatenate([jd, jo], axis=2)


def field_covariance(mag: MagCalibration, m: npt.ArrayLike) -> FloatArray:
    """(N, 3, 3) covariance (document unit^2) of each calibrated reading m (N, 3) from the calibration's `cov`;
    NaN where the document carries no covariance."""
    cols = MAG_PARAMS.cols("D", "o")
    cov = np.asarray(mag.cov, dtype=np.float64)[np.ix_(cols, cols)]
    j = field_jacobian(mag, m)
    jc = np.einsum("nip,pq,njq->nij", j, cov, j)
    out: FloatArray = 0.5 * (jc + jc.transpose(0, 2, 1))        # exactly symmetric, as ROS consumers assume
    return out
