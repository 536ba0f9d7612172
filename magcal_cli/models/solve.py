"""The one nonlinear least-squares solver: Levenberg-Marquardt on SO(3)^N x R^p.

Residual factors touch one state k (and optionally its successor k+1) and the global parameters theta,
so the normal equations are block-banded in the trajectory with a dense border (Huang et al. 2025,
Appendix A; methods.md section 3). The trajectory is eliminated with a banded Cholesky factorisation
(LAPACK pbtrf/pbtrs through scipy, normal.py), the p x p Schur complement is solved densely: O(N) per iteration.
The marginal covariance of theta is the inverse of the Schur complement at the optimum.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt
from scipy import linalg

from magcal_cli import so3
from magcal_cli.models import normal
from magcal_cli.models.factor import Factor, Linearize, run_start
from magcal_cli.streams import FloatArray

#: normal equations whose [Hxt, gx] is this large are solved in place and released before the trial point is
#: linearised (issue 39: 29 MB of a 60-min flight's peak); smaller ones are kept for a rejected step, which would
#: otherwise linearise its point again: log171 rejects 128 of its 654 steps, and took 8 % longer
IN_PLACE_BYTES = 16 * 2**20
#: the smallest damping: where a solve that starts at a neighbouring optimum begins (`Options.lambda0`)
LAMBDA_FLOOR = 1e-12

#: the system a Levenberg-Marquardt step solves (`iterate`)
S = TypeVar("S")


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


#: row groups whose leverage is computed at once: the (rows, k, p) products for a whole factor were a 60-min
#: flight's peak (issue 39)
LEVERAGE_ROWS = 8192

Rows = slice | npt.NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Marginals:
    """Blocks of H^-1 on the sparsity pattern of H (marginal covariances), made for the states asked: state k
    (3, 3), states k and k+1 (3, 3), state k with theta (3, p); theta's (p, p) is `tt`. Held are the trajectory's
    own blocks (`normal.selected_inverse`), W = Hxx^-1 Hxt (N, 3, p), not a copy, and tt: the blocks with theta
    are made for the states asked only."""

    z_xx: FloatArray
    z_next: FloatArray
    w: FloatArray
    tt: FloatArray

    def xt(self, i: Rows) -> FloatArray:
        """Blocks (state i, theta): -W_i S^-1."""
        return -(self.w[i] @ self.tt)

    def xx(self, i: Rows) -> FloatArray:
        """Blocks (state i, state i): Z_ii + W_i S^-1 W_i^T."""
        w_s = self.w[i] @ self.tt
        out: FloatArray = self.z_xx[i] + w_s @ self.w[i].transpose(0, 2, 1)
        return out

    def x_next(self, i: Rows, nxt: Rows) -> FloatArray:
        """Blocks (state i, state i + 1), i < N - 1, with `nxt` the states i + 1: Z_i,i+1 + W_i S^-1 W_i+1^T."""
        out: FloatArray = self.z_next[i] + (self.w[i] @ self.tt) @ self.w[nxt].transpose(0, 2, 1)
        return out


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
    #: Hxx^-1 Hxt (N, 3, p): how the optimal trajectory follows theta (the sandwich eliminates it with this)
    hxx_inv_hxt: FloatArray = field(repr=False)
    _band: int = field(repr=False)
    _off: FloatArray | None = field(default=None, repr=False)
    _weights: tuple[FloatArray, ...] = field(default=(), repr=False)

    def residuals_only(self) -> Solution:
        """The optimum, its cost and covariance and each factor's residual rows, without the Jacobians and the
        trajectory's blocks: what an estimate keeps (on 60 000 epochs they are ~100 MB, issue 39)."""
        return replace(self, factors=tuple(Factor(f.name, f.r) for f in self.factors), _hxx_diag=np.zeros((0, 3, 3)),
                       hxx_inv_hxt=np.zeros((0, 3, self.theta.size)), _off=None, _weights=())

    def marginals(self) -> Marginals:
        """Selected inverse of the undamped information at the optimum, O(N) (see `normal.selected_inverse`)."""
        n = self._hxx_diag.shape[0]
        off = self._off if self._off is not None and self._band == 5 else np.zeros((max(n - 1, 0), 3, 3))
        z_xx, z_next = normal.selected_inverse(self._hxx_diag, off)
        return Marginals(z_xx, z_next, self.hxx_inv_hxt, self.cov_theta)

    def leverage(self, factor: Factor, marginals: Marginals | None = None) -> FloatArray:
        """Diagonal of the hat matrix J H^-1 J^T for a factor's rows (M, m); unary or consecutive-binary."""
        if factor.J_next is not None and self._band != 5:
            msg = "leverage of a binary factor needs the tridiagonal trajectory it was solved with"
            raise ValueError(msg)
        if factor.J_next is None and factor.J_x is not None and self._band == 2 and marginals is None:
            return self._leverage_block_diagonal(factor)
        z = marginals or self.marginals()
        return _in_blocks(factor, lambda f: self._leverage_rows(f, z))

    def _leverage_rows(self, f: Factor, z: Marginals) -> FloatArray:
        """`leverage` of some of a factor's row groups (`Factor.rows`)."""
        h = np.zeros(f.r.shape)
        p = self.theta.size
        cols = f.theta_slice(p)
        jt = f.J_theta if isinstance(cols, slice) else f.full_theta(p)
        cols = cols if isinstance(cols, slice) else slice(0, p)
        if jt is not None:
            h += np.einsum("mkp,mkp->mk", jt @ z.tt[cols, cols], jt)
        if f.idx is None or f.J_x is None:
            return h
        at = run_start(f.idx)                              # a run of states: their blocks as views, not copies
        i = f.idx if at is None else slice(at, at + f.idx.shape[0])
        h += np.einsum("mki,mki->mk", f.J_x @ z.xx(i), f.J_x)
        if jt is not None:
            h += 2.0 * np.einsum("mkp,mkp->mk", f.J_x @ z.xt(i)[:, :, cols], jt)
        if f.J_next is not None:
            i1 = f.idx + 1 if at is None else slice(at + 1, at + 1 + f.idx.shape[0])
            h += np.einsum("mki,mki->mk", f.J_next @ z.xx(i1), f.J_next)
            h += 2.0 * np.einsum("mki,mki->mk", f.J_x @ z.x_next(i, i1), f.J_next)
            if jt is not None:
                h += 2.0 * np.einsum("mkp,mkp->mk", f.J_next @ z.xt(i1)[:, :, cols], jt)
        return h

    def _leverage_block_diagonal(self, factor: Factor) -> FloatArray:
        """Unary factors on a block-diagonal trajectory: one 3x3 inverse per state, a block of rows at a time."""
        return _in_blocks(factor, self._block_diagonal_rows)

    def _block_diagonal_rows(self, f: Factor) -> FloatArray:
        """`_leverage_block_diagonal` of some of a factor's row groups."""
        p_tt = self.cov_theta
        h = np.zeros(f.r.shape)
        jt = f.full_theta(self.theta.size)
        if jt is not None:
            h += np.einsum("mkp,pq,mkq->mk", jt, p_tt, jt)
        if f.J_x is not None and f.idx is not None:
            w = self.hxx_inv_hxt[f.idx]                               # (M, 3, p) = Hxx^-1 Hxt
            p_kk = np.linalg.inv(self._hxx_diag[f.idx]) + w @ p_tt @ w.transpose(0, 2, 1)
            h += np.einsum("mki,mij,mkj->mk", f.J_x, p_kk, f.J_x)
            if jt is not None:
                p_kt = -w @ p_tt
                h += 2.0 * np.einsum("mki,mip,mkp->mk", f.J_x, p_kt, jt)
        return h


def _in_blocks(factor: Factor, each: Callable[[Factor], FloatArray]) -> FloatArray:
    """`each` of LEVERAGE_ROWS row groups of a factor at a time, (M, m) in all: each row's own digits either way."""
    h = np.zeros(factor.r.shape)
    for a in range(0, factor.r.shape[0], LEVERAGE_ROWS):
        rows = slice(a, a + LEVERAGE_ROWS)
        h[rows] = each(factor.rows(rows))
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


def solve(linearize: Linearize, states0: FloatArray, theta0: FloatArray,
          opts: Options | None = None) -> Solution:
    """Minimise 1/2 sum |r|^2 (or a robust loss) over states (right perturbation) and theta."""
    # the dense blocks are small (N x 3 x p): multi-threaded BLAS only adds overhead, and on a loaded machine
    # its spinning threads cost ~100x (measured on 2 shared cores)
    with normal.one_blas_thread():
        return _solve(linearize, states0, theta0, opts or Options())


@dataclass(frozen=True, eq=False)
class Linearised:
    """The Gauss-Newton system at a point, factorised once; `step` refits other data of the same rows from that
    point (a replicate simulated there) with the point's Jacobians: one step of `solve` at its default damping,
    without linearising and factorising again. The Jacobians depend on the data only at second order."""

    factors: tuple[Factor, ...]
    system: normal.Factorised

    def step(self, residuals: Sequence[FloatArray]) -> tuple[FloatArray, FloatArray]:
        """(dx (N, 3), dtheta) for the factors' rows with these residuals (l2 loss)."""
        n, p = self.system.x.shape[0] // 3, self.system.s_inv.shape[0]
        with normal.one_blas_thread():
            return self.system.step(*normal.gradient(self.factors, residuals, n, p))


def linearised(linearize: Linearize, states: FloatArray, theta: FloatArray, lam: float = Options.lambda0
               ) -> Linearised:
    """`Linearised` at (states, theta), damped as a first step of `solve` is (l2 loss)."""
    n, p = np.shape(states)[0], np.size(theta)
    with normal.one_blas_thread():
        factors = tuple(linearize(states, theta, True))
        u = 5 if any(f.J_next is not None for f in factors) else 2
        ne = normal.assemble_unit(factors, n, p)
        return Linearised(factors, normal.factorise(ne, lam, u))


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
            lam = max(lam / 3.0, LAMBDA_FLOOR)
            log.append(f"iter {it}: cost {cost:.6g}, step {size:.2e}, lambda {lam:.1e}")
            if size < opts.step_tol or rel < opts.cost_tol or drop < opts.abs_cost_tol:
                converged = True
                break
        else:
            # the rejected point's factors and Jacobians go now, not when the next trial replaces them: kept through
            # the next, more damped solve of the same system, they were a 60-min flight's peak (issue 39)
            del trial, new_states, new_theta
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
    """The factors and robust weights at a point, and their normal equations while a step is being solved there."""

    factors: Sequence[Factor]
    weights: list[FloatArray]
    #: the same point's factors again, to the same digits (the Jacobians went into equations since released)
    relinearize: Callable[[], Sequence[Factor]]
    equations: normal.NormalEquations | None = None
    #: the factors keep their residual rows only
    stripped: bool = False

    def assembled(self, n: int, p: int) -> normal.NormalEquations:
        """The normal equations, assembled on first use; the factors then keep their residual rows only: a point's
        Jacobians beside the next trial point's were a 60-min flight's peak (issue 39). After `release` (a
        rejected step solves the same system again, more damped) the point is linearised again."""
        if self.equations is None:
            if self.stripped:
                self.factors = self.relinearize()
            self.factors = list(self.factors)
            self.equations = normal.assemble_stripping(self.factors, self.weights, n, p)
            self.stripped = True
        return self.equations

    def release(self) -> None:
        """Drop the equations while the trial point is linearised: both at once were the 60-min flight's peak
        after the Jacobians went (issue 39); a rejected step assembles them again (`_solve`: large ones only)."""
        self.equations = None


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
        return cost, _System(factors, weights, partial(linearize, states, theta, True))

    def step(system: _System, lam: float) -> tuple[FloatArray, FloatArray]:
        ne = system.assembled(n, p)
        big = ne.xg.nbytes >= IN_PLACE_BYTES
        try:                # large: solved in place, and a rejected or singular step assembles them again
            dx, dt, *_ = normal.step(ne, lam, u, consume=big)
        finally:
            if big:
                system.release()
        return dx, dt

    out = iterate(evaluate, step, states0, theta0, opts)
    system = out.system
    if opts.covariance and system.stripped:
        # stopped on a point whose Jacobians went into its equations (a rejected last step): the same point's
        # factors again, to the same digits
        system = _System(system.relinearize(), system.weights, system.relinearize, system.equations)
    factors, weights = system.factors, system.weights
    log = list(out.log)
    if not opts.covariance:
        return Solution(out.states, out.theta, out.cost, out.iterations, out.converged, np.full((p, p), np.nan),
                        tuple(log), tuple(factors), np.full((n, 3, 3), np.nan), np.full((n, 3, p), np.nan), u,
                        None, tuple(weights))
    ne = system.assembled(n, p)
    try:
        _, _, s_inv, hdiag, w = normal.undamped(ne, u, log, remake=lambda: normal.assemble(factors, weights, n, p))
    except (np.linalg.LinAlgError, linalg.LinAlgError):
        log.append("the information is singular at the optimum: the data do not determine all unknowns")
        s_inv, hdiag, w = np.full((p, p), np.nan), ne.diag, np.full((n, 3, p), np.nan)
    assert w is not None
    return Solution(out.states, out.theta, out.cost, out.iterations, out.converged, s_inv, tuple(log),
                    tuple(factors), hdiag, w, u, ne.off, tuple(weights))
