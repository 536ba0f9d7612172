"""Cluster-robust (sandwich) covariance of theta for residuals correlated within time blocks.

When residuals share an unmodelled, slowly varying error (an accelerometer bias tilting every vertical,
a field disturbance), the information matrix overstates what the data know. The sandwich estimator
cov = S^-1 (sum_c E_c E_c^T) S^-1 * C/(C-1) uses the per-cluster score of theta after eliminating the
trajectory, E_c = sum_{rows in c} (J_theta^T r - W_k^T J_x^T r), with W = Hxx^-1 Hx_theta and S the Schur
complement (Liang & Zeger 1986; Cameron & Miller 2015 for the small-C correction).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from magcal_cli.detect import chi2_ppf
from magcal_cli.models.factor import Factor, run_start
from magcal_cli.models.solve import Solution
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

#: row groups whose eliminated Jacobians (rows, k, p) are made at once (`_per_cluster`)
CHUNK_ROWS = 4096


def cluster_robust_cov(sol: Solution, clusters: Sequence[IntArray], lags: int = 0) -> FloatArray:
    """Sandwich covariance of theta; clusters[i] (M_i,) gives the cluster id of each row group of factor i
    (negative ids leave rows out, e.g. priors, which are not data).

    With lags > 0, clusters are ordered in time and neighbours up to `lags` apart are allowed to correlate:
    Bartlett weights 1 - l/(lags+1) keep the estimate positive semi-definite (Newey & West 1987).
    """
    s_inv = sol.cov_theta
    scores = cluster_scores(sol, clusters)
    return s_inv @ newey_west(scores, lags) @ s_inv


def _eliminated(sol: Solution, f: Factor, p: int, rows: slice | IntArray = slice(None)) -> FloatArray:
    """A factor's Jacobian by theta with the trajectory eliminated, (M, k, p): J_theta - J_x W (rows whitened), for
    the row groups `rows` (default all)."""
    r = f.r[rows]
    out = np.zeros((*r.shape, p))
    if f.idx is not None:
        for jx, shift in ((f.J_x, 0), (f.J_next, 1)):
            if jx is not None:
                idx = f.idx[rows] + shift
                start = run_start(idx)                  # a run of states: W's rows as a view, not a copy
                w = sol.hxx_inv_hxt
                out -= jx[rows] @ (w[idx] if start is None else w[start:start + idx.shape[0]])
    if f.J_theta is not None:
        out[:, :, f.theta_slice(p)] += f.J_theta[rows]
    return out


def cluster_scores(sol: Solution, clusters: Sequence[IntArray]) -> FloatArray:
    """Per-cluster gradient of the cost by theta after eliminating the trajectory, (C, p): E_c above."""
    return _per_cluster(sol, clusters, information=False)[0]


def cluster_scores_and_information(sol: Solution, clusters: Sequence[IntArray]) -> tuple[FloatArray, FloatArray]:
    """Per-cluster scores E_c (C, p), as `cluster_scores`, and Gauss-Newton information H_c (C, p, p) of theta
    after eliminating the trajectory, from one pass: how each cluster's score moves with a step d of theta
    (E_c + H_c d), to first order."""
    scores, info = _per_cluster(sol, clusters, information=True)
    assert info is not None
    return scores, info


def _per_cluster(sol: Solution, clusters: Sequence[IntArray], information: bool
                 ) -> tuple[FloatArray, FloatArray | None]:
    """Each cluster's score and (when asked) information, summed over its row groups (negative ids left out)."""
    p = sol.cov_theta.shape[0]
    n = _count(clusters)
    scores, info = np.zeros((n, p)), np.zeros((n, p, p)) if information else None
    for f, c in zip(sol.factors, clusters, strict=True):
        keep = np.flatnonzero(c >= 0)
        if not keep.size:
            continue
        # rows sorted by cluster, one (rows x p)^T (rows x p) product per cluster: per-row p x p outer products
        # summed with np.add.at took seconds on a long log
        order = keep[np.argsort(c[keep], kind="stable")]
        ids, first = np.unique(c[order], return_index=True)
        in_order = order.size == f.r.shape[0] and not np.any(np.diff(order) != 1)   # time clusters usually are
        ends = np.append(first[1:], order.size)
        # whole clusters of about CHUNK_ROWS rows at a time: all rows' (M, k, p) at once was a 60-min flight's
        # peak (issue 39), and one chunk per cluster costs a few numpy calls per second of log
        chunk = np.searchsorted(first, first + CHUNK_ROWS, side="left")
        a = 0
        while a < ids.size:
            b = max(int(chunk[a]), a + 1)
            lo0, hi0 = int(first[a]), int(ends[b - 1])
            rows = slice(lo0, hi0) if in_order else order[lo0:hi0]
            j, r = _eliminated(sol, f, p, rows), f.r[rows]
            for cid, lo, hi in zip(ids[a:b], first[a:b] - lo0, ends[a:b] - lo0, strict=True):
                block = j[lo:hi].reshape(-1, p)
                scores[cid] += block.T @ r[lo:hi].reshape(-1)
                if info is not None:
                    info[cid] += block.T @ block
            a = b
    return scores, info


def _count(clusters: Sequence[IntArray]) -> int:
    """Number of clusters (ids run from 0)."""
    return int(max(int(c.max()) for c in clusters if c.size) + 1)


def newey_west(scores: FloatArray, lags: int) -> FloatArray:
    """Sum of outer products of time-ordered scores (C, p) with Bartlett-weighted neighbours up to `lags`
    apart, times the small-sample factor C/(C-1)."""
    n = scores.shape[0]
    meat = scores.T @ scores
    for lag in range(1, min(lags, n - 1) + 1):
        cross = scores[:-lag].T @ scores[lag:]
        meat += (1.0 - lag / (lags + 1.0)) * (cross + cross.T)
    return np.asarray(meat * (n / max(n - 1, 1)), dtype=np.float64)


def bartlett_dof(clusters: int, lags: int) -> float:
    """Degrees of freedom of a Newey-West variance from `clusters` scores with Bartlett weights."""
    return clusters / (1.0 + 2.0 * sum((1.0 - k / (lags + 1.0)) ** 2 for k in range(1, lags + 1)))


def factor_clusters(factors: Sequence[Factor], epoch_ids: IntArray) -> list[IntArray]:
    """Cluster ids of each factor's row groups from the ids of the epochs they touch (-1: no epoch, e.g. a
    prior, which is not data)."""
    return [epoch_ids[f.idx] if f.idx is not None else np.full(f.r.shape[0], -1, np.int64) for f in factors]


def time_clusters(t: npt.ArrayLike, count: int = 40, min_length_s: float = 5.0) -> IntArray:
    """Cluster ids of samples at times t: about `count` contiguous blocks, each at least min_length_s long."""
    t = np.asarray(t, dtype=np.float64)
    span = float(t.max() - t.min()) if t.size else 0.0
    length = max(span / count, min_length_s)
    ids = np.floor((t - t.min()) / length).astype(np.int64)
    return np.unique(ids, return_inverse=True)[1].astype(np.int64)


def widening(sol: Solution, clusters: Sequence[IntArray], lags: int = 4,
             false_alarm: float = 1e-3) -> FloatArray:
    """Per-parameter std factors >= 1: sqrt(sandwich / model variance) where that ratio is significant.

    Under a correct noise model the ratio of a Newey-West variance to the model variance is about
    chi2(nu)/nu with nu = C / (1 + 2 sum_l w_l^2) for C clusters and Bartlett weights w_l; only ratios
    above its 1 - false_alarm quantile widen (so simulated, well-specified data keep the model covariance).
    """
    sand = cluster_robust_cov(sol, clusters, lags)
    return std_factors(np.diag(sol.cov_theta), np.diag(sand), _count(clusters), lags, false_alarm)


def std_factors(model: FloatArray, robust: FloatArray, clusters: int, lags: int, false_alarm: float = 1e-3
                ) -> FloatArray:
    """sqrt(robust / model) variances where that ratio exceeds its 1 - false_alarm quantile under a correct
    noise model (chi2(nu)/nu, nu from `bartlett_dof`), else 1."""
    nu = bartlett_dof(clusters, lags)
    threshold = chi2_ppf(1.0 - false_alarm, nu) / nu
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(model > 0, robust / model, 1.0)
    out: FloatArray = np.where(ratio > threshold, np.sqrt(ratio), 1.0)
    return out
