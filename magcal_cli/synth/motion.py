"""The simulator's continuous-time truth: the attitude R(t) and the translation, defined at every instant.

Scenarios produce attitude knots on a fine grid of OVERSAMPLE knots per IMU period; between the knots R(t) is
a cubic Hermite curve in the chart at each knot (C1: the body rate w(t) is continuous and w'(t) exists
between the knots), and beyond the first and last knot it continues at the end rates. The translation is a
piecewise-linear NED acceleration on its own knots, integrated exactly, so the acceleration is continuous and
an instantaneous sample of it is defined. Nothing here knows how a sensor samples (synth/sampling.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.streams import FloatArray

#: fine-grid knots per IMU period: the truth is generated at ten times the rate it is sampled at
OVERSAMPLE = 10


def smooth(values: npt.ArrayLike, dt: float, t: npt.ArrayLike) -> FloatArray:
    """Samples (K, ...) taken every dt s from t = 0, at times `t` by the Catmull-Rom cubic (held beyond the ends).

    A local cubic Hermite with central-difference slopes: C1, exact for quadratics, and constant wherever four
    neighbouring samples are (so a still pose stays exactly still). Draws made once per IMU sample are spread
    onto the fine grid with it, so their statistics do not depend on OVERSAMPLE.
    """
    return smoother(values, dt)(t)


def smoother(values: npt.ArrayLike, dt: float) -> Callable[[npt.ArrayLike], FloatArray]:
    """`smooth` of these samples as a function of t, the slopes computed once (for a fine grid made in blocks)."""
    v = np.asarray(values, dtype=np.float64)
    slope = np.empty_like(v)
    slope[1:-1] = 0.5 * (v[2:] - v[:-2])
    slope[0], slope[-1] = v[1] - v[0], v[-1] - v[-2]

    def at(t: npt.ArrayLike) -> FloatArray:
        x = np.clip(np.asarray(t, dtype=np.float64) / dt, 0.0, len(v) - 1)
        k = np.minimum(np.floor(x).astype(np.int64), len(v) - 2)
        s = (x - k).reshape(x.shape + (1,) * (v.ndim - 1))
        s2, s3 = s * s, s * s * s
        out: FloatArray = ((2 * s3 - 3 * s2 + 1) * v[k] + (s3 - 2 * s2 + s) * slope[k]
                           + (3 * s2 - 2 * s3) * v[k + 1] + (s3 - s2) * slope[k + 1])
        return out

    return at


def fine_times(duration: float, rate: float) -> FloatArray:
    """The fine grid over [0, duration]: OVERSAMPLE knots per IMU period of 1 / rate s."""
    out: FloatArray = np.arange(fine_count(duration, rate)) / (rate * OVERSAMPLE)
    return out


def fine_count(duration: float, rate: float) -> int:
    """The number of knots of `fine_times(duration, rate)`."""
    return int(round(duration * rate * OVERSAMPLE)) + 1


#: knots evaluated at once: a long flight's fine grid (4 000 knots/s at 400 Hz) is never held whole
BLOCK = 1 << 16

#: the knots (M, 3, 3) or accelerations (M, 3) of a fine grid at the given knot indices (M,), made on demand
KnotSource = Callable[[npt.NDArray[np.int64]], FloatArray]


def _spans(k: npt.NDArray[np.int64]) -> list[tuple[int, int]]:
    """Cut query positions into runs of at most BLOCK queries (their knot span is what a block evaluates)."""
    return [(i, min(i + BLOCK, len(k))) for i in range(0, len(k), BLOCK)]


def _by_blocks(f: Callable[[FloatArray], FloatArray], t: npt.ArrayLike, shape: tuple[int, ...]) -> FloatArray:
    """f of (M,) times, BLOCK times at a time (each row depends on its own time only), into one (M, *shape)."""
    t = np.asarray(t, dtype=np.float64)
    out = np.empty((len(t), *shape))
    for i in range(0, len(t), BLOCK):
        out[i:i + BLOCK] = f(t[i:i + BLOCK])
    return out


def hermite_pieces(knots: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Knot rates w_i (N+1, 3) and chart coefficients (N, 3, 3) of knots (N+1, 3, 3): see `Trajectory`.

    w_i = (xi_i-1 + xi_i) / (2 dt), xi_i = Log(R_i^T R_i+1) (one-sided at the two ends); Log(R_i^T R_i-1) =
    -xi_i-1 exactly (a rotation fixes its own axis), so this is the central difference in the chart at R_i.
    The end tangents in the chart are dt w_i and dt J_r(xi_i)^-1 w_i+1, since d/ds Exp(p) = Exp(p) [J_r(p) p']x.
    Every row depends on its neighbours only, so a block with one knot of margin gives the rows of the whole.
    """
    xi = so3.log(np.swapaxes(knots[:-1], -1, -2) @ knots[1:])
    rates = np.empty((len(knots), 3))
    rates[0], rates[-1] = xi[0] / dt, xi[-1] / dt
    rates[1:-1] = (xi[:-1] + xi[1:]) / (2.0 * dt)
    m0 = dt * rates[:-1]
    m1 = dt * np.einsum("nij,nj->ni", so3.right_jacobian_inv(xi), rates[1:])
    return rates, np.stack([m0, 3.0 * xi - 2.0 * m0 - m1, m0 - 2.0 * xi + m1], axis=1)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """The true attitude R(t) body->NED: `count` knots R_i every dt s from t = 0 (made by `source` a block at
    a time), knot body rates w_i and, per interval, the chart curve p_i(s) = c1 s + c2 s^2 + c3 s^3,
    s = t / dt - i (`hermite_pieces`).

    R(t) = R_i Exp(p_i(s)) is the cubic Hermite curve in the chart at R_i that meets R_i+1 and has the body
    rates w_i, w_i+1 at its ends; for a constant-rate rotation it is the geodesic (slerp). Queries are
    evaluated BLOCK at a time from the knots they reach, so an hour at 400 Hz (14 M knots) is never held.
    """

    source: KnotSource
    count: int
    dt: float

    @classmethod
    def from_knots(cls, knots: npt.ArrayLike, dt: float) -> Trajectory:
        """The trajectory through knots (N+1, 3, 3) every dt s."""
        held = np.asarray(knots, dtype=np.float64)
        return cls(lambda idx: held[idx], len(held), dt)

    @property
    def knots(self) -> FloatArray:
        """All knots (N+1, 3, 3) (the whole grid: for short trajectories and tests)."""
        return self.source(np.arange(self.count))

    @property
    def rates(self) -> FloatArray:
        """All knot body rates (N+1, 3) rad/s."""
        return hermite_pieces(self.knots, self.dt)[0]

    @property
    def end(self) -> float:
        """Time (s) of the last knot."""
        return (self.count - 1) * self.dt

    def _pieces(self, u: npt.NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """Knots R_k (U, 3, 3) and chart coefficients (U, 3, 3) of the intervals u (sorted, unique): from
        knots k-1..k+2 of each (a sampled grid uses few of its intervals: an IMU stamp every tenth), or from
        the run of knots that covers them where they are dense. Row for row what `hermite_pieces` of the
        whole grid gives."""
        n, dt = self.count - 1, self.dt
        lo, hi = max(int(u[0]) - 1, 0), min(int(u[-1]) + 3, self.count)
        if 4 * len(u) >= hi - lo:
            knots = self.source(np.arange(lo, hi))
            return knots[u - lo], hermite_pieces(knots, dt)[1][u - lo]
        near = self.source(np.clip(u[:, None] + np.arange(-1, 3), 0, n).ravel()).reshape(len(u), 4, 3, 3)
        xi = so3.log(np.swapaxes(near[:, :-1], -1, -2) @ near[:, 1:])
        before, step, after = xi[:, 0], xi[:, 1], xi[:, 2]
        r0 = np.where((u == 0)[:, None], step / dt, (before + step) / (2.0 * dt))
        # C order, as the whole grid's rates: einsum sums in another order over a Fortran-ordered operand
        r1 = np.ascontiguousarray(np.where((u == n - 1)[:, None], step / dt, (step + after) / (2.0 * dt)))
        m0 = dt * r0
        m1 = dt * np.einsum("nij,nj->ni", so3.right_jacobian_inv(step), r1)
        return near[:, 1], np.stack([m0, 3.0 * step - 2.0 * m0 - m1, m0 - 2.0 * step + m1], axis=1)

    def _edge_rates(self) -> tuple[FloatArray, FloatArray]:
        """The body rates at the first and the last knot (one-sided)."""
        first = hermite_pieces(self.source(np.arange(2)), self.dt)[0][0]
        last = hermite_pieces(self.source(np.arange(self.count - 2, self.count)), self.dt)[0][-1]
        return first, last

    def _chart(self, t: npt.ArrayLike, with_knots: bool = False
               ) -> tuple[FloatArray | None, FloatArray, FloatArray]:
        """R_k (with_knots), chart point p and dp/dt * dt at times t; beyond the ends p grows at the end rate."""
        x = np.asarray(t, dtype=np.float64) / self.dt
        n = self.count - 1
        k = np.clip(np.floor(x).astype(np.int64), 0, n - 1)
        s_all = (x - k)[:, None]
        p, dp = np.empty((len(x), 3)), np.empty((len(x), 3))
        base = np.empty((len(x), 3, 3)) if with_knots else None
        for i, j in _spans(k):
            u, which = np.unique(k[i:j], return_inverse=True)
            knots, coef = self._pieces(u)
            c, s = coef[which], s_all[i:j]
            p[i:j] = ((c[:, 2] * s + c[:, 1]) * s + c[:, 0]) * s
            dp[i:j] = (3.0 * c[:, 2] * s + 2.0 * c[:, 1]) * s + c[:, 0]
            if base is not None:
                base[i:j] = knots[which]
        before, after = x < 0, x > n
        if before.any() or after.any():
            first, last = self._edge_rates()
            edge = np.where(before[:, None], first, last) * self.dt
            u = np.where(before, x, x - n)[:, None]
            outside = (before | after)[:, None]
            p, dp = np.where(outside, u * edge, p), np.where(outside, edge, dp)
            if base is not None and after.any():
                base[after] = self.source(np.array([n]))[0]
        return base, p, dp

    def at(self, t: npt.ArrayLike) -> FloatArray:
        """R(t) (M, 3, 3) at (M,) times in seconds."""
        return _by_blocks(self._at, t, (3, 3))

    def _at(self, t: FloatArray) -> FloatArray:
        knots, p, _ = self._chart(t, with_knots=True)
        assert knots is not None
        out: FloatArray = knots @ so3.exp(p)
        return out

    def rate(self, t: npt.ArrayLike) -> FloatArray:
        """The body rate w(t) (M, 3) rad/s: J_r(p) dp/dt, exactly (R^T dR/dt = [w]x)."""
        return _by_blocks(self._rate, t, (3,))

    def _rate(self, t: FloatArray) -> FloatArray:
        _, p, dp = self._chart(t)
        _, b, c = so3.exp_coefficients(p)
        pxv = np.cross(p, dp)
        out: FloatArray = (dp - b[:, None] * pxv + c[:, None] * np.cross(p, pxv)) / self.dt
        return out

    def rate_and_acceleration(self, t: npt.ArrayLike, h: float | None = None) -> tuple[FloatArray, FloatArray]:
        """Body rate w (M, 3) rad/s and its derivative w' (M, 3) rad/s^2 at `t`.

        w' is the central difference of the exact rate with step h (default dt / 1000): w' is continuous
        inside a knot interval and jumps at the knots, where this is the mean of its two one-sided values.
        """
        t = np.asarray(t, dtype=np.float64)
        h = self.dt * 1e-3 if h is None else h
        return self.rate(t), (self.rate(t + h) - self.rate(t - h)) / (2.0 * h)


def _integrate(a: FloatArray, dt: float, v0: FloatArray, p0: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Velocity and position at knots (M, 3) from the accelerations there, starting at v0, p0 (first knot):
    v_i+1 = v_i + dt (a_i + a_i+1) / 2, p_i+1 = p_i + v_i dt + dt^2 (2 a_i + a_i+1) / 6. A running sum, so a
    block started from the values at its first knot gives the rows of the whole bit for bit."""
    v = np.concatenate([v0[None], 0.5 * dt * (a[:-1] + a[1:])]).cumsum(axis=0)
    p = np.concatenate([p0[None], v[:-1] * dt + dt * dt * (2.0 * a[:-1] + a[1:]) / 6.0]).cumsum(axis=0)
    return v, p


@dataclass(frozen=True, eq=False)
class Motion:
    """A translation in NED: acceleration a_i (m/s^2) at `count` knots t_i = i dt (made by `source` a block at a
    time), linear in between, and the velocity and position (m) integrated exactly from it (p is piecewise
    cubic), kept at every BLOCK-th knot (`v`, `p`) and integrated on from there on demand. Beyond the ends the
    end acceleration is held."""

    dt: float
    source: KnotSource
    count: int
    v: FloatArray
    p: FloatArray

    @classmethod
    def from_acceleration(cls, a: npt.ArrayLike, dt: float, v0: npt.ArrayLike = (0.0, 0.0, 0.0)) -> Motion:
        """Integrate the knot accelerations (N+1, 3) from the origin at velocity v0."""
        held = np.asarray(a, dtype=np.float64)
        return cls.from_source(lambda idx: held[idx], len(held), dt, v0)

    @classmethod
    def from_source(cls, source: KnotSource, count: int, dt: float, v0: npt.ArrayLike = (0.0, 0.0, 0.0)) -> Motion:
        """Integrate the accelerations `source` makes, a block at a time, keeping v and p at every BLOCK-th knot."""
        v, p = np.asarray(v0, dtype=np.float64), np.zeros(3)
        vs, ps = [v], [p]
        for lo in range(0, count - 1, BLOCK):
            hi = min(lo + BLOCK, count - 1)
            vb, pb = _integrate(source(np.arange(lo, hi + 1)), dt, v, p)
            v, p = vb[-1].copy(), pb[-1].copy()     # not views: each would keep its whole block alive
            vs.append(v)
            ps.append(p)
        return cls(dt, source, count, np.array(vs), np.array(ps))

    def _split(self, t: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """a_k, v_k, p_k of each time's knot k, time since that knot (M, 1) s and the jerk (M, 3) there (0 beyond
        the ends)."""
        t = np.asarray(t, dtype=np.float64)
        n = self.count - 1
        k = np.clip(np.floor(t / self.dt).astype(np.int64), 0, n)
        k = np.where(t < 0, 0, k)
        a, v, p, jerk = (np.empty((len(t), 3)) for _ in range(4))
        # by the stretch between two kept knots: sparse queries (GNSS fixes) never integrate the whole grid at once
        order = np.argsort(k, kind="stable")
        cuts = np.searchsorted(k[order] // BLOCK, np.arange(n // BLOCK + 2))
        for b in range(len(cuts) - 1):
            sel = order[cuts[b]:cuts[b + 1]]
            if not len(sel):
                continue
            kk, lo = k[sel], b * BLOCK
            ab = self.source(np.arange(lo, min(int(kk.max()) + 2, self.count)))
            vb, pb = _integrate(ab, self.dt, self.v[b], self.p[b])
            jb = np.diff(ab, axis=0, append=ab[-1:]) / self.dt
            a[sel], v[sel], p[sel], jerk[sel] = ab[kk - lo], vb[kk - lo], pb[kk - lo], jb[kk - lo]
        outside = ((t < 0) | (k == n))[:, None]
        return a, v, p, (t - k * self.dt)[:, None], np.where(outside, 0.0, jerk)

    def position(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED position (m) at `t` (s)."""
        a, v, p, s, j = self._split(t)
        out: FloatArray = p + s * (v + s * (0.5 * a + s * j / 6.0))
        return out

    def acceleration(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED acceleration (m/s^2) at `t` (s)."""
        a, _, _, s, j = self._split(t)
        out: FloatArray = a + s * j
        return out
