"""SO(3): hat/vee, Exp/Log, right Jacobians, quaternions, Wahba and polar factors — the only copy.

Conventions (stated once): rotation matrices act on column vectors; `R` maps body to nav (v_n = R v_b);
perturbations are on the right, R <- R Exp(phi), phi in the body frame; quaternions are scalar first
(w, x, y, z). Every function accepts leading batch dimensions.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from magcal_cli.streams import FloatArray

#: below this angle (rad) the closed forms lose precision and the Taylor series (to theta^4) is exact
#: to double precision: the first neglected term is ~theta^6/5040 < 1e-22.
_SMALL = 1e-4


def hat(v: npt.ArrayLike) -> FloatArray:
    """Skew matrix [v]x of (..., 3) vectors, so that hat(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def vee(m: npt.ArrayLike) -> FloatArray:
    """Inverse of hat: the (..., 3) vector of (the skew part of) (..., 3, 3) matrices."""
    m = np.asarray(m, dtype=np.float64)
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1
    )


def hat_squared(v: FloatArray) -> FloatArray:
    """hat(v) @ hat(v) = v v^T - |v|^2 I, entry by entry (the Exp and Jacobian formulas below run on thousands
    of rows per call, where a 3x3 matmul per row costs several times more)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    xx, yy, zz = x * x, y * y, z * z
    out = np.empty(v.shape[:-1] + (9,))
    out[..., 0], out[..., 4], out[..., 8] = -(yy + zz), -(xx + zz), -(xx + yy)
    out[..., 1] = out[..., 3] = x * y
    out[..., 2] = out[..., 6] = x * z
    out[..., 5] = out[..., 7] = y * z
    result: FloatArray = out.reshape(v.shape[:-1] + (3, 3))
    return result


def _coefficients(phi: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """theta, sin(t)/t, (1-cos t)/t^2, (t-sin t)/t^3 with Taylor branches near zero."""
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(t)) / (t * t))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / (t * t * t))
    return theta, a, b, c


def exp(phi: npt.ArrayLike) -> FloatArray:
    """Exp: rotation vectors (..., 3) -> rotation matrices (..., 3, 3) (Rodrigues)."""
    phi = np.asarray(phi, dtype=np.float64)
    _, a, b, _ = _coefficients(phi)
    k = hat(phi)
    return np.eye(3) + a[..., None, None] * k + b[..., None, None] * hat_squared(phi)


def log(rot: npt.ArrayLike) -> FloatArray:
    """Log: rotation matrices (..., 3, 3) -> rotation vectors (..., 3) with norm in [0, pi].

    Goes through the quaternion (Shepperd's method in scipy), which stays accurate near 0 and near pi.
    """
    from scipy.spatial.transform import Rotation  # on use: scipy.spatial costs ~0.2 s (issue 27)

    rot = np.asarray(rot, dtype=np.float64)
    flat = rot.reshape(-1, 3, 3)
    out = Rotation.from_matrix(flat).as_rotvec()
    result: FloatArray = out.reshape(rot.shape[:-2] + (3,))
    return result


def right_jacobian(phi: npt.ArrayLike) -> FloatArray:
    """J_r(phi): Exp(phi + d) ~= Exp(phi) Exp(J_r(phi) d) (Chirikjian 2011, eq. 10.86; Forster 2017 eq. 8)."""
    phi = np.asarray(phi, dtype=np.float64)
    _, _, b, c = _coefficients(phi)
    k = hat(phi)
    return np.eye(3) - b[..., None, None] * k + c[..., None, None] * hat_squared(phi)


def right_jacobian_inv(phi: npt.ArrayLike) -> FloatArray:
    """J_r(phi)^-1 = I + k/2 + (1/t^2 - cot(t/2)/(2t)) k^2 (Forster 2017 eq. 9), finite up to |phi| < 2 pi."""
    phi = np.asarray(phi, dtype=np.float64)
    d = jr_inv_coefficient(np.linalg.norm(phi, axis=-1))
    k = hat(phi)
    return np.eye(3) + 0.5 * k + d[..., None, None] * hat_squared(phi)


def jr_inv_coefficient(theta: FloatArray) -> FloatArray:
    """The k^2 coefficient 1/t^2 - cot(t/2)/(2t) of J_r^-1 at angles theta (Taylor series near zero)."""
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    out: FloatArray = np.where(small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
                               1.0 / (t * t) - 1.0 / (2.0 * t * np.tan(t / 2.0)))
    return out


def left_jacobian(phi: npt.ArrayLike) -> FloatArray:
    """J_l(phi) = J_r(-phi): Exp(phi + d) ~= Exp(J_l(phi) d) Exp(phi)."""
    return right_jacobian(-np.asarray(phi, dtype=np.float64))


def from_quat(q: npt.ArrayLike) -> FloatArray:
    """Rotation matrices from (..., 4) quaternions (w, x, y, z); they need not be normalised."""
    from scipy.spatial.transform import Rotation  # on use: scipy.spatial costs ~0.2 s (issue 27)

    q = np.asarray(q, dtype=np.float64)
    flat = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix()
    result: FloatArray = flat.reshape(q.shape[:-1] + (3, 3))
    return result


def as_quat(rot: npt.ArrayLike) -> FloatArray:
    """(..., 4) quaternions (w, x, y, z) with w >= 0 of rotation matrices."""
    from scipy.spatial.transform import Rotation  # on use: scipy.spatial costs ~0.2 s (issue 27)

    rot = np.asarray(rot, dtype=np.float64)
    flat = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat(canonical=True, scalar_first=True)
    result: FloatArray = flat.reshape(rot.shape[:-2] + (4,))
    return result


def from_rpy(rpy: npt.ArrayLike) -> FloatArray:
    """Rz(yaw) Ry(pitch) Rx(roll) from (..., 3) roll, pitch, yaw in radians (roll applied first)."""
    from scipy.spatial.transform import Rotation  # on use: scipy.spatial costs ~0.2 s (issue 27)

    rpy = np.asarray(rpy, dtype=np.float64)
    flat = Rotation.from_euler("ZYX", rpy.reshape(-1, 3)[:, ::-1]).as_matrix()
    result: FloatArray = flat.reshape(rpy.shape[:-1] + (3, 3))
    return result


def as_rpy(rot: npt.ArrayLike) -> FloatArray:
    """(..., 3) roll, pitch, yaw in radians with rot = Rz(yaw) Ry(pitch) Rx(roll)."""
    from scipy.spatial.transform import Rotation  # on use: scipy.spatial costs ~0.2 s (issue 27)

    rot = np.asarray(rot, dtype=np.float64)
    flat = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_euler("ZYX")[:, ::-1]
    result: FloatArray = flat.reshape(rot.shape[:-2] + (3,))
    return result


def project(m: npt.ArrayLike) -> FloatArray:
    """The nearest rotation matrices (Frobenius norm) to (..., 3, 3) matrices."""
    u, _, vt = np.linalg.svd(np.asarray(m, dtype=np.float64))
    sign = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= sign[..., None]
    result: FloatArray = u @ vt
    return result


def wahba(body: npt.ArrayLike, nav: npt.ArrayLike, weights: npt.ArrayLike | None = None) -> FloatArray:
    """R minimising sum_i w_i |nav_i - R body_i|^2, batched: body (..., M, 3), nav (M, 3) or (..., M, 3).

    The SVD solution of Wahba's problem (Markley 1988), equivalent to Davenport's q-method.
    """
    body = np.asarray(body, dtype=np.float64)
    nav = np.broadcast_to(np.asarray(nav, dtype=np.float64), body.shape)
    w = np.ones(body.shape[-2]) if weights is None else np.asarray(weights, dtype=np.float64)
    b = np.einsum("...mi,...mj,m->...ij", nav, body, w)
    return project(b)


def polar(m: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Polar factors m = U P with U a rotation (det +1) and P symmetric; P is positive definite iff det m > 0."""
    u_, s, vt = np.linalg.svd(np.asarray(m, dtype=np.float64))
    sign = np.sign(np.linalg.det(u_ @ vt))
    u_[..., :, 2] *= sign[..., None]
    s = s.copy()
    s[..., 2] *= sign
    return u_ @ vt, vt.swapaxes(-1, -2) @ (s[..., :, None] * vt)


def angle(rot: npt.ArrayLike) -> FloatArray:
    """Rotation angle(s) in radians, in [0, pi]."""
    result: FloatArray = np.linalg.norm(log(rot), axis=-1)
    return result


def cumulative_product(rots: npt.ArrayLike, reproject: bool = True) -> FloatArray:
    """Prefix products P_k = R_0 R_1 ... R_k of (N, 3, 3) rotations, by a log-depth scan (Hillis-Steele).

    ceil(log2 N) batched products instead of N sequential ones, with the stack axis innermost (a 3x3 matmul per
    row costs several times more); the result is re-projected onto SO(3) unless `reproject` is False (each P_k
    is then a product of only ~log2 N factors, orthogonal to ~1e-15).
    """
    out = np.array(rots, dtype=np.float64)
    if out.shape[0] > 1:
        cm = np.ascontiguousarray(out.transpose(1, 2, 0))
        shift = 1
        while shift < cm.shape[2]:
            cm[:, :, shift:] = np.einsum("ikn,kjn->ijn", cm[:, :, :-shift], cm[:, :, shift:])
            shift *= 2
        out = np.ascontiguousarray(cm.transpose(2, 0, 1))
    return _reorthogonalised(out) if reproject else out


def _reorthogonalised(m: FloatArray) -> FloatArray:
    """`project` of (N, 3, 3) matrices; one Bjorck-Bowie step m (3 I - m^T m) / 2 when all are orthogonal to 1e-8
    (its error is then below 1e-16, and it is ten times cheaper than the SVD), else the SVD."""
    cm = np.ascontiguousarray(m.transpose(1, 2, 0))
    gram = np.einsum("kin,kjn->ijn", cm, cm)
    for i in range(3):
        gram[i, i] -= 1.0
    if not gram.size or float(np.max(np.abs(gram))) > 1e-8:
        return project(m)
    step: FloatArray = cm - 0.5 * np.einsum("ikn,kjn->ijn", cm, gram)
    return np.ascontiguousarray(step.transpose(2, 0, 1))


def log_small(rot: npt.ArrayLike, limit: float = 3.0) -> FloatArray:
    """Log of rotations whose angle is mostly below `limit` (rad): atan2 of the skew and symmetric parts.

    theta = atan2(|v|, (tr R - 1)/2) with v = vee(R - R^T)/2 = sin(theta) axis is accurate at every angle
    except near pi, where the axis is lost in v; rows beyond `limit` go through `log`. Several times faster
    than the quaternion route for the small residual rotations of least-squares factors.
    """
    rot = np.asarray(rot, dtype=np.float64)
    v = vee(rot)
    ratio, theta = log_ratio(np.linalg.norm(v, axis=-1), 0.5 * (np.trace(rot, axis1=-2, axis2=-1) - 1.0))
    out: FloatArray = ratio[..., None] * v
    far = theta > limit
    if np.any(far):
        out[far] = log(rot[far])
    return out


def log_ratio(s: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """theta / sin(theta) and theta = atan2(s, c) from s = |vee(R)| = sin(theta) and c = (tr R - 1) / 2."""
    theta = np.arctan2(s, c)
    small = s < _SMALL
    ratio: FloatArray = np.where(small, 1.0 + s * s / 6.0, theta / np.where(small, 1.0, s))
    return ratio, theta


#: hat(v) = v @ _HAT_BASIS reshaped: the generators [e_x]x, [e_y]x, [e_z]x as rows
_HAT_BASIS = np.array([[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0], [0, -1, 0, 1, 0, 0, 0, 0, 0]],
                      dtype=np.float64)


def times_hat(m: FloatArray, v: FloatArray) -> FloatArray:
    """m [v]x for one (3, 3) matrix m and (N, 3) vectors v, as one (N, 3) x (3, 9) product (the entries of m [v]x
    are linear in v): a stacked matmul would loop over N tiny products."""
    basis = (m @ _HAT_BASIS.reshape(3, 3, 3)).reshape(3, 9)       # row l: m [e_l]x
    out: FloatArray = (v @ basis).reshape(v.shape[:-1] + (3, 3))
    return out


def exp_coefficients(phi: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """sin(t)/t, (1-cos t)/t^2, (t-sin t)/t^3 of (..., 3) rotation vectors, as `exp_and_right_jacobian` uses them:
    the Taylor series to theta^4 when every angle is below 1e-2 rad."""
    t2 = np.einsum("...i,...i->...", phi, phi)
    if t2.size and float(t2.max()) < 1e-4:
        return (1.0 + t2 * (-1.0 / 6.0 + t2 / 120.0), 0.5 + t2 * (-1.0 / 24.0 + t2 / 720.0),
                1.0 / 6.0 + t2 * (-1.0 / 120.0 + t2 / 5040.0))
    _, a, b, c = _coefficients(phi)
    return a, b, c


def exp_and_right_jacobian(phi: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Exp(phi) and J_r(phi) of (..., 3) rotation vectors from one evaluation of the coefficients (filter loops).

    When every angle is below 1e-2 rad (a filter's update increments) the Taylor series to theta^4 is exact to
    double precision (first neglected term ~theta^6/5040 < 1e-15), evaluated without square root or branches.
    """
    phi = np.asarray(phi, dtype=np.float64)
    a, b, c = exp_coefficients(phi)
    k = (phi @ _HAT_BASIS).reshape(phi.shape[:-1] + (3, 3))
    k2 = hat_squared(phi)
    a, b, c = a[..., None, None], b[..., None, None], c[..., None, None]
    return np.eye(3) + a * k + b * k2, np.eye(3) - b * k + c * k2


def slerp(rots: FloatArray, t_rots: FloatArray, t: FloatArray) -> FloatArray:
    """Rotations (N, 3, 3) at increasing times t_rots (N >= 2) at times t, along the geodesic between the two
    neighbours (held at the first and last outside their span)."""
    j = np.clip(np.searchsorted(t_rots, t, side="right") - 1, 0, t_rots.size - 2)
    w = np.clip((t - t_rots[j]) / (t_rots[j + 1] - t_rots[j]), 0.0, 1.0)
    out: FloatArray = rots[j] @ exp(w[:, None] * log(np.swapaxes(rots[j], -1, -2) @ rots[j + 1]))
    return out

