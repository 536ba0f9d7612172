"""Not-a-knot cubic splines through samples, and their values and slopes: scipy's CubicSpline, digit for digit.

Written out because `scipy.interpolate` costs 0.09-0.36 s to import (issue 27) and magcal needs only this
spline. The slopes solve the tridiagonal system of C2 continuity with the not-a-knot ends (de Boor 1978,
ch. IV); the pieces are the cubic Hermite polynomials of the samples and slopes. The arithmetic follows
scipy 1.17's `CubicSpline` and `PPoly` (interpolate/_cubic.py, _ppoly.pyx) operation for operation, so the
values are the same to the last digit (tests/effects/test_spline.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.linalg import solve, solve_banded

from magcal_cli.streams import FloatArray


@dataclass(frozen=True, eq=False)
class Spline:
    """A cubic spline: knots x (n,), samples y (n, ...) and the knots' slopes s (n, ...). A piece's coefficients are
    made when a time asks for it: a 400 Hz channel of a two-hour log has 2.9 million pieces, and all their
    coefficients at once (4 per piece) were the biggest allocation of its diagnosis (issue 39). Each piece's are the
    same operations on the same numbers either way: the same digits."""

    x: FloatArray
    y: FloatArray
    s: FloatArray

    def __call__(self, t: npt.ArrayLike, deriv: int = 0) -> FloatArray:
        """Values (deriv 0) or slopes (deriv 1) at times t (..., then the samples' trailing shape); beyond the
        knots the end pieces are extended."""
        if deriv not in (0, 1):
            msg = f"deriv must be 0 or 1, not {deriv}"
            raise ValueError(msg)
        t = np.asarray(t, dtype=np.float64)
        flat = t.ravel()
        piece = np.clip(np.searchsorted(self.x, flat, side="right") - 1, 0, self.x.size - 2)
        c3, c2, c1, c0 = _coefficients(self.x, self.y, self.s, piece)
        h = (flat - self.x[piece]).reshape((-1,) + (1,) * (self.y.ndim - 1))
        # scipy's evaluate_poly1: a sum of c_k z prefactor with z = h^k built up by products, lowest power first
        if deriv == 0:
            z2 = h * h
            out = c0 * 1.0 + c1 * h * 1.0 + c2 * z2 * 1.0 + c3 * (z2 * h) * 1.0
        else:
            out = c1 * 1.0 * 1.0 + c2 * h * 2.0 + c3 * (h * h) * 3.0
        result: FloatArray = out.reshape(t.shape + self.y.shape[1:])
        return result


def _coefficients(x: FloatArray, y: FloatArray, s: FloatArray, piece: npt.NDArray[np.intp]
                  ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The coefficients of h^3, h^2, h, 1 of the given pieces, as scipy's CubicSpline makes them for every piece."""
    dxr = (x[piece + 1] - x[piece]).reshape((-1,) + (1,) * (y.ndim - 1))
    slope = (y[piece + 1] - y[piece]) / dxr
    s0 = s[piece]
    t = (s0 + s[piece + 1] - 2 * slope) / dxr
    return t / dxr, (slope - s0) / dxr - t, s0, y[piece]


def cubic(x: npt.ArrayLike, y: npt.ArrayLike) -> Spline:
    """The not-a-knot cubic spline through (x, y): x (n,) strictly increasing with n >= 2, y (n, ...)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    n = x.size
    dx = np.diff(x)
    if n < 2 or y.shape[0] != n or not np.all(dx > 0):
        msg = f"a spline needs >= 2 strictly increasing knots and one sample per knot (got {n} knots, {y.shape[0]})"
        raise ValueError(msg)
    if not np.all(np.isfinite(x)) or not np.all(np.isfinite(y)):         # scipy's CubicSpline refuses them too
        msg = "a spline needs finite knots and samples"
        raise ValueError(msg)
    dxr = dx.reshape((n - 1,) + (1,) * (y.ndim - 1))
    slope = np.diff(y, axis=0) / dxr
    if n == 2:                                          # a line
        s = np.concatenate([slope, slope])
    elif n == 3:                                        # both ends not-a-knot: the parabola through the three
        a = np.array([[1.0, 1.0, 0.0], [dx[1], 2 * (dx[0] + dx[1]), dx[0]], [0.0, 1.0, 1.0]])
        b = np.stack([2 * slope[0], 3 * (dxr[0] * slope[1] + dxr[1] * slope[0]), 2 * slope[1]])
        s = solve(a, b.reshape(3, -1), overwrite_a=True, overwrite_b=True, check_finite=False).reshape(b.shape)
    else:
        s = _slopes(x, dx, dxr, slope)
    return Spline(x, y, s)


def _slopes(x: FloatArray, dx: FloatArray, dxr: FloatArray, slope: FloatArray) -> FloatArray:
    """The knots' slopes (n, ...) of the C2 spline with not-a-knot ends, n >= 4: one tridiagonal solve."""
    n = x.size
    a = np.zeros((3, n))                                # banded: upper, diagonal, lower
    b = np.empty((n,) + slope.shape[1:])
    a[1, 1:-1] = 2 * (dx[:-1] + dx[1:])
    a[0, 2:] = dx[:-1]
    a[-1, :-2] = dx[1:]
    b[1:-1] = 3 * (dxr[1:] * slope[:-1] + dxr[:-1] * slope[1:])
    # not-a-knot: the third derivative is continuous across the second and the second-to-last knots
    a[1, 0], a[0, 1] = dx[1], x[2] - x[0]
    d = x[2] - x[0]
    b[0] = ((dxr[0] + 2 * d) * dxr[1] * slope[0] + dxr[0] ** 2 * slope[1]) / d
    a[1, -1], a[-1, -2] = dx[-2], x[-1] - x[-3]
    d = x[-1] - x[-3]
    b[-1] = (dxr[-1] ** 2 * slope[-2] + (2 * d + dxr[-1]) * dxr[-2] * slope[-1]) / d
    s: FloatArray = solve_banded((1, 1), a, b.reshape(n, -1), overwrite_ab=True, overwrite_b=True,
                                 check_finite=False).reshape(b.shape)
    return s
