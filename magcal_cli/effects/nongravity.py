"""`nongravity_acceleration`: in flight the accelerometer sees R^T (a_n - g_n), not just gravity (mismatch.md E4).

a_n comes from the log's position (GPS/EKF): converted to local NED metres (WGS84 radii), resampled on a uniform
grid and differentiated twice with a Savitzky-Golay filter whose gain stays within 2.5 % of 1 up to 0.6 Hz (a
cubic over 1 s passed only 93 % at 0.3 Hz, which biased kappa 3-6 % high on simulated flights). Both resamplings
are cubic splines: linear interpolation attenuates a 0.3 Hz sway by 0.2 % per step, which put kappa 1-4 of its std
high on simulated hand-held logs (0.02 % with splines). The term is kappa R^T a_n(t + delay), nested at kappa = 0:
kappa = 1 says the log's acceleration has the right scale, and delay_s is the position's latency.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.effects import spline
from magcal_cli.effects.base import (
    Effect,
    Inputs,
    Kinematics,
    NotTestable,
    Point,
    Target,
    Term,
    pick,
)
from magcal_cli.params import ParamBlock
from magcal_cli.streams import FloatArray, Kind, Stream

#: WGS84 semi-major axis (m) and first eccentricity squared (meridian and prime-vertical radii at the log's latitude)
WGS84_A, WGS84_E2 = 6378137.0, 6.69437999014e-3
#: grid rate (Hz), Savitzky-Golay window (s) and polynomial order for the second derivative of position: order 7
#: over 2 s passes 0.98 at 0.6 Hz and turns 1 cm of white position noise into 0.15 m/s^2
GRID_HZ = 10.0
WINDOW_S = 2.0
POLY_ORDER = 7
#: fixes further apart than this (s) leave a gap the acceleration is not interpolated across
MAX_GAP_S = 1.0
#: below this RMS (m/s^2) the vehicle hardly accelerates: nothing to test
MIN_RMS = 0.2
#: the position's latency (s): a GNSS fix describes where the receiver was some 0.1-0.3 s before it was logged
#: (ArduPilot's EKF assumes 220 ms, PX4's 110 ms). A prior N(0.15, 0.15) keeps it determined when kappa ~ 0 (it
#: exists only under the alternative); left out, a 0.2 s lag put log171's dips 3 deg below the WMM's
DELAY_PRIOR = (0.15, 0.15)
#: how far (s) beyond the filter's half window from an end or a gap the acceleration counts as unknown: three
#: prior stds of the delay from its prior mean, and the spline's ringing next to the zeroed stretch
KNOWN_MARGIN_S = 0.5


def acceleration_grid(pos: Stream) -> tuple[FloatArray, FloatArray]:
    """A uniform time grid (G,) s and the NED acceleration (G, 3) m/s^2 on it from a (lat deg, lon deg, alt m)
    stream; zero where it is not known (the ends, gaps between fixes)."""
    lat0, lon0, alt0 = np.median(pos.values, axis=0)
    w = 1.0 - WGS84_E2 * np.sin(np.deg2rad(lat0)) ** 2
    meridian, prime = WGS84_A * (1.0 - WGS84_E2) / w**1.5, WGS84_A / np.sqrt(w)
    # offsets from the median fix, not absolute arc lengths: the second-derivative filter's weights sum to zero
    # only to ~1e-12, which on 5e6 m of absolute northing left a constant 3 mm/s^2 that tilted D by 0.06 deg
    north = np.deg2rad(pos.values[:, 0] - lat0) * meridian
    east = np.deg2rad(pos.values[:, 1] - lon0) * prime * np.cos(np.deg2rad(lat0))
    down = alt0 - pos.values[:, 2]
    keep = np.concatenate([[True], np.diff(pos.t) > 0])             # a spline needs increasing times
    grid = np.arange(pos.t[0], pos.t[-1], 1.0 / GRID_HZ)
    ned = spline.cubic(pos.t[keep], np.stack([north, east, down], axis=1)[keep])(grid)
    window = max(POLY_ORDER + 2, int(WINDOW_S * GRID_HZ) | 1)
    if grid.size <= window:
        msg = f"the position ({pos.id}) is too short to differentiate"
        raise NotTestable(msg)
    acc = _second_derivative(ned, window, 1.0 / GRID_HZ)
    # a degree-7 fit extrapolates wildly at the ends and across gaps between fixes (17 m/s^2 at the first fix of
    # a real log): no acceleration is known there, so none is claimed (and `known` keeps those rows out)
    acc[~known(pos, grid, 0.0)] = 0.0
    return grid, acc


def _second_derivative(x: FloatArray, window: int, delta: float) -> FloatArray:
    """The Savitzky-Golay (POLY_ORDER, odd `window`) second derivative of x along axis 0: scipy.signal.savgol_filter's
    coefficients and convolution, so the same digits, except the first and last window // 2 rows, which that filter
    extrapolates and which are 0 here (`known` drops them anyway). scipy.signal is not imported: it brings
    scipy.stats, 0.2-1.2 s (issue 27)."""
    from scipy.linalg import lstsq
    from scipy.ndimage import convolve1d

    half = window // 2
    design = np.arange(-half, window - half, dtype=np.float64)[::-1] ** np.arange(POLY_ORDER + 1.0).reshape(-1, 1)
    unit = np.zeros(POLY_ORDER + 1)
    unit[2] = 2.0 / delta**2
    coeffs = lstsq(design, unit, cond=np.finfo(np.float64).eps * max(design.shape))[0]
    out: FloatArray = convolve1d(x, coeffs, axis=0, mode="constant")
    out[:half] = 0.0
    out[out.shape[0] - half:] = 0.0
    return out


def known(pos: Stream, t: FloatArray, margin: float) -> npt.NDArray[np.bool_]:
    """Whether the acceleration at times t (K,) is known from the fixes: inside their span, away from its ends
    and from gaps between fixes by the filter's half window plus `margin` (s)."""
    half = 0.5 * WINDOW_S + margin
    ok: npt.NDArray[np.bool_] = (t >= pos.t[0] + half) & (t <= pos.t[-1] - half)
    for i in np.flatnonzero(np.diff(pos.t) > MAX_GAP_S):
        ok &= (t < pos.t[i] - half) | (t > pos.t[i + 1] + half)
    return ok


def sample(grid: FloatArray, acc: FloatArray, t: FloatArray, deriv: int = 0) -> FloatArray:
    """The grid's acceleration (deriv 0) or jerk (deriv 1) at times t (K, 3) by a cubic spline; 0 off the grid."""
    return _on(spline.cubic(grid, acc), grid, t, deriv)


def _on(curve: spline.Spline, grid: FloatArray, t: FloatArray, deriv: int) -> FloatArray:
    """`curve` (the grid's acceleration) or its derivative at times t; 0 off the grid."""
    out: FloatArray = curve(t, deriv)
    out[(t < grid[0]) | (t > grid[-1])] = 0.0
    return out


def acceleration_ned(pos: Stream, t: FloatArray) -> FloatArray:
    """NED acceleration (K, 3) m/s^2 at times t from a (lat deg, lon deg, alt m) stream."""
    return sample(*acceleration_grid(pos), t)


def fixes(aux: tuple[Stream, ...]) -> Stream:
    """The log's position channel, its valid fixes only (NotTestable with fewer than 10)."""
    s = pick(aux, Kind.POSITION)
    finite = np.all(np.isfinite(s.values), axis=1)
    if finite.sum() < 10:
        msg = f"the position ({s.id}) has fewer than 10 valid fixes"
        raise NotTestable(msg)
    return Stream(s.kind, s.id, s.t[finite], s.values[finite], s.source, s.native_unit)


def rms(a_n: FloatArray) -> float:
    """RMS magnitude (m/s^2) of accelerations (K, 3)."""
    return float(np.sqrt(np.mean(np.sum(a_n**2, axis=1))))


def flying(aux: tuple[Stream, ...]) -> bool:
    """True when the log's position shows the vehicle accelerating (RMS >= MIN_RMS): a flight or a drive whose
    accelerometer is not a plumb line, and whose acceleration the log measured."""
    try:
        s = fixes(aux)
        return rms(acceleration_ned(s, s.t)) >= MIN_RMS
    except NotTestable:
        return False


class NonGravity(Effect):
    """The vehicle's own acceleration from the log's position."""

    id = "nongravity_acceleration"
    target = Target.ACCEL
    params = (ParamBlock("kappa", 1, "none", "non-gravity acceleration"), ParamBlock("delay_s", 1, "none"))
    units: ClassVar[dict[str, str]] = {"kappa": "1", "delay_s": "s", "sigma_a": "m/s^2"}
    channels = (Kind.POSITION,)
    limits: ClassVar[dict[str, float]] = {"kappa": 2.0, "delay_s": 1.0}
    separating_experiment = ("hand-held rotations with the vehicle kept still in position, or a flight with a logged GPS velocity")
    physics_left_out = ("The vehicle accelerated (manoeuvres, turns), so the accelerometer's vertical was not "
                        "gravity alone.")

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """The position's acceleration on its grid, in the magnetic NED frame; needs the vehicle to accelerate."""
        s = fixes(aux)
        grid, acc = acceleration_grid(s)
        acc = acc @ so3.exp([0.0, 0.0, declination])                     # true NED -> magnetic NED
        curve = spline.cubic(grid, acc)
        sigma = rms(_on(curve, grid, kin.t + DELAY_PRIOR[0], 0))
        if sigma < MIN_RMS:
            msg = f"the vehicle hardly accelerates (RMS {sigma:.2f} m/s^2 from {s.id})"
            raise NotTestable(msg)
        # where the fixes do not give the acceleration (before the first, after the last, across gaps) the term
        # says 0, which is a claim, not an absence of one: 1.7 m/s^2 of sway in the first and last second of a
        # simulated 2-minute log tilted D by 0.06 deg (chi^2 44 on 9 dof) once the accelerometer's level fell to
        # its sensor noise. Those accelerometer rows are left out, except where the IMU itself shows the vehicle
        # still (log171's 34 s on the ground before its first fix hold its best view of gravity); the margin
        # covers the delay's range
        inside = known(s, kin.t + DELAY_PRIOR[0], KNOWN_MARGIN_S)
        weight = (inside if kin.still is None else inside | kin.still).astype(np.float64)
        # "_" constants are the term's tables, not reported
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"weight": weight}, (s.id,),
                      {"source": f"position ({s.id}), differentiated twice", "sigma_a": sigma,
                       "_grid": grid, "_spline": curve})

    def weights(self, inp: Inputs) -> FloatArray | None:
        """The accelerometer rows where the fixes give the acceleration or the IMU shows the vehicle still."""
        return inp.channels["weight"]

    def start(self) -> FloatArray:
        """kappa = 0, the delay at its prior."""
        return np.array([0.0, DELAY_PRIOR[0]])

    def prior(self) -> tuple[FloatArray, FloatArray]:
        """Only the delay has a prior."""
        return np.array([0.0, DELAY_PRIOR[0]]), np.array([np.inf, DELAY_PRIOR[1]])

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """kappa R^T a_n(t + delay) (the fix stamped t was taken at t - delay); d/dkappa = R^T a_n;
        d/ddelay = kappa R^T j_n (the jerk); d/dphi = kappa [R^T a_n]x."""
        c = inp.constants
        when = inp.t + float(beta[1])
        # the spline is built once per binding (inputs): building it per linearisation cost 10 % of a diagnosis
        v = np.einsum("mji,mj->mi", at.rot, _on(c["_spline"], c["_grid"], when, 0))
        jerk = np.einsum("mji,mj->mi", at.rot, _on(c["_spline"], c["_grid"], when, 1))
        return Term(float(beta[0]) * v, np.stack([v, float(beta[0]) * jerk], axis=2), float(beta[0]) * so3.hat(v))

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """The field is not affected."""
        return t, y


EFFECT = NonGravity()
