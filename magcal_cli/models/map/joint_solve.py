"""Normal equations and Levenberg-Marquardt steps of the joint fit of many magnetometers (joint.py), structured.

`normal.py` assembles H_xtheta (3K x p) and eliminates the trajectory with p right-hand sides; for M magnetometers
p = 6 + 13 M (396 for Huang et al.'s 30) and that banded solve dominates (22 s for 30 magnetometers, 5 minutes).
When every magnetometer reads at the same epochs the coupling has low rank whatever M is: with the north and down
directions in the body, n_k = R_k^T e_N and d_k = R_k^T e_D, magnetometer i sees m = c_i n_k + s_i d_k (c, s: cos,
sin of its dip), and its factor r = L (y - D m - o) gives (P = D^T L^T L, M_ = P D)

    J_x^T J_theta = -[m]x P [m^T kron I | I | D dm],   dm = -s_i n_k + c_i d_k,

whose columns are fixed combinations (coefficients from c_i, s_i, P and M_) of 42 vectors per state: n_k x e_a,
d_k x e_a and those times n_k[l] or d_k[l]. So H_xtheta = B C with B (3K x 48: these 42 and the accelerometer and
gyro bias columns) and C (48 x p): the banded solve takes 48 right-hand sides and S = H_tt - C^T (Y^T Y) C with
Y = U^-T B. The magnetometers' own blocks (H_xx, H_tt, gradients) come from moments of n_k and d_k, O(K) per
magnetometer. `mag.mag_factor` stays the reference: tests/models/test_map_joint.py checks every block against it
and the gradient against finite differences.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy import linalg
from scipy.linalg import lapack

from magcal_cli import so3
from magcal_cli.models.accel import accel_factor
from magcal_cli.models.factor import Factor, scale_rows
from magcal_cli.models.gyro import Preintegrated, gyro_factor
from magcal_cli.models.mag import MagLayout
from magcal_cli.models.normal import band, schur_inverse, selected_inverse
from magcal_cli.models.solve import Options, iterate
from magcal_cli.params import MAG, Layout
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

#: where D, o and dip sit in a magnetometer's 13 columns (params.MAG: vec D column-major, o, dip)
D_AT, O_AT, DIP_AT = MAG.slice("D"), MAG.slice("o"), MAG.slice("dip")
#: the shared basis: 6 vectors n x e_a, d x e_a, then 36 (n x e_a) n_l, (n x e_a) d_l, (d x e_a) n_l, (d x e_a) d_l
R_MAG = 42


@dataclass(frozen=True, eq=False)
class JointData:
    """What the structured cost needs: accelerometer at the states (K, 3) with its row factors (K,) (interpolation
    and held-out weights), the gyro preintegration, readings (M, K, 3) in each magnetometer's scale, its noise std
    (M, 3), the magnetometer row weights (K,) or None, the accelerometer std (3,), the layout and where each
    magnetometer's blocks sit in it."""

    acc: FloatArray
    acc_rows: FloatArray
    pre: Preintegrated
    mag: FloatArray
    mag_std: FloatArray
    mag_rows: FloatArray | None
    acc_std: FloatArray
    layout: Layout
    #: each magnetometer's 13 columns (D#i, o#i, dip#i)
    cols: tuple[IntArray, ...]
    _km: FloatArray | None = field(default=None, repr=False)

    @property
    def mag_km(self) -> FloatArray:
        """The readings as (K, M, 3), made once."""
        if self._km is None:
            object.__setattr__(self, "_km", np.ascontiguousarray(self.mag.transpose(1, 0, 2)))
        assert self._km is not None
        return self._km

    @property
    def mags(self) -> int:
        """Number of magnetometers."""
        return int(self.mag.shape[0])

    def mag_at(self, i: int) -> MagLayout:
        """Where magnetometer i's D, o and dip sit in theta."""
        c = self.mag_cols(i)
        return MagLayout(int(c[D_AT.start]), int(c[O_AT.start]), int(c[DIP_AT.start]))

    def mag_cols(self, i: int) -> IntArray:
        """Magnetometer i's 13 theta columns (D, o, dip)."""
        return self.cols[i]


def imu_factors(data: JointData, states: FloatArray, theta: FloatArray, jac: bool) -> tuple[Factor, Factor]:
    """The accelerometer and gyro factors (`accel.accel_factor`, `gyro.gyro_factor`) on the states."""
    lay = data.layout
    k = states.shape[0]
    fa = accel_factor(states, data.acc, np.diag(1.0 / data.acc_std), theta, lay.slice("accelerometer_bias").start,
                      np.arange(k), jacobians=jac, compact=True)
    return scale_rows(fa, data.acc_rows), gyro_factor(states, theta, data.pre, lay.slice("gyroscope_bias").start, jac)


def _mags(data: JointData, states: FloatArray, theta: FloatArray
          ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Every magnetometer at the states: unwhitened residuals e (K, M, 3), D (M, 3, 3), cos and sin of the dips
    (M,); magnetometer i predicts D_i (c_i n_k + s_i d_k) + o_i (one (K, 3) x (3, 3M) product per direction)."""
    th = theta[np.array(data.cols)]                                       # (M, 13): vec D, o, dip
    d = th[:, D_AT].reshape(-1, 3, 3).transpose(0, 2, 1)
    c, s = np.cos(th[:, DIP_AT.start]), np.sin(th[:, DIP_AT.start])
    dt_cat = d.transpose(2, 0, 1)                                         # [a, i, b] = D_i[b, a]
    k, n_m = states.shape[0], th.shape[0]
    pred = states[:, 0, :] @ (dt_cat * c[None, :, None]).reshape(3, -1) + \
        states[:, 2, :] @ (dt_cat * s[None, :, None]).reshape(3, -1)
    e = data.mag_km - pred.reshape(k, n_m, 3) - th[None, :, O_AT]
    return e, d, c, s


def cost(data: JointData, states: FloatArray, theta: FloatArray) -> float:
    """1/2 the sum of squared whitened residuals."""
    fa, fg = imu_factors(data, states, theta, False)
    e = _mags(data, states, theta)[0] / data.mag_std[None, :, :]
    w2 = 1.0 if data.mag_rows is None else data.mag_rows[:, None, None] ** 2
    return 0.5 * float(np.sum(fa.r**2) + np.sum(fg.r**2) + np.sum(w2 * e**2))


def mag_residuals(data: JointData, states: FloatArray, theta: FloatArray) -> FloatArray:
    """Every magnetometer's whitened residuals (M, K, 3), row weights applied."""
    e = _mags(data, states, theta)[0].transpose(1, 0, 2) / data.mag_std[:, None, :]
    return np.asarray(e if data.mag_rows is None else e * data.mag_rows[None, :, None], dtype=np.float64)


@dataclass
class Normal:
    """H = [[H_xx, B C], [C^T B^T, H_tt]] and g = J^T r: H_xx's blocks diag (K, 3, 3) and off (K-1, 3, 3), the
    coupling's basis B (K, 3, r) and coefficients C (r, p), H_tt (p, p), gx (K, 3), gt (p,)."""

    diag: FloatArray
    off: FloatArray
    basis: FloatArray
    coef: FloatArray
    htt: FloatArray
    gx: FloatArray
    gt: FloatArray


def basis(states: FloatArray) -> FloatArray:
    """The 42 shared coupling vectors per state (K, 3, 42), order of R_MAG's comment (a, then l, a outer)."""
    n_b, d_b = states[:, 0, :], states[:, 2, :]
    eye = np.eye(3)
    nx = np.cross(n_b[:, None, :], eye[None, :, :])             # (K, a, 3): n x e_a
    dx = np.cross(d_b[:, None, :], eye[None, :, :])
    prods = [u[:, :, None, :] * v[:, None, :, None] for u in (nx, dx) for v in (n_b, d_b)]   # (K, a, l, 3)
    cols = [nx, dx] + [p.reshape(-1, 9, 3) for p in prods]
    return np.concatenate(cols, axis=1).transpose(0, 2, 1)


def coefficients(d: FloatArray, sinv: FloatArray, c: float, s: float) -> FloatArray:
    """C_i (42, 13): J_x^T J_theta of magnetometer i = basis @ C_i (columns vec D, o, dip); sinv = L^T L (3, 3)."""
    p = d.T @ sinv
    mm = p @ d
    out = np.zeros((R_MAG, MAG.size))
    out[0:3, O_AT], out[3:6, O_AT] = -c * p, -s * p
    for q, (wd, wdip) in enumerate((((-c * c), c * s), ((-c * s), -c * c), ((-s * c), s * s), ((-s * s), -s * c))):
        at = 6 + 9 * q + 3 * np.arange(3)                        # rows (a, l) = at[a] + l
        for lcol in range(3):                                    # D column j + 3 l: w_q P[a, j]
            out[at + lcol, D_AT.start + 3 * lcol:D_AT.start + 3 * lcol + 3] = wd * p
        out[6 + 9 * q:15 + 9 * q, DIP_AT.start] = wdip * mm.reshape(9)     # dip: w_q M_[a, b] at row (a, b)
    return out


def normal(data: JointData, states: FloatArray, theta: FloatArray) -> tuple[float, Normal]:
    """The cost and the structured normal equations at (states, theta)."""
    lay = data.layout
    k, p = states.shape[0], theta.size
    diag, off = np.zeros((k, 3, 3)), np.zeros((k - 1, 3, 3))
    gx, gt, htt = np.zeros((k, 3)), np.zeros(p), np.zeros((p, p))
    hxt_imu = np.zeros((k, 3, 6))
    fa, fg = imu_factors(data, states, theta, True)
    total = 0.5 * float(np.sum(fa.r**2) + np.sum(fg.r**2))
    ba, bg = lay.slice("accelerometer_bias"), lay.slice("gyroscope_bias")
    for f, cols, at in ((fa, ba, slice(0, 3)), (fg, bg, slice(3, 6))):
        assert f.J_x is not None and f.J_theta is not None
        jt = f.J_theta
        jt2 = jt.reshape(-1, 3)
        htt[cols, cols] += jt2.T @ jt2
        gt[cols] += jt2.T @ f.r.reshape(-1)
        rows = slice(0, f.r.shape[0])
        diag[rows] += f.J_x.transpose(0, 2, 1) @ f.J_x
        gx[rows] += np.einsum("mki,mk->mi", f.J_x, f.r)
        hxt_imu[rows, :, at] += f.J_x.transpose(0, 2, 1) @ jt
        if f.J_next is not None:
            diag[1:] += f.J_next.transpose(0, 2, 1) @ f.J_next
            off += f.J_x.transpose(0, 2, 1) @ f.J_next
            gx[1:] += np.einsum("mki,mk->mi", f.J_next, f.r)
            hxt_imu[1:, :, at] += f.J_next.transpose(0, 2, 1) @ jt
    w2 = np.ones(k) if data.mag_rows is None else data.mag_rows**2
    n_b, d_b = states[:, 0, :], states[:, 2, :]
    hn, hd = so3.hat(n_b), so3.hat(d_b)
    mom = {(u, v): (w2[:, None] * a).T @ b for u, a in (("n", n_b), ("d", d_b)) for v, b in (("n", n_b), ("d", d_b))}
    first = {"n": w2 @ n_b, "d": w2 @ d_b}
    coef = np.zeros((6 + R_MAG, p))
    coef[0:3, ba], coef[3:6, bg] = np.eye(3), np.eye(3)
    e, ds, cs, ss = _mags(data, states, theta)
    sinvs = 1.0 / data.mag_std**2                                         # (M, 3): L^T L, diagonal
    we = e * (w2[:, None, None] * sinvs[None, :, :])                      # L^T L e, weighted, (K, M, 3)
    total += 0.5 * float(np.sum(we * e))
    flat = we.reshape(k, -1)
    # J_x^T r = sum_i [m_i]x P_i e_i = n x sum_i c_i P_i e_i + d x sum_i s_i P_i e_i, P_i e_i = D_i^T L^T L e_i
    gx += np.cross(n_b, flat @ (cs[:, None, None] * ds).reshape(-1, 3))
    gx += np.cross(d_b, flat @ (ss[:, None, None] * ds).reshape(-1, 3))
    we_n, we_d = (flat.T @ n_b).reshape(-1, 3, 3), (flat.T @ d_b).reshape(-1, 3, 3)   # sum_k we n^T, we d^T
    we_sum = we.sum(axis=0)
    g_nn, g_nd, g_dd = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    for i in range(data.mags):
        d, c, s = ds[i], float(cs[i]), float(ss[i])
        sinv = np.diag(sinvs[i])
        g = d.T @ sinv @ d
        g_nn, g_nd, g_dd = g_nn + c * c * g, g_nd + c * s * g, g_dd + s * s * g
        mc = data.mag_cols(i)
        mm = c * c * mom["n", "n"] + c * s * (mom["n", "d"] + mom["d", "n"]) + s * s * mom["d", "d"]
        dmm = -s * c * mom["n", "n"] - s * s * mom["n", "d"] + c * c * mom["d", "n"] + c * s * mom["d", "d"]
        dmdm = s * s * mom["n", "n"] - s * c * (mom["n", "d"] + mom["d", "n"]) + c * c * mom["d", "d"]
        m1, dm1 = c * first["n"] + s * first["d"], -s * first["n"] + c * first["d"]
        h = np.zeros((MAG.size, MAG.size))
        dip = DIP_AT.start
        h[D_AT, D_AT] = np.kron(mm, sinv)
        h[D_AT, O_AT] = np.kron(m1[:, None], sinv)
        h[D_AT, dip] = (sinv @ d @ dmm).ravel(order="F")
        h[O_AT, O_AT] = float(w2.sum()) * sinv
        h[O_AT, dip] = sinv @ d @ dm1
        h[dip, dip] = float(np.trace(g @ dmdm))
        h = np.triu(h) + np.triu(h, 1).T
        htt[np.ix_(mc, mc)] += h
        we_m, we_dm = c * we_n[i] + s * we_d[i], -s * we_n[i] + c * we_d[i]
        gt[mc] += -np.concatenate([we_m.ravel(order="F"), we_sum[i], [float(np.trace(d.T @ we_dm))]])
        coef[6:, mc] = coefficients(d, sinv, c, s)
    cross = hn.transpose(0, 2, 1) @ g_nd @ hd
    diag += w2[:, None, None] * (hn.transpose(0, 2, 1) @ g_nn @ hn + hd.transpose(0, 2, 1) @ g_dd @ hd + cross
                                 + cross.transpose(0, 2, 1))
    b = np.concatenate([hxt_imu, basis(states) * w2[:, None, None]], axis=2)
    return total, Normal(diag, off, b, coef, htt, gx, gt)


@dataclass(frozen=True, eq=False)
class JointSolution:
    """The optimum, its cost and log; at the optimum S^-1 (cov_theta), V = H_xx^-1 B (K, 3, r) so that
    H_xx^-1 H_xtheta = V C, and the selected inverse of H_xx (t_xx (K, 3, 3), t_next (K-1, 3, 3))."""

    states: FloatArray
    theta: FloatArray
    cost: float
    iterations: int
    converged: bool
    cov_theta: FloatArray
    log: tuple[str, ...]
    v: FloatArray
    coef: FloatArray
    t_xx: FloatArray
    t_next: FloatArray


def _tb(cb: FloatArray, rhs: FloatArray, trans: str) -> FloatArray:
    """U^-T rhs (trans "T") or U^-1 rhs (trans "N") for the banded upper Cholesky factor cb."""
    out, info = lapack.dtbtrs(cb, rhs, uplo="U", trans=trans)
    if info != 0:
        msg = "banded triangular solve failed"
        raise np.linalg.LinAlgError(msg)
    return np.asarray(out, dtype=np.float64)


def step(ne: Normal, lam: float, lam_theta: float | None = None
         ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The damped step (dx (K, 3), dtheta), S^-1, the damped H_xx blocks, the banded factor and Y = U^-T B."""
    k = ne.gx.shape[0]
    diag = ne.diag.copy()
    dd = np.einsum("nii->ni", diag)
    dd += lam * (dd + 1e-9 * float(np.mean(dd)))
    scale = float(np.mean(np.diag(ne.htt)))
    lt = lam if lam_theta is None else lam_theta
    htt = ne.htt + lt * np.diag(np.diag(ne.htt) + 1e-9 * max(scale, 1e-300))
    cb = linalg.cholesky_banded(band(diag, ne.off, 5), overwrite_ab=True, lower=False, check_finite=False)
    r = ne.basis.shape[2]
    sol = _tb(cb, np.concatenate([ne.basis.reshape(3 * k, r), ne.gx.reshape(3 * k, 1)], axis=1), "T")
    y_b, y = sol[:, :r], sol[:, r]
    gram = y_b.T @ y_b
    s = htt - ne.coef.T @ gram @ ne.coef
    s = 0.5 * (s + s.T)
    s_inv = schur_inverse(s)
    dt = s_inv @ (ne.coef.T @ (y_b.T @ y) - ne.gt)
    dx = -_tb(cb, (y + y_b @ (ne.coef @ dt))[:, None], "N")[:, 0]
    return dx.reshape(k, 3), dt, s_inv, diag, cb, y_b


def solve_joint(data: JointData, states0: FloatArray, theta0: FloatArray, opts: Options) -> JointSolution:
    """`solve.iterate` (the one Levenberg-Marquardt loop) on the structured normal equations."""
    def advance(ne: Normal, lam: float) -> tuple[FloatArray, FloatArray]:
        dx, dt, *_ = step(ne, lam)
        return dx, dt

    out = iterate(lambda states, theta: normal(data, states, theta), advance, states0, theta0, opts)
    return at_optimum(out.system, out.states, out.theta, out.cost, out.iterations, out.converged, out.log)


def at_optimum(ne: Normal, states: FloatArray, theta: FloatArray, cur: float, iterations: int, converged: bool,
               log: Sequence[str]) -> JointSolution:
    """S^-1, V and H_xx's selected inverse of the undamped information (a trace of damping on the trajectory
    when it is numerically singular, as `normal.undamped`)."""
    for lam_theta in (None, 0.0):
        try:
            _, _, s_inv, diag, cb, y_b = step(ne, 0.0 if lam_theta is None else 1e-9, lam_theta)
            break
        except (np.linalg.LinAlgError, linalg.LinAlgError):
            if lam_theta is not None:
                raise
    k, r = ne.gx.shape[0], ne.basis.shape[2]
    v = _tb(cb, y_b, "N").reshape(k, 3, r)
    t_xx, t_next = selected_inverse(diag, ne.off)
    return JointSolution(states, theta, cur, iterations, converged, s_inv, tuple(log), v, ne.coef, t_xx, t_next)
