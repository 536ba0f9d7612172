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

    Goes through the quaternion (`_quat_of`), which stays accurate near 0 and near pi.
    """
    rot = np.asarray(rot, dtype=np.float64)
    q = _canonical(_quat_of(rot))
    w, v = q[..., 0], q[..., 1:]
    norm = np.sqrt(np.sum(v * v, axis=-1))
    theta = 2.0 * np.arctan2(norm, w)
    small = theta <= 1e-3
    t2 = theta * theta
    # theta / sin(theta / 2) and its series below 1e-3 rad (scipy's as_rotvec)
    scale = np.where(small, 2.0 + t2 / 12.0 + 7.0 * t2 * t2 / 2880.0,
                     theta / (np.sin(theta / 2.0) + small))
    result: FloatArray = scale[..., None] * v
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
    """Rotation matrices from (..., 4) quaternions (w, x, y, z); they need not be normalised, but a quaternion of
    norm 0 is no rotation (ValueError, as scipy's from_quat)."""
    q = np.asarray(q, dtype=np.float64)
    if np.any(np.all(q == 0, axis=-1)):
        msg = "not a rotation: a quaternion of norm 0"
        raise ValueError(msg)
    return _matrix(_unit(q))


def _matrix(q: FloatArray) -> FloatArray:
    """Rotation matrices of (..., 4) unit quaternions (w, x, y, z), by scipy's formula (same digits)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz, ww = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    out = np.stack([xx - yy - zz + ww, 2 * (xy - zw), 2 * (xz + yw),
                    2 * (xy + zw), -xx + yy - zz + ww, 2 * (yz - xw),
                    2 * (xz - yw), 2 * (yz + xw), -xx - yy + zz + ww], axis=-1)
    result: FloatArray = out.reshape(w.shape + (3, 3))
    return result


def _unit(q: FloatArray) -> FloatArray:
    """(w, x, y, z) quaternions divided by their norm, summed x, y, z, w as scipy does (same digits)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    result: FloatArray = q / np.sqrt(x * x + y * y + z * z + w * w)[..., None]
    return result


def _compose(p: FloatArray, q: FloatArray) -> FloatArray:
    """Quaternion products p q of (..., 4) (w, x, y, z) quaternions."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([pw * qw - px * qx - py * qy - pz * qz, pw * qx + qw * px + (py * qz - pz * qy),
                     pw * qy + qw * py + (pz * qx - px * qz), pw * qz + qw * pz + (px * qy - py * qx)], axis=-1)


def as_quat(rot: npt.ArrayLike) -> FloatArray:
    """(..., 4) quaternions (w, x, y, z) with w >= 0 of rotation matrices."""
    return _canonical(_quat_of(np.asarray(rot, dtype=np.float64)))


def from_rpy(rpy: npt.ArrayLike) -> FloatArray:
    """Rz(yaw) Ry(pitch) Rx(roll) from (..., 3) roll, pitch, yaw in radians (roll applied first)."""
    rpy = np.asarray(rpy, dtype=np.float64)
    half = rpy / 2.0
    axes = np.zeros(rpy.shape + (4,))               # the three elementary quaternions, each about its axis
    axes[..., 0] = np.cos(half)
    for k in range(3):
        axes[..., k, k + 1] = np.sin(half[..., k])
    # composed yaw first and not normalised again, as scipy's from_euler("ZYX") does (same digits)
    return _matrix(_compose(_compose(axes[..., 2, :], axes[..., 1, :]), axes[..., 0, :]))


def as_rpy(rot: npt.ArrayLike) -> FloatArray:
    """(..., 3) roll, pitch, yaw in radians with rot = Rz(yaw) Ry(pitch) Rx(roll), each in [-pi, pi].

    From the quaternion (Bernardes & Viollet 2022, the method of scipy's as_euler): accurate up to the gimbal
    lock, where (pitch within 1e-7 rad of +-90 deg) roll and yaw are one angle; it is given to yaw, roll is 0.
    """
    w, x, y, z = np.moveaxis(_quat_of(np.asarray(rot, dtype=np.float64)), -1, 0)
    # intrinsic Z-Y-X is extrinsic x-y-z; the quaternion permuted for the axes (i, j, k) = (x, y, z), sign +1
    a, b, c, d = w - y, x + z, y + w, z - x
    half_sum, half_diff = np.arctan2(b, a), np.arctan2(d, c)
    middle = 2.0 * np.arctan2(np.hypot(c, d), np.hypot(a, b))
    near0, near_pi = np.abs(middle) <= 1e-7, np.abs(middle - np.pi) <= 1e-7
    free = ~(near0 | near_pi)
    first = np.where(free, half_sum - half_diff, 0.0)                      # roll
    third = np.where(free, half_sum + half_diff, np.where(near0, 2.0 * half_sum, 2.0 * half_diff))   # yaw
    out = np.stack([first, middle - np.pi / 2.0, third], axis=-1)
    result: FloatArray = np.where(out < -np.pi, out + 2.0 * np.pi, np.where(out > np.pi, out - 2.0 * np.pi, out))
    return result


def _quat_of(rot: FloatArray) -> FloatArray:
    """Unit quaternions (w, x, y, z), either sign, of (..., 3, 3) matrices that are projected onto SO(3) first
    unless orthogonal to 1e-12 (Shepperd's method as in scipy: the largest of w, x, y, z is solved for first, so
    it stays accurate near 0 and pi); a matrix with det <= 0 is no rotation (ValueError)."""
    det = np.linalg.det(rot)
    if np.any(det <= 0):
        msg = f"not a rotation: a matrix with determinant {float(np.min(det)):.3g}"
        raise ValueError(msg)
    gram = rot @ np.swapaxes(rot, -1, -2)
    eye = np.eye(3)
    off = ~np.all(np.abs(gram - eye) <= 1e-12 + 1e-5 * eye, axis=(-2, -1))      # np.isclose's test, faster
    if np.any(off):
        rot = rot.copy()
        rot[off] = project(rot[off])
    m = rot.reshape(-1, 3, 3)
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    choice = np.argmax(np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], trace], axis=-1), axis=-1)
    q = np.empty((m.shape[0], 4))                  # (x, y, z, w) while built, as in the method's statement
    rows = np.arange(m.shape[0])
    for i in range(3):
        sel = rows[choice == i]
        j, k = (i + 1) % 3, (i + 2) % 3
        q[sel, i] = 1.0 - trace[sel] + 2.0 * m[sel, i, i]
        q[sel, j] = m[sel, j, i] + m[sel, i, j]
        q[sel, k] = m[sel, k, i] + m[sel, i, k]
        q[sel, 3] = m[sel, k, j] - m[sel, j, k]
    sel = rows[choice == 3]
    q[sel, 0] = m[sel, 2, 1] - m[sel, 1, 2]
    q[sel, 1] = m[sel, 0, 2] - m[sel, 2, 0]
    q[sel, 2] = m[sel, 1, 0] - m[sel, 0, 1]
    q[sel, 3] = 1.0 + trace[sel]
    result: FloatArray = _unit(q[:, [3, 0, 1, 2]]).reshape(rot.shape[:-2] + (4,))
    return result


def _canonical(q: FloatArray) -> FloatArray:
    """The sign of each (w, x, y, z) quaternion with w > 0, or the first nonzero of x, y, z > 0 when w = 0."""
    lead = np.where(q[..., 0] != 0, q[..., 0], np.where(q[..., 1] != 0, q[..., 1],
                                                        np.where(q[..., 2] != 0, q[..., 2], q[..., 3])))
    result: FloatArray = np.where((lead < 0)[..., None], -q, q)
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
    is then a product of only ~log2 N factors, orthogonal to ~1e-15). One component-major copy is scanned and
    re-projected in place: a copy per stage was a two-hour log's peak (issue 39).
    """
    rots = np.asarray(rots, dtype=np.float64)
    if rots.shape[0] <= 1:
        out = np.array(rots)
        return _reorthogonalised(out) if reproject else out
    cm = np.array(rots.transpose(1, 2, 0), order="C")          # our own copy, whatever the input's layout
    shift = 1
    while shift < cm.shape[2]:
        cm[:, :, shift:] = np.einsum("ikn,kjn->ijn", cm[:, :, :-shift], cm[:, :, shift:])
        shift *= 2
    return _reorthogonalised_cm(cm) if reproject else np.ascontiguousarray(cm.transpose(2, 0, 1))


def _reorthogonalised(m: FloatArray) -> FloatArray:
    """`project` of (N, 3, 3) matrices; one Bjorck-Bowie step m (3 I - m^T m) / 2 when all are orthogonal to 1e-8
    (its error is then below 1e-16, and it is ten times cheaper than the SVD), else the SVD."""
    return _reorthogonalised_cm(np.ascontiguousarray(m.transpose(1, 2, 0)))


def _reorthogonalised_cm(cm: FloatArray) -> FloatArray:
    """`_reorthogonalised` of a component-major stack (3, 3, N) that it may overwrite; returns (N, 3, 3)."""
    gram = np.einsum("kin,kjn->ijn", cm, cm)
    for i in range(3):
        gram[i, i] -= 1.0
    if not gram.size or float(np.max(np.abs(gram))) > 1e-8:
        return project(np.ascontiguousarray(cm.transpose(2, 0, 1)))
    step = np.einsum("ikn,kjn->ijn", cm, gram)
    del gram
    step *= 0.5
    cm -= step                                       # cm - 0.5 cm (m^T m - I), element by element as before
    del step
    return np.ascontiguousarray(cm.transpose(2, 0, 1))


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


#: squared angle (rad^2) below which `exp_coefficients` takes the Taylor series (angles below 1e-2 rad)
SERIES_T2 = 1e-4


def exp_coefficients(phi: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """sin(t)/t, (1-cos t)/t^2, (t-sin t)/t^3 of (..., 3) rotation vectors, as `exp_and_right_jacobian` uses them:
    the Taylor series to theta^4 when every angle is below 1e-2 rad."""
    t2 = np.einsum("...i,...i->...", phi, phi)
    if t2.size and float(t2.max()) < SERIES_T2:
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

