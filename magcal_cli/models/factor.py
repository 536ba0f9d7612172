"""Factors: whitened residual rows and their Jacobian blocks, what every model hands the solver (solve.py)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]


def run_start(idx: IntArray) -> int | None:
    """The first entry when idx is a run of consecutive integers (states, theta columns: the common case), else
    None."""
    m = idx.shape[0]
    if m and idx[-1] - idx[0] == m - 1 and (m < 3 or bool(np.all(np.diff(idx) == 1))):
        return int(idx[0])
    return None


@dataclass(frozen=True, eq=False)
class Factor:
    """Whitened residual rows r (M, m); row group i touches state idx[i] through J_x (M, m, 3),
    state idx[i] + 1 through J_next (M, m, 3) and theta through J_theta (M, m, p); any may be None.

    With `theta_cols` (q,) J_theta is compact, (M, m, q): only the theta entries it names are touched.
    """

    name: str
    r: FloatArray
    idx: IntArray | None = None
    J_x: FloatArray | None = None
    J_next: FloatArray | None = None
    J_theta: FloatArray | None = None
    theta_cols: IntArray | None = None

    def theta_slice(self, p: int) -> slice | IntArray:
        """Where J_theta's columns sit in theta: a slice when contiguous (all of theta without theta_cols)."""
        c = self.theta_cols
        if c is None:
            return slice(0, p)
        start = run_start(c)
        return c if start is None else slice(start, start + c.size)

    def rows(self, sel: slice) -> Factor:
        """The factor's row groups `sel` (views)."""
        def cut(a: npt.NDArray[Any] | None) -> Any:
            return None if a is None else a[sel]
        return Factor(self.name, self.r[sel], cut(self.idx), cut(self.J_x), cut(self.J_next), cut(self.J_theta),
                      self.theta_cols)

    def full_theta(self, p: int) -> FloatArray | None:
        """J_theta expanded to all p columns."""
        if self.J_theta is None or self.theta_cols is None:
            return self.J_theta
        out = np.zeros(self.J_theta.shape[:2] + (p,))
        out[:, :, self.theta_cols] = self.J_theta
        return out


#: linearize(states (N,3,3), theta (p,), with_jacobians) -> factors
Linearize = Callable[[FloatArray, FloatArray, bool], Sequence[Factor]]


def scale_rows(f: Factor, s: FloatArray, in_place: bool = False) -> Factor:
    """A factor's rows multiplied by s (M,); `in_place`: into the factor's own writeable arrays, for a factor just
    made that nothing else holds (a scaled copy beside each was 40 MB of a 60-min flight's peak, issue 39)."""
    def mul(a: FloatArray | None) -> FloatArray | None:
        if a is None:
            return None
        col = s.reshape((-1,) + (1,) * (a.ndim - 1))
        return np.multiply(a, col, out=a) if in_place and a.flags.writeable else a * col
    return Factor(f.name, f.r * s[:, None], f.idx, mul(f.J_x), mul(f.J_next), mul(f.J_theta), f.theta_cols)


def diagonal_of(l_inv: FloatArray) -> FloatArray | None:
    """The diagonal of a noise L^-1 when it is diagonal (every noise model here), else None."""
    d: FloatArray = np.diagonal(l_inv)
    return None if np.any(l_inv - np.diag(d)) else d


def whiten(l_inv: FloatArray, x: FloatArray) -> FloatArray:
    """L^-1 x for a stack x (M, 3, k): a diagonal L^-1 scales rows, which is exact and an order of magnitude cheaper
    than a matmul per row."""
    d = diagonal_of(l_inv)
    if d is not None:
        out: FloatArray = d[:, None] * x
        return out
    return np.asarray(l_inv @ x, dtype=np.float64)


def gaussian_factor(name: str, cols: IntArray, mean: FloatArray, std: FloatArray, theta: FloatArray,
                    jacobians: bool) -> Factor:
    """A Gaussian prior on theta entries `cols`: rows (theta_c - mean) / std, one per entry, with their diagonal
    compact Jacobian."""
    r = ((theta[cols] - mean) / std)[:, None]
    if not jacobians:
        return Factor(name, r)
    jt = np.zeros((cols.size, 1, cols.size))
    jt[np.arange(cols.size), 0, np.arange(cols.size)] = 1.0 / std
    return Factor(name, r, None, None, None, jt, np.asarray(cols, np.int64))
