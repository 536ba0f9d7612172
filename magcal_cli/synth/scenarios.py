"""The `multirotor` and `rover` scenarios: attitude plus a translation that the attitude makes physical.

Conventions: NED navigation frame, FRD body axes (x forward, y right, z down, as PX4 and ArduPilot log them),
R = Rz(yaw) Ry(pitch) Rx(roll) body->NED. Both return their truth on the fine grid (synth/motion.py): attitude
knots at OVERSAMPLE times the IMU rate and a `Motion`, a continuous NED acceleration whose double integral is
the logged position, so the accelerometer's f(t) = R(t)^T (a_n(t) - g_n) and the position agree at every
instant. A multirotor's acceleration comes from its thrust axis: a_n = R (-k v_b,x, -k v_b,y, -T) + g_n (rotor
drag k, thrust T per unit mass), so in a steady turn the accelerometer's "down" is the thrust axis, not
gravity; its controller runs at the IMU rate (it integrates its state step by step) and its attitude and
acceleration are spread smoothly onto the fine grid. A rover moves along its body x axis over uneven ground:
v_n = v R e_x, so a_n = v' R e_x + v R (w x e_x) (centripetal v w); it is generated on the fine grid directly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.align import columns
from magcal_cli.models.accel import G
from magcal_cli.streams import FloatArray
from magcal_cli.synth.motion import (
    BLOCK,
    OVERSAMPLE,
    Motion,
    Trajectory,
    fine_count,
    fine_times,
    smoother,
)

Intervals = tuple[tuple[float, float], ...]

#: shortest durations (s) the phases fit in: ground, take-off, flight, landing, ground; park, drive, park
MIN_DURATION = {"multirotor": 90.0, "rover": 60.0}
#: rotor drag (1/s): the horizontal body-frame specific force is -k v_b (bounds the speed at g tan(tilt) / k)
ROTOR_DRAG = 0.35
#: roll and pitch of a flying multirotor stay within this (deg): a tanh limit of the commanded tilt
TILT_LIMIT_DEG = 22.0
#: roll and pitch of the rover on its terrain: std and limit (deg)
TERRAIN_STD_DEG, TERRAIN_LIMIT_DEG = 2.0, 5.0
#: multirotor phases (s): on the ground, take-off climb, descent, on the ground after touchdown (braking first)
GROUND_S, TAKEOFF_S, DESCENT_S, LANDED_S, BRAKE_S = 10.0, 6.0, 8.0, 12.0, 1.0
#: horizontal position hold (natural frequency 0.5 rad/s, damping 0.9) and altitude hold (2 rad/s, 0.9)
HOLD_GAINS, ALTITUDE_GAINS = (0.25, 0.9), (4.0, 3.6)
#: rover: parked at both ends (s), cruise speeds (m/s), circle radii (m), the stop leg's ramps and hold (s)
PARK_S, CRUISE_MPS, RADIUS_M, STOP_RAMP_S, STOP_HOLD_S = 10.0, (2.5, 4.0), (6.0, 14.0), 3.0, 4.0


class Scenario(NamedTuple):
    """A scenario's truth: the attitude, its translation (None: a pure rotation), still intervals (s) and the
    intervals (s) in which motors run at flight speed (take-off to touchdown; empty: no motors).

    A still interval runs from the first to the last IMU stamp of a span in which the body is at rest, with one
    IMU period of margin where the smoothing onto the fine grid reaches into the span from a move.
    """

    trajectory: Trajectory
    motion: Motion | None
    still: Intervals
    motors: Intervals = ()


class Limits(NamedTuple):
    """The multirotor's flight envelope: the tilt (deg, the body z axis from vertical) and the horizontal NED
    acceleration (m/s^2). Both None: the original controller (roll and pitch each softly within
    TILT_LIMIT_DEG); either given: the limited one (tilt within `tilt_deg`, default TILT_LIMIT_DEG)."""

    tilt_deg: float | None = None
    accel_mps2: float | None = None

    @property
    def active(self) -> bool:
        """Whether the limited controller flies."""
        return self.tilt_deg is not None or self.accel_mps2 is not None

    def orbit_cap(self, radius: float) -> float:
        """The largest centripetal acceleration (m/s^2) of an orbit of `radius` (m) that leaves room to manoeuvre:
        60 % of the acceleration limit, and a thrust (centripetal plus the drag k v at v = sqrt(a_c r)) that
        tilts at most 70 % of the tilt limit."""
        cap = math.inf if self.accel_mps2 is None else 0.6 * self.accel_mps2
        h = 0.7 * G * math.tan(math.radians(self.tilt_deg if self.tilt_deg is not None else TILT_LIMIT_DEG))
        k2r = ROTOR_DRAG**2 * radius
        return min(cap, 0.5 * (math.sqrt(k2r * k2r + 4.0 * h * h) - k2r))


#: the original flight: no limits beyond roll and pitch each softly within TILT_LIMIT_DEG
NO_LIMITS = Limits()


def min_jerk(s: npt.ArrayLike) -> FloatArray:
    """Smooth 0 -> 1 profile with zero velocity and acceleration at both ends (s clipped to [0, 1])."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    out: FloatArray = s**3 * (10.0 - 15.0 * s + 6.0 * s * s)
    return out


def plateau(s: npt.ArrayLike, ramp: float = 0.15) -> FloatArray:
    """0 -> 1 at a constant rate between raised-cosine ramps of `ramp` at both ends (s clipped to [0, 1])."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)

    def up(x: FloatArray) -> FloatArray:
        out: FloatArray = x / 2.0 - ramp / (2.0 * np.pi) * np.sin(np.pi * np.minimum(x, ramp) / ramp)
        return out

    q = np.where(s < ramp, up(s), np.where(s > 1.0 - ramp, 1.0 - ramp - up(1.0 - s), s - ramp / 2.0))
    out: FloatArray = q / (1.0 - ramp)
    return out


def band(rng: np.random.Generator, n: int, fs: float, lo: float, hi: float, std: float,
         oversample: int = 1) -> FloatArray:
    """n samples at fs Hz of Gaussian noise band-limited to lo..hi Hz (flat spectrum, random phases), scaled to std.

    With `oversample` the same draw comes at fs * oversample Hz ((n - 1) * oversample + 1 samples): the
    band-limited signal between the samples, exactly (its spectrum zero-padded), equal to them at every fs sample.
    """
    f = np.fft.rfftfreq(n, 1.0 / fs)
    spec = (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * ((f >= lo) & (f <= hi))
    sd = float(np.std(np.fft.irfft(spec, n)))
    x = np.fft.irfft(spec, n * oversample)[:(n - 1) * oversample + 1] * oversample
    out: FloatArray = x * (std / sd) if sd > 0 else x
    return out


def _soft(x: FloatArray, limit: float) -> FloatArray:
    """limit tanh(x / limit): linear for small x, never beyond +-limit."""
    out: FloatArray = limit * np.tanh(x / limit)
    return out


def _still(a: float, b: float, rate: float) -> tuple[float, float]:
    """First and last IMU stamps in [a, b], keeping one IMU period of margin at the end."""
    return math.ceil(a * rate - 1e-9) / rate, (math.floor(b * rate + 1e-9) - 1) / rate


def _slots(rng: np.random.Generator, span: tuple[float, float], lengths: list[float],
           busy: list[tuple[float, float]]) -> list[float]:
    """Start times of non-overlapping windows of `lengths` in span, clear of `busy` (2 s gaps), drawn at random."""
    starts: list[float] = []
    taken = list(busy)
    for length in lengths:
        for _ in range(200):
            t0 = rng.uniform(span[0], span[1] - length)
            if all(t0 + length + 2.0 < a or t0 > b + 2.0 for a, b in taken):
                starts.append(t0)
                taken.append((t0, t0 + length))
                break
    return starts


def pulse(s: FloatArray) -> FloatArray:
    """Tilt one way then back (a dash and a stop) over s in [0, 1], peak 1, zero rate at both ends."""
    inside = (s > 0.0) & (s < 1.0)
    out: FloatArray = np.where(inside, np.sin(2 * np.pi * s) * np.sin(np.pi * s) ** 2, 0.0) / (3 * np.sqrt(3) / 8)
    return out


def _rotation(roll: float, pitch: float, yaw: float) -> tuple[float, ...]:
    """Rz(yaw) Ry(pitch) Rx(roll) row by row (R00, R01, ..., R22), as so3.from_rpy builds it."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
            sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
            -sp, cp * sr, cp * cr)


def _flight_plan(rng: np.random.Generator, t: FloatArray, duration: float,
                 limits: Limits = NO_LIMITS) -> tuple[FloatArray, ...]:
    """Commands of the flight: hold target r (N+1, 2) NED m, altitude h (m), yaw, pilot roll and pitch (rad).

    Pilot tilt: band-limited 0.05-0.5 Hz noise (std 5 deg) plus dash-and-stop pulses (12-18 deg, 1.5-3 s).
    Yaw: slow wander (0.005-0.05 Hz, std 25 deg), pirouettes (360 deg at 45-90 deg/s on average), and an orbit
    of one or two laps (radius 15-30 m, centripetal 1.2-2.5 m/s^2, at most `limits.orbit_cap` when limited)
    with the nose along the track.
    """
    rate = 1.0 / float(t[1] - t[0])
    n1 = len(t)
    t_to, t_td = GROUND_S, duration - LANDED_S
    f0, f1 = t_to + TAKEOFF_S + 2.0, t_td - DESCENT_S - 12.0      # pilot activity; home 12 s before descent
    gate = min_jerk((t - f0) / 5.0) * min_jerk((f1 - t) / 5.0)
    span = (f0 + 5.0, f1 - 5.0)
    h = (rng.uniform(10.0, 20.0) + _soft(band(rng, n1, rate, 0.005, 0.05, 2.5), 6.0)) \
        * min_jerk((t - t_to) / TAKEOFF_S) * min_jerk((t_td - t) / DESCENT_S)
    home = min_jerk((t - t_to - 2.0) / 10.0) * min_jerk((t_td - DESCENT_S - t) / 12.0)
    r = np.column_stack([band(rng, n1, rate, 0.003, 0.02, 15.0), band(rng, n1, rate, 0.003, 0.02, 15.0)])
    pilot = gate[:, None] * np.column_stack([band(rng, n1, rate, 0.05, 0.5, np.deg2rad(5.0)),
                                             band(rng, n1, rate, 0.05, 0.5, np.deg2rad(5.0))])
    lengths = list(rng.uniform(1.5, 3.0, max(2, round(4 * (f1 - f0) / 220.0))))
    for t0, length in zip(_slots(rng, span, lengths, []), lengths, strict=False):
        beta, amp = rng.uniform(0.0, 2 * np.pi), np.deg2rad(rng.uniform(12.0, 18.0))
        pilot += amp * pulse((t - t0) / length)[:, None] * np.array([np.cos(beta), np.sin(beta)])
    yaw = rng.uniform(-np.pi, np.pi) + gate * band(rng, n1, rate, 0.005, 0.05, np.deg2rad(25.0))
    radius, a_c = rng.uniform(15.0, 30.0), rng.uniform(1.2, 2.5)
    if limits.active:
        a_c = min(a_c, limits.orbit_cap(radius))
    lap = 2 * np.pi * radius / np.sqrt(a_c * radius) / (1.0 - 0.15)     # plateau speed sqrt(a_c radius)
    laps = 2 if 2 * lap < (span[1] - span[0]) / 2 else 1 if lap < (span[1] - span[0]) / 2 else 0
    orbit = _slots(rng, span, [laps * lap], []) if laps else []
    lengths = [360.0 / rng.uniform(45.0, 90.0) for _ in range(max(1, round(3 * (f1 - f0) / 220.0)))]
    for t0, length in zip(_slots(rng, span, lengths, [(o, o + laps * lap) for o in orbit]), lengths, strict=False):
        yaw = yaw + rng.choice([-1.0, 1.0]) * 2 * np.pi * min_jerk((t - t0) / length)
    for t0 in orbit:
        sign = rng.choice([-1.0, 1.0])
        turn = sign * 2 * np.pi * laps * plateau((t - t0) / (laps * lap))
        phi0 = float(np.interp(t0, t, yaw)) - sign * np.pi / 2     # the track starts along the nose
        r = r + radius * np.column_stack([np.cos(phi0 + turn) - np.cos(phi0), np.sin(phi0 + turn) - np.sin(phi0)])
        yaw = yaw + turn
    return r * home[:, None], h, yaw, pilot[:, 0], pilot[:, 1]


def _thrust_acceleration(roll: float, pitch: float, yaw: float, v: list[float], az_cmd: float) -> list[float]:
    """a_n = R (-k v_b,x, -k v_b,y, -T) + g_n with the thrust T that gives the vertical acceleration az_cmd."""
    m = _rotation(roll, pitch, yaw)
    fx = -ROTOR_DRAG * (m[0] * v[0] + m[3] * v[1] + m[6] * v[2])       # rotor drag on v_b,x and v_b,y
    fy = -ROTOR_DRAG * (m[1] * v[0] + m[4] * v[1] + m[7] * v[2])
    thrust = (m[6] * fx + m[7] * fy + G - az_cmd) / m[8]                # the thrust that gives az_cmd
    return [m[0] * fx + m[1] * fy - m[2] * thrust, m[3] * fx + m[4] * fy - m[5] * thrust,
            m[6] * fx + m[7] * fy - m[8] * thrust + G]


def _limited(a_h: tuple[float, float], yaw: float, pilot: tuple[float, float], ww: float,
             pad: tuple[float, float], v: list[float], az_cmd: float, limits: Limits) -> tuple[float, float]:
    """Roll and pitch of the limited controller: the hold's horizontal acceleration a_h plus the pilot's tilt (as
    the acceleration it asks for), saturated softly at the acceleration limit; the tilt that gives it (drag
    compensated), its magnitude limited softly (tanh); blended with the pad attitude by the authority ww.
    With an acceleration limit, a few fixed-point steps on the exact acceleration of the thrust axis make the
    realised acceleration the saturated one (the tilt's small-angle inversion is only approximate)."""
    c, s = math.cos(yaw), math.sin(yaw)
    fwd, right = -G * math.tan(pilot[1]), G * math.tan(pilot[0])
    ax, ay = a_h[0] + c * fwd - s * right, a_h[1] + s * fwd + c * right
    if limits.accel_mps2 is not None and (norm := math.hypot(ax, ay)) > 0.0:
        f = limits.accel_mps2 * math.tanh(norm / limits.accel_mps2) / norm
        ax, ay = ax * f, ay * f
    lim = math.radians(limits.tilt_deg if limits.tilt_deg is not None else TILT_LIMIT_DEG)
    tx, ty = ax + ROTOR_DRAG * v[0], ay + ROTOR_DRAG * v[1]
    roll, pitch = pad
    for _ in range(8):
        roll, pitch = math.atan((c * ty - s * tx) / G), -math.atan((c * tx + s * ty) / G)
        if (q := math.hypot(roll, pitch)) > 0.0:
            f = lim * math.tanh(q / lim) / q
            roll, pitch = roll * f, pitch * f
        roll, pitch = ww * roll + (1.0 - ww) * pad[0], ww * pitch + (1.0 - ww) * pad[1]
        if limits.accel_mps2 is None:
            break
        a = _thrust_acceleration(roll, pitch, yaw, v, az_cmd)
        ex, ey = ax - a[0], ay - a[1]
        if math.hypot(ex, ey) < 1e-9:
            break
        tx, ty = tx + ex, ty + ey
    return roll, pitch


def multirotor(rng: np.random.Generator, rate: float, duration: float, limits: Limits = NO_LIMITS) -> Scenario:
    """10 s on the ground, take-off, a flight in position hold with the pilot's tilt, pirouettes and an orbit
    on top, descent back home, 12 s on the ground (the first second brakes what speed is left).

    The altitude and horizontal position holds act through the thrust and the tilt of the thrust axis only:
    a_n = R (-k v_b,x, -k v_b,y, -T) + g_n, integrated step by step (the tilt depends on the state). `limits`
    bounds the tilt and the horizontal acceleration (`Limits`).
    """
    n, dt = round(duration * rate), 1.0 / rate
    t = np.arange(n + 1, dtype=np.float64) * dt
    r, h, yaw, pilot_roll, pilot_pitch = _flight_plan(rng, t, duration, limits)
    r_d, z_d = np.gradient(r, dt, axis=0), np.gradient(-h, dt)
    pads = np.deg2rad(rng.uniform(-1.0, 1.0, (2, 2))).tolist()   # roll, pitch on the pad before and after
    t_to, t_td = GROUND_S, duration - LANDED_S
    k_td = math.ceil(t_td * rate - 1e-9)
    keep = 1.0 - min_jerk((t[1:] - k_td * dt) / BRAKE_S)
    w = min_jerk((t - t_to) / 3.0) * min_jerk((t_td - t) / 3.0)   # authority of the tilt commands
    lim, (kp, kd), (kpz, kdz) = np.deg2rad(TILT_LIMIT_DEG), HOLD_GAINS, ALTITUDE_GAINS
    cols = (r[:, 0], r[:, 1], r_d[:, 0], r_d[:, 1], np.gradient(r_d[:, 0], dt), np.gradient(r_d[:, 1], dt),
            -h, z_d, np.gradient(z_d, dt), yaw, pilot_roll, pilot_pitch, w)
    p, v = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    v_td: list[float] = []
    rolls, pitches, acc = np.zeros(n + 1), np.zeros(n + 1), np.zeros((n, 3))
    # the controller steps in Python floats, a block of the references at a time (whole lists of an hour at
    # 400 Hz would take 0.6 GB)
    for base in range(0, n + 1, BLOCK):
        rn, re, vn_r, ve_r, an_r, ae_r, z_r, vz_r, az_r, psi, p_roll, p_pitch, ww = (
            c[base:base + BLOCK].tolist() for c in cols)
        for k in range(base, min(base + BLOCK, n + 1)):
            j = k - base
            air = t_to <= k * dt < t_td
            roll, pitch = pads[int(k * dt > duration / 2)]
            az_cmd = 0.0
            if air:
                az_cmd = az_r[j] + kpz * (z_r[j] - p[2]) + kdz * (vz_r[j] - v[2])
                ax = an_r[j] + kp * (rn[j] - p[0]) + kd * (vn_r[j] - v[0])
                ay = ae_r[j] + kp * (re[j] - p[1]) + kd * (ve_r[j] - v[1])
                if limits.active:
                    roll, pitch = _limited((ax, ay), psi[j], (p_roll[j], p_pitch[j]), ww[j], (roll, pitch), v, az_cmd,
                                           limits)
                else:
                    ax, ay = ax + ROTOR_DRAG * v[0], ay + ROTOR_DRAG * v[1]
                    c, s = math.cos(psi[j]), math.sin(psi[j])
                    cmd_roll = math.atan((c * ay - s * ax) / G) + p_roll[j]
                    cmd_pitch = -math.atan((c * ax + s * ay) / G) + p_pitch[j]
                    roll = ww[j] * lim * math.tanh(cmd_roll / lim) + (1.0 - ww[j]) * roll
                    pitch = ww[j] * lim * math.tanh(cmd_pitch / lim) + (1.0 - ww[j]) * pitch
            rolls[k], pitches[k] = roll, pitch
            if k == n:
                break
            if air:
                a = _thrust_acceleration(roll, pitch, psi[j], v, az_cmd)
            elif k >= k_td:                                                     # on the pad: brake what is left
                v_td = v_td or list(v)
                a = [(vi * keep[k] - v[i]) / dt for i, vi in enumerate(v_td)]
            else:
                a = [0.0, 0.0, 0.0]
            for i in range(3):
                p[i] += v[i] * dt + 0.5 * a[i] * dt * dt
                v[i] += a[i] * dt
            acc[k] = a
    still = (_still(0.0, t_to, rate), _still(k_td * dt + BRAKE_S + 1.0, duration, rate))
    count = fine_count(n * dt, rate)
    rpy = smoother(np.column_stack([rolls, pitches, yaw]), dt)
    mid = t[:-1] + 0.5 * dt

    # the fine grid is made a block at a time where it is used (an hour at 400 Hz is 14 M knots, 1 GB each for
    # the attitude and its coefficients): the knot times exactly those of fine_times
    def rot(idx: npt.NDArray[np.int64]) -> FloatArray:
        return so3.from_rpy(rpy(idx / (rate * OVERSAMPLE)))

    # the acceleration the controller held over [t_k, t_k+1), continuous through the interval midpoints (same
    # integral over the log, so the vehicle still comes to rest)
    def a_n(idx: npt.NDArray[np.int64]) -> FloatArray:
        return columns(idx / (rate * OVERSAMPLE), mid, acc)

    dtf = dt / OVERSAMPLE
    return Scenario(Trajectory(rot, count, dtf), Motion.from_source(a_n, count, dtf), still, ((t_to, t_td),))


def _terrain(rng: np.random.Generator, s: FloatArray) -> FloatArray:
    """Roll or pitch (rad) over distance s (m): six waves of 4-40 m, std TERRAIN_STD_DEG, limited softly."""
    wavelength, phase, amp = rng.uniform(4.0, 40.0, 6), rng.uniform(0.0, 2 * np.pi, 6), rng.standard_normal(6)
    amp *= np.deg2rad(TERRAIN_STD_DEG) / np.sqrt(np.sum(amp**2) / 2.0)
    return _soft(np.sin(2 * np.pi * s[:, None] / wavelength + phase) @ amp, np.deg2rad(TERRAIN_LIMIT_DEG))


def rover(rng: np.random.Generator, rate: float, duration: float) -> Scenario:
    """Parked 10 s, a drive of straights, full circles and figure-eights (two opposite circles) with one stop
    of 4 s half-way, parked 10 s. Speed: cruise 2.5-4 m/s +- 12 % (0.01-0.1 Hz); no side slip."""
    n, dt = round(duration * rate), 1.0 / rate
    t = fine_times(n * dt, rate)
    dtf = dt / OVERSAMPLE
    t_a, t_b = PARK_S, duration - PARK_S
    v0 = rng.uniform(*CRUISE_MPS)
    at, end, half = t_a + rng.uniform(8.0, 14.0), t_b - rng.uniform(8.0, 12.0), t_a + 0.45 * (t_b - t_a)
    yaw = np.full(t.size, rng.uniform(-np.pi, np.pi))
    speed = v0 * (1.0 + band(rng, n + 1, rate, 0.01, 0.1, 0.12, OVERSAMPLE)) * min_jerk((t - t_a) / 4.0) \
        * min_jerk((t_b - t) / 4.0)
    stops: list[float] = []
    while True:
        kind = "stop" if not stops and at > half else ("circle", "eight", "straight")[rng.choice(3, p=(0.4, 0.35, 0.25))]
        lap = 2 * np.pi * rng.uniform(*RADIUS_M) / (v0 * (1.0 - 0.15))   # radius at cruise on the plateau
        length = {"circle": lap, "eight": 2 * lap, "straight": rng.uniform(4.0, 12.0),
                  "stop": 2 * STOP_RAMP_S + STOP_HOLD_S}[kind]
        if at + length > end:
            break
        sign = rng.choice([-1.0, 1.0])
        if kind == "stop":
            stops.append(at)
            hold = at + STOP_RAMP_S
            speed *= min_jerk((hold - t) / STOP_RAMP_S) + min_jerk((t - hold - STOP_HOLD_S) / STOP_RAMP_S)
        for k in range({"circle": 1, "eight": 2}.get(kind, 0)):
            yaw += (-1) ** k * sign * 2 * np.pi * plateau((t - at - k * lap) / lap)
        at += length
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dtf)])
    rot = so3.from_rpy(np.column_stack([_terrain(rng, dist), _terrain(rng, dist), yaw]))
    v_n = speed[:, None] * rot[:, :, 0]
    # a_n is the central difference of v_n on the fine grid, so it sees a stop's edge one fine step away: the
    # still intervals start one IMU period after the speed reaches zero
    still = (_still(0.0, t_a, rate),
             *(_still(s + STOP_RAMP_S + dt, s + STOP_RAMP_S + STOP_HOLD_S, rate) for s in stops),
             _still(t_b + dt, duration, rate))
    a_n = np.gradient(v_n, dtf, axis=0, edge_order=2)
    return Scenario(Trajectory.from_knots(rot, dtf), Motion.from_acceleration(a_n, dtf, v_n[0]), still)
