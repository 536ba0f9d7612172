"""The one nonlinear least-squares solver: Levenberg-Marquardt on SO(3)^N x R^p.

Residual factors touch one state k (and optionally its successor k+1) and the global parameters theta,
so the normal equations are block-banded in the trajectory with a dense border (Huang et al. 2025,
Appendix A; methods.md section 3). The trajectory is eliminated with a banded Cholesky factorisation
(LAPACK pbtrf/pbtrs through scipy), the p x p Schur complement is solved densely: O(N) per iteration.
The marginal covariance of theta is the inverse of the Schur complement at the optimum.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy import linalg

from .. import so3

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Factor:
    """Whitened residual rows r (M, m); row group i touches state idx[i] through J_x (M, m, 3),
    state idx[i] + 1 through J_next (M, m, 3) and theta through J_theta (M, m, p); any may be None."""

    name: str
    r: FloatArray
    idx: IntArray | None = None
    J_x: FloatArray | None = None
    J_next: FloatArray | None = None
    J_theta: FloatArray | None = None


#: linearize(states (N,3,3), theta (p,), with_jacobians) -> factors
Linearize = Callable[[FloatArray, FloatArray, bool], Sequence[Factor]]


@dataclass(frozen=True)
class Options:
    """Stopping rules and damping; defaults follow the authors' code (step norm < 1e-6)."""

    max_iterations: int = 100
    step_tol: float = 1e-6
    cost_tol: float = 1e-12
    lambda0: float = 1e-6
    loss: str = "l2"
    loss_scale: float = 3.0


@dataclass(frozen=True, eq=False)
class Solution:
    """The optimum, its cost, the iteration log and the Gauss-Newton information at the optimum."""

    states: FloatArray
    theta: FloatArray
    cost: float
    iterations: int
    converged: bool
    cov_theta: FloatArray
    log: tuple[str, ...]
    factors: tuple[Factor, ...]
    _hxx_diag: FloatArray = field(repr=False)
    _w: FloatArray = field(repr=False)
    _band: int = field(repr=False)

    def leverage(self, factor: Factor) -> FloatArray:
        """Diagonal of the hat matrix J H^-1 J^T for a unary factor's rows (M, m); block-diagonal trajectories only."""
        if self._band != 2 or factor.J_next is not None:
            msg = "leverage is implemented for unary factors on a block-diagonal trajectory"
            raise ValueError(msg)
        p_tt = self.cov_theta
        h = np.zeros(factor.r.shape)
        if factor.J_theta is not None:
            h += np.einsum("mkp,pq,mkq->mk", factor.J_theta, p_tt, factor.J_theta)
        if factor.J_x is not None and factor.idx is not None:
            w = self._w[factor.idx]                                   # (M, 3, p) = Hxx^-1 Hxt
            p_kk = np.linalg.inv(self._hxx_diag[factor.idx]) + w @ p_tt @ w.transpose(0, 2, 1)
            h += np.einsum("mki,mij,mkj->mk", factor.J_x, p_kk, factor.J_x)
            if factor.J_theta is not None:
                p_kt = -w @ p_tt
                h += 2.0 * np.einsum("mki,mip,mkp->mk", factor.J_x, p_kt, factor.J_theta)
        return h


def _robust_weights(factors: Sequence[Factor], opts: Options) -> tuple[float, list[FloatArray]]:
    """Cost 1/2 sum rho(|r_i|^2) and the IRLS row-group weights rho'(s) (Triggs et al. 2000, sec. 6.8)."""
    cost, weights = 0.0, []
    c2 = opts.loss_scale**2
    for f in factors:
        s = np.einsum("mk,mk->m", f.r, f.r)
        if opts.loss == "huber":
            w = np.where(s <= c2, 1.0, np.sqrt(c2 / np.maximum(s, 1e-300)))
            rho = np.where(s <= c2, s, 2.0 * np.sqrt(c2 * s) - c2)
        elif opts.loss == "cauchy":
            w = 1.0 / (1.0 + s / c2)
            rho = c2 * np.log1p(s / c2)
        else:
            w, rho = np.ones_like(s), s
        cost += 0.5 * float(rho.sum())
        weights.append(w)
    return cost, weights


@dataclass
class _Normal:
    """Assembled normal equations H = [[Hxx, Hxt], [Htx, Htt]], gradient g = J^T r."""

    diag: FloatArray       # (N, 3, 3)
    off: FloatArray        # (N-1, 3, 3), block (k, k+1)
    hxt: FloatArray        # (N, 3, p)
    htt: FloatArray        # (p, p)
    gx: FloatArray         # (N, 3)
    gt: FloatArray         # (p,)


def _assemble(factors: Sequence[Factor], weights: Sequence[FloatArray], n: int, p: int) -> _Normal:
    """Accumulate J^T W J and J^T W r factor by factor (vectorised over rows)."""
    ne = _Normal(np.zeros((n, 3, 3)), np.zeros((max(n - 1, 0), 3, 3)), np.zeros((n, 3, p)),
                 np.zeros((p, p)), np.zeros((n, 3)), np.zeros(p))
    for f, w in zip(factors, weights):
        r = f.r * w[:, None]
        if f.J_theta is not None:
            jt = f.J_theta
            ne.htt += np.einsum("mkp,m,mkq->pq", jt, w, jt)
            ne.gt += np.einsum("mkp,mk->p", jt, r)
        for jx, idx in ((f.J_x, f.idx), (f.J_next, None if f.idx is None else f.idx + 1)):
            if jx is None or idx is None:
                continue
            np.add.at(ne.diag, idx, np.einsum("mki,m,mkj->mij", jx, w, jx))
            np.add.at(ne.gx, idx, np.einsum("mki,mk->mi", jx, r))
            if f.J_theta is not None:
                np.add.at(ne.hxt, idx, np.einsum("mki,m,mkp->mip", jx, w, f.J_theta))
        if f.J_x is not None and f.J_next is not None and f.idx is not None:
            np.add.at(ne.off, f.idx, np.einsum("mki,m,mkj->mij", f.J_x, w, f.J_next))
    return ne


def _band(diag: FloatArray, off: FloatArray, u: int) -> FloatArray:
    """Upper banded storage ab[u + i - j, j] = H[i, j] of the block-tridiagonal trajectory matrix."""
    n = diag.shape[0]
    ab = np.zeros((u + 1, 3 * n))
    for a in range(3):
        for b in range(a, 3):
            ab[u - (b - a), 3 * np.arange(n) + b] = diag[:, a, b]
    if u == 5:
        for a in range(3):
            for b in range(3):
                ab[u - (3 + b - a), 3 * np.arange(1, n) + b] = off[:, a, b]
    return ab


def _step(ne: _Normal, lam: float, u: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Solve the damped normal equations; returns dx (N,3), dtheta, S^-1, damped Hxx blocks, Hxx^-1 Hxt."""
    n, p = ne.gx.shape[0], ne.gt.size
    diag = ne.diag.copy()
    d = np.einsum("nii->ni", diag)
    floor = 1e-9 * (float(np.mean(d)) if d.size else 1.0)
    d += lam * (d + floor)                                   # Marquardt scaling with a floor
    htt = ne.htt + lam * np.diag(np.diag(ne.htt) + 1e-9 * max(float(np.mean(np.diag(ne.htt))), 1e-300))
    cb = linalg.cholesky_banded(_band(diag, ne.off, u), lower=False, check_finite=False)
    rhs = np.concatenate([ne.hxt.reshape(3 * n, p), ne.gx.reshape(3 * n, 1)], axis=1)
    sol = linalg.cho_solve_banded((cb, False), rhs, check_finite=False)
    w, hinv_g = sol[:, :p], sol[:, p]
    hxt = ne.hxt.reshape(3 * n, p)
    s = htt - hxt.T @ w
    s = 0.5 * (s + s.T)
    s_inv = np.linalg.inv(s)
    dt = s_inv @ (-ne.gt + hxt.T @ hinv_g)
    dx = -(hinv_g + w @ dt)
    return dx.reshape(n, 3), dt, s_inv, diag, w.reshape(n, 3, p)


def solve(linearize: Linearize, states0: FloatArray, theta0: FloatArray, opts: Options | None = None) -> Solution:
    """Minimise 1/2 sum |r|^2 (or a robust loss) over states (right perturbation) and theta."""
    opts = opts or Options()
    states, theta = np.array(states0, dtype=np.float64), np.array(theta0, dtype=np.float64)
    n, p = states.shape[0], theta.size
    factors = linearize(states, theta, True)
    u = 5 if any(f.J_next is not None for f in factors) else 2
    cost, weights = _robust_weights(factors, opts)
    lam, log, converged, it = opts.lambda0, [f"start: cost {cost:.6g}"], False, 0
    for it in range(1, opts.max_iterations + 1):
        ne = _assemble(factors, weights, n, p)
        try:
            dx, dt, *_ = _step(ne, lam, u)
        except (np.linalg.LinAlgError, linalg.LinAlgError):
            lam *= 10.0
            log.append(f"iter {it}: singular system, lambda -> {lam:.1e}")
            if lam > 1e12:
                break
            continue
        new_states, new_theta = states @ so3.exp(dx), theta + dt
        new_cost, _ = _robust_weights(linearize(new_states, new_theta, False), opts)
        step = float(np.sqrt(np.sum(dx * dx) + dt @ dt))
        if np.isfinite(new_cost) and new_cost <= cost:
            rel = (cost - new_cost) / max(cost, 1e-300)
            states, theta, cost = new_states, new_theta, new_cost
            lam = max(lam / 3.0, 1e-12)
            log.append(f"iter {it}: cost {cost:.6g}, step {step:.2e}, lambda {lam:.1e}")
            factors = linearize(states, theta, True)
            _, weights = _robust_weights(factors, opts)
            if step < opts.step_tol or rel < opts.cost_tol:
                converged = True
                break
        else:
            lam *= 10.0
            log.append(f"iter {it}: rejected (cost {new_cost:.6g}), lambda -> {lam:.1e}")
            if step < opts.step_tol:
                converged = True
                break
            if lam > 1e12:
                break
    ne = _assemble(factors, weights, n, p)
    _, _, s_inv, hdiag, w = _step(ne, 0.0, u)
    return Solution(states, theta, cost, it, converged, s_inv, tuple(log), tuple(factors), hdiag, w, u)
