"""Continuous-time truth behind the injected effects: the rotation between IMU epochs and the auxiliary signals.

Built from the simulated trajectory and seeded generators only; no estimator's equations are reused. The true
attitude between the IMU epochs t_k = k dt is R(t) = R_k Exp(p_k(s)), s = (t - t_k) / dt, with p_k the cubic
Hermite curve in the chart at R_k that meets R_k+1 and has the knot body rates w_k, w_k+1 at its ends. It
passes through every R_k, so the simulated gyro (the rotation vector of R_k^T R_k+1 over dt, what an ideal
delta-angle gyro reports) still integrates exactly to the trajectory; for a constant-rate rotation it is the
geodesic. Before t_0 and after t_N it continues at the end rates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from . import so3

FloatArray = npt.NDArray[np.float64]

#: WGS84 semi-major axis (m) and first eccentricity squared
WGS84_A, WGS84_E2 = 6378137.0, 6.69437999014e-3
#: where the simulated vehicle flies: PX4 SITL's home (deg, deg, m above MSL), as the .bin writer logs it
HOME = (47.397742, 8.545594, 488.0)
#: rate (Hz) of the grid the auxiliary signals are defined on (linear between its samples)
SIGNAL_RATE_HZ = 200.0
#: seconds the signal grids extend beyond the log at both ends (room for a time offset)
MARGIN_S = 2.0


@dataclass(frozen=True, eq=False)
class Trajectory:
    """The true attitude as a function of time: knots R_k (N+1, 3, 3) body->NED every dt s, knot body rates."""

    knots: FloatArray
    dt: float
    rates: FloatArray

    @classmethod
    def from_knots(cls, knots: FloatArray, dt: float) -> Trajectory:
        """Knot rates w_k = (xi_k-1 + xi_k) / (2 dt), xi_k = Log(R_k^T R_k+1) (one-sided at the two ends).

        Log(R_k^T R_k-1) = -xi_k-1 exactly (a rotation fixes its own axis), so this is the central difference
        in the chart at R_k.
        """
        xi = so3.log(np.swapaxes(knots[:-1], -1, -2) @ knots[1:])
        rates = np.empty((len(knots), 3))
        rates[0], rates[-1] = xi[0] / dt, xi[-1] / dt
        rates[1:-1] = (xi[:-1] + xi[1:]) / (2.0 * dt)
        return cls(knots, dt, rates)

    def at(self, t: npt.ArrayLike) -> FloatArray:
        """R(t) of (M,) times in seconds (t = 0 is the first knot)."""
        t = np.asarray(t, dtype=np.float64)
        n = len(self.knots) - 1
        x = t / self.dt
        k = np.clip(np.floor(x).astype(np.int64), 0, n - 1)
        s = (x - k)[:, None]
        r0, r1 = self.knots[k], self.knots[k + 1]
        xi = so3.log(np.swapaxes(r0, -1, -2) @ r1)
        m0 = self.dt * self.rates[k]
        m1 = self.dt * np.einsum("nij,nj->ni", so3.right_jacobian_inv(xi), self.rates[k + 1])
        h10, h01, h11 = s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2   # cubic Hermite basis
        out: FloatArray = r0 @ so3.exp(h10 * m0 + h01 * xi + h11 * m1)
        before, after = x < 0, x > n
        if before.any():
            out[before] = self.knots[0] @ so3.exp(self.rates[0] * t[before, None])
        if after.any():
            out[after] = self.knots[-1] @ so3.exp(self.rates[-1] * (t[after, None] - n * self.dt))
        return out

    def rate_and_acceleration(self, t: npt.ArrayLike, h: float | None = None) -> tuple[FloatArray, FloatArray]:
        """Body rate w (M, 3) rad/s and its derivative (M, 3) rad/s^2 at `t`, by central differences of step h.

        In the chart at R(t), psi(tau) = Log(R(t)^T R(t + tau)): w = psi'(0) and, because J_r(psi) psi' has no
        first-order term in psi at psi = 0, w' = psi''(0). Default h = dt / 10 (a fine grid at ten times the
        IMU rate); where w' jumps (at the knots) this is the mean of its two one-sided values.
        """
        t = np.asarray(t, dtype=np.float64)
        h = self.dt / 10.0 if h is None else h
        r0t = np.swapaxes(self.at(t), -1, -2)
        plus, minus = so3.log(r0t @ self.at(t + h)), so3.log(r0t @ self.at(t - h))
        return (plus - minus) / (2.0 * h), (plus + minus) / h**2


@dataclass(frozen=True, eq=False)
class Signal:
    """A scalar signal defined by samples on a fine grid, linear in between (its exact continuous truth)."""

    t: FloatArray
    v: FloatArray

    def __call__(self, t: npt.ArrayLike) -> FloatArray:
        """Values at times `t` (s)."""
        out: FloatArray = np.interp(np.asarray(t, dtype=np.float64), self.t, self.v)
        return out


def _grid(duration: float) -> FloatArray:
    """The signal grid: SIGNAL_RATE_HZ from -MARGIN_S to duration + MARGIN_S."""
    n = int(np.ceil((duration + 2 * MARGIN_S) * SIGNAL_RATE_HZ)) + 1
    return -MARGIN_S + np.arange(n) / SIGNAL_RATE_HZ


def _lowpass(x: FloatArray, tau: float, fs: float) -> FloatArray:
    """First-order lag y' = (x - y) / tau, discretised exactly for a piecewise-constant input, from rest at x[0]."""
    from scipy.signal import lfilter

    a = float(np.exp(-1.0 / (tau * fs)))
    y, _ = lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])
    return np.asarray(y, dtype=np.float64)


def _steps(rng: np.random.Generator, t: FloatArray, every_s: tuple[float, float],
           levels: tuple[float, float]) -> FloatArray:
    """A piecewise-constant signal that jumps to a uniform level in `levels` at intervals uniform in `every_s`."""
    out = np.zeros_like(t)
    at = float(t[0])
    while at < t[-1]:
        at += rng.uniform(*every_s)
        out[t >= at] = rng.uniform(*levels)
    return out


@dataclass(frozen=True, eq=False)
class Power:
    """The vehicle's throttle command u in [0, 1], battery current I > 0 (A) and battery voltage (V)."""

    throttle: Signal
    current: Signal
    voltage: Signal


#: power-system profiles: "flight" (the default) and "hover" (constant hover, no payload: designed collinearity)
POWER_PROFILES = ("flight", "hover")
#: "hover": the throttle rises by this fraction, with this time constant (s), as the pack's polarisation builds up
HOVER_RISE, HOVER_TAU_S = 0.25, 120.0


def power(rng: np.random.Generator, duration: float, profile: str = "flight") -> Power:
    """A hovering multirotor's power system, independent of the simulated attitude.

    Throttle: hover at 0.38 plus climbs and descents (steps to -0.12..+0.12 every 6-20 s) plus pilot and
    controller activity (white noise band-passed to 0.1-5 Hz, std 0.05), kept within 0.08..0.75. Motor current
    48 A * u^1.5 behind a 60 ms first-order ESC and motor lag, plus 0.8 A of avionics and a 2.5 A payload that
    switches on and off independently of the throttle (so current and throttle are not one signal). Voltage:
    a 4S pack's open-circuit 16.8 V falling with the charge drawn from a 5 Ah pack, minus 20 mOhm x I of sag.
    `profile` "hover" holds a constant hover without payload whose throttle rises by HOVER_RISE with time
    constant HOVER_TAU_S as the pack's polarisation builds up (activity std 0.002), so current, throttle and a
    warming board's temperature are nearly proportional (designed collinearity, correlation > 0.99).
    """
    from scipy.signal import butter, sosfiltfilt

    if profile not in POWER_PROFILES:
        msg = f"power profile {profile!r}: choose one of {', '.join(POWER_PROFILES)}"
        raise ValueError(msg)
    t = _grid(duration)
    fs = SIGNAL_RATE_HZ
    sos = butter(2, [0.1, 5.0], btype="bandpass", fs=fs, output="sos")
    activity = sosfiltfilt(sos, rng.standard_normal(t.size))
    if profile == "hover":
        activity *= 0.002 / float(np.std(activity))
        rise = HOVER_RISE * (1.0 - np.exp(-np.clip(t, 0.0, None) / HOVER_TAU_S))
        u = np.clip(0.38 * (1.0 + rise) + activity, 0.08, 0.75)
    else:
        activity *= 0.05 / float(np.std(activity))
        u = np.clip(0.38 + _steps(rng, t, (6.0, 20.0), (-0.12, 0.12)) + activity, 0.08, 0.75)
    payload = 0.0 * t if profile == "hover" else 2.5 * (_steps(rng, t, (8.0, 30.0), (0.0, 1.0)) > 0.5)
    current = _lowpass(48.0 * u**1.5, 0.06, fs) + 0.8 + payload
    drawn_ah = np.concatenate([[0.0], np.cumsum(current[1:]) / fs / 3600.0])
    voltage = 16.8 - 1.6 * drawn_ah / 5.0 - 0.020 * current
    return Power(Signal(t, u), Signal(t, current), Signal(t, voltage))


def temperature(duration: float, start: float = 25.0, end: float = 45.0, tau_s: float = 150.0) -> Signal:
    """A board warming up after power-on: start + (end - start)(1 - exp(-t / tau_s)) degC (t < 0: start)."""
    t = _grid(duration)
    return Signal(t, start + (end - start) * (1.0 - np.exp(-np.clip(t, 0.0, None) / tau_s)))


@dataclass(frozen=True, eq=False)
class Path:
    """The vehicle's translation in NED (m): p(t) = sum_j A_j sin(2 pi f_j t + phi_j), A_j (3,) per component."""

    amplitude: FloatArray
    freq_hz: FloatArray
    phase: FloatArray

    def position(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED position (m) relative to HOME."""
        arg = 2 * np.pi * np.asarray(t, dtype=np.float64)[:, None] * self.freq_hz + self.phase
        out: FloatArray = np.sin(arg) @ self.amplitude
        return out

    def velocity(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED velocity (m/s)."""
        w = 2 * np.pi * self.freq_hz
        arg = w * np.asarray(t, dtype=np.float64)[:, None] + self.phase
        out: FloatArray = (np.cos(arg) * w) @ self.amplitude
        return out

    def acceleration(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED acceleration (m/s^2): the second derivative of `position`, analytically."""
        w = 2 * np.pi * self.freq_hz
        arg = w * np.asarray(t, dtype=np.float64)[:, None] + self.phase
        out: FloatArray = (-np.sin(arg) * w**2) @ self.amplitude
        return out


@dataclass(frozen=True, eq=False)
class Motion:
    """A scenario's translation in NED: acceleration a_k (N, 3) m/s^2 held over [k dt, (k+1) dt) (the interval
    gyro sample k covers), velocity v (N+1, 3) m/s and position p (N+1, 3) m at the knots, integrated exactly
    from it; in between the position is the quadratic p_k + v_k s + a_k s^2 / 2."""

    dt: float
    a: FloatArray
    v: FloatArray
    p: FloatArray

    @classmethod
    def from_acceleration(cls, a: FloatArray, dt: float, v0: npt.ArrayLike = (0.0, 0.0, 0.0)) -> Motion:
        """Integrate a_k from rest at the origin (or at velocity v0): v_k+1 = v_k + a_k dt,
        p_k+1 = p_k + v_k dt + a_k dt^2 / 2."""
        a = np.asarray(a, dtype=np.float64)
        v = np.concatenate([np.asarray(v0, dtype=np.float64)[None], a * dt]).cumsum(axis=0)
        p = np.concatenate([np.zeros((1, 3)), v[:-1] * dt + a * (0.5 * dt * dt)]).cumsum(axis=0)
        return cls(dt, a, v, p)

    def _split(self, t: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """Interval index k (clipped to the log) and the time since its start (s), (M, 1)."""
        t = np.asarray(t, dtype=np.float64)
        # + 1e-9: an IMU epoch k / rate divided by dt may round to just below k
        k = np.clip(np.floor(t / self.dt + 1e-9).astype(np.int64), 0, len(self.a) - 1)
        return k, (t - k * self.dt)[:, None]

    def position(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED position (m) at `t` (s): the piecewise quadratic."""
        k, s = self._split(t)
        out: FloatArray = self.p[k] + self.v[k] * s + 0.5 * self.a[k] * s * s
        return out

    def acceleration(self, t: npt.ArrayLike) -> FloatArray:
        """(M, 3) NED acceleration (m/s^2) at `t` (s): a_k of the interval holding t."""
        out: FloatArray = self.a[self._split(t)[0]]
        return out


def path(rng: np.random.Generator, t: FloatArray, sigma_a: float) -> Path:
    """Four smooth sway components of 0.08-0.3 Hz (vertical at 40 %), scaled so that the RMS over `t` of each
    NED acceleration component is sigma_a (m/s^2); displacements are then a few metres for sigma_a ~ 1."""
    freq = rng.uniform(0.08, 0.3, 4)
    amp = rng.standard_normal((4, 3)) * np.array([1.0, 1.0, 0.4])
    p = Path(amp, freq, rng.uniform(0.0, 2 * np.pi, 4))
    rms = float(np.sqrt(np.mean(p.acceleration(t) ** 2)))
    return Path(amp * (sigma_a / rms if rms > 0 else 0.0), freq, p.phase)


def geodetic(ned: FloatArray, home: tuple[float, float, float] = HOME) -> FloatArray:
    """(M, 3) latitude, longitude (deg) and altitude (m) of NED offsets (m) from `home` (local tangent plane,
    WGS84 meridian and prime-vertical radii at home; exact to ~1e-6 of the offset over a few hundred metres)."""
    lat0 = np.deg2rad(home[0])
    w = 1.0 - WGS84_E2 * np.sin(lat0) ** 2
    meridian, prime = WGS84_A * (1.0 - WGS84_E2) / w**1.5, WGS84_A / np.sqrt(w)
    lat = home[0] + np.rad2deg(ned[:, 0] / (meridian + home[2]))
    lon = home[1] + np.rad2deg(ned[:, 1] / ((prime + home[2]) * np.cos(lat0)))
    return np.column_stack([lat, lon, home[2] - ned[:, 2]])


def local(lla: FloatArray, home: tuple[float, float, float] = HOME) -> FloatArray:
    """Inverse of `geodetic`: NED offsets (m) from `home` of (M, 3) latitude, longitude (deg), altitude (m)."""
    lat0 = np.deg2rad(home[0])
    w = 1.0 - WGS84_E2 * np.sin(lat0) ** 2
    meridian, prime = WGS84_A * (1.0 - WGS84_E2) / w**1.5, WGS84_A / np.sqrt(w)
    north = np.deg2rad(lla[:, 0] - home[0]) * (meridian + home[2])
    east = np.deg2rad(lla[:, 1] - home[1]) * (prime + home[2]) * np.cos(lat0)
    return np.column_stack([north, east, home[2] - lla[:, 2]])


def window(t: npt.ArrayLike, windows: FloatArray, ramp_s: float = 1.0) -> FloatArray:
    """1 inside the windows (K, 2) s, 0 outside, with raised-cosine ramps of up to ramp_s inside each edge."""
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros_like(t)
    for t0, t1 in windows:
        ramp = min(ramp_s, 0.5 * (t1 - t0))
        x = np.clip(np.minimum(t - t0, t1 - t) / ramp, 0.0, 1.0) if ramp > 0 else np.zeros_like(t)
        out = np.maximum(out, 0.5 - 0.5 * np.cos(np.pi * x))
    return out
