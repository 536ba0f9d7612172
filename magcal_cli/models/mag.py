"""Magnetometer residual y - D R^T m_n(dip) - o and its Jacobians (methods.md sections 1-3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .. import so3
from .solve import Factor

FloatArray = npt.NDArray[np.float64]
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
               idx: IntArray | None, jacobians: bool = True, name: str = "mag") -> Factor:
    """Whitened r = L^-1 (y - D R^T m_n - o) for rows with rotations rot (M, 3, 3) and readings y (M, 3).

    Jacobians with R <- R Exp(phi): dr/dphi = -L^-1 D [R^T m_n]x, dr/dvec(D) = -L^-1 ((R^T m_n)^T kron I),
    dr/do = -L^-1, dr/ddip = -L^-1 D R^T [-sin dip, 0, cos dip]^T.
    """
    d, o, dip = layout.unpack(theta)
    mb = np.einsum("mji,j->mi", rot, field_nav(dip))
    r = (y - mb @ d.T - o) @ l_inv.T
    if not jacobians:
        return Factor(name, r)
    m = y.shape[0]
    jt = np.zeros((m, 3, theta.size))
    jt[:, :, layout.D:layout.D + 9] = -np.einsum("ik,mj->mijk", l_inv, mb).reshape(m, 3, 9)
    jt[:, :, layout.o:layout.o + 3] = -l_inv
    dm = np.einsum("mji,j->mi", rot, np.array([-np.sin(dip), 0.0, np.cos(dip)]))
    jt[:, :, layout.dip] = -dm @ (l_inv @ d).T
    jx = -(l_inv @ d) @ so3.hat(mb)
    return Factor(name, r, idx, jx, None, jt)
