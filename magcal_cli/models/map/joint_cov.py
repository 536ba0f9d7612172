"""Noise levels and covariance honesty of the joint fit of many magnetometers (joint.py), at its size.

`noise.variance_ratios` and `sandwich.widening` do the same for one magnetometer through `Solution.leverage` and
`sandwich.cluster_scores`, which expand every factor's Jacobian to all p columns of theta and need
H_xx^-1 H_xtheta (3K x p): with p = 6 + 13 M (396 for 30 magnetometers) that is M times the work. Here every
factor keeps its own columns and H_xx^-1 H_xtheta stays factored as V C (joint_solve.py), V (3K x 48).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from magcal_cli.detect import chi2_ppf
from magcal_cli.models.factor import Factor, scale_rows
from magcal_cli.models.mag import mag_factor
from magcal_cli.models.map.joint_solve import JointData, JointSolution, imu_factors
from magcal_cli.models.map.noise import group_ratio
from magcal_cli.models.normal import scatter
from magcal_cli.models.sandwich import bartlett_dof, newey_west, time_clusters
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]


def factors(data: JointData, states: FloatArray, theta: FloatArray) -> list[Factor]:
    """The fit's factors with Jacobians from their reference implementations: accelerometer, gyro, then each
    magnetometer's `mag.mag_factor` (named mag#i), row weights applied."""
    k = states.shape[0]
    out = list(imu_factors(data, states, theta, True))
    for i in range(data.mags):
        f = mag_factor(states, data.mag[i], np.diag(1.0 / data.mag_std[i]), theta, data.mag_at(i), np.arange(k),
                       True, name=f"mag#{i}", compact=True)
        out.append(f if data.mag_rows is None else scale_rows(f, data.mag_rows))
    return out


def _cols(f: Factor, p: int) -> slice:
    """A factor's contiguous theta columns (the joint layout keeps every factor's block contiguous)."""
    c = f.theta_slice(p)
    if not isinstance(c, slice):
        msg = f"factor {f.name}: its theta columns are not contiguous"
        raise ValueError(msg)
    return c


def leverages(sol: JointSolution, fs: list[Factor]) -> list[FloatArray]:
    """Per factor, the sum over its rows of the diagonal of the hat matrix J H^-1 J^T, per axis (m,): what
    `Solution.leverage` gives summed over rows, the degrees of freedom the unknowns take from each axis.

    H^-1's blocks with H_xx^-1 H_xtheta = V C: Z_xx,k = T_kk + V_k Q V_k^T, Z_x,k+1 = T_k,k+1 + V_k Q V_k+1^T with
    Q = C S^-1 C^T, Z_xtheta,k = -V_k C S^-1 and S^-1 (T: the selected inverse of H_xx alone).
    """
    p = sol.theta.size
    k, r = sol.v.shape[0], sol.v.shape[2]
    cs = sol.coef @ sol.cov_theta                                          # (r, p)
    vq = sol.v @ (cs @ sol.coef.T)
    z_xx = sol.t_xx + vq @ sol.v.transpose(0, 2, 1)
    z_next = sol.t_next + vq[:-1] @ sol.v[1:].transpose(0, 2, 1)
    v2 = sol.v.reshape(3 * k, r)
    out = []
    for f in fs:
        c = _cols(f, p)
        jt = f.J_theta
        assert jt is not None and f.idx is not None and f.J_x is not None
        m, q = f.r.shape[0], jt.shape[2]
        ws = (v2 @ cs[:, c]).reshape(k, 3, q)                              # -Z_xtheta over this factor's columns
        i = f.idx
        gram = np.einsum("mkp,mkq->kpq", jt, jt) if m < 64 else np.stack(
            [jt[:, a, :].T @ jt[:, a, :] for a in range(jt.shape[1])])
        h = np.einsum("kpq,pq->k", gram, sol.cov_theta[c, c])

        def quad(a: FloatArray, z: FloatArray, b: FloatArray) -> FloatArray:
            """sum over rows of diag(a z b^T), per axis (a z as three broadcast products: numpy's batched matmul
            of 3 x 3 blocks is slower)."""
            az = a[:, :, 0, None] * z[:, None, 0, :] + a[:, :, 1, None] * z[:, None, 1, :] + \
                a[:, :, 2, None] * z[:, None, 2, :]
            return np.asarray(np.sum(az * b, axis=(0, 2)), dtype=np.float64)

        h += quad(f.J_x, z_xx[i], f.J_x) - 2.0 * quad(f.J_x, ws[i], jt)
        if f.J_next is not None:
            h += quad(f.J_next, z_xx[i + 1], f.J_next) + 2.0 * quad(f.J_x, z_next[i], f.J_next)
            h -= 2.0 * quad(f.J_next, ws[i + 1], jt)
        out.append(h)
    return out


def joint_variance_ratios(sol: JointSolution, fs: list[Factor], loss: str = "l2", c: float = 3.0) -> FloatArray:
    """Variance factors sum(r^2) / (rows - leverage) as `noise.variance_ratios` computes them: accelerometer (3
    axes), gyro (1), then each magnetometer (3 axes), from `factors`."""
    out = {f.name: group_ratio(f, h, loss, c) for f, h in zip(fs, leverages(sol, fs), strict=True)}
    return np.concatenate([out["accel"], out["gyro"], *(out[f"mag#{i}"] for i in range(len(fs) - 2))])


def joint_widening(sol: JointSolution, fs: list[Factor], t: FloatArray, lags: int = 4,
                   false_alarm: float = 1e-3) -> FloatArray:
    """`sandwich.widening` for the joint fit: per-parameter std factors >= 1 from the time-clustered scores
    E_c = sum_{rows in c} (J_theta^T r - W_k^T J_x^T r), W_k = V_k C, clusters of ~40 blocks of the epochs."""
    n, p = sol.states.shape[0], sol.theta.size
    ids = time_clusters(t)
    count = int(ids.max()) + 1
    scores = np.zeros((count, p))
    g = np.zeros((n, 3))
    back = np.zeros((count, sol.v.shape[2]))
    for f in fs:
        assert f.idx is not None and f.J_x is not None and f.J_theta is not None
        part = np.zeros((count, f.J_theta.shape[2]))
        np.add.at(part, ids[f.idx], np.einsum("mkq,mk->mq", f.J_theta, f.r))
        scores[:, _cols(f, p)] += part
        scatter(g, f.idx, np.einsum("mki,mk->mi", f.J_x, f.r))
        if f.J_next is not None:
            # a binary row's score stays in its first state's cluster, as sandwich.factor_clusters puts it
            np.add.at(back, ids[f.idx], np.einsum("mir,mi->mr", sol.v[f.idx + 1],
                                                   np.einsum("mki,mk->mi", f.J_next, f.r)))
    np.add.at(back, ids, np.einsum("kir,ki->kr", sol.v, g))
    scores -= back @ sol.coef
    s_inv = sol.cov_theta
    sand = s_inv @ newey_west(scores, lags) @ s_inv
    model = np.diag(s_inv)
    nu = bartlett_dof(count, lags)
    threshold = chi2_ppf(1.0 - false_alarm, nu) / nu
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(model > 0, np.diag(sand) / model, 1.0)
    return np.asarray(np.where(ratio > threshold, np.sqrt(ratio), 1.0), dtype=np.float64)
