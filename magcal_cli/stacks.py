"""Stacks of small matrices stored component-major, (i, j, M): products and SO(3) pieces that run along M.

np.matmul on (M, 3, 3) stacks loops over M tiny products (~150 ns each); with the stack axis last, one product
is nine length-M multiply-adds, several times faster. The gyro factor chains about ten such products per
linearisation (models/gyro.py); `cm` and `rm` convert at its ends. Formulas follow so3.py (the only copy of the
scalar coefficients).
"""

from __future__ import annotations

import numpy as np

from magcal_cli import so3
from magcal_cli.streams import FloatArray


def cm(x: FloatArray) -> FloatArray:
    """(M, i, j) row-major stack -> (i, j, M), contiguous."""
    return np.ascontiguousarray(x.transpose(1, 2, 0))


def rm(x: FloatArray) -> FloatArray:
    """(i, j, M) -> (M, i, j), contiguous."""
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def mul(a: FloatArray, b: FloatArray) -> FloatArray:
    """a @ b per stack entry."""
    out: FloatArray = np.einsum("ikn,kjn->ijn", a, b)
    return out


def tmul(a: FloatArray, b: FloatArray) -> FloatArray:
    """a^T @ b per stack entry."""
    out: FloatArray = np.einsum("kin,kjn->ijn", a, b)
    return out


def mult(a: FloatArray, b: FloatArray) -> FloatArray:
    """a @ b^T per stack entry."""
    out: FloatArray = np.einsum("ikn,jkn->ijn", a, b)
    return out


def hat(v: FloatArray) -> FloatArray:
    """[v]x of vectors v (M, 3), component-major (3, 3, M)."""
    return _hat(np.ascontiguousarray(v.T))


def _hat(v: FloatArray) -> FloatArray:
    """[v]x of vectors v (3, M)."""
    x, y, z = v
    k = np.zeros((3, 3, v.shape[1]))
    k[0, 1], k[0, 2], k[1, 0], k[1, 2], k[2, 0], k[2, 1] = -z, y, z, -x, -y, x
    return k


def _hat_and_square(v: FloatArray) -> tuple[FloatArray, FloatArray]:
    """[v]x and [v]x^2 of vectors v (3, M)."""
    x, y, z = v
    k = _hat(v)
    xx, yy, zz = x * x, y * y, z * z
    k2 = np.empty_like(k)
    k2[0, 0], k2[1, 1], k2[2, 2] = -(yy + zz), -(xx + zz), -(xx + yy)
    k2[0, 1] = k2[1, 0] = x * y
    k2[0, 2] = k2[2, 0] = x * z
    k2[1, 2] = k2[2, 1] = y * z
    return k, k2


def _plus_identity(m: FloatArray) -> FloatArray:
    """m + I per stack entry, in place."""
    for i in range(3):
        m[i, i] += 1.0
    return m


def exp(phi: FloatArray) -> FloatArray:
    """so3.exp of rotation vectors phi (M, 3), component-major (3, 3, M), each rotation's coefficients chosen by its
    own angle. `so3.exp_coefficients` takes its series only when every angle of the batch is small, so a rotation's
    digits depended on the others beside it: time_offset integrates a subset of samples again (its memo) and must
    get the digits of the whole, or a diagnosis worker, whose memo saw other fits, moves the last digits."""
    a, b = np.empty(phi.shape[0]), np.empty(phi.shape[0])
    small = np.einsum("...i,...i->...", phi, phi) < so3.SERIES_T2
    for rows in (small, ~small):
        if rows.any():
            a[rows], b[rows], _ = so3.exp_coefficients(phi[rows])
    k, k2 = _hat_and_square(np.ascontiguousarray(phi.T))
    return _plus_identity(a * k + b * k2)


def minus_identity(m: FloatArray) -> FloatArray:
    """m - I per stack entry, as a new array."""
    out = m.copy()
    for i in range(3):
        out[i, i] -= 1.0
    return out


def exp_and_right_jacobian(phi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """so3.exp_and_right_jacobian of rotation vectors phi (M, 3), both component-major (3, 3, M)."""
    a, b, c = so3.exp_coefficients(phi)
    k, k2 = _hat_and_square(np.ascontiguousarray(phi.T))
    return _plus_identity(a * k + b * k2), _plus_identity(-b * k + c * k2)


def right_jacobian_inv(r: FloatArray) -> FloatArray:
    """so3.right_jacobian_inv of rotation vectors r (3, M), component-major."""
    k, k2 = _hat_and_square(r)
    d = so3.jr_inv_coefficient(np.linalg.norm(r, axis=0))
    return _plus_identity(0.5 * k + d * k2)


def log_small_transposed(rt: FloatArray, limit: float = 3.0) -> FloatArray:
    """so3.log_small of the rotations whose transposes are rt (3, 3, M), as vectors (3, M)."""
    v = 0.5 * np.stack([rt[1, 2] - rt[2, 1], rt[2, 0] - rt[0, 2], rt[0, 1] - rt[1, 0]])
    ratio, theta = so3.log_ratio(np.linalg.norm(v, axis=0), 0.5 * (rt[0, 0] + rt[1, 1] + rt[2, 2] - 1.0))
    out: FloatArray = ratio * v
    far = theta > limit
    if np.any(far):
        out[:, far] = so3.log(rt[:, :, far].transpose(2, 1, 0)).T
    return out
