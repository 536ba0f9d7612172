"""Epochs that average several readings (epochs.Groups): how effects and the report see a group.

Reading j of epoch k's group sees the body frame R_j = R_k dR_kj, with dR_kj the gyro preintegrated from the
group's first reading. Its field is D dR_kj^T u + o with u = R_k^T m_n, so the group's mean reading is
D N u + o with N = mean_j dR_kj^T (gyro.Within, with its first-order change by the gyro bias correction); the
accelerometer's mean alike with g_b = R_k^T g_n. The base factors predict these means (`mag.mag_factor`,
`accel.accel_factor` with `within`); here the effect terms get the groups' mean body vectors, and the report the
readings' own residuals.

The readings of a group are tied by the gyro alone, without its noise between them: at the few tens of
milliseconds a group spans, that noise turns the body by a small fraction of the magnetometer's noise
(docs/decisions.md, "Readings averaged per epoch").
"""

from __future__ import annotations

import numpy as np

from magcal_cli.effects.base import Point
from magcal_cli.models.epochs import Groups
from magcal_cli.models.gyro import group_rotations
from magcal_cli.models.problem import Problem
from magcal_cli.streams import FloatArray


def averaged(at: Point, n: FloatArray) -> Point:
    """The point as the effect terms of a group's mean reading see it: each body vector the group's mean (N u), and
    `rot` the map R_k N^T whose transpose gives it (nongravity's R^T a_n)."""
    def mean(v: FloatArray) -> FloatArray:
        out: FloatArray = np.einsum("kij,kj->ki", n, v)
        return out
    return Point(at.rot @ n.transpose(0, 2, 1), mean(at.m_b), mean(at.dm_b_ddip), mean(at.g_b), at.D, at.pre)


def reading_residuals(problem: Problem, groups: Groups, mean_residual: FloatArray, states: FloatArray, d: FloatArray,
                      m_n: FloatArray, bias: FloatArray) -> FloatArray:
    """Each reading's residual (n, 3), from its group's mean residual (K, 3) and how the reading and its
    prediction D dR_kj^T u_k depart from their group's means (the gyro integrated with the fitted `bias`): what
    the report calls the model residual, which the mean residual understates by sqrt(k) for white noise."""
    k_of = groups.epoch_of
    v = np.einsum("nji,nj->ni", group_rotations(problem, groups, bias), (states.transpose(0, 2, 1) @ m_n)[k_of])
    out: FloatArray = groups.y - groups.mean(groups.y)[k_of] - (v - groups.mean(v)[k_of]) @ d.T
    out += mean_residual[k_of]
    return out
