"""The pure-rotation scenarios `paper` (methods.md section 5) and `handheld`, as attitude knots on the fine grid.

Both return a `Scenario` whose trajectory is defined at every instant (synth/motion.py) with knots at
OVERSAMPLE times the IMU rate; the sensors sample it later (synth/sampling.py).
"""

from __future__ import annotations

import numpy as np

from magcal_cli import so3
from magcal_cli.streams import FloatArray
from magcal_cli.synth.motion import OVERSAMPLE, Trajectory, fine_times, smooth
from magcal_cli.synth.scenarios import Scenario, min_jerk

#: a level ROS (FLU) body in NED: x north, y west, z up
FLU_LEVEL = np.diag([1.0, -1.0, -1.0])
#: the paper's random rate component: std per axis (rad/s) and its band edge as a fraction of the IMU rate
PAPER_RATE_STD, PAPER_BAND = 0.05, 1.0 / 8.0


def band_limited(x: FloatArray, cutoff: float, fs: float, std: float) -> FloatArray:
    """Columns of x (N, k), sampled at fs Hz, without their content above `cutoff` Hz (a zero-phase FFT low-pass:
    nothing above the cut-off, nothing below it changed or delayed), each rescaled to `std`."""
    spec = np.fft.rfft(x, axis=0)
    spec[np.fft.rfftfreq(len(x), 1.0 / fs) > cutoff] = 0.0
    y = np.fft.irfft(spec, len(x), axis=0)
    sd = np.std(y, axis=0)
    out: FloatArray = y * np.where(sd > 0, std / np.where(sd > 0, sd, 1.0), 0.0)
    return out


def paper(rng: np.random.Generator, rate: float, duration: float | None) -> Scenario:
    """From I, at body rates v + 0.05 randn(3) rad/s for 2 pi/|v| s each, v in 0.1 {x, y, z, x+y, x+z, y+z}.

    The random part is drawn once per IMU sample (as in the authors' simulate.m, so its statistics do not depend
    on the fine grid), at the IMU stamps and at the end, then band-limited to rate / 8 (`band_limited`, std kept
    at 0.05 rad/s per axis: a real gyro's anti-aliasing filter never passes a rate with content up to Nyquist,
    and docs/simulate-scenarios.md says why), and spread smoothly onto the fine grid (motion.smooth); the
    knots integrate it at the midpoints of the fine intervals.
    """
    axes = 0.1 * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1]], dtype=float)
    spans = 2.0 * np.pi / np.linalg.norm(axes, axis=1)
    if duration is not None:
        spans = np.full(6, duration / 6.0)
    counts = np.ceil(spans * rate).astype(int)
    counts[-1] += 1                                   # the draw at the end of the last IMU period
    draws = PAPER_RATE_STD * rng.standard_normal((counts.sum(), 3))
    omega = np.repeat(axes, counts, axis=0) + band_limited(draws, PAPER_BAND * rate, rate, PAPER_RATE_STD)
    dt = 1.0 / (rate * OVERSAMPLE)
    mid = (np.arange((len(omega) - 1) * OVERSAMPLE) + 0.5) * dt
    steps = so3.exp(smooth(omega, 1.0 / rate, mid) * dt)
    knots = np.concatenate([np.eye(3)[None], so3.cumulative_product(steps)])
    return Scenario(Trajectory.from_knots(knots, dt), None, ())


def paper_trajectory(rng: np.random.Generator, rate: float, duration: float | None) -> FloatArray:
    """The `paper` attitude at the IMU stamps k / rate, k = 0 .. N (N + 1 rotations (N+1, 3, 3)), for callers that
    build their own records from rotations."""
    traj = paper(rng, rate, duration).trajectory
    return traj.at(np.arange(round(traj.end * rate) + 1) / rate)


def _pose_with_up(up_body: FloatArray, yaw: float) -> FloatArray:
    """A body->NED rotation that maps the body vector `up_body` to up, then turned by `yaw` about down."""
    up = up_body / np.linalg.norm(up_body)
    axis = np.cross(up, [0.0, 0.0, -1.0])
    s, c = float(np.linalg.norm(axis)), float(-up[2])
    if s < 1e-9:
        align = np.eye(3) if c > 0 else so3.exp([np.pi, 0.0, 0.0])
    else:
        align = so3.exp(axis / s * np.arctan2(s, c))
    return so3.exp([0.0, 0.0, yaw]) @ align


def handheld(rng: np.random.Generator, rate: float, duration: float | None) -> Scenario:
    """10 s still, then moves about varying axes between >= 12 still poses of 2-4 s, then 10 s still.

    The poses point the body's up direction at the 6 faces and 8 corners of a cube (plus random ones), each
    with a random heading, in random order. Holds start and end on IMU stamps; a move from pose P to Q takes
    R(s) = P Exp(mj(s) Log(P^T Q)) Exp(sin(pi mj(s)) wobble), mj the min-jerk profile (smooth at both ends).
    """
    n_poses = 16 if duration is None else max(12, int((duration - 20.0) / 6.0))
    ups = np.concatenate([np.eye(3), -np.eye(3), np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T])
    extra = rng.standard_normal((max(0, n_poses - len(ups)), 3))
    ups = np.concatenate([ups, extra])[rng.permutation(max(n_poses, len(ups)))][:n_poses]
    start = FLU_LEVEL @ so3.exp([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    poses = [start] + [_pose_with_up(u_, rng.uniform(-np.pi, np.pi)) for u_ in ups] + [start]
    holds = [10.0] + list(rng.uniform(2.0, 4.0, n_poses)) + [10.0]
    still, moves, t = [], [], 0.0
    for k, (pose, hold) in enumerate(zip(poses, holds, strict=True)):
        n = int(round(hold * rate))
        still.append((t, t + (n - 1) / rate))
        t += n / rate
        if k + 1 < len(poses):
            n_move = int(round(rng.uniform(2.0, 3.5) * rate))
            moves.append(((n_move + 1) / rate, so3.log(pose.T @ poses[k + 1]), rng.standard_normal(3) * 0.4))
            t += n_move / rate
    ends = np.array([b for _, b in still])
    length = np.array([m[0] for m in moves] + [np.inf])
    phi = np.array([m[1] for m in moves] + [np.zeros(3)])
    wobble = np.array([m[2] for m in moves] + [np.zeros(3)])
    tf = fine_times(float(ends[-1]), rate)
    seg = np.searchsorted(np.array([a for a, _ in still]), tf + 1e-9, side="right") - 1     # the hold before t
    s = min_jerk((tf - ends[seg]) / length[seg])[:, None]
    knots = np.array(poses)[seg] @ so3.exp(s * phi[seg]) @ so3.exp(np.sin(np.pi * s) * wobble[seg])
    return Scenario(Trajectory.from_knots(knots, 1.0 / (rate * OVERSAMPLE)), None, tuple(still))
