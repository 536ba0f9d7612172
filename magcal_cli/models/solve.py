"""The one nonlinear least-squares solver: Levenberg-Marquardt on SO(3)^N x R^p.

Residual factors touch one state k (and optionally its successor k+1) and the global parameters theta,
so the normal equations are block-banded in the trajectory with a dense border (Huang et al. 2025,
Appendix A; methods.md section 3). The trajectory is eliminated with a banded Cholesky factorisation
(LAPACK pbtrf/pbtrs through scipy), the p x p Schur complement is solved densely: O(N) per iteration.
The marginal covariance of theta is the inverse of the Schur complement at the optimum.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np
import numpy.typing as npt
from scipy import linalg
from scipy.linalg import lapack
from threadpoolctl import ThreadpoolController

from magcal_cli import so3
from magcal_cli.models import stacks
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]
#: the system a Levenberg-Marquardt step solves (`iterate`)
S = TypeVar("S")
_BLAS: list[ThreadpoolController] = []


def one_blas_thread() -> AbstractContextManager[Any]:
    """BLAS limited to one thread inside the block. The library scan is done once (threadpoolctl's
    `threadpool_limits` repeats it on every call, 3 ms: 6 % of a diagnosis that solves a few hundred times)."""
    if not _BLAS:
        _BLAS.append(ThreadpoolController())
    limiter: AbstractContextManager[Any] = _BLAS[0].limit(limits=1, user_api="blas")
    return limiter


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

    def full_theta(self, p: int) -> FloatArray | None:
        """J_theta expanded to all p columns."""
        if self.J_theta is None or self.theta_cols is None:
            return self.J_theta
        out = np.zeros(self.J_theta.shape[:2] + (p,))
        out[:, :, self.theta_cols] = self.J_theta
        return out


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
    abs_cost_tol: float = 0.0        # also stop when an accepted step lowers the cost by less than this
    #: False: the caller wants the optimum and its residuals only (a replicate's refit, a held-out score): no
    #: covariance (NaN), and the last iteration's trial point is linearised without Jacobians
    covariance: bool = True


@dataclass(frozen=True, eq=False)
class Marginals:
    """Blocks of H^-1 on the sparsity pattern of H (marginal covariances): state k (N, 3, 3), states k and
    k+1 (N-1, 3, 3), state k with theta (N, 3, p) and theta (p, p)."""

    xx: FloatArray
    x_next: FloatArray
    xt: FloatArray
    tt: FloatArray


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
    _off: FloatArray | None = field(default=None, repr=False)
    _weights: tuple[FloatArray, ...] = field(default=(), repr=False)

    def marginals(self) -> Marginals:
        """Selected inverse of the undamped information at the optimum, O(N) (see `selected_inverse`)."""
        n = self._hxx_diag.shape[0]
        off = self._off if self._off is not None and self._band == 5 else np.zeros((max(n - 1, 0), 3, 3))
        z_xx, z_next = selected_inverse(self._hxx_diag, off)
        w_s = self._w @ self.cov_theta                                  # Hxx^-1 Hxt S^-1, (N, 3, p)
        xx = z_xx + w_s @ self._w.transpose(0, 2, 1)
        x_next = z_next + w_s[:-1] @ self._w[1:].transpose(0, 2, 1)
        return Marginals(xx, x_next, -w_s, self.cov_theta)

    def leverage(self, factor: Factor, marginals: Marginals | None = None) -> FloatArray:
        """Diagonal of the hat matrix J H^-1 J^T for a factor's rows (M, m); unary or consecutive-binary."""
        if factor.J_next is not None and self._band != 5:
            msg = "leverage of a binary factor needs the tridiagonal trajectory it was solved with"
            raise ValueError(msg)
        if factor.J_next is None and factor.J_x is not None and self._band == 2 and marginals is None:
            return self._leverage_block_diagonal(factor)
        z = marginals or self.marginals()
        h = np.zeros(factor.r.shape)
        p = self.theta.size
        cols = factor.theta_slice(p)
        jt = factor.J_theta if isinstance(cols, slice) else factor.full_theta(p)
        cols = cols if isinstance(cols, slice) else slice(0, p)
        if jt is not None:
            h += np.einsum("mkp,mkp->mk", jt @ z.tt[cols, cols], jt)
        if factor.idx is None or factor.J_x is None:
            return h
        i = factor.idx
        h += np.einsum("mki,mki->mk", factor.J_x @ z.xx[i], factor.J_x)
        if jt is not None:
            h += 2.0 * np.einsum("mkp,mkp->mk", factor.J_x @ z.xt[i][:, :, cols], jt)
        if factor.J_next is not None:
            h += np.einsum("mki,mki->mk", factor.J_next @ z.xx[i + 1], factor.J_next)
            h += 2.0 * np.einsum("mki,mki->mk", factor.J_x @ z.x_next[i], factor.J_next)
            if jt is not None:
                h += 2.0 * np.einsum("mkp,mkp->mk", factor.J_next @ z.xt[i + 1][:, :, cols], jt)
        return h

    def _leverage_block_diagonal(self, factor: Factor) -> FloatArray:
        """Unary factors on a block-diagonal trajectory: one 3x3 inverse per state."""
        p_tt = self.cov_theta
        h = np.zeros(factor.r.shape)
        jt = factor.full_theta(self.theta.size)
        if jt is not None:
            h += np.einsum("mkp,pq,mkq->mk", jt, p_tt, jt)
        if factor.J_x is not None and factor.idx is not None:
            w = self._w[factor.idx]                                   # (M, 3, p) = Hxx^-1 Hxt
            p_kk = np.linalg.inv(self._hxx_diag[factor.idx]) + w @ p_tt @ w.transpose(0, 2, 1)
            h += np.einsum("mki,mij,mkj->mk", factor.J_x, p_kk, factor.J_x)
            if jt is not None:
                p_kt = -w @ p_tt
                h += 2.0 * np.einsum("mki,mip,mkp->mk", factor.J_x, p_kt, jt)
        return h


def selected_inverse(diag: FloatArray, off: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Diagonal (N, 3, 3) and super-diagonal (N-1, 3, 3) blocks of A^-1 for SPD block-tridiagonal A, in O(N).

    The forward pivots F_k (A_kk minus what states < k contribute) are the Gram matrices of the diagonal
    blocks of A's banded Cholesky factor; the backward pivots G_k come from factoring A with its block order
    reversed. The marginal of states (k, k+1) is then [[F_k, A_k,k+1], [A_k+1,k, G_k+1]]^-1 (a 6x6 inverse per
    pair): two LAPACK factorisations, no sequential Python loop.
    """
    n = diag.shape[0]
    if n == 1:
        return np.asarray(np.linalg.inv(diag), dtype=np.float64), np.zeros((0, 3, 3))
    fwd = _pivots(diag, off)
    bwd = _pivots(diag[::-1], off[::-1].transpose(0, 2, 1))[::-1]
    pair = np.empty((n - 1, 6, 6))
    pair[:, :3, :3], pair[:, :3, 3:] = fwd[:-1], off
    pair[:, 3:, :3], pair[:, 3:, 3:] = off.transpose(0, 2, 1), bwd[1:]
    pinv = np.linalg.inv(pair)
    xx = np.concatenate([pinv[:, :3, :3], pinv[-1:, 3:, 3:]])
    return 0.5 * (xx + xx.transpose(0, 2, 1)), pinv[:, :3, 3:]


def _pivots(diag: FloatArray, off: FloatArray) -> FloatArray:
    """Block pivots F_k = U_kk^T U_kk of the upper banded Cholesky factor U of a block-tridiagonal matrix."""
    n, u = diag.shape[0], 5
    cb = linalg.cholesky_banded(_band(diag, off, u), lower=False, check_finite=False)
    ukk = np.zeros((n, 3, 3))
    cols = 3 * np.arange(n)
    for a in range(3):
        for b in range(a, 3):
            ukk[:, a, b] = cb[u - (b - a), cols + b]
    return ukk.transpose(0, 2, 1) @ ukk


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


def run_start(idx: IntArray) -> int | None:
    """The first entry when idx is a run of consecutive integers (states, theta columns: the common case), else
    None."""
    m = idx.shape[0]
    if m and idx[-1] - idx[0] == m - 1 and (m < 3 or bool(np.all(np.diff(idx) == 1))):
        return int(idx[0])
    return None


def _scatter(target: FloatArray, idx: IntArray, values: FloatArray, start: int | None = -1) -> None:
    """target[idx] += values; a slice add when idx is a run of consecutive states from `start` (`run_start`'s answer,
    -1: find out here)."""
    if start == -1:
        start = run_start(idx)
    if start is None:
        np.add.at(target, idx, values)
    else:
        target[start:start + idx.shape[0]] += values


def _gram(a: FloatArray, b: FloatArray) -> FloatArray:
    """a^T b per row group of (M, k, 3) stacks, on component-major stacks (models/stacks.py): np.matmul loops over
    M tiny products, ~2.5x slower (the block-diagonal and off-diagonal trajectory blocks)."""
    sa = stacks.cm(a)
    out: FloatArray = stacks.tmul(sa, sa if b is a else stacks.cm(b)).transpose(2, 0, 1)
    return out


def _assemble(factors: Sequence[Factor], weights: Sequence[FloatArray], n: int, p: int) -> _Normal:
    """Accumulate J^T W J and J^T W r factor by factor (vectorised over rows; theta blocks through BLAS)."""
    ne = _Normal(np.zeros((n, 3, 3)), np.zeros((max(n - 1, 0), 3, 3)), np.zeros((n, 3, p)),
                 np.zeros((p, p)), np.zeros((n, 3)), np.zeros(p))
    for f, w in zip(factors, weights, strict=True):
        unit = bool(np.all(w == 1.0))
        r = f.r if unit else f.r * w[:, None]
        jt_w = None
        cols = f.theta_slice(p)
        if not isinstance(cols, slice):                       # scattered columns: expand (rare)
            f = Factor(f.name, f.r, f.idx, f.J_x, f.J_next, f.full_theta(p))
            cols = slice(0, p)
        if f.J_theta is not None:
            jt = f.J_theta
            q = jt.shape[2]
            jt_w = jt if unit else jt * w[:, None, None]
            jt2 = jt.reshape(-1, q)
            ne.htt[cols, cols] += jt_w.reshape(-1, q).T @ jt2
            ne.gt[cols] += jt2.T @ r.reshape(-1)
        if f.idx is None:
            continue
        start = run_start(f.idx)
        hxt = ne.hxt[:, :, cols]                              # a view: scatters below write into ne.hxt
        for jx, shift in ((f.J_x, 0), (f.J_next, 1)):
            if jx is None:
                continue
            at = None if start is None else start + shift
            idx = f.idx + shift
            _scatter(ne.diag, idx, _gram(jx, jx if unit else jx * w[:, None, None]), at)
            _scatter(ne.gx, idx, np.einsum("mki,mk->mi", jx, r), at)
            if jt_w is not None:
                _scatter(hxt, idx, jx.transpose(0, 2, 1) @ jt_w, at)
        if f.J_x is not None and f.J_next is not None:
            _scatter(ne.off, f.idx, _gram(f.J_x, f.J_next if unit else f.J_next * w[:, None, None]), start)
    return ne


def _band(diag: FloatArray, off: FloatArray, u: int) -> FloatArray:
    """Upper banded storage ab[u + i - j, j] = H[i, j] of the block-tridiagonal trajectory matrix (Fortran order,
    as LAPACK takes it: no copy on the way in)."""
    n = diag.shape[0]
    ab = np.zeros((u + 1, 3 * n), order="F")
    for a in range(3):
        for b in range(a, 3):
            ab[u - (b - a), b::3] = diag[:, a, b]
    if u == 5:
        for a in range(3):
            for b in range(3):
                ab[u - (3 + b - a), 3 + b::3] = off[:, a, b]
    return ab


def _schur(ne: _Normal, lam: float, u: int, lam_theta: float | None = None
           ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The damped Schur complement S = Htt - X^T X with X = U^-T Hxt, y = U^-T gx (Hxx = U^T U, banded
    Cholesky): returns S, X, y, the banded factor and the damped Hxx blocks. `lam_theta` damps Htt (default
    `lam`)."""
    n, p = ne.gx.shape[0], ne.gt.size
    diag = ne.diag.copy()
    d = np.einsum("nii->ni", diag)
    floor = 1e-9 * (float(np.mean(d)) if d.size else 1.0)
    d += lam * (d + floor)                                   # Marquardt scaling with a floor
    scale = float(np.mean(np.diag(ne.htt))) if ne.htt.size else 1.0     # no theta: a trajectory-only problem
    lam_t = lam if lam_theta is None else lam_theta
    htt = ne.htt + lam_t * np.diag(np.diag(ne.htt) + 1e-9 * max(scale, 1e-300))
    cb = linalg.cholesky_banded(_band(diag, ne.off, u), lower=False, check_finite=False)
    rhs = np.empty((3 * n, p + 1), order="F")          # LAPACK's layout: solved in place, no copies
    rhs[:, :p], rhs[:, p] = ne.hxt.reshape(3 * n, p), ne.gx.reshape(3 * n)
    sol, info = lapack.dtbtrs(cb, rhs, uplo="U", trans="T", overwrite_b=1)
    if info != 0:
        msg = "banded triangular solve failed"
        raise np.linalg.LinAlgError(msg)
    x, y = sol[:, :p], sol[:, p]
    s = htt - x.T @ x
    return 0.5 * (s + s.T), x, y, cb, diag


def _step(ne: _Normal, lam: float, u: int, need_w: bool = False, lam_theta: float | None = None
          ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """Solve the damped normal equations; returns dx (N,3), dtheta, S^-1, damped Hxx blocks and, if asked,
    Hxx^-1 Hxt (N,3,p): dtheta = S^-1 (X^T y - gt), dx = -U^-1 (y + X dtheta) (see `_schur`).
    """
    n, p = ne.gx.shape[0], ne.gt.size
    s, x, y, cb, diag = _schur(ne, lam, u, lam_theta)
    # Jacobi scaling before the inverse: theta mixes units (tesla, rad, m/s^2) with very different scales
    sd = np.diag(s)
    if np.any(~np.isfinite(sd)) or np.any(sd <= 0.0):
        msg = "Schur complement not positive definite"
        raise np.linalg.LinAlgError(msg)
    js = 1.0 / np.sqrt(sd)
    s_inv = js[:, None] * np.linalg.inv(js[:, None] * s * js[None, :]) * js[None, :]
    dt = s_inv @ (x.T @ y - ne.gt)
    back = np.empty((3 * n, 1 + p if need_w else 1), order="F")
    back[:, 0] = y + x @ dt
    if need_w:
        back[:, 1:] = x
    back, info = lapack.dtbtrs(cb, back, uplo="U", trans="N", overwrite_b=1)
    if info != 0:
        msg = "banded triangular solve failed"
        raise np.linalg.LinAlgError(msg)
    dx = -back[:, 0]
    w = back[:, 1:].reshape(n, 3, p) if need_w else None
    return dx.reshape(n, 3), dt, s_inv, diag, w


def solve(linearize: Linearize, states0: FloatArray, theta0: FloatArray,
          opts: Options | None = None) -> Solution:
    """Minimise 1/2 sum |r|^2 (or a robust loss) over states (right perturbation) and theta."""
    # the dense blocks are small (N x 3 x p): multi-threaded BLAS only adds overhead, and on a loaded machine
    # its spinning threads cost ~100x (measured on 2 shared cores)
    with one_blas_thread():
        return _solve(linearize, states0, theta0, opts or Options())


@dataclass(frozen=True, eq=False)
class Iterated(Generic[S]):
    """Where the Levenberg-Marquardt loop stopped: the point, its cost, the system built there (`S`, e.g. factors
    and robust weights), the iterations, whether it converged, and one log line per iteration."""

    states: FloatArray
    theta: FloatArray
    cost: float
    system: S
    iterations: int
    converged: bool
    log: tuple[str, ...]


def iterate(evaluate: Callable[[FloatArray, FloatArray], tuple[float, S]],
            step: Callable[[S, float], tuple[FloatArray, FloatArray]],
            states0: FloatArray, theta0: FloatArray, opts: Options) -> Iterated[S]:
    """The Levenberg-Marquardt rules, whatever builds the system: `evaluate` linearises at a point (its cost and
    system), `step` solves the damped system there for (dx, dtheta). States move by right perturbation."""
    states, theta = np.array(states0, dtype=np.float64), np.array(theta0, dtype=np.float64)
    cost, system = evaluate(states, theta)
    lam, log, converged, it = opts.lambda0, [f"start: cost {cost:.6g}"], False, 0
    for it in range(1, opts.max_iterations + 1):
        try:
            dx, dt = step(system, lam)
        except (np.linalg.LinAlgError, linalg.LinAlgError):
            lam *= 10.0
            log.append(f"iter {it}: singular system, lambda -> {lam:.1e}")
            if lam > 1e12:
                break
            continue
        new_states, new_theta = states @ so3.exp(dx), theta + dt
        # linearise at the trial point straight away: steps are nearly always accepted, so this saves the
        # separate residual-only evaluation per iteration
        new_cost, trial = evaluate(new_states, new_theta)
        size = float(np.sqrt(np.sum(dx * dx) + dt @ dt))
        if np.isfinite(new_cost) and new_cost <= cost:
            drop = cost - new_cost
            rel = drop / max(cost, 1e-300)
            states, theta, cost, system = new_states, new_theta, new_cost, trial
            lam = max(lam / 3.0, 1e-12)
            log.append(f"iter {it}: cost {cost:.6g}, step {size:.2e}, lambda {lam:.1e}")
            if size < opts.step_tol or rel < opts.cost_tol or drop < opts.abs_cost_tol:
                converged = True
                break
        else:
            lam *= 10.0
            log.append(f"iter {it}: rejected (cost {new_cost:.6g}), lambda -> {lam:.1e}")
            if size < opts.step_tol:
                converged = True
                break
            if lam > 1e12:
                break
    return Iterated(states, theta, cost, system, it, converged, tuple(log))


@dataclass
class _System:
    """The factors and robust weights at a point, and their normal equations once assembled (a rejected step
    solves the same system again with more damping)."""

    factors: Sequence[Factor]
    weights: list[FloatArray]
    normal: _Normal | None = None

    def assembled(self, n: int, p: int) -> _Normal:
        """The normal equations, assembled on first use."""
        if self.normal is None:
            self.normal = _assemble(self.factors, self.weights, n, p)
        return self.normal


def _solve(linearize: Linearize, states0: FloatArray, theta0: FloatArray, opts: Options) -> Solution:
    """`iterate` on the factors' block-banded normal equations, then the covariance at the optimum."""
    n, p = np.shape(states0)[0], np.size(theta0)
    u = 2
    calls = 0

    def evaluate(states: FloatArray, theta: FloatArray) -> tuple[float, _System]:
        nonlocal u, calls
        # without a covariance the last possible trial point needs no Jacobians: no step is taken from it
        jac = opts.covariance or calls < opts.max_iterations
        calls += 1
        factors = linearize(states, theta, jac)
        if jac:
            u = 5 if any(f.J_next is not None for f in factors) else 2
        cost, weights = _robust_weights(factors, opts)
        return cost, _System(factors, weights)

    def step(system: _System, lam: float) -> tuple[FloatArray, FloatArray]:
        dx, dt, *_ = _step(system.assembled(n, p), lam, u)
        return dx, dt

    out = iterate(evaluate, step, states0, theta0, opts)
    factors, weights = out.system.factors, out.system.weights
    log = list(out.log)
    if not opts.covariance:
        return Solution(out.states, out.theta, out.cost, out.iterations, out.converged, np.full((p, p), np.nan),
                        tuple(log), tuple(factors), np.full((n, 3, 3), np.nan), np.full((n, 3, p), np.nan), u,
                        None, tuple(weights))
    ne = out.system.assembled(n, p)
    try:
        _, _, s_inv, hdiag, w = _undamped(ne, u, log)
    except (np.linalg.LinAlgError, linalg.LinAlgError):
        log.append("the information is singular at the optimum: the data do not determine all unknowns")
        s_inv, hdiag, w = np.full((p, p), np.nan), ne.diag, np.full((n, 3, p), np.nan)
    assert w is not None
    return Solution(out.states, out.theta, out.cost, out.iterations, out.converged, s_inv, tuple(log),
                    tuple(factors), hdiag, w, u, ne.off, tuple(weights))


def _undamped(ne: _Normal, u: int, log: list[str] | None = None, need_w: bool = True
              ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """`_step` on the undamped information; when that is numerically singular (a rigid gyro, a flat log), with a
    trace (1e-9) of damping on the trajectory blocks only, and failing that on theta too, which leaves
    undetermined directions huge rather than NaN (the observability check then names them)."""
    for lam_theta in (None, 0.0, 1e-9):
        try:
            out = _step(ne, 0.0 if lam_theta is None else 1e-9, u, need_w=need_w, lam_theta=lam_theta)
        except (np.linalg.LinAlgError, linalg.LinAlgError):
            if lam_theta == 1e-9:
                raise
            continue
        if lam_theta is not None and log is not None:
            log.append(f"the information is nearly singular at the optimum (covariance with 1e-9 damping of the "
                       f"{'trajectory' if lam_theta == 0.0 else 'trajectory and theta'})")
        return out
    raise AssertionError  # pragma: no cover - the loop returns or raises


def marginal_covariance(linearize: Linearize, states: FloatArray, theta: FloatArray,
                        trajectory_damping: float = 0.0) -> FloatArray:
    """Inverse Schur complement of the Gauss-Newton information at a given point (no iterations), e.g. the
    Cramer-Rao bound of theta when evaluated at the truth with the true noise levels. `trajectory_damping` (a
    trace, e.g. 1e-9) keeps a nearly rigid trajectory from cancelling theta's information in the Schur
    complement (flat logs); theta stays undamped."""
    factors = linearize(np.asarray(states, dtype=np.float64), np.asarray(theta, dtype=np.float64), True)
    n, p = states.shape[0], theta.size
    u = 5 if any(f.J_next is not None for f in factors) else 2
    with one_blas_thread():
        ne = _assemble(factors, [np.ones(f.r.shape[0]) for f in factors], n, p)
        if trajectory_damping > 0.0:
            return _step(ne, trajectory_damping, u, lam_theta=0.0)[2]
        return _undamped(ne, u, need_w=False)[2]          # the covariance only: no Hxx^-1 Hxt


def information(linearize: Linearize, states: FloatArray, theta: FloatArray) -> FloatArray:
    """The Schur complement S of the Gauss-Newton information at a given point: what the data know about theta
    with the trajectory eliminated (singular where the motion determines nothing; models/partial.py)."""
    factors = linearize(np.asarray(states, dtype=np.float64), np.asarray(theta, dtype=np.float64), True)
    n, p = states.shape[0], theta.size
    u = 5 if any(f.J_next is not None for f in factors) else 2
    with one_blas_thread():
        ne = _assemble(factors, [np.ones(f.r.shape[0]) for f in factors], n, p)
        # a trace of damping on the trajectory only: a numerically singular trajectory still gives S, and S keeps
        # its null directions (what the motion cannot determine)
        return _schur(ne, 1e-9, u, 0.0)[0]
