"""The factors' block-banded normal equations: assembly, banded elimination of the trajectory, Schur complement."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import linalg
from scipy.linalg import lapack
from threadpoolctl import ThreadpoolController

from magcal_cli import stacks
from magcal_cli.models.factor import Factor, IntArray, Linearize, run_start
from magcal_cli.streams import FloatArray

_BLAS: list[ThreadpoolController] = []
#: how many blocks (on any thread) are inside one_blas_thread, and the limiter the first of them set
_ONE_THREAD: dict[str, Any] = {"depth": 0, "limiter": None}
_ONE_THREAD_LOCK = threading.Lock()


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS limited to one thread inside the block. The library scan is done once (threadpoolctl's
    `threadpool_limits` repeats it on every call, 3 ms: 6 % of a diagnosis that solves a few hundred times).

    The limit is process-wide, so it is counted: the first block in sets it and the last one out restores it.
    Each block setting and restoring it on its own let one diagnosis thread restore two BLAS threads while another
    was mid-solve, which made the held-out evidence differ in its last digits from run to run under load.
    """
    with _ONE_THREAD_LOCK:
        if not _BLAS:
            _BLAS.append(ThreadpoolController())
        if _ONE_THREAD["depth"] == 0:
            _ONE_THREAD["limiter"] = _BLAS[0].limit(limits=1, user_api="blas")
        _ONE_THREAD["depth"] += 1
    try:
        yield
    finally:
        with _ONE_THREAD_LOCK:
            _ONE_THREAD["depth"] -= 1
            if _ONE_THREAD["depth"] == 0:
                _ONE_THREAD["limiter"].restore_original_limits()
                _ONE_THREAD["limiter"] = None


@dataclass
class NormalEquations:
    """Assembled normal equations H = [[Hxx, Hxt], [Htx, Htt]], gradient g = J^T r.

    Hxt and gx are views of one (3N, p + 1) Fortran-order array, `xg`, the layout the banded solve takes: a step
    may solve in it (`consume`), where a copy beside it was a 60-min flight's peak (issue 39)."""

    diag: FloatArray       # (N, 3, 3)
    off: FloatArray        # (N-1, 3, 3), block (k, k+1)
    hxt: FloatArray        # (N, 3, p), a view of xg
    htt: FloatArray        # (p, p)
    gx: FloatArray         # (N, 3), a view of xg
    gt: FloatArray         # (p,)
    xg: FloatArray         # (3N, p + 1): [Hxt, gx] with the state's three rows in turn, Fortran order
    #: a step solved in xg: Hxt and gx now hold U^-T Hxt and U^-T gx
    consumed: bool = False


def scatter(target: FloatArray, idx: IntArray, values: FloatArray, start: int | None = -1) -> None:
    """target[idx] += values; a slice add when idx is a run of consecutive states from `start` (`run_start`'s answer,
    -1: find out here)."""
    if start == -1:
        start = run_start(idx)
    if start is None:
        np.add.at(target, idx, values)
    else:
        target[start:start + idx.shape[0]] += values


def _gram(a: FloatArray, b: FloatArray) -> FloatArray:
    """a^T b per row group of (M, k, 3) stacks, on component-major stacks (stacks.py): np.matmul loops over
    M tiny products, ~2.5x slower (the block-diagonal and off-diagonal trajectory blocks)."""
    sa = stacks.cm(a)
    out: FloatArray = stacks.tmul(sa, sa if b is a else stacks.cm(b)).transpose(2, 0, 1)
    return out


def _add_gradient(f: Factor, r: FloatArray, gx: FloatArray, gt: FloatArray, cols: slice, start: int | None) -> None:
    """gx += J_x^T r (at state idx and idx + 1), gt[cols] += J_theta^T r, for one factor's (weighted) rows r."""
    if f.J_theta is not None:
        gt[cols] += f.J_theta.reshape(-1, f.J_theta.shape[2]).T @ r.reshape(-1)
    if f.idx is None:
        return
    for jx, shift in ((f.J_x, 0), (f.J_next, 1)):
        if jx is not None:
            scatter(gx, f.idx + shift, np.einsum("mki,mk->mi", jx, r), None if start is None else start + shift)


def _expanded(f: Factor, p: int) -> tuple[Factor, slice]:
    """The factor and where its theta columns sit, with scattered columns expanded to all p (rare)."""
    cols = f.theta_slice(p)
    if isinstance(cols, slice):
        return f, cols
    return Factor(f.name, f.r, f.idx, f.J_x, f.J_next, f.full_theta(p)), slice(0, p)


def gradient(factors: Sequence[Factor], residuals: Sequence[FloatArray], n: int, p: int
             ) -> tuple[FloatArray, FloatArray]:
    """J^T r with the factors' Jacobians and other residuals of the same rows (unit weights): (gx (N, 3), gt)."""
    gx, gt = np.zeros((n, 3)), np.zeros(p)
    for f, r in zip(factors, residuals, strict=True):
        f, cols = _expanded(f, p)
        _add_gradient(f, r, gx, gt, cols, None if f.idx is None else run_start(f.idx))
    return gx, gt


def assemble(factors: Sequence[Factor], weights: Sequence[FloatArray], n: int, p: int) -> NormalEquations:
    """Accumulate J^T W J and J^T W r factor by factor (vectorised over rows; theta blocks through BLAS)."""
    ne = _zeros(n, p)
    for f, w in zip(factors, weights, strict=True):
        _add(ne, f, w, p)
    return ne


def assemble_stripping(factors: list[Factor], weights: Sequence[FloatArray], n: int, p: int) -> NormalEquations:
    """`assemble`, replacing each factor in `factors` by its residual rows as soon as it is added: one factor's
    Jacobians at a time beside the equations, not all of them (issue 39). The same sums in the same order."""
    ne = _zeros(n, p)
    for i, w in enumerate(weights):
        f = factors[i]
        factors[i] = Factor(f.name, f.r)
        _add(ne, f, w, p)
        del f
    return ne


def _zeros(n: int, p: int) -> NormalEquations:
    """Empty normal equations for n states and p parameters."""
    xg = np.zeros((3 * n, p + 1), order="F")
    hxt = xg[:, :p].T.reshape(p, n, 3).transpose(1, 2, 0)          # views: [k, i, j] is xg[3 k + i, j]
    return NormalEquations(np.zeros((n, 3, 3)), np.zeros((max(n - 1, 0), 3, 3)), hxt, np.zeros((p, p)),
                           xg[:, p].reshape(n, 3), np.zeros(p), xg)


#: rows whose J_x^T J_theta are made and added at once
ADD_BLOCK = 8192


def _add(ne: NormalEquations, f: Factor, w: FloatArray, p: int) -> None:
    """One factor's J^T W J and J^T W r into `ne`."""
    unit = bool(np.all(w == 1.0))
    r = f.r if unit else f.r * w[:, None]
    jt_w = None
    f, cols = _expanded(f, p)
    start = None if f.idx is None else run_start(f.idx)
    _add_gradient(f, r, ne.gx, ne.gt, cols, start)
    if f.J_theta is not None:
        jt = f.J_theta
        q = jt.shape[2]
        jt_w = jt if unit else jt * w[:, None, None]
        ne.htt[cols, cols] += jt_w.reshape(-1, q).T @ jt.reshape(-1, q)
    if f.idx is None:
        return
    hxt = ne.hxt[:, :, cols]                              # a view: scatters below write into ne.hxt
    for jx, shift in ((f.J_x, 0), (f.J_next, 1)):
        if jx is None:
            continue
        at = None if start is None else start + shift
        idx = f.idx + shift
        scatter(ne.diag, idx, _gram(jx, jx if unit else jx * w[:, None, None]), at)
        if jt_w is not None:
            # a block of rows at a time: the whole (M, 3, q) product beside the equations was 23 MB of a 60-min
            # flight's peak (issue 39); each row's product and its add are the same either way: the same digits
            for a in range(0, idx.shape[0], ADD_BLOCK):
                b = slice(a, a + ADD_BLOCK)
                scatter(hxt, idx[b], jx[b].transpose(0, 2, 1) @ jt_w[b], None if at is None else at + a)
    if f.J_x is not None and f.J_next is not None:
        scatter(ne.off, f.idx, _gram(f.J_x, f.J_next if unit else f.J_next * w[:, None, None]), start)


def band(diag: FloatArray, off: FloatArray, u: int) -> FloatArray:
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


#: pairs of states whose 6x6 marginal is inverted at once (`selected_inverse`)
PAIR_BLOCK = 8192


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
    xx, nxt = np.empty((n, 3, 3)), np.empty((n - 1, 3, 3))
    # a block of pairs at a time: two (N, 6, 6) stacks were a 60-min flight's peak (issue 39); each 6x6 inverse is
    # its own LAPACK call, so the digits do not depend on the block
    for a in range(0, n - 1, PAIR_BLOCK):
        b = min(a + PAIR_BLOCK, n - 1)
        pair = np.empty((b - a, 6, 6))
        pair[:, :3, :3], pair[:, :3, 3:] = fwd[a:b], off[a:b]
        pair[:, 3:, :3], pair[:, 3:, 3:] = off[a:b].transpose(0, 2, 1), bwd[a + 1:b + 1]
        pinv = np.linalg.inv(pair)
        xx[a:b], nxt[a:b] = pinv[:, :3, :3], pinv[:, :3, 3:]
    xx[-1] = pinv[-1, 3:, 3:]
    xx += xx.transpose(0, 2, 1).copy()
    xx *= 0.5
    return xx, nxt


def _pivots(diag: FloatArray, off: FloatArray) -> FloatArray:
    """Block pivots F_k = U_kk^T U_kk of the upper banded Cholesky factor U of a block-tridiagonal matrix."""
    n, u = diag.shape[0], 5
    cb = linalg.cholesky_banded(band(diag, off, u), overwrite_ab=True, lower=False, check_finite=False)
    ukk = np.zeros((n, 3, 3))
    cols = 3 * np.arange(n)
    for a in range(3):
        for b in range(a, 3):
            ukk[:, a, b] = cb[u - (b - a), cols + b]
    return ukk.transpose(0, 2, 1) @ ukk


def _schur(ne: NormalEquations, lam: float, u: int, lam_theta: float | None = None, consume: bool = False
           ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The damped Schur complement S = Htt - X^T X with X = U^-T Hxt, y = U^-T gx (Hxx = U^T U, banded
    Cholesky): returns S, X, y, the banded factor, the damped Hxx blocks and [X, y] (3N, p + 1), Fortran order,
    whose views X and y are. `lam_theta` damps Htt (default `lam`). `consume`: solved in `ne.xg` itself, which
    leaves `ne` good for nothing more (its Hxt and gx are gone); otherwise in a copy."""
    if ne.consumed:
        msg = "normal equations solved in place already: assemble them again"
        raise ValueError(msg)
    p = ne.gt.size
    diag = ne.diag.copy()
    d = np.einsum("nii->ni", diag)
    floor = 1e-9 * (float(np.mean(d)) if d.size else 1.0)
    d += lam * (d + floor)                                   # Marquardt scaling with a floor
    scale = float(np.mean(np.diag(ne.htt))) if ne.htt.size else 1.0     # no theta: a trajectory-only problem
    lam_t = lam if lam_theta is None else lam_theta
    htt = ne.htt + lam_t * np.diag(np.diag(ne.htt) + 1e-9 * max(scale, 1e-300))
    cb = linalg.cholesky_banded(band(diag, ne.off, u), overwrite_ab=True, lower=False, check_finite=False)
    rhs = ne.xg if consume else ne.xg.copy(order="F")    # LAPACK's layout: solved in place
    ne.consumed = consume
    sol, info = lapack.dtbtrs(cb, rhs, uplo="U", trans="T", overwrite_b=1)
    if info != 0:
        msg = "banded triangular solve failed"
        raise np.linalg.LinAlgError(msg)
    x, y = sol[:, :p], sol[:, p]
    s = htt - x.T @ x
    return 0.5 * (s + s.T), x, y, cb, diag, sol


def step(ne: NormalEquations, lam: float, u: int, need_w: bool = False, lam_theta: float | None = None,
         consume: bool = False) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """Solve the damped normal equations; returns dx (N,3), dtheta, S^-1, damped Hxx blocks and, if asked,
    Hxx^-1 Hxt (N,3,p): dtheta = S^-1 (X^T y - gt), dx = -U^-1 (y + X dtheta) (see `_schur`, and its `consume`).
    """
    n, p = ne.gx.shape[0], ne.gt.size
    s, x, y, cb, diag, xy = _schur(ne, lam, u, lam_theta, consume)
    s_inv = schur_inverse(s)
    dt = s_inv @ (x.T @ y - ne.gt)
    if need_w:
        # U^-1 [X, y + X dtheta] in place of [X, y]: a second (3N, p) array beside X was a 60-min flight's peak
        # (issue 39); the triangular solve takes each column alone, so the digits are the same
        xy[:, p] = y + x @ dt
        back = xy
    else:
        back = np.empty((3 * n, 1), order="F")
        back[:, 0] = y + x @ dt
    back, info = lapack.dtbtrs(cb, back, uplo="U", trans="N", overwrite_b=1)
    if info != 0:
        msg = "banded triangular solve failed"
        raise np.linalg.LinAlgError(msg)
    dx = -back[:, -1]
    w = back[:, :p].reshape(n, 3, p) if need_w else None
    return dx.reshape(n, 3), dt, s_inv, diag, w


@dataclass(frozen=True, eq=False)
class Factorised:
    """The damped normal equations at a point, factorised (`_schur`): the Gauss-Newton step for any gradient with
    the same information costs two banded triangular solves (replicates simulated at that point)."""

    cb: FloatArray         # banded Cholesky factor U of the damped Hxx
    x: FloatArray          # U^-T Hxt (3N, p)
    s_inv: FloatArray      # inverse damped Schur complement

    def step(self, gx: FloatArray, gt: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(dx (N, 3), dtheta) for gradient (gx, gt), as `step` computes them."""
        y = _triangular(self.cb, gx.reshape(-1, 1), "T")[:, 0]
        dt = self.s_inv @ (self.x.T @ y - gt)
        dx = -_triangular(self.cb, (y + self.x @ dt)[:, None], "N")[:, 0]
        return dx.reshape(-1, 3), dt


def _triangular(cb: FloatArray, b: FloatArray, trans: str) -> FloatArray:
    """U^-T b or U^-1 b for the banded upper factor U."""
    out, info = lapack.dtbtrs(cb, np.asfortranarray(b, dtype=np.float64), uplo="U", trans=trans)
    if info != 0:
        msg = "banded triangular solve failed"
        raise np.linalg.LinAlgError(msg)
    return np.asarray(out)


def factorise(ne: NormalEquations, lam: float, u: int) -> Factorised:
    """The factors of `step`'s damped system, kept for steps with other gradients."""
    s, x, _, cb, _, _ = _schur(ne, lam, u, consume=True)        # X lives on in the factors: no copy of it
    return Factorised(cb, x, schur_inverse(s))


def undamped(ne: NormalEquations, u: int, log: list[str] | None = None, need_w: bool = True,
             remake: Callable[[], NormalEquations] | None = None
             ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """`step` on the undamped information; when that is numerically singular (a rigid gyro, a flat log), with a
    trace (1e-9) of damping on the trajectory blocks only, and failing that on theta too, which leaves
    undetermined directions huge rather than NaN (the observability check then names them). `remake`: the same
    equations assembled again; given, each attempt solves in place (`_schur`'s consume) and a retry remakes them."""
    for lam_theta in (None, 0.0, 1e-9):
        try:
            out = step(ne, 0.0 if lam_theta is None else 1e-9, u, need_w=need_w, lam_theta=lam_theta,
                       consume=remake is not None)
        except (np.linalg.LinAlgError, linalg.LinAlgError):
            if lam_theta == 1e-9:
                raise
            if ne.consumed and remake is not None:
                ne = remake()
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
    at = np.asarray(states, dtype=np.float64), np.asarray(theta, dtype=np.float64)
    factors = list(linearize(*at, True))
    n, p = states.shape[0], theta.size
    u = 5 if any(f.J_next is not None for f in factors) else 2

    def again() -> NormalEquations:
        return assemble_unit(list(linearize(*at, True)), n, p, strip=True)

    with one_blas_thread():
        # each factor's Jacobians go as they are added: all of them beside the equations were a 60-min flight's
        # peak (issue 39)
        ne = assemble_unit(factors, n, p, strip=True)
        del factors
        if trajectory_damping > 0.0:
            return step(ne, trajectory_damping, u, lam_theta=0.0, consume=True)[2]
        return undamped(ne, u, need_w=False, remake=again)[2]          # the covariance only: no Hxx^-1 Hxt


def assemble_unit(factors: Sequence[Factor], n: int, p: int, strip: bool = False) -> NormalEquations:
    """`assemble` with unit weights; `strip`: `assemble_stripping`, on a list of factors nothing else needs."""
    weights = [np.ones(f.r.shape[0]) for f in factors]
    if strip:
        assert isinstance(factors, list)
        return assemble_stripping(factors, weights, n, p)
    return assemble(factors, weights, n, p)


def information(linearize: Linearize, states: FloatArray, theta: FloatArray) -> FloatArray:
    """The Schur complement S of the Gauss-Newton information at a given point: what the data know about theta
    with the trajectory eliminated (singular where the motion determines nothing; models/partial.py)."""
    factors = list(linearize(np.asarray(states, dtype=np.float64), np.asarray(theta, dtype=np.float64), True))
    n, p = states.shape[0], theta.size
    u = 5 if any(f.J_next is not None for f in factors) else 2
    with one_blas_thread():
        ne = assemble_unit(factors, n, p, strip=True)
        del factors
        # a trace of damping on the trajectory only: a numerically singular trajectory still gives S, and S keeps
        # its null directions (what the motion cannot determine)
        return _schur(ne, 1e-9, u, 0.0, consume=True)[0]


def schur_inverse(s: FloatArray) -> FloatArray:
    """S^-1 of a Schur complement, Jacobi-scaled before the inverse: theta mixes units (tesla, rad, m/s^2) with
    very different scales. A non-positive or non-finite diagonal raises LinAlgError."""
    sd = np.diag(s)
    if np.any(~np.isfinite(sd)) or np.any(sd <= 0.0):
        msg = "Schur complement not positive definite"
        raise np.linalg.LinAlgError(msg)
    js = 1.0 / np.sqrt(sd)
    out: FloatArray = js[:, None] * np.linalg.inv(js[:, None] * s * js[None, :]) * js[None, :]
    return out
