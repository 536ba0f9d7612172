"""Epochs that average several readings (epochs.Groups): what their mean predicts, as terms on the base factors.

Reading j of epoch k's group sees the body frame R_j = R_k dR_kj, with dR_kj the gyro preintegrated from the
group's first reading (gyro.Within). Its field is D dR_kj^T u + o with u = R_k^T m_n, so the group's mean reading
predicts D (A u + sum_a u_a B_a db) + o, and its mean specific force -(A g_b + sum_a g_b,a B_a db) + b_a with
g_b = R_k^T g_n (A, B: gyro.Within; db: the gyro bias correction). Written as a term added to the one-reading prediction, D (N - I) u with
N = A + M, M[:, a] = B_a db, the group rides on the base factors like an effect: dN u / dphi = N [u]x,
d/ddb = sum_a u_a B_a.

The readings of a group are tied by the gyro alone, without its noise between them: at the few tens of
milliseconds a group spans, that noise turns the body by a small fraction of the magnetometer's noise
(docs/decisions.md, "Readings averaged per epoch").
"""

from __future__ import annotations

import numpy as np

from magcal_cli import so3
from magcal_cli.effects.base import Point, Term
from magcal_cli.models.gyro import Within
from magcal_cli.streams import FloatArray


def mixed(within: Within, db: FloatArray) -> FloatArray:
    """N = A + M (K, 3, 3), M[:, :, a] = B_a db: the map from u = R_k^T v to the group's mean of R_j^T v."""
    out: FloatArray = within.A + np.einsum("kaij,j->kia", within.B, db)
    return out


def averaged(at: Point, n: FloatArray) -> Point:
    """The point as the effect terms of a group's mean reading see it: each body vector the group's mean (N u), and
    `rot` the map R_k N^T whose transpose gives it (nongravity's R^T a_n)."""
    def mean(v: FloatArray) -> FloatArray:
        out: FloatArray = np.einsum("kij,kj->ki", n, v)
        return out
    return Point(at.rot @ n.transpose(0, 2, 1), mean(at.m_b), mean(at.dm_b_ddip), mean(at.g_b), at.D, at.pre)


def _by_bias(within: Within, u: FloatArray) -> FloatArray:
    """sum_a u_a B_a (K, 3, 3): the mean of dR_kj^T u's derivative by the bias correction."""
    out: FloatArray = np.einsum("ka,kaij->kij", u, within.B)
    return out


def mag_term(within: Within, at: Point, db: FloatArray) -> Term:
    """D (N - I) u: the mean reading's prediction less the first reading's; beta: the gyro bias correction. `at`:
    the point at the groups' first readings (`cost.point_at` without `pre`)."""
    n_i = mixed(within, db) - np.eye(3)
    v = np.einsum("kij,kj->ki", n_i, at.m_b)
    m = v.shape[0]
    d_d = np.zeros((m, 3, 3, 3))                 # d (D v) / d vec(D), column-major: entry (i, j + 3 k) is v_j at k = i
    for i in range(3):
        d_d[:, i, :, i] = v
    d_dip = np.einsum("kij,kj->ki", n_i, at.dm_b_ddip) @ at.D.T
    d_state = np.einsum("ab,kbc->kac", at.D, n_i @ so3.hat(at.m_b))
    return Term(v @ at.D.T, np.einsum("ab,kbc->kac", at.D, _by_bias(within, at.m_b)), d_state,
                {"D": d_d.reshape(m, 3, 9), "dip": d_dip[:, :, None]})


def acc_term(within: Within, at: Point, db: FloatArray) -> Term:
    """-(N - I) g_b: the mean specific force's prediction less the first reading's; beta: the gyro bias
    correction. `at`: the point at the groups' first readings."""
    n_i = mixed(within, db) - np.eye(3)
    value = -np.einsum("kij,kj->ki", n_i, at.g_b)
    return Term(value, -_by_bias(within, at.g_b), -(n_i @ so3.hat(at.g_b)))
