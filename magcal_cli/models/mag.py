"""Magnetometer residual y - D R^T m_n(dip) - o and its Jacobians (methods.md sections 1-3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.models.factor import Factor, diagonal_of
from magcal_cli.models.gyro import Within
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class MagLayout:
    """Where one magnetometer's D (9, column-major), o (3) and dip sit in theta."""

    D: int
    o: int
    dip: int

    @classmethod
    def packed(cls, start: int) -> MagLayout:
        """D, o, dip stored contiguously from `start` (13 entries)."""
        return cls(start, start + 9, start + 12)

    def unpack(self, theta: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        """D (3, 3), o (3,), dip of this magnetometer."""
        return (theta[self.D:self.D + 9].reshape(3, 3, order="F"), theta[self.o:self.o + 3],
                float(theta[self.dip]))


def field_nav(dip: float) -> FloatArray:
    """Unit field in NED, [cos dip, 0, sin dip]."""
    return np.array([np.cos(dip), 0.0, np.sin(dip)])


def mag_factor(rot: FloatArray, y: FloatArray, l_inv: FloatArray, theta: FloatArray, layout: MagLayout,
               idx: IntArray | None, jacobians: bool = True, name: str = "mag",
               compact: bool = False, within: Within | None = None, bias_at: int = 0) -> Factor:
    """Whitened r = L^-1 (y - D R^T m_n - o) for rows with rotations rot (M, 3, 3) and readings y (M, 3).

    Jacobians with R <- R Exp(phi): dr/dphi = -L^-1 D [R^T m_n]x, dr/dvec(D) = -L^-1 ((R^T m_n)^T kron I),
    dr/do = -L^-1, dr/ddip = -L^-1 D R^T [-sin dip, 0, cos dip]^T. `compact`: J_theta holds only the 13
    columns of this magnetometer (theta_cols: D, o, dip).

    `within` (gyro.Within): y is the mean of a group of readings, predicted D N u + o with u = R^T m_n and
    N = A + M(db) (db = theta[bias_at:bias_at+3], the gyro bias correction); then dr/dphi = -L^-1 D N [u]x,
    dr/ddb = -L^-1 D sum_a u_a B_a, and the columns run from b_g (those between, a gyro effect's, stay zero).
    """
    d, o, dip = layout.unpack(theta)
    u = np.einsum("mji,j->mi", rot, field_nav(dip))
    n = None if within is None else within.mixed(theta[bias_at:bias_at + 3])
    mb = u if n is None else np.einsum("mij,mj->mi", n, u)
    r = (y - mb @ d.T - o) @ l_inv.T
    if not jacobians:
        return Factor(name, r)
    m = y.shape[0]
    cols = np.concatenate([np.arange(layout.D, layout.D + 9), np.arange(layout.o, layout.o + 3),
                           [layout.dip]])
    if within is not None:
        cols = np.concatenate([np.arange(bias_at, layout.D), cols])
    lead = cols.size - 13
    jt = np.zeros((m, 3, cols.size)) if compact else np.zeros((m, 3, theta.size))
    at_d, at_o, at_dip = (lead, lead + 9, lead + 12) if compact else (layout.D, layout.o, layout.dip)
    diag = diagonal_of(l_inv)
    if diag is None:
        jt[:, :, at_d:at_d + 9] = -np.einsum("ik,mj->mijk", l_inv, mb).reshape(m, 3, 9)
    else:                      # diagonal L^-1: row i only touches D's row i (entries i, i + 3, i + 6)
        for i in range(3):
            jt[:, i, at_d + i:at_d + 9:3] = mb * -diag[i]
    jt[:, :, at_o:at_o + 3] = -l_inv
    dm = np.einsum("mji,j->mi", rot, np.array([-np.sin(dip), 0.0, np.cos(dip)]))
    if n is not None:
        dm = np.einsum("mij,mj->mi", n, dm)
    jt[:, :, at_dip] = -dm @ (l_inv @ d).T
    lead_d = -(l_inv @ d)
    if within is None or n is None:
        jx = so3.times_hat(lead_d, mb)
    else:
        jx = lead_d @ (n @ so3.hat(u))
        at_b = 0 if compact else bias_at
        jt[:, :, at_b:at_b + 3] = lead_d @ within.by_bias(u)
    return Factor(name, r, idx, jx, None, jt, cols.astype(np.int64) if compact else None)
