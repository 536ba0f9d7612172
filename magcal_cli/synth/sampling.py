"""How the simulated sensors sample the continuous-time truth: their stamps and what each sample stands for.

IMU sample k is stamped t_k = k / rate. With Sampling.INSTANT (ROS sensor_msgs/Imu, ArduPilot IMU, CSV
exports) it is the value at t_k. With Sampling.PRECEDING (a delta-angle / delta-velocity IMU such as PX4's
sensor_combined, "the average ... over the last sampling period") it is the mean over [t_k - 1/rate, t_k]:
the gyro as the rotation vector of R(t_k - dt)^T R(t_k) over dt (what a coning-compensated integrator
reports), the accelerometer as the time mean of the instantaneous specific force (Gauss-Legendre quadrature).
The magnetometer has its own rate and phase, t_j = phase + j / mag_rate, and each reading is instantaneous.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np

from magcal_cli.errors import MagcalError
from magcal_cli.streams import FloatArray, Sampling
from magcal_cli.synth.motion import OVERSAMPLE

#: a real board stamps its magnetometer up to this long (s) after the IMU; the default phase is drawn below it
MAX_PHASE_S = 0.005
#: second entry of the seed of the magnetometer phase's generator (apart from the base simulation's draws)
PHASE_TAG = 0x9A5E
#: Gauss-Legendre nodes (on [0, 1]) and weights per sub-interval of a mean: exact for cubics
_NODES, _WEIGHTS = (np.polynomial.legendre.leggauss(2)[0] + 1.0) / 2.0, np.polynomial.legendre.leggauss(2)[1] / 2.0
#: quadrature nodes evaluated per block (bounds the memory of a long, fast log)
BLOCK = 1 << 17


class ImuTruth(Protocol):
    """What an ideal IMU measures, as functions of time (inject.Injected)."""

    def rate(self, t: FloatArray) -> FloatArray:
        """Instantaneous measured body rate (M, 3) rad/s."""
        ...

    def mean_rate(self, t0: FloatArray, t1: FloatArray) -> FloatArray:
        """Measured mean body rate (M, 3) rad/s over [t0, t1]."""
        ...

    def force(self, t: FloatArray) -> FloatArray:
        """Instantaneous measured specific force (M, 3) m/s^2."""
        ...


def check_rates(rate: float, mag_rate: float) -> None:
    """Both rates finite and > 0 Hz, else a MagcalError."""
    for name, value in (("rate", rate), ("mag_rate", mag_rate)):
        if not (math.isfinite(value) and value > 0):
            msg = f"simulate: {name} must be a finite number of Hz > 0, got {value:g}"
            raise MagcalError(msg)


def check_phase(phase: float, mag_rate: float) -> None:
    """0 <= phase < 1 / mag_rate, else a MagcalError that says the range."""
    if not (math.isfinite(phase) and 0.0 <= phase < 1.0 / mag_rate):
        msg = (f"simulate: mag_phase_s must be >= 0 and < 1/mag_rate = {1.0 / mag_rate:g} s (one magnetometer "
               f"period), got {phase:g}")
        raise MagcalError(msg)


def draw_phase(seed: int, mag_rate: float) -> float:
    """The default magnetometer phase: uniform in [0, min(MAX_PHASE_S, 1 / mag_rate)) from a generator of its own."""
    return float(np.random.default_rng([seed, PHASE_TAG]).uniform(0.0, min(MAX_PHASE_S, 1.0 / mag_rate)))


def imu_stamps(n: int, rate: float) -> FloatArray:
    """t_k = k / rate, k = 0 .. n-1 (s)."""
    out: FloatArray = np.arange(n) / rate
    return out


def mag_stamps(phase: float, mag_rate: float, end: float) -> FloatArray:
    """t_j = phase + j / mag_rate for every j with t_j <= end (s): inside the IMU log."""
    count = math.floor((end - phase) * mag_rate + 1e-9) + 1 if end >= phase else 0
    out: FloatArray = phase + np.arange(count) / mag_rate
    return out


def window_mean(f: Callable[[FloatArray], FloatArray], t: FloatArray, period: float,
                pieces: int = OVERSAMPLE) -> FloatArray:
    """The mean of f (M, 3) over [t - period, t] for each stamp t: two Gauss-Legendre nodes on each of `pieces`
    equal sub-intervals (with the fine grid's knots on their ends, each piece holds one smooth cubic span)."""
    offsets = ((np.arange(pieces)[:, None] + _NODES) / pieces - 1.0).ravel() * period
    weights = np.tile(_WEIGHTS / pieces, pieces)
    out = np.empty((len(t), 3))
    step = max(1, BLOCK // offsets.size)
    for i in range(0, len(t), step):                  # blocks of samples, not a loop per sample
        tt = t[i:i + step, None] + offsets
        out[i:i + step] = np.einsum("q,mqj->mj", weights, f(tt.ravel()).reshape(tt.shape + (3,)))
    return out


def check_sampling(sampling: Sampling) -> None:
    """INSTANT or PRECEDING, else a MagcalError: no real IMU stamps the start of the interval it averages."""
    if sampling not in (Sampling.INSTANT, Sampling.PRECEDING):
        msg = (f"simulate: imu_sampling {Sampling(sampling).value} is not simulated (no real IMU stamps the start "
               "of the interval it averages); use Sampling.INSTANT or Sampling.PRECEDING")
        raise MagcalError(msg)


def sample_imu(truth: ImuTruth, t: FloatArray, rate: float, sampling: Sampling) -> tuple[FloatArray, FloatArray]:
    """Noise-free gyro and accelerometer samples (N, 3) stamped t, as a `sampling` IMU at `rate` Hz reports them."""
    check_sampling(sampling)
    if sampling is Sampling.INSTANT:
        # a block of stamps at a time: each sample depends on its own stamp only, and the attitude (M, 3, 3) and
        # the temporaries of an hour at 400 Hz would take several hundred MB at once
        gyro, acc = np.empty((len(t), 3)), np.empty((len(t), 3))
        for i in range(0, len(t), BLOCK):
            gyro[i:i + BLOCK], acc[i:i + BLOCK] = truth.rate(t[i:i + BLOCK]), truth.force(t[i:i + BLOCK])
        return gyro, acc
    return truth.mean_rate(t - 1.0 / rate, t), window_mean(truth.force, t, 1.0 / rate)
