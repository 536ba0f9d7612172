"""The simulator's auxiliary truth as functions of time: power system, warm-up, sway, geodesy and windows.

Built from seeded generators only; no estimator's equations are reused. The attitude and the scenario's own
translation are in synth/motion.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli.streams import FloatArray

#: WGS84 semi-major axis (m) and first eccentricity squared
WGS84_A, WGS84_E2 = 6378137.0, 6.69437999014e-3
#: where the simulated vehicle flies: PX4 SITL's home (deg, deg, m above MSL), as the .bin writer logs it
HOME = (47.397742, 8.545594, 488.0)
#: rate (Hz) of the grid the auxiliary signals are defined on (linear between its samples)
SIGNAL_RATE_HZ = 200.0
#: seconds the signal grids extend beyond the log at both ends (room for a time offset)
MARGIN_S = 2.0


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
