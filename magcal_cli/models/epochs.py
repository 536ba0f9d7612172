"""What every trajectory-based estimator (joint MAP, the EKF baselines) prepares alike: one magnetometer's epochs
with the accelerometer interpolated onto them, and the start noise levels.

More readings than MAX_EPOCHS (or faster than MAX_EPOCH_RATE_HZ) are kept in groups for the joint MAP (of at most
GROUP_MAX readings while the epochs stay below GROUPED_EPOCHS_FACTOR x MAX_EPOCHS): a state at
each group's first reading, the group's mean reading as its observation, and the gyro preintegrated to every
reading of the group to say what that mean predicts (gyro.Within, mag.mag_factor, accel.accel_factor). The EKF
baselines take every k-th reading.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from magcal_cli.align import interpolate
from magcal_cli.detect import pooled_std
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.problem import Problem
from magcal_cli.streams import FloatArray, Stream

#: at most this many epochs per magnetometer, at most this epoch rate (else k readings per epoch, or every k-th)
MAX_EPOCHS = 60_000
MAX_EPOCH_RATE_HZ = 100.0
#: readings averaged per epoch are at most GROUP_MAX until the epochs reach GROUPED_EPOCHS_FACTOR x MAX_EPOCHS:
#: longer groups of a flight's readings, whose residuals are correlated over tens of ms, moved the 120-min fit 0.34
#: std from a fit on every reading (groups of 3: 0.10), and 120 000 states fit the 1 GB a two-hour flight is given
#: (issue 39)
GROUP_MAX = 3
GROUPED_EPOCHS_FACTOR = 2
MIN_EPOCHS = 50
#: without still segments the gyro noise starts at the quietest-window level divided by this
GYRO_START_DIVISOR = 10.0
#: typical bias magnitudes (m/s^2, rad/s) to compare bias uncertainties of different magnetometers' fits
BIAS_SCALE = np.array([0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3])
#: readings further apart than this many median periods start a new group: the gyro ties a group's readings
#: rigidly, which is no model across a dropout
GROUP_GAP_PERIODS = 4.0


@dataclass(frozen=True, eq=False)
class Groups:
    """The readings an epoch averages: their times t (n,) s, the readings y (n, 3) in the fit's scale, and where
    each epoch's readings start, `start` (K + 1,) (epoch k: readings start[k] .. start[k+1] - 1; its state is at
    the first)."""

    t: FloatArray
    y: FloatArray
    start: npt.NDArray[np.int64]

    @property
    def counts(self) -> npt.NDArray[np.int64]:
        """Readings per epoch (K,)."""
        return np.diff(self.start)

    @property
    def epoch_of(self) -> npt.NDArray[np.int64]:
        """The epoch each reading belongs to (n,)."""
        return np.repeat(np.arange(self.counts.size), self.counts)

    def mean(self, x: FloatArray) -> FloatArray:
        """Each epoch's mean of rows x (n, ...) of its readings."""
        out: FloatArray = np.add.reduceat(x, self.start[:-1], axis=0)
        out /= self.counts.reshape((-1,) + (1,) * (x.ndim - 1))
        return out


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
    #: the readings each epoch averages (None: one each); `mag` and `acc` are then the groups' means
    groups: Groups | None = None

    @property
    def mag_factor(self) -> FloatArray | None:
        """The factor (K,) by which averaging shrinks the magnetometer's noise std (None: one reading each)."""
        return None if self.groups is None else 1.0 / np.sqrt(self.groups.counts)

    @property
    def t_obs(self) -> FloatArray:
        """The time each epoch's observation stands for: its readings' mean time (the state's time t when one)."""
        return self.t if self.groups is None else self.groups.mean(self.groups.t)

    def readings(self, xyz: FloatArray) -> FloatArray:
        """The epochs' observations of a stream's readings xyz (one row per reading): the group means."""
        if self.groups is None:
            return xyz[self.index]
        return self.groups.mean(xyz[self.index])


@dataclass(frozen=True)
class Noise:
    """Per-sample standard deviations per axis: accelerometer (m/s^2), gyro (rad/s), magnetometer (scaled)."""

    acc: FloatArray
    gyr: FloatArray
    mag: FloatArray


def epochs_for(problem: Problem, mag: Stream, scale: float, max_epochs: int | None = None,
               average: bool = False) -> Epochs:
    """The magnetometer readings inside the IMU span, the accelerometer linearly interpolated onto them; beyond
    `max_epochs` or MAX_EPOCH_RATE_HZ, k readings averaged per epoch (`average`, the joint MAP) or every k-th
    (`readings_per_epoch`)."""
    max_epochs = MAX_EPOCHS if max_epochs is None else max_epochs
    t_imu = problem.acc.t
    index = np.flatnonzero((mag.t >= t_imu[0]) & (mag.t <= t_imu[-1]))
    notes = []
    dt = float(np.median(np.diff(t_imu)))
    if index.size:
        index = index[np.concatenate([[True], np.diff(mag.t[index]) > 0.01 * dt])]
    t = mag.t[index]
    rate = 1.0 / float(np.median(np.diff(t))) if t.size > 1 else 0.0
    step = readings_per_epoch(t.size, rate, max_epochs, average)
    if step > 1 and average:
        return _grouped(problem, mag, scale, index, step, rate)
    if step > 1:
        n = t.size
        index = index[::step]
        t = mag.t[index]
        notes.append(f"{mag.id}: {n} readings at {rate:.0f} Hz; used every {step}th ({t.size} epochs, "
                     f"{rate / step:.0f} Hz) to bound time and memory (the paper decimates too)")
    _enough(problem, mag, t.size)
    acc, factor, j, w = _acc_at(problem, t)
    return Epochs(mag.id, t, mag.xyz[index] / scale, acc, factor, scale, tuple(notes), index, (j, w))


def readings_per_epoch(n: int, rate: float, max_epochs: int = MAX_EPOCHS, average: bool = False) -> int:
    """k: every k-th of n readings at `rate` Hz taken, or k averaged per epoch (`average`), so that there are at most
    `max_epochs` epochs and at most MAX_EPOCH_RATE_HZ; averaged groups stay at GROUP_MAX readings up to
    GROUPED_EPOCHS_FACTOR x `max_epochs` epochs."""
    if not n:
        return 1
    per = int(np.ceil(n / max_epochs))
    if average and per > GROUP_MAX:
        per = max(GROUP_MAX, int(np.ceil(n / (GROUPED_EPOCHS_FACTOR * max_epochs))))
    return max(per, int(np.ceil(rate / MAX_EPOCH_RATE_HZ)))


def _enough(problem: Problem, mag: Stream, k: int) -> None:
    """InsufficientDataError unless there are MIN_EPOCHS epochs."""
    if k < MIN_EPOCHS:
        msg = (f"{problem.where}: {mag.id} has only {k} readings inside the IMU's time span (need >= "
               f"{MIN_EPOCHS}); check that both sensors were logged at the same time, or widen --start/--end")
        raise InsufficientDataError(msg)


def _acc_at(problem: Problem, t: FloatArray
            ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int64], FloatArray]:
    """The accelerometer interpolated at t, the factor by which that shrinks its noise std, the samples and
    weights of the interpolation."""
    t_imu = problem.acc.t
    acc = interpolate(problem.acc, t)
    j = np.clip(np.searchsorted(t_imu, t, side="right") - 1, 0, t_imu.size - 2)
    w = np.clip((t - t_imu[j]) / (t_imu[j + 1] - t_imu[j]), 0.0, 1.0)
    factor = np.sqrt((1.0 - w) ** 2 + w**2)        # std of (1-w) a_j + w a_j+1 relative to one sample's
    return acc, factor, j, w


def _grouped(problem: Problem, mag: Stream, scale: float, index: npt.NDArray[np.int64], step: int,
             rate: float) -> Epochs:
    """Epochs of `step` consecutive readings each, a new group after a dropout or a window the gyro did not
    measure (the gyro carries a group's readings to its first); observations are the groups' means."""
    t = mag.t[index]
    new = np.zeros(t.size, dtype=bool)
    new[::step] = True
    if t.size > 1:
        period = float(np.median(np.diff(t)))
        new[1:] |= np.diff(t) > GROUP_GAP_PERIODS * period
        for t0, t1 in problem.unmeasured:
            new[1:] |= (t[1:] > t0) & (t[:-1] < t1)
    groups = Groups(t, mag.xyz[index] / scale, np.append(np.flatnonzero(new), t.size).astype(np.int64))
    k = groups.counts.size
    _enough(problem, mag, k)
    acc, _, j, w = _acc_at(problem, t)
    # the mean is sum_i c_i a_i over the IMU samples the group's readings interpolate (readings faster than the IMU
    # share samples): its noise std is sqrt(sum_i c_i^2) of one sample's
    group = groups.epoch_of
    key = np.concatenate([group * (problem.acc.t.size + 1) + j, group * (problem.acc.t.size + 1) + j + 1])
    _, at = np.unique(key, return_inverse=True)
    coef = np.bincount(at.reshape(-1), np.concatenate([1.0 - w, w]) / np.tile(groups.counts[group], 2))
    owner = np.zeros(at.max() + 1, dtype=np.int64)                 # the group of each (group, sample) pair
    owner[at.reshape(-1)] = np.tile(group, 2)
    factor = np.sqrt(np.bincount(owner, coef**2, minlength=k))
    note = (f"{mag.id}: {t.size} readings at {rate:.0f} Hz; each epoch averages {step} consecutive readings "
            f"({k} epochs, {rate / step:.0f} Hz), the gyro carrying them to the epoch, to bound time and memory")
    return Epochs(mag.id, t[groups.start[:-1]], groups.mean(groups.y), groups.mean(acc), factor, scale, (note,),
                  index, None, groups)


def initial_noise(problem: Problem, mag: Stream, scale: float, fit_rms: float) -> Noise:
    """Start noise levels: IMU from its quietest windows, magnetometer from still data or the ellipsoid."""
    still = problem.still
    m = pooled_std(mag, still.segments) / scale if still.segments else np.full(3, fit_rms)
    m = np.where(np.isfinite(m), m, fit_rms)
    # without a still segment the quietest windows still contain motion: their gyro level is an upper bound.
    # The variance-component iteration converges fast from below and slowly from above, so start low.
    gyr = still.gyr_noise if still.segments else still.gyr_noise / GYRO_START_DIVISOR
    return Noise(np.maximum(still.acc_noise, 1e-4), np.maximum(gyr, 1e-6), np.maximum(m, 1e-5))
