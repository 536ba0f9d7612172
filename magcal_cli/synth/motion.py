"""The simulator's continuous-time truth: the attitude R(t) and the translation, defined at every instant.

Scenarios produce attitude knots on a fine grid of OVERSAMPLE knots per IMU period; between the knots R(t) is
a cubic Hermite curve in the chart at each knot (C1: the body rate w(t) is continuous and w'(t) exists
between the knots), and beyond the first and last knot it continues at the end rates. The translation is a
piecewise-linear NED acceleration on its own knots, integrated exactly, so the acceleration is continuous and
an instantaneous sample of it is defined. Nothing here knows how a sensor samples (synth/sampling.py).
"""

from __future__ import annotations

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
    v = np.asarray(values, dtype=np.float64)
    slope = np.empty_like(v)
    slope[1:-1] = 0.5 * (v[2:] - v[:-2])
    slope[0], slope[-1] = v[1] - v[0], v[-1] - v[-2]
    x = np.clip(np.asarray(t, dtype=np.float64) / dt, 0.0, len(v) - 1)
    k = np.minimum(np.floor(x).astype(np.int64), len(v) - 2)
    s = (x - k).reshape(x.shape + (1,) * (v.ndim - 1))
    s2, s3 = s * s, s * s * s
    out: FloatArray = ((2 * s3 - 3 * s2 + 1) * v[k] + (s3 - 2 * s2 + s) * slope[k]
                       + (3 * s2 - 2 * s3) * v[k + 1] + (s3 - s2) * slope[k + 1])
    return out


def fine_times(duration: float, rate: float) -> FloatArray:
    """The fine grid over [0, duration]: OVERSAMPLE knots per IMU period of 1 / rate s."""
    n = int(round(duration * rate * OVERSAMPLE))
    out: FloatArray = np.arange(n + 1) / (rate * OVERSAMPLE)
    return out


@dataclass(frozen=True, eq=False)
class Trajectory:
    """The true attitude R(t) body->NED: knots R_i (N+1, 3, 3) every dt s from t = 0, knot body rates w_i (N+1, 3)
    and, per interval, the chart curve p_i(s) = c1 s + c2 s^2 + c3 s^3, s = t / dt - i (coefficients (N, 3, 3)).

    R(t) = R_i Exp(p_i(s)) is the cubic Hermite curve in the chart at R_i that meets R_i+1 and has the body
    rates w_i, w_i+1 at its ends; for a constant-rate rotation it is the geodesic (slerp).
    """

    knots: FloatArray
    dt: float
    rates: FloatArray
    coefficients: FloatArray

    @classmethod
    def from_knots(cls, knots: npt.ArrayLike, dt: float) -> Trajectory:
        """Knot rates w_i = (xi_i-1 + xi_i) / (2 dt), xi_i = Log(R_i^T R_i+1) (one-sided at the two ends).

        Log(R_i^T R_i-1) = -xi_i-1 exactly (a rotation fixes its own axis), so this is the central difference
        in the chart at R_i. The end tangents in the chart are dt w_i and dt J_r(xi_i)^-1 w_i+1, since
        d/ds Exp(p) = Exp(p) [J_r(p) p']x.
        """
        knots = np.asarray(knots, dtype=np.float64)
        xi = so3.log(np.swapaxes(knots[:-1], -1, -2) @ knots[1:])
        rates = np.empty((len(knots), 3))
        rates[0], rates[-1] = xi[0] / dt, xi[-1] / dt
        rates[1:-1] = (xi[:-1] + xi[1:]) / (2.0 * dt)
        m0 = dt * rates[:-1]
        m1 = dt * np.einsum("nij,nj->ni", so3.right_jacobian_inv(xi), rates[1:])
        coefficients = np.stack([m0, 3.0 * xi - 2.0 * m0 - m1, m0 - 2.0 * xi + m1], axis=1)
        return cls(knots, dt, rates, coefficients)

    @property
    def end(self) -> float:
        """Time (s) of the last knot."""
        return (len(self.knots) - 1) * self.dt

    def _chart(self, t: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], FloatArray, FloatArray]:
        """Base knot index, chart point p and dp/dt * dt at times t; beyond the ends p grows at the end rate."""
        x = np.asarray(t, dtype=np.float64) / self.dt
        n = len(self.knots) - 1
        k = np.clip(np.floor(x).astype(np.int64), 0, n - 1)
        s = (x - k)[:, None]
        c = self.coefficients[k]
        p = ((c[:, 2] * s + c[:, 1]) * s + c[:, 0]) * s
        dp = (3.0 * c[:, 2] * s + 2.0 * c[:, 1]) * s + c[:, 0]
        before, after = x < 0, x > n
        if before.any() or after.any():
            k = np.where(after, n, k)
            edge = np.where(before[:, None], self.rates[0], self.rates[-1]) * self.dt
            u = np.where(before, x, x - n)[:, None]
            outside = (before | after)[:, None]
            p, dp = np.where(outside, u * edge, p), np.where(outside, edge, dp)
        return k, p, dp

    def at(self, t: npt.ArrayLike) -> FloatArray:
        """R(t) (M, 3, 3) at (M,) times in seconds."""
        k, p, _ = self._chart(t)
        out: FloatArray = self.knots[k] @ so3.exp(p)
        return out

    def rate(self, t: npt.ArrayLike) -> FloatArray:
        """The body rate w(t) (M, 3) rad/s: J_r(p) dp/dt, exactly (R^T dR/dt = [w]x)."""
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


@dataclass(frozen=True, eq=False)
class Motion:
    """A translation in NED: acceleration a_i (N+1, 3) m/s^2 at knots t_i = i dt, linear in between, and the
    velocity v_i (m/s) and position p_i (m) at the knots integrated exactly from it (p is piecewise cubic).
    Beyond the ends the end acceleration is held."""

    dt: float
    a: FloatArray
    v: FloatArray
    p: FloatArray

    @classmethod
    def from_acceleration(cls, a: npt.ArrayLike, dt: float, v0: npt.ArrayLike = (0.0, 0.0, 0.0)) -> Motion:
        """Integrate the knot accelerations from the origin at velocity v0: v_i+1 = v_i + dt (a_i + a_i+1) / 2,
        p_i+1 = p_i + v_i dt + dt^2 (2 a_i + a_i+1) / 6."""
        a = np.asarray(a, dtype=np.float64)
        start = np.asarray(v0, dtype=np.float64)[None]
        v = np.concatenate([start, 0.5 * dt * (a[:-1] + a[1:])]).cumsum(axis=0)
        p = np.concatenate([np.zeros((1, 3)), v[:-1] * dt + dt * dt * (2.0 * a[:-1] + a[1:]) / 6.0]).cumsum(axis=0)
        return cls(dt, a, v, p)

    def _split(self, t: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], FloatArray, FloatArray]:
        """Knot index, time since that knot (M, 1) s and the jerk (M, 3) there (0 beyond the ends)."""
        t = np.asarray(t, dtype=np.float64)
        n = len(self.a) - 1
        k = np.clip(np.floor(t / self.dt).astype(np.int64), 0, n)
        jerk = np.diff(self.a, axis=0, append=self.a[-1:]) / self.dt
        k = np.where(t < 0, 0, k)
        outside = ((t < 0) | (k == n))[:, None]
        return k, (t - k * self.dt)[:, None], np.where(outside, 0.0, jerk[k])

    def position(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED position (m) at `t` (s)."""
        k, s, j = self._split(t)
        out: FloatArray = self.p[k] + s * (self.v[k] + s * (0.5 * self.a[k] + s * j / 6.0))
        return out

    def acceleration(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED acceleration (m/s^2) at `t` (s)."""
        k, s, j = self._split(t)
        out: FloatArray = self.a[k] + s * j
        return out
