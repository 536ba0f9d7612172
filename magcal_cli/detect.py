"""Stationary segments: where the gyro and accelerometer show only noise (pure functions on streams).

The noise level is the chi-square-corrected low quantile of moving-window standard deviations (the
quietest windows are still); each window is then tested against chi-square bounds at that level.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import numpy.typing as npt

from magcal_cli.config import StillConfig
from magcal_cli.errors import InsufficientDataError, StreamError
from magcal_cli.streams import FloatArray, Stream
from magcal_cli.units import G


def chi2_ppf(q: float, df: float) -> float:
    """The chi-square quantile: bit-identical to `scipy.stats.chi2.ppf(q, df)` (the same 2 gammaincinv(df/2, q),
    nan for df <= 0) without importing scipy.stats, which costs 0.3-1.2 s (issue 27)."""
    from scipy import special

    return float(2 * special.gammaincinv(df / 2, q))


@dataclass(frozen=True, eq=False)
class Segment:
    """One still interval: IMU samples [i0, i1), times in s, mean specific force and angular rate."""

    i0: int
    i1: int
    start: float
    end: float
    acc: FloatArray
    gyr: FloatArray

    @property
    def n(self) -> int:
        """Number of IMU samples."""
        return self.i1 - self.i0

    @property
    def vertical(self) -> FloatArray:
        """Unit vector along the mean specific force (up, in the body frame)."""
        return self.acc / np.linalg.norm(self.acc)


@dataclass(frozen=True, eq=False)
class StillResult:
    """Segments found, the per-sample noise std (per axis) they were judged by, and the still mask."""

    segments: tuple[Segment, ...]
    acc_noise: FloatArray
    gyr_noise: FloatArray
    gyr_bias: FloatArray
    mask: npt.NDArray[np.bool_]


#: samples per block of `_window_sums`'s running sums: the whole log's sums and their temporaries were ten arrays the size
#: of the IMU at once (0.7 GB for two hours at 400 Hz, issue 39)
MOVING_BLOCK = 1 << 16


def _window_sums(x: FloatArray, n: int) -> Iterator[tuple[int, int, FloatArray, FloatArray]]:
    """Sums (s1, s2) of x - median(x) and of its square over the windows k0..k1 of n samples, a block at a time.

    Running sums c_i = sum of the first i samples: each block's cumulative sum starts from the last one's end (a sum
    accumulates in order, so the digits are those of one cumulative sum over the whole log), and its windows take
    the n sums before the block from the last one's tail."""
    med = np.median(x, axis=0)                         # centring keeps E[x^2] - E[x]^2 well conditioned
    total, d = x.shape
    count = max(total - n + 1, 0)
    tail1, tail2 = np.zeros((1, d)), np.zeros((1, d))  # c_k for k in [i0 - n, i0] (fewer at the start)
    step = max(MOVING_BLOCK, 4 * n)
    for i0 in range(0, total, step):
        xc = x[i0:i0 + step] - med
        c1 = np.cumsum(np.concatenate([tail1[-1:], xc]), axis=0)[1:]
        c2 = np.cumsum(np.concatenate([tail2[-1:], xc * xc]), axis=0)[1:]
        c1, c2 = np.concatenate([tail1, c1]), np.concatenate([tail2, c2])   # c_k for k in [i0 - len(tail) + 1 ...]
        first = i0 + 1 - tail1.shape[0]                                    # the k of c1[0]
        k0, k1 = max(first, 0), min(i0 + xc.shape[0] - n, count - 1)       # windows whose sums are all here
        if k1 >= k0:
            yield (k0, k1, c1[k0 + n - first:k1 + n + 1 - first] - c1[k0 - first:k1 + 1 - first],
                   c2[k0 + n - first:k1 + n + 1 - first] - c2[k0 - first:k1 + 1 - first])
        tail1, tail2 = c1[-(n + 1):], c2[-(n + 1):]


def _window_stats(x: FloatArray, n: int) -> Iterator[tuple[int, int, FloatArray, FloatArray]]:
    """Mean and variance (ddof=1) over the windows k0..k1 of n samples, a block at a time: window k covers x[k:k+n]
    (the mean of x - median(x)). The detector judges each block and keeps booleans, not log-sized statistics
    (issue 39)."""
    for k0, k1, s1, s2 in _window_sums(x, n):
        mean = s1 / n
        yield k0, k1, mean, np.maximum(s2 - s1 * mean, 0.0) / (n - 1)


def _moving_var(x: FloatArray, n: int) -> FloatArray:
    """Every window's variance (`_window_stats`), without holding the means (a log-sized array)."""
    var = np.empty((max(x.shape[0] - n + 1, 0), x.shape[1]))
    for k0, k1, _, v in _window_stats(x, n):
        var[k0:k1 + 1] = v
    return var


def noise_std(x: FloatArray, n: int, quantile: float) -> FloatArray:
    """Per-axis noise std: the smaller of two estimates that fail in different ways.

    The `quantile` of window variances (chi-square corrected) is exact when some windows are still but
    absorbs the motion when none is; the MAD of second differences (var = 6 sigma^2 for white noise) ignores
    smooth motion but absorbs jitter. With short windows at low rates the first alone let a steady
    rotation pass as noise (paper protocol at 10 Hz).
    """
    # the work arrays are the size of the log: each is partitioned in place and dropped before the next is made
    # (five at once were a two-hour log's peak, issue 39); a quantile or a median does not depend on the order
    var = _moving_var(x, n)
    q = np.quantile(var, quantile, axis=0, overwrite_input=True)
    del var
    by_windows: FloatArray = np.sqrt(q * (n - 1) / chi2_ppf(quantile, n - 1))
    if len(x) < 3:
        return by_windows
    d2 = np.diff(x, n=2, axis=0)
    d2 -= np.median(d2, axis=0, overwrite_input=True)
    np.abs(d2, out=d2)
    by_differences = 1.4826 * np.median(d2, axis=0, overwrite_input=True) / np.sqrt(6.0)
    out: FloatArray = np.minimum(by_windows, by_differences)
    return out


def _runs(mask: npt.NDArray[np.bool_]) -> list[tuple[int, int]]:
    """[start, stop) index pairs of the True runs of a boolean array."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))


def _resolution_floor(x: FloatArray) -> FloatArray:
    """Per-axis quantisation noise step/sqrt(12), so integer-logged signals are not judged noise-free."""
    d = np.diff(x, axis=0)
    np.abs(d, out=d)
    d[~(d > 0)] = np.inf                                 # in place (NaN too, as np.where did): one log-sized array
    step = np.min(d, axis=0) if len(d) else np.full(x.shape[1], np.inf)
    return np.where(np.isfinite(step), step / np.sqrt(12.0), 0.0)


@dataclass(frozen=True, eq=False)
class _Signal:
    """A three-axis signal whose block means must stay constant while still, with its per-sample noise."""

    t: FloatArray
    x: FloatArray
    sd: FloatArray

    @cached_property
    def sums(self) -> FloatArray:
        """The running sums (N + 1, 3) of x from 0, made once: every run and every split reads them (they were made
        again each time, a copy of the whole log per candidate run)."""
        out = np.empty((self.x.shape[0] + 1, self.x.shape[1]))
        out[0] = 0.0
        np.cumsum(self.x, axis=0, out=out[1:])
        return out


def _steady_parts(sig: list[_Signal], t_imu: FloatArray, i0: int, i1: int, n: int,
                  alpha: float) -> list[tuple[int, int]]:
    """Split IMU samples [i0, i1) until every signal's n-sample block means agree with the part's mean.

    A still body sees a constant specific force and a constant field; a slow rotation that hides in the
    noise of one short window drifts across a run (about the vertical only the field shows it). The worst
    block is removed until each part passes a chi-square test (3 dof, Bonferroni over blocks and signals).
    """
    todo, out = [(i0, i1)], []
    while todo:
        j0, j1 = todo.pop()
        blocks = (j1 - j0) // n
        if blocks < 2:
            out.append((j0, j1))
            continue
        edges = t_imu[j0 + n * np.arange(blocks + 1) - (np.arange(blocks + 1) == blocks)]
        dev = np.zeros(blocks)
        for s in sig:
            lo, hi = np.searchsorted(s.t, edges[:-1]), np.searchsorted(s.t, edges[1:])
            c = s.sums
            cnt = (hi - lo).astype(np.float64)
            ok = cnt > 0
            if not ok.any():                            # this signal has no samples in the run (a dropout)
                continue
            means = (c[hi[ok]] - c[lo[ok]]) / cnt[ok, None]
            centre = np.sum(means * cnt[ok, None], axis=0) / cnt[ok].sum()
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                chi = np.nan_to_num(np.sum((means - centre) ** 2 / (s.sd**2 / cnt[ok, None]), axis=1), posinf=1e300)
            dev[ok] = np.maximum(dev[ok], chi)
        worst = int(np.argmax(dev))
        if dev[worst] <= chi2_ppf(1.0 - alpha / (blocks * len(sig)), 3):
            out.append((j0, j1))
            continue
        cut0, cut1 = j0 + worst * n, j0 + (worst + 1) * n
        todo += [(j0, cut0), (cut1 if worst < blocks - 1 else j1, j1)]
    return sorted(p for p in out if p[1] > p[0])


def detect_still(acc: Stream, gyr: Stream, cfg: StillConfig, mags: tuple[Stream, ...] = ()) -> StillResult:
    """Still segments of an IMU whose accelerometer and gyro share timestamps; magnetometers, when given,
    must be steady too (they reveal rotations about the vertical that the accelerometer cannot see)."""
    if len(acc) != len(gyr) or not np.allclose(acc.t, gyr.t):
        msg = f"{acc.source}: accelerometer and gyro timestamps differ; stillness needs one IMU time base"
        raise StreamError(msg)
    rate = acc.rate_hz
    n = max(5, int(round(cfg.window_s * rate)))
    if len(acc) < 2 * n:
        msg = f"{acc.source}: only {len(acc)} IMU samples; a still-segment search needs at least {2 * n}"
        raise StreamError(msg)
    # each window statistic is judged a block at a time, and one sensor's samples are read (as float64, from the
    # stream's float32) at a time: log-sized statistics beside both sensors were a long log's peak (issue 39)
    var_bound = chi2_ppf(1.0 - cfg.false_alarm, n - 1) / (n - 1)
    count = len(acc) - n + 1
    candidates, at_rest = np.empty(count, dtype=bool), np.empty(count, dtype=bool)
    a = acc.xyz
    a_sd = np.maximum(noise_std(a, n, cfg.noise_quantile), np.maximum(_resolution_floor(a), 1e-12))
    limit, centre = var_bound * a_sd**2, np.median(a, axis=0)
    for k0, k1, mean, var in _window_stats(a, n):
        candidates[k0:k1 + 1] = np.all(var <= limit, axis=1)
        mean += centre
        at_rest[k0:k1 + 1] = np.abs(np.linalg.norm(mean, axis=1) / G - 1.0) <= cfg.gravity_tolerance
    del a
    candidates &= at_rest
    del at_rest
    w = gyr.xyz
    w_sd = np.maximum(noise_std(w, n, cfg.noise_quantile), np.maximum(_resolution_floor(w), 1e-12))
    limit, centre = var_bound * w_sd**2, np.median(w, axis=0)
    rows, means = [], []                               # the candidate windows' mean rates
    for k0, k1, mean, var in _window_stats(w, n):
        candidates[k0:k1 + 1] &= np.all(var <= limit, axis=1)
        take = candidates[k0:k1 + 1]
        rows.append(k0 + np.flatnonzero(take))
        means.append(mean[take] + centre)
    at, w_mean = np.concatenate(rows), np.concatenate(means)
    bias = np.median(w_mean, axis=0) if at.size else np.zeros(3)
    # a still window's mean rate differs from the bias by noise/sqrt(n) plus the allowed bias drift
    allow = np.deg2rad(cfg.rate_allowance_dps)
    rate_bound = np.mean(w_sd**2) / n * chi2_ppf(1.0 - cfg.false_alarm, 3) + 3.0 * allow**2
    still_win = np.zeros(count, dtype=bool)
    still_win[at] = np.sum((w_mean - bias) ** 2, axis=1) <= rate_bound
    del rows, means, w_mean
    a = acc.xyz
    # window k covers samples k..k+n-1: a sample is still when some still window contains it
    mask = np.convolve(still_win.astype(np.int64), np.ones(n, dtype=np.int64))[: len(acc)] > 0
    trim = int(round(cfg.edge_trim_s * rate))
    segments = []
    signals = [_Signal(acc.t, a, a_sd)]
    for m in mags:
        n_m = max(5, int(round(cfg.window_s * m.rate_hz)))
        if len(m) >= 2 * n_m:
            floor = np.maximum(_resolution_floor(m.xyz) if m.resolution is None else m.resolution, 1e-300)
            signals.append(_Signal(m.t, m.xyz, np.maximum(noise_std(m.xyz, n_m, cfg.noise_quantile), floor)))
    parts = [p for i0, i1 in _runs(mask) for p in _steady_parts(signals, acc.t, i0, i1, n, cfg.false_alarm)]
    for i0, i1 in parts:
        j0, j1 = i0 + trim, i1 - trim
        if j1 - j0 < cfg.min_samples or acc.t[j1 - 1] - acc.t[j0] < cfg.min_duration_s:
            continue
        segments.append(Segment(j0, j1, float(acc.t[j0]), float(acc.t[j1 - 1]),
                                a[j0:j1].mean(axis=0), w[j0:j1].mean(axis=0)))
    if segments:
        idx = np.concatenate([np.arange(s.i0, s.i1) for s in segments])
        bias = w[idx].mean(axis=0)
    return StillResult(tuple(segments), a_sd, w_sd, bias, mask)


def window_means(stream: Stream, segments: tuple[Segment, ...] | list[Segment]) -> tuple[FloatArray, FloatArray]:
    """Mean (K, width) and sample count (K,) of `stream` inside each segment's [start, end]."""
    t = stream.t
    lo = np.searchsorted(t, [s.start for s in segments], side="left")
    hi = np.searchsorted(t, [s.end for s in segments], side="right")
    c = np.concatenate([np.zeros((1, stream.values.shape[1])), np.cumsum(stream.values, axis=0)])
    counts = (hi - lo).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = (c[hi] - c[lo]) / counts[:, None]
    return means, counts


def pooled_std(stream: Stream, segments: tuple[Segment, ...] | list[Segment]) -> FloatArray:
    """Per-axis std of `stream` about each segment's own mean, pooled over segments (ddof per segment)."""
    t = stream.t
    ss, dof = np.zeros(stream.values.shape[1]), 0
    for s in segments:                                  # one vectorised reduction per segment, not per sample
        x = stream.values[np.searchsorted(t, s.start):np.searchsorted(t, s.end, side="right")]
        if len(x) > 1:
            ss += np.sum((x - x.mean(axis=0)) ** 2, axis=0)
            dof += len(x) - 1
    return np.sqrt(ss / dof) if dof else np.full(stream.values.shape[1], np.nan)


#: what every dead-sensor error ends with: why, and what to do
DEAD_ADVICE = ("the sensor is stuck, disconnected or not enabled (or the column is a placeholder). Check the sensor "
               "and its logging, and record again")


def check_signal(stream: Stream) -> None:
    """Refuse a sensor that reads one value, or NaN, throughout (stuck, disconnected, not enabled, or zero-filled)."""
    x = stream.values
    if len(x) and not np.isfinite(x).all(axis=1).any():
        msg = f"{stream.source}: the {stream.kind.value} {stream.id} reads NaN in all {len(x)} samples; {DEAD_ADVICE}"
        raise InsufficientDataError(msg)
    if len(x) < 2 or not np.all(x == x[0]):
        return
    what = "zero" if not np.any(x[0]) else "the same value"
    msg = f"{stream.source}: the {stream.kind.value} {stream.id} reads {what} in all {len(x)} samples; {DEAD_ADVICE}"
    raise InsufficientDataError(msg)


def check_dead(stream: Stream, why: str | None, where: str) -> None:
    """Refuse a magnetometer its reader judged dead or stuck on the readings as logged (`Recording.dead`), by name."""
    if why:
        msg = f"{where}: {stream.id}: the {stream.kind.value} measures no field as logged ({why}); {DEAD_ADVICE}"
        raise InsufficientDataError(msg)


#: an acceleration beyond this (m/s^2, 6 g) is an impact: no vehicle or hand motion a calibration uses reaches it
IMPACT = 6.0 * G
#: a gyro reading within this share of the log's largest, where that is at least GYRO_FAST, is taken as saturated
SATURATION_SHARE, GYRO_FAST = 0.97, np.deg2rad(1000.0)
#: margin (s) around unmeasured samples: the rotation just before and after an impact is not trustworthy either
UNMEASURED_MARGIN_S = 0.25


def padded_runs(t: FloatArray, flagged: npt.NDArray[np.bool_], pad_s: float, min_run_s: float = 0.0
                ) -> list[list[float]]:
    """[[t0, t1], ...] of the runs of flagged samples at least `min_run_s` long, padded by `pad_s` on each side
    and merged where the padding overlaps."""
    out: list[list[float]] = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flagged.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if t[b - 1] - t[a] >= min_run_s:
            lo, hi = float(t[a] - pad_s), float(t[b - 1] + pad_s)
            if out and lo <= out[-1][1]:
                out[-1][1] = hi
            else:
                out.append([lo, hi])
    return out


def unmeasured_windows(acc: Stream, gyr: Stream) -> tuple[tuple[float, float], ...]:
    """Time windows (s) whose motion the IMU did not measure: impacts and a gyro at the top of its range.

    A crash spins the vehicle beyond the gyro's range and shakes the accelerometer beyond gravity; the
    integrated rotation across it is wrong by tens of degrees, so a trajectory must not be carried through.
    The accelerometer and gyro share their time stamps (detect_still checks it).
    """
    w = np.abs(gyr.xyz).max(axis=1)
    top = float(w.max()) if w.size else 0.0
    bad = np.linalg.norm(acc.xyz, axis=1) > IMPACT
    if top >= GYRO_FAST:
        bad |= w >= SATURATION_SHARE * top
    return tuple((a, b) for a, b in padded_runs(acc.t, bad, UNMEASURED_MARGIN_S))


#: seconds over which the gyro's own noise is measured where it moves (`gyro_noise_scale`)
NOISE_BLOCK_S = 2.0
#: the 4th difference x_k-2 - 4 x_k-1 + 6 x_k - 4 x_k+1 + x_k+2 cancels any cubic motion; its norm turns it into noise
FOURTH = np.array([1.0, -4.0, 6.0, -4.0, 1.0])
#: with at least this much still data (s) its noise levels are the sensors' white noise (the estimators' floors)
MIN_STILL_S = 2.0
#: blocks of `gyro_noise_scale` judged at once
NOISE_CHUNK = 256


@dataclass(frozen=True, eq=False)
class BlockScale:
    """A value per sample held over blocks of `size` samples: sample k's is values[k // size] (B, 3). An array of
    every sample's copy was 35 MB for an hour at 400 Hz (issue 39)."""

    values: FloatArray
    size: int
    #: the sample that index 0 stands for (`from_sample`)
    start: int = 0

    def __getitem__(self, k: npt.NDArray[np.int64]) -> FloatArray:
        """The values of samples k (M,): (M, 3)."""
        out: FloatArray = self.values[(np.asarray(k) + self.start) // self.size]
        return out

    def from_sample(self, i0: int) -> BlockScale:
        """The same scale indexed from sample i0 (a slice of the samples starting there)."""
        return replace(self, start=self.start + i0)


def _fourth(x: npt.ArrayLike) -> FloatArray:
    """Normalised 4th differences of (M, 3) samples ('same' length, zero-padded at both ends) in float64."""
    x64 = np.asarray(x, dtype=np.float64)
    out: FloatArray = np.stack([np.convolve(x64[:, i], FOURTH, mode="same") for i in range(3)], axis=1)
    return out / np.linalg.norm(FOURTH)


def gyro_noise_scale(gyr: Stream, still: StillResult, block_s: float = NOISE_BLOCK_S) -> BlockScale | None:
    """Each gyro sample's white-noise std relative to the still level (3 axes), never below 1; None without MIN_STILL_S
    of still data (no rest level to compare with: the estimators then fit one level to the whole log).

    A running motor shakes the IMU: in flight a multirotor's gyro is several times noisier than at rest (the
    independent simulator's flight: 0.01 against 0.003 rad/s; log171: 0.016-0.065 against 0.0005). The level is
    measured from the gyro itself: the robust spread of its 4th differences, which cancel the smooth motion, over
    blocks of `block_s`, held over each block.
    """
    level, held, n = still.gyr_noise, gyr.stored, gyr.t.size
    if sum(s.end - s.start for s in still.segments) < MIN_STILL_S or n < 2 * FOURTH.size or not np.all(level > 0):
        return None
    size = max(int(round(block_s * gyr.rate_hz)), 20)
    blocks = -(-n // size)
    # 'same' pads with zeros at the log's ends: its first two and last two differences are the nearest full ones
    first, last = _fourth(held[:FOURTH.size])[2], _fourth(held[n - FOURTH.size:])[2]
    spread = np.empty((blocks, 3))
    half = FOURTH.size // 2
    # NOISE_CHUNK blocks at a time, each with the two samples either side its differences need: the whole log's
    # differences and their deviations were four hour-sized (N, 3) arrays, a 60-min flight's peak (issue 39). Every
    # difference and every block's median are the same operations on the same samples: the same digits
    for b0 in range(0, blocks, NOISE_CHUNK):
        b1 = min(b0 + NOISE_CHUNK, blocks)
        a, z = b0 * size, min(b1 * size, n)
        lo = max(a - half, 0)
        d = _fourth(held[lo:min(z + half, n)])[a - lo:a - lo + z - a]
        d[:max(2 - a, 0)] = first
        d[max(n - 2 - a, 0):] = last
        padded = np.concatenate([d, np.repeat(last[None], (b1 - b0) * size - (z - a), axis=0)]).reshape(-1, size, 3)
        spread[b0:b1] = 1.4826 * np.median(np.abs(padded - np.median(padded, axis=1, keepdims=True)), axis=1)
    return BlockScale(np.maximum(spread / level, 1.0), size)
