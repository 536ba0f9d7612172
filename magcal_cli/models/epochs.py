"""What every trajectory-based estimator (joint MAP, the EKF baselines) prepares alike: one magnetometer's epochs
with the accelerometer interpolated onto them, and the start noise levels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from magcal_cli.align import interpolate
from magcal_cli.detect import pooled_std
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.problem import Problem
from magcal_cli.streams import FloatArray, Stream

#: at most this many epochs per magnetometer, at most this epoch rate (else every k-th reading is used)
MAX_EPOCHS = 60_000
MAX_EPOCH_RATE_HZ = 100.0
MIN_EPOCHS = 50
#: without still segments the gyro noise starts at the quietest-window level divided by this
GYRO_START_DIVISOR = 10.0
#: typical bias magnitudes (m/s^2, rad/s) to compare bias uncertainties of different magnetometers' fits
BIAS_SCALE = np.array([0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3])


@dataclass(frozen=True, eq=False)
class Epochs:
    """One magnetometer's epochs: times (K,) s, readings / scale (K, 3), accelerometer interpolated onto them
    (K, 3) m/s^2 and the factor (K,) by which interpolation shrinks its noise std (not the correlation it gives
    epochs that share a sample: the fit leaves that to the time-clustered sandwich)."""

    mag_id: str
    t: FloatArray
    mag: FloatArray
    acc: FloatArray
    acc_factor: FloatArray
    scale: float
    notes: tuple[str, ...] = ()
    index: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))   # readings used
    #: the accelerometer samples j (K,) and weights w (K,) of the interpolation (1 - w) a_j + w a_j+1: epochs that
    #: share a sample share its noise (diagnose/ppc.py simulates it so); None: each epoch's own sample
    acc_at: tuple[npt.NDArray[np.int64], FloatArray] | None = None


@dataclass(frozen=True)
class Noise:
    """Per-sample standard deviations per axis: accelerometer (m/s^2), gyro (rad/s), magnetometer (scaled)."""

    acc: FloatArray
    gyr: FloatArray
    mag: FloatArray


def epochs_for(problem: Problem, mag: Stream, scale: float, max_epochs: int = MAX_EPOCHS) -> Epochs:
    """The magnetometer readings inside the IMU span, the accelerometer linearly interpolated onto them."""
    t_imu = problem.acc.t
    index = np.flatnonzero((mag.t >= t_imu[0]) & (mag.t <= t_imu[-1]))
    notes = []
    dt = float(np.median(np.diff(t_imu)))
    if index.size:
        index = index[np.concatenate([[True], np.diff(mag.t[index]) > 0.01 * dt])]
    t = mag.t[index]
    rate = 1.0 / float(np.median(np.diff(t))) if t.size > 1 else 0.0
    step = max(int(np.ceil(t.size / max_epochs)), int(np.ceil(rate / MAX_EPOCH_RATE_HZ))) if t.size else 1
    if step > 1:
        n = t.size
        index = index[::step]
        t = mag.t[index]
        notes.append(f"{mag.id}: {n} readings at {rate:.0f} Hz; used every {step}th ({t.size} epochs, "
                     f"{rate / step:.0f} Hz) to bound time and memory (the paper decimates too)")
    if t.size < MIN_EPOCHS:
        msg = (f"{problem.where}: {mag.id} has only {t.size} readings inside the IMU's time span (need >= "
               f"{MIN_EPOCHS}); check that both sensors were logged at the same time, or widen --start/--end")
        raise InsufficientDataError(msg)
    acc = interpolate(problem.acc, t)
    j = np.clip(np.searchsorted(t_imu, t, side="right") - 1, 0, t_imu.size - 2)
    w = np.clip((t - t_imu[j]) / (t_imu[j + 1] - t_imu[j]), 0.0, 1.0)
    factor = np.sqrt((1.0 - w) ** 2 + w**2)        # std of (1-w) a_j + w a_j+1 relative to one sample's
    return Epochs(mag.id, t, mag.xyz[index] / scale, acc, factor, scale, tuple(notes), index, (j, w))


def initial_noise(problem: Problem, mag: Stream, scale: float, fit_rms: float) -> Noise:
    """Start noise levels: IMU from its quietest windows, magnetometer from still data or the ellipsoid."""
    still = problem.still
    m = pooled_std(mag, still.segments) / scale if still.segments else np.full(3, fit_rms)
    m = np.where(np.isfinite(m), m, fit_rms)
    # without a still segment the quietest windows still contain motion: their gyro level is an upper bound.
    # The variance-component iteration converges fast from below and slowly from above, so start low.
    gyr = still.gyr_noise if still.segments else still.gyr_noise / GYRO_START_DIVISOR
    return Noise(np.maximum(still.acc_noise, 1e-4), np.maximum(gyr, 1e-6), np.maximum(m, 1e-5))
