"""Gyro preintegration between magnetometer epochs (Forster et al. 2017) and its residual factor.

methods.md section 3 item 3 (Huang et al. 2025, eqs. 16-18; the authors' gyroPreIntegration.m). A gyro sample
y_k holds over [t_k, t_k+1) (zero-order hold; timing.for_estimator turns every log's gyro into this form). The
interval between two epochs is cut
at every IMU time stamp into pieces, so epochs need not coincide with IMU samples (partial first and last
pieces); when they do, every piece is one whole IMU sample and this is eq. 16 with L samples per interval.

Forster's recursions for dR, its bias Jacobian and its covariance run over the piece slots of an interval
(about L of them), vectorised over all intervals: no loop over samples.
"""

from __future__ import annotations

import threading
import weakref
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from magcal_cli import so3, stacks
from magcal_cli.detect import BlockScale
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.factor import Factor
from magcal_cli.streams import FloatArray

if TYPE_CHECKING:
    from magcal_cli.models.epochs import Epochs, Groups
    from magcal_cli.models.problem import Problem

IntArray = npt.NDArray[np.int64]
#: preintegrations that keep their component-major stacks, the most recently linearised: kept on every one, the
#: stacks outlived their fits in each estimate's context (13 MB per 60 000 epochs, four sets at a 60-min flight's
#: held-out folds, issue 39); one made again costs three copies, a tenth of a linearisation
CM_KEEP = 2
_CM_HOLDERS: deque[weakref.ref[Preintegrated]] = deque()
_CM_LOCK = threading.Lock()


@dataclass(frozen=True, eq=False)
class Preintegrated:
    """Relative rotations between consecutive epochs (K-1 intervals), integrated with the gyro bias `bias`.

    delta: dR_ij (K-1, 3, 3); d_bias: d dR / d b_g for the right perturbation dR Exp(d_bias db) (Forster
    eq. 44); `cov`: covariance of the rotation-vector error (rad^2); `l_inv`: L^-1 with cov = L L^T; duration
    (K-1,) s; noise_std: the per-sample gyro noise (rad/s) the covariance stands for.
    """

    epochs: FloatArray
    bias: FloatArray
    delta: FloatArray
    d_bias: FloatArray
    #: `cov` and `l_inv` before the variance factors `scales` (`scaled`)
    cov_base: FloatArray
    l_inv_base: FloatArray
    duration: FloatArray
    noise_std: FloatArray
    d_scale: FloatArray | None = None
    #: (K-1,) intervals that overlap a window the gyro could not measure (saturation, impact): no gyro factor
    broken: npt.NDArray[np.bool_] | None = None
    #: epochs that average readings (epochs.Groups): each group's mean rotation to its readings and its bias
    #: Jacobian, which mag.mag_factor and accel.accel_factor predict the means with; None: one reading per epoch
    within: Within | None = None
    #: the variance factors applied since preintegration, in turn: applied when `cov` or `l_inv` is read, so a
    #: fit's rescaled noise does not hold a second pair beside the one a cache keeps (8.6 MB per 60 000 epochs)
    scales: tuple[float, ...] = ()

    @property
    def cov(self) -> FloatArray:
        """Covariance of the rotation-vector error (K-1, 3, 3), rad^2."""
        out = self.cov_base
        for f in self.scales:
            out = out * f
        return out

    @property
    def l_inv(self) -> FloatArray:
        """L^-1 (K-1, 3, 3) with cov = L L^T."""
        out = self.l_inv_base
        for f in self.scales:
            out = out / np.sqrt(f)
        return out

    def component_major(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """delta, l_inv and d_bias as component-major stacks (3, 3, K-1) (stacks.py), kept while this is one of the
        CM_KEEP preintegrations most recently asked."""
        got: tuple[FloatArray, FloatArray, FloatArray] | None = self.__dict__.get("_cm")
        if got is None:
            got = (stacks.cm(self.delta), stacks.cm(self.l_inv), stacks.cm(self.d_bias))
            object.__setattr__(self, "_cm", got)
        with _CM_LOCK:
            for ref in [r for r in _CM_HOLDERS if r() is self or r() is None]:
                _CM_HOLDERS.remove(ref)
            _CM_HOLDERS.append(weakref.ref(self))
            while len(_CM_HOLDERS) > CM_KEEP:
                old = _CM_HOLDERS.popleft()()
                if old is not None:
                    old.__dict__.pop("_cm", None)
        return got

    def drop_component_major(self) -> None:
        """Let the component-major stacks go until a linearisation asks for them again."""
        with _CM_LOCK:
            self.__dict__.pop("_cm", None)

    def scaled(self, variance_factor: float) -> Preintegrated:
        """The same preintegration with its noise covariance multiplied by `variance_factor`."""
        return replace(self, noise_std=self.noise_std * np.sqrt(variance_factor),
                       scales=(*self.scales, variance_factor))


@dataclass(frozen=True, eq=False)
class Within:
    """What the gyro says about the readings an epoch averages (epochs.Groups): A (K, 3, 3), the mean over the
    group's readings j of dR_kj^T (dR_kj: the rotation from the epoch's first reading to reading j, dR_kk = I), and
    B (K, 3, 3, 3), B[k, a] the mean of [dR_kj^T e_a]x J_kj, with J_kj dR_kj's bias Jacobian (right perturbation):
    the mean of dR_kj^T u is A u + sum_a u_a B[k, a] db to first order in the bias correction db."""

    A: FloatArray
    B: FloatArray

    def mixed(self, db: FloatArray) -> FloatArray:
        """N = A + M (K, 3, 3), M[:, :, a] = B_a db: the map from u = R_k^T v to the group's mean of R_j^T v at the
        bias correction db."""
        k = self.B.shape[0]               # one (9K, 3) x (3,) product: [k, a, i] = (B_a db)_i, then N[k, i, a]
        out: FloatArray = self.A + (self.B.reshape(-1, 3) @ db).reshape(k, 3, 3).transpose(0, 2, 1)
        return out

    def by_bias(self, u: FloatArray) -> FloatArray:
        """sum_a u_a B_a (K, 3, 3): the derivative of the group's mean of R_j^T v by db, for u = R_k^T v (K, 3)."""
        out: FloatArray = np.einsum("ka,kaij->kij", u, self.B)
        return out


def pieces(t_imu: FloatArray, epochs: FloatArray) -> tuple[IntArray, FloatArray, IntArray]:
    """Cut [epochs[0], epochs[-1]] at IMU stamps and epochs: IMU sample, duration (s), interval per piece."""
    inner = t_imu[(t_imu > epochs[0]) & (t_imu < epochs[-1])]
    cuts = np.unique(np.concatenate([epochs, inner]))
    start, dur = cuts[:-1], np.diff(cuts)
    sample = np.searchsorted(t_imu, start, side="right") - 1
    interval = np.searchsorted(epochs, start, side="right") - 1
    return sample.astype(np.int64), dur, interval.astype(np.int64)


def _slots(t_imu: FloatArray, epochs: FloatArray) -> Iterator[tuple[IntArray, IntArray, FloatArray]]:
    """The pieces (`pieces`) one slot at a time: the intervals that have an i-th piece, its IMU sample and duration."""
    sample, dur, interval = pieces(t_imu, epochs)
    first = np.searchsorted(interval, np.arange(epochs.size - 1), side="left")
    slot = np.arange(sample.size) - first[interval]
    order = np.argsort(slot, kind="stable")
    bounds = np.searchsorted(slot[order], np.arange(int(slot.max()) + 2))
    for j in range(bounds.size - 1):
        at = order[bounds[j]:bounds[j + 1]]
        yield interval[at], sample[at], dur[at]


def rotations(t_imu: FloatArray, gyr: FloatArray, epochs: FloatArray, bias: FloatArray) -> FloatArray:
    """dR between consecutive epochs (K-1, 3, 3), as `preintegrate` makes it, without its Jacobians and covariance."""
    delta = np.broadcast_to(np.eye(3), (epochs.size - 1, 3, 3)).copy()
    for rows, smp, dur in _slots(t_imu, epochs):
        delta[rows] = delta[rows] @ so3.exp((gyr[smp] - bias) * dur[:, None])
    return delta


def broken_intervals(epochs: FloatArray, windows: tuple[tuple[float, float], ...]) -> npt.NDArray[np.bool_]:
    """(K-1,) True where the interval between consecutive epochs overlaps one of the `windows` (s)."""
    out = np.zeros(max(epochs.size - 1, 0), dtype=bool)
    for t0, t1 in windows:
        out |= (epochs[1:] > t0) & (epochs[:-1] < t1)
    return out


def preintegrate(t_imu: FloatArray, gyr: FloatArray, epochs: FloatArray, bias: FloatArray,
                 noise_std: FloatArray, where: str = "gyro", scale_jacobian: bool = False,
                 breaks: tuple[tuple[float, float], ...] = (), scale: BlockScale | None = None,
                 dt: float | None = None) -> Preintegrated:
    """Preintegrate gyro samples gyr (N, 3) rad/s at t_imu (N,) between consecutive epochs (K,) s.

    noise_std (3,) is the per-sample white-noise std (rad/s) at the nominal IMU period dt; a piece of
    duration d adds diag(noise_std^2) dt d to the rate-integral covariance (noise density^2 x d), which is
    the discrete sigma^2 dt^2 for a whole sample and scales with time for partial pieces and gaps. (The
    authors' code passes sigma where sigma^2 belongs; this is the variance.)

    The pieces are laid out as (K-1, Lmax) with zero-duration padding (an identity step), and Forster's
    recursions (eqs. 35, 44, 63) run over the Lmax piece slots, vectorised over all intervals at once.
    `scale_jacobian`: also d dR / d s for a gyro scale error (the bias Jacobian with each piece weighted by its
    rotation vector: the scale acts as a per-sample bias diag(w_j) s; effects/gyro_scale.py).
    `breaks`: time windows the gyro did not measure (Problem.unmeasured); an interval overlapping one carries no
    gyro factor (L^-1 = 0) and an orientation-unknown covariance (pi^2 rad^2) for the filters. `scale` (per sample, 3)
    multiplies each sample's noise std (a flight's vibration, Problem.gyr_scale; None: 1). `dt`: the nominal IMU
    period (None: the median spacing of `t_imu`; a slice of a log's samples passes the whole log's).
    """
    if epochs.size < 2 or epochs[0] < t_imu[0] or np.any(np.diff(epochs) <= 0.0):
        msg = (f"{where}: preintegration needs at least two increasing magnetometer epochs inside the IMU "
               "time span; check the log's time stamps")
        raise InsufficientDataError(msg)
    k = epochs.size - 1
    dt = float(np.median(np.diff(t_imu))) if dt is None else dt
    delta = np.broadcast_to(np.eye(3), (k, 3, 3)).copy()
    d_bias = np.zeros((k, 3, 3))
    cov = np.zeros((k, 3, 3))
    d_scale = np.zeros((k, 3, 3)) if scale_jacobian else None
    # one piece slot at a time (L ~ rate ratio of them), each vectorised over all intervals: holding every slot's
    # Exp and J_r at once cost 72 B x 4 per IMU sample (0.5 GB for an hour at 400 Hz, issue 39)
    for rows, smp, dur in _slots(t_imu, epochs):
        phi = np.zeros((k, 3))
        d = np.zeros(k)
        phi[rows] = (gyr[smp] - bias) * dur[:, None]
        d[rows] = dur
        step, jr = so3.exp(phi), so3.right_jacobian(phi)
        q = (noise_std**2)[None, :] * (dt * d)[:, None]                         # diag Q of each piece
        if scale is not None:
            grow = np.ones((k, 3))
            grow[rows] = scale[smp] ** 2
            q = q * grow
        e_t = step.transpose(0, 2, 1)
        delta = delta @ step
        d_bias = e_t @ d_bias - jr * d[:, None, None]
        if d_scale is not None:
            d_scale = e_t @ d_scale - jr * phi[:, None, :]
        cov = e_t @ cov @ step + (jr * q[:, None, :]) @ jr.transpose(0, 2, 1)
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        msg = (f"{where}: a preintegration interval has no gyro noise (zero-length or degenerate); check the "
               "time stamps")
        raise InsufficientDataError(msg) from None
    l_inv = np.linalg.inv(chol)
    broken = broken_intervals(epochs, breaks) if breaks else None
    if broken is not None and broken.any():
        l_inv[broken], cov[broken] = 0.0, np.pi**2 * np.eye(3)
    return Preintegrated(epochs, np.array(bias, dtype=np.float64), delta, d_bias, cov, l_inv,
                         np.diff(epochs), np.array(noise_std, dtype=np.float64), d_scale, broken)


def preintegrate_log(problem: Problem, epochs: FloatArray, bias: FloatArray, noise_std: FloatArray,
                     where: str = "gyro", scale_jacobian: bool = False, groups: Groups | None = None
                     ) -> Preintegrated:
    """`preintegrate` over the problem's gyro, with the windows it did not measure and its in-flight noise profile
    (Problem.unmeasured, Problem.gyr_scale): the one way every estimator preintegrates a log. With `groups` (the
    readings each epoch averages; `epochs` are their first readings), also what the gyro says within each group."""
    if groups is None:
        return preintegrate(problem.gyr.t, problem.gyr.xyz, epochs, bias, noise_std, where, scale_jacobian,
                            problem.unmeasured, problem.gyr_scale)
    parts = []
    dt = float(np.median(np.diff(problem.gyr.t)))
    for g0, g1, lo, hi in _group_blocks(groups):
        i0, t_imu, gyr = _span(problem, groups.t[lo], groups.t[hi])
        scale = None if problem.gyr_scale is None else problem.gyr_scale.from_sample(i0)
        fine = preintegrate(t_imu, gyr, groups.t[lo:hi + 1], bias, noise_std, where, scale_jacobian,
                            problem.unmeasured, scale, dt)
        parts.append(_compose(fine, groups.start[g0:g1 + 1] - lo, g1 < groups.counts.size))
    return _joined(parts, epochs, bias, noise_std, where)


def _span(problem: Problem, t0: float, t1: float) -> tuple[int, FloatArray, FloatArray]:
    """The gyro samples a block of readings from t0 to t1 integrates over: the first one's index, their stamps and
    rates (float64). A block's own, not the log's: each block's pieces were cut from every IMU stamp, and its rates
    read from the whole log (issue 39). The same samples, so the same digits."""
    t = problem.gyr.t
    i0 = max(int(np.searchsorted(t, t0, side="right")) - 1, 0)
    i1 = int(np.searchsorted(t, t1, side="left")) + 1
    return i0, t[i0:i1], problem.gyr.stored[i0:i1].astype(np.float64)


def preintegrate_epochs(problem: Problem, ep: Epochs, bias: FloatArray, noise_std: FloatArray, where: str = "gyro",
                        scale_jacobian: bool = False) -> Preintegrated:
    """`preintegrate_log` between an Epochs' states, with its groups when its epochs average readings: the times
    and the groups always from the same Epochs (a preintegration without them predicts a group's mean as one
    reading)."""
    return preintegrate_log(problem, ep.t, bias, noise_std, where, scale_jacobian, ep.groups)


#: groups of readings preintegrated at once
GROUP_BLOCK = 16384


def _group_blocks(groups: Groups) -> Iterator[tuple[int, int, int, int]]:
    """Blocks of GROUP_BLOCK groups (g0, g1) with the readings lo .. hi they integrate over: their own and the next
    block's first, up to the last reading. Every reading's interval at once is three times the epochs' (issue 39);
    a last block of one lone reading has no interval to integrate, so it joins the block before."""
    k, n = groups.counts.size, groups.t.size
    ends = list(range(GROUP_BLOCK, k, GROUP_BLOCK)) + [k]
    if len(ends) > 1 and groups.start[ends[-2]] == n - 1:
        del ends[-2]
    for g0, g1 in zip([0, *ends[:-1]], ends, strict=True):
        yield g0, g1, int(groups.start[g0]), int(groups.start[g1]) if g1 < k else n - 1


def group_rotations(problem: Problem, groups: Groups, bias: FloatArray) -> FloatArray:
    """Each reading's rotation dR_kj (n, 3, 3) from its group's first reading, the gyro integrated with `bias`."""
    out = np.broadcast_to(np.eye(3), (groups.t.size, 3, 3)).copy()
    for g0, g1, lo, hi in _group_blocks(groups):
        _, t_imu, gyr = _span(problem, groups.t[lo], groups.t[hi])
        fine = rotations(t_imu, gyr, groups.t[lo:hi + 1], bias)
        start, n_g = groups.start[g0:g1] - lo, groups.counts[g0:g1]
        for m in range(1, int(n_g.max())):
            at = start[n_g > m] + m
            out[lo + at] = out[lo + at - 1] @ fine[at - 1]
    return out


@dataclass(frozen=True)
class _Block:
    """A block of groups' composed intervals (all but possibly the last group's) and their `Within` sums."""

    delta: FloatArray
    d_bias: FloatArray
    cov: FloatArray
    d_scale: FloatArray | None
    broken: npt.NDArray[np.bool_]
    A: FloatArray
    B: FloatArray


def _compose(fine: Preintegrated, start: IntArray, last_closed: bool) -> _Block:
    """Compose the intervals between consecutive readings (`fine`) over groups whose readings start at
    start[g] (local; start[-1] is where the next group starts): each group's interval to the next group's first
    reading (all but the last group's unless `last_closed`), and the group's `Within` sums. Forster's recursions
    (eqs. 35, 44, 63) over whole intervals: dR <- dR d, J <- d^T J + J_d, C <- d^T C d + C_d."""
    n_g = np.diff(start)
    g = n_g.size
    closed = g if last_closed else g - 1
    delta = np.broadcast_to(np.eye(3), (g, 3, 3)).copy()
    d_bias, cov = np.zeros((g, 3, 3)), np.zeros((g, 3, 3))
    d_scale = None if fine.d_scale is None else np.zeros((g, 3, 3))
    a_sum = np.broadcast_to(np.eye(3), (g, 3, 3)).copy()      # dR_kk^T = I
    b_sum = np.zeros((g, 3, 3, 3))
    broken = np.zeros(g, dtype=bool)
    for m in range(int(n_g.max())):
        rows = np.flatnonzero((m < n_g) & (np.arange(g) < closed) | (m + 1 < n_g))
        i = start[rows] + m                                       # the reading interval composed now
        d, d_t = fine.delta[i], fine.delta[i].transpose(0, 2, 1)
        delta[rows] = delta[rows] @ d
        d_bias[rows] = d_t @ d_bias[rows] + fine.d_bias[i]
        cov[rows] = d_t @ cov[rows] @ d + fine.cov[i]
        if d_scale is not None and fine.d_scale is not None:
            d_scale[rows] = d_t @ d_scale[rows] + fine.d_scale[i]
        if fine.broken is not None:
            broken[rows] |= fine.broken[i]
        inside = rows[m + 1 < n_g[rows]]                          # reading m + 1 is still the group's
        a_sum[inside] += delta[inside].transpose(0, 2, 1)
        for a in range(3):                                        # [dR^T e_a]x: the hat of dR's row a
            b_sum[inside, a] += so3.hat(delta[inside, a, :]) @ d_bias[inside]
    scale = 1.0 / n_g[:, None, None]
    return _Block(delta[:closed], d_bias[:closed], cov[:closed], None if d_scale is None else d_scale[:closed],
                  broken[:closed], a_sum * scale, b_sum * scale[:, :, :, None])


def _joined(parts: list[_Block], epochs: FloatArray, bias: FloatArray, noise_std: FloatArray, where: str
            ) -> Preintegrated:
    """The groups' preintegration from `_compose`'s blocks."""
    def cat(name: str) -> FloatArray:
        return np.concatenate([getattr(p, name) for p in parts])
    cov = cat("cov")
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    broken = cat("broken").astype(bool)
    try:
        l_inv = np.asarray(np.linalg.inv(np.linalg.cholesky(np.where(broken[:, None, None], np.eye(3), cov))),
                       dtype=np.float64)
    except np.linalg.LinAlgError:
        msg = (f"{where}: a preintegration interval has no gyro noise (zero-length or degenerate); check the "
               "time stamps")
        raise InsufficientDataError(msg) from None
    if broken.any():
        l_inv[broken], cov[broken] = 0.0, np.pi**2 * np.eye(3)
    d_scale = None if parts[0].d_scale is None else cat("d_scale")
    return Preintegrated(epochs, np.array(bias, dtype=np.float64), cat("delta"), cat("d_bias"), cov, l_inv,
                         np.diff(epochs), np.array(noise_std, dtype=np.float64), d_scale,
                         broken if broken.any() else None, Within(cat("A"), cat("B")))


def gyro_factor(states: FloatArray, theta: FloatArray, pre: Preintegrated, bias_at: int,
                jacobians: bool = True, extra: tuple[FloatArray, FloatArray, IntArray] | None = None) -> Factor:
    """Whitened r = L^-1 Log((dR Exp(d_bias db))^T R_i^T R_j) on consecutive states (methods.md section 3).

    db = theta[bias_at:bias_at+3] is the bias correction relative to `pre.bias`. With right perturbations:
    dr/dphi_i = -L^-1 J_r^-1(r) R_j^T R_i, dr/dphi_j = L^-1 J_r^-1(r),
    dr/ddb = -L^-1 J_r^-1(r) Exp(r)^T J_r(d_bias db) d_bias.
    `extra` (g (K-1, 3), dg/dbeta (K-1, 3, q), beta's theta columns): effect terms added to the perturbation
    d_bias db, with the same Jacobian pattern.
    """
    db = theta[bias_at:bias_at + 3]
    g_db = pre.d_bias @ db
    if extra is not None:
        g_db = g_db + extra[0]
    # component-major stacks (stacks.py): the diagnosis linearises this factor ~1500 times per log. The
    # same Exp with or without Jacobians, so that a solver's cost does not depend on which it asked for
    delta, l_inv, d_bias = pre.component_major()
    s = stacks.cm(states)
    rel = stacks.tmul(s[:, :, :-1], s[:, :, 1:])                     # R_i^T R_j
    del s       # each (3, 3, K) stack goes once used: a dozen at once were 50 MB on 60 000 epochs (issue 39)
    exp_g, jr_g = stacks.exp_and_right_jacobian(g_db)
    err_t = stacks.tmul(rel, stacks.mul(delta, exp_g))              # err^T
    del exp_g
    r = stacks.log_small_transposed(err_t)
    rw = np.ascontiguousarray(np.einsum("ijn,jn->ni", l_inv, r))
    if not jacobians:
        return Factor("gyro", rw)
    a = stacks.mul(l_inv, stacks.right_jacobian_inv(r))
    lead = stacks.mul(a, stacks.mul(err_t, jr_g))
    del err_t, jr_g
    np.negative(lead, out=lead)
    jt = stacks.rm(stacks.mul(lead, d_bias))
    cols = np.arange(bias_at, bias_at + 3)
    if extra is not None:
        jt = np.concatenate([jt, stacks.rm(lead) @ extra[1]], axis=2)
        cols = np.concatenate([cols, extra[2]])
    del lead
    j_x = stacks.mult(a, rel)
    del rel
    np.negative(j_x, out=j_x)
    j_next = stacks.rm(a)
    del a
    return Factor("gyro", rw, np.arange(r.shape[1]), stacks.rm(j_x), j_next, jt, cols.astype(np.int64))
