"""Long logs in bounded memory (issue 39): what the memory-light forms compute is what the whole-log forms did.

Each reference below is written from the definition, holding every sample's value at once as the code did before
(the forms that cost 72 B per IMU sample); the memory-light code must give the same digits, or the same rotations
to rounding where it multiplies in another order.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.effects import time_offset
from magcal_cli.effects.time_offset import Gyro, attitude_at
from magcal_cli.models.map.effects import kinematics
from magcal_cli.models.problem import Problem
from magcal_cli.streams import Kind, Sampling, Stream


def _gyro(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.uniform(0.002, 0.003, n)), rng.normal(0.0, 2.0, (n, 3))


def _sequential_attitude(t_gyr: np.ndarray, w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Q(t): one rotation per gyro sample, multiplied in turn (zero-order hold over [t_j, t_j+1))."""
    q = [np.eye(3)]
    for j in range(t_gyr.size - 1):
        q.append(q[-1] @ so3.exp(w[j] * (t_gyr[j + 1] - t_gyr[j])))
    at = np.clip(np.searchsorted(t_gyr, t, side="right") - 1, 0, t_gyr.size - 1)
    return np.array([q[i] @ so3.exp(w[i] * (s - t_gyr[i])) for i, s in zip(at, t, strict=True)])


@pytest.mark.parametrize("n", [1, 2, time_offset.KEY, time_offset.KEY + 1, 3 * time_offset.KEY + 5, 2000])
def test_time_offset_attitude_is_the_gyro_integrated_sample_by_sample(n: int) -> None:
    """Kept every KEY samples and integrated on between them: the sequential product, at stamps, between stamps and
    beyond both ends, with the bias removed as the fit gives it."""
    t_gyr, raw = _gyro(n)
    bias = np.array([0.01, -0.02, 0.03])
    rng = np.random.default_rng(1)
    t = np.sort(np.concatenate([rng.uniform(t_gyr[0] - 0.01, t_gyr[-1] + 0.01, 300), t_gyr[: min(n, 50)]]))
    got = attitude_at(Gyro(t_gyr, raw, bias), t)
    np.testing.assert_allclose(got, _sequential_attitude(t_gyr, raw - bias, t), rtol=0, atol=1e-12)


def test_time_offset_memo_gives_the_digits_of_a_fresh_integration() -> None:
    """A fit's next tau reuses the last call's per-time attitudes: bit for bit what integrating all times afresh
    gives (MAGCAL_JOBS=1 and 2 must agree, whatever else a process integrated before)."""
    t_gyr, raw = _gyro(20_000)
    g = Gyro(t_gyr, raw, np.zeros(3))
    keys = time_offset.keyframes(g)
    t = np.sort(np.random.default_rng(2).uniform(t_gyr[0], t_gyr[-1], 4000))
    memo: dict[str, object] = {}
    for tau in (0.0, 0.004, 0.0041, -0.02):
        kept, _ = time_offset._attitude_cm(g, keys, t - tau, memo)
        fresh, _ = time_offset._attitude_cm(g, keys, t - tau)
        assert np.array_equal(kept, fresh)


def _problem(n: int) -> Problem:
    t_gyr, raw = _gyro(n, 3)
    acc = Stream(Kind.ACCELEROMETER, "imu", t_gyr, np.tile([0.0, 0.0, -9.81], (n, 1)), "test", "m/s^2")
    gyr = Stream(Kind.GYROSCOPE, "imu", t_gyr, raw, "test", "rad/s", sampling=Sampling.FOLLOWING)
    return Problem("test", "imu", acc, gyr, (), None, ())  # type: ignore[arg-type]


def test_kinematics_on_the_rows_it_reads_matches_the_whole_log() -> None:
    """omega and omega_dot at epochs from the gyro rows their interpolation reads: the digits of the computation over
    every sample (a bias-free copy of the log, its derivative and the interval middles)."""
    from magcal_cli.align import columns
    from magcal_cli.models.map.effects import OMEGA_DOT_WINDOW_S

    problem = _problem(5000)
    g = problem.gyr
    bias = np.array([0.003, -0.001, 0.002])
    w = g.xyz - bias
    dt = float(np.median(np.diff(g.t)))
    half = max(1, int(round(OMEGA_DOT_WINDOW_S / dt / 2)))
    lo, hi = np.clip(np.arange(g.t.size) - half, 0, g.t.size - 1), np.clip(np.arange(g.t.size) + half, 0,
                                                                         g.t.size - 1)
    wdot = (w[hi] - w[lo]) / np.maximum(g.t[hi] - g.t[lo], 1e-12)[:, None]
    for t in (g.t[10:-10:7], np.linspace(g.t[0] - 1.0, g.t[-1] + 1.0, 777), g.t + 0.5 * dt):
        kin = kinematics(problem, t, bias)
        assert np.array_equal(kin.omega, columns(t, g.t + 0.5 * dt, w))
        assert np.array_equal(kin.omega_dot, columns(t, g.t + 0.5 * dt, wdot))
        assert kin.gyr is g.xyz and np.array_equal(kin.gyr_bias, bias)


def test_a_stream_keeps_a_frozen_array_and_copies_a_writeable_one() -> None:
    """A read-only float64 array (another stream's slice) is kept, not copied; a caller's writeable array is copied,
    so freezing the stream never freezes the caller's array."""
    t = np.arange(5.0)
    values = np.ones((5, 3))
    s = Stream(Kind.GYROSCOPE, "g", t, values, "test", "rad/s")
    assert t.flags.writeable and values.flags.writeable and not np.shares_memory(s.values, values)
    cut = s.between(None, None)
    assert cut.values is s.values or np.shares_memory(cut.values, s.values)
    assert not cut.values.flags.writeable


@pytest.mark.parametrize(("total", "n"), [(4, 5), (5, 5), (6, 5), (100, 7), (1000, 64), (1025, 64), (3000, 300)])
def test_still_windows_a_block_at_a_time_are_the_whole_log_sums(total: int, n: int,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """The still detector's window means and variances, its running sums made a block at a time (blocks of 256
    here, so windows straddle their edges): the digits of one cumulative sum over the whole log."""
    from magcal_cli import detect

    monkeypatch.setattr(detect, "MOVING_BLOCK", 256)
    x = np.random.default_rng(total).normal(3.0, 2.0, (total, 3))
    y = x - np.median(x, axis=0)
    c1 = np.concatenate([np.zeros((1, 3)), np.cumsum(y, axis=0)])
    c2 = np.concatenate([np.zeros((1, 3)), np.cumsum(y * y, axis=0)])
    s1, s2 = c1[n:] - c1[:-n], c2[n:] - c2[:-n]
    count = max(total - n + 1, 0)
    mean, var = np.full((count, 3), np.nan), np.full((count, 3), np.nan)
    for k0, k1, m, v in detect._window_stats(x, n):
        mean[k0:k1 + 1], var[k0:k1 + 1] = m, v
    assert np.array_equal(mean, s1 / n)
    assert np.array_equal(var, np.maximum(s2 - s1 * (s1 / n), 0.0) / (n - 1))


def test_bound_inputs_kept_for_the_latest_start_biases_only() -> None:
    """A diagnosis binds time_offset at each fit's own gyro bias, and its inputs hold an attitude per KEY IMU samples:
    the problem's cache keeps the KEEP latest per effect and magnetometer (a two-hour log held 6 sets, 155 MB). A
    kept one is served again as it is; one dropped is made again, to the same digits."""
    from magcal_cli.models.map import effects as map_effects

    problem = _problem(4000)
    t = problem.gyr.t[5:-5:10]
    mag = Stream(Kind.MAGNETOMETER, "mag", t, np.ones((t.size, 3)), "test", "T")
    biases = [np.array([0.001 * k, 0.0, 0.0]) for k in range(map_effects.KEEP + 2)]
    first = map_effects.bind(problem, mag, t, biases[0], ["time_offset"])[0][0].inputs
    for b in biases[1:]:
        map_effects.bind(problem, mag, t, b, ["time_offset"])
    kept = [k for k in map_effects._INPUTS.keys(problem) if k[0] == "time_offset"]
    assert len(kept) == map_effects.KEEP
    latest = map_effects.bind(problem, mag, t, biases[-1], ["time_offset"])[0][0].inputs
    assert map_effects.bind(problem, mag, t, biases[-1], ["time_offset"])[0][0].inputs is latest
    again = map_effects.bind(problem, mag, t, biases[0], ["time_offset"])[0][0].inputs
    assert again is not first
    assert np.array_equal(again.channels["q_t"], first.channels["q_t"])
    assert np.array_equal(again.constants["_keys"], first.constants["_keys"])


def test_time_offset_attitudes_of_a_subset_are_the_whole_logs_digits() -> None:
    """A rotation's digits do not depend on the samples integrated beside it: time_offset's memo integrates again
    only the times that changed sample, so a subset (all small angles: the series) must give what the whole log
    (with fast samples: the closed form, before) gave. Before, the series was taken only when every angle of a batch
    was small, and a diagnosis worker, whose memo had seen other fits, moved the 13th digit (2015-10-11_19-59-09)."""
    from magcal_cli import stacks

    rng = np.random.default_rng(4)
    phi = np.concatenate([rng.normal(0.0, 1e-3, (500, 3)), rng.normal(0.0, 0.3, (20, 3))])
    rng.shuffle(phi)
    whole = stacks.exp(phi)
    small = np.flatnonzero(np.einsum("ij,ij->i", phi, phi) < 1e-4)
    for rows in (small, small[::7], np.arange(phi.shape[0])[::3]):
        assert np.array_equal(stacks.exp(np.ascontiguousarray(phi[rows])), whole[:, :, rows])
    t_gyr, raw = _gyro(3000)
    raw[::50] *= 200.0                               # a few fast samples among slow ones
    g = Gyro(t_gyr, raw, np.zeros(3))
    keys = time_offset.keyframes(g)
    j = np.sort(rng.choice(t_gyr.size - 1, 400, replace=False))
    calm = j[(j % time_offset.KEY == time_offset.KEY - 1) & (j % 50 > 10)]
    assert np.array_equal(time_offset._at_samples(g, keys, calm),
                          time_offset._at_samples(g, keys, j)[:, :, np.searchsorted(j, calm)])


def test_a_channel_resampled_again_at_the_same_times_is_the_kept_result() -> None:
    """`resample` keeps its last results per stream: the same times give the same read-only array (the digits of a
    fresh spline), other times a fresh one, and no more than RESAMPLED_KEEP sets stay."""
    from magcal_cli.effects import base

    rng = np.random.default_rng(2)
    t_s = np.cumsum(rng.uniform(0.002, 0.003, 5000))
    s = Stream(Kind.TEMPERATURE, "IMU[0]", t_s, 30.0 + np.cumsum(rng.normal(0, 0.01, 5000)), "test", "degC")
    t = np.linspace(t_s[0], t_s[-1], 777)
    first = base.resample(s, t)
    np.testing.assert_array_equal(first, base.resampled(s, t))
    assert base.resample(s, t.copy()) is first and not first.flags.writeable
    other = [base.resample(s, t + k * 1e-3) for k in range(1, base.RESAMPLED_KEEP + 2)]
    assert all(o is not first for o in other)
    assert len(base._RESAMPLED.keys(s)) == base.RESAMPLED_KEEP
    assert base.resample(s, t) is not first                     # evicted, made again to the same digits
    np.testing.assert_array_equal(base.resample(s, t), first)


@pytest.mark.parametrize("n", [3, 50, 4001])
def test_the_noise_estimate_is_its_definition(n: int) -> None:
    """`detect.noise_std` partitions its work arrays in place: the same digits as the definition on copies (the
    chi-square-corrected quantile of window variances, and the MAD of second differences), with a NaN sample too."""
    from magcal_cli import detect
    from magcal_cli.detect import chi2_ppf

    rng = np.random.default_rng(n)
    x = np.cumsum(rng.normal(0.0, 0.1, (n, 3)), axis=0) + rng.normal(0.0, 0.01, (n, 3))
    if n > 10:
        x[7, 2] = np.nan
    w, q = min(11, n), 0.1
    var = detect._moving_var(x, w)
    want = np.sqrt(np.quantile(var, q, axis=0) * (w - 1) / chi2_ppf(q, w - 1))
    d2 = np.diff(x, n=2, axis=0)
    want = np.minimum(want, 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / np.sqrt(6.0))
    np.testing.assert_array_equal(detect.noise_std(x, w, q), want)


def _messy_imu(n: int = 3000, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """IMU stamps and (N, 6) accelerometer and gyro values with every fault the cleaning handles: non-finite values,
    a corrupt lone stamp, a clock that jumps back, stamps out of order, duplicates, a value beyond physical
    limits, a vanished specific force and a saturated gyro axis."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.0025 + 100.0
    v = np.column_stack([rng.normal(0, 1, (n, 3)) + [0, 0, -9.8], rng.normal(0, 0.5, (n, 3))])
    v[10, 1], t[20] = np.nan, np.inf
    t[400] += 5000.0                                             # a lone corrupt stamp
    t[2500:] -= 3.0                                              # a clock reset: the longer part is kept
    t[[600, 601]] = t[[601, 600]]                                # out of order
    t[700] = t[699]                                              # a repeated stamp
    v[800, 0] = 1e6                                              # beyond physical limits
    v[900, :3] = 0.0                                             # a vanished specific force
    v[1000:1030, 4] = v[:, 4].max() + 1.0                        # a gyro axis at its wall
    return t, v


def test_cleaning_by_rows_is_cleaning_the_array() -> None:
    """`clean_rows` and `sensor_rows` name the rows `clean_time` and `sensor_checks` keep, in their order, and say
    the same: a reader whose kinds are separate arrays takes exactly those rows from each."""
    from magcal_cli.align import clean_rows, clean_time
    from magcal_cli.readers.checks import sensor_checks, sensor_rows

    t, v = _messy_imu()
    kinds = (Kind.ACCELEROMETER, Kind.GYROSCOPE)
    want_t, want_v, want_notes = clean_time(t, v, "IMU[0]")
    want_t, want_v, checked = sensor_checks(kinds, want_t, want_v, "IMU[0]")
    acc, gyr = np.ascontiguousarray(v[:, :3]), np.ascontiguousarray(v[:, 3:])
    finite = np.isfinite(t) & np.all(np.isfinite(acc), axis=1) & np.all(np.isfinite(gyr), axis=1)
    got_t, rows, notes = clean_rows(t, finite, "IMU[0]")
    assert rows is not None and len(want_notes) >= 4
    acc, gyr = acc[rows], gyr[rows]
    got_t, rows, more = sensor_rows(kinds, got_t, [acc, gyr], "IMU[0]")
    assert rows is not None and len(checked) >= 3
    np.testing.assert_array_equal(got_t, want_t)
    np.testing.assert_array_equal(np.column_stack([acc[rows], gyr[rows]]), want_v)
    assert notes + more == want_notes + checked
    clean = np.arange(50) * 0.01
    assert clean_rows(clean, np.ones(50, bool), "x")[1] is None


def test_a_dataflash_record_read_as_one_array_per_kind_gives_the_same_streams() -> None:
    """`finish` of an IMU record whose accelerometer and gyro are separate arrays (the ArduPilot reader's, no
    (N, 6) copy) gives the streams, notes and stamps of the same record as one (N, 6) array (PX4's)."""
    from pathlib import Path

    from magcal_cli.readers.dataflash.streams import Pending, finish

    t, v = _messy_imu()
    kinds, units = (Kind.ACCELEROMETER, Kind.GYROSCOPE), ("m/s^2", "rad/s")
    recs = []
    for values in (v.copy(), (np.ascontiguousarray(v[:, :3]), np.ascontiguousarray(v[:, 3:]))):
        temp = Pending((Kind.TEMPERATURE,), "IMU[0]", t, np.full((t.size, 1), 30.0), "x.Temp", ("degC",))
        recs.append(finish(Path("x.bin"), "dataflash", [Pending(kinds, "IMU[0]", t, values, "x.Acc/Gyr", units),
                                                      temp], {}, []))
    one, split = recs
    assert one.notes == split.notes and len(one.notes) >= 7
    for a, b in zip(one.streams, split.streams, strict=True):
        assert (a.kind, a.id) == (b.kind, b.id)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.values, b.values)
        assert b.values.flags.c_contiguous and not b.values.flags.writeable


def test_attitude_interpolated_a_block_of_times_at_a_time_is_the_whole() -> None:
    """`align._slerp` interpolates SLERP_BLOCK times at a time: the same bits as all at once (each rotation is
    computed on its own), blocks of any size."""
    from magcal_cli import align

    rng = np.random.default_rng(1)
    ts = np.cumsum(rng.uniform(0.01, 0.03, 500))
    q = so3.as_quat(so3.cumulative_product(so3.exp(rng.normal(0, 0.05, (500, 3)))))
    s = Stream(Kind.ATTITUDE, "ATT", ts, q, "x", "quaternion")
    t = np.sort(rng.uniform(ts[0], ts[-1], 1001))
    whole = align._slerp(s, t)
    old = align.SLERP_BLOCK
    try:
        align.SLERP_BLOCK = 64
        np.testing.assert_array_equal(align._slerp(s, t), whole)
    finally:
        align.SLERP_BLOCK = old
    assert np.allclose(np.linalg.norm(whole, axis=1), 1.0)


def test_forget_drops_the_inputs_of_the_effects_not_kept() -> None:
    """Once a screening is decided its inputs are not asked again (each training fold binds at its own start bias):
    `forget` drops them, keeping the named effects' (issue 39: time_offset's 26 MB went through the folds)."""
    from magcal_cli.models.map import effects as map_effects

    problem = _problem(4000)
    t = problem.gyr.t[5:-5:10]
    mag = Stream(Kind.MAGNETOMETER, "mag", t, np.ones((t.size, 3)), "test", "T")
    map_effects.bind(problem, mag, t, np.zeros(3), ["time_offset", "temperature_drift"])
    assert {k[0] for k in map_effects._INPUTS.keys(problem)} == {"time_offset", "temperature_drift"}
    map_effects.forget(problem, keep=["temperature_drift"])
    assert {k[0] for k in map_effects._INPUTS.keys(problem)} == {"temperature_drift"}
    map_effects.forget(problem)
    assert map_effects._INPUTS.keys(problem) == []


def test_component_major_stacks_kept_for_the_latest_preintegrations_only() -> None:
    """The gyro factor's component-major stacks are kept on the CM_KEEP preintegrations most recently linearised, not
    on every one an estimate's context holds (issue 39); one dropped is made again, to the same digits."""
    from magcal_cli.models import gyro

    rng = np.random.default_rng(2)
    t = np.arange(400) * 0.0025
    w = rng.normal(size=(400, 3))
    pres = [gyro.preintegrate(t, w, t[::8], np.full(3, 0.001 * k), np.full(3, 0.01)) for k in range(gyro.CM_KEEP + 2)]
    first = pres[0].component_major()
    for p in pres[1:]:
        p.component_major()
    assert [("_cm" in p.__dict__) for p in pres] == [False] * 2 + [True] * gyro.CM_KEEP
    pres[1].component_major()                      # asked again: kept again, the oldest of the others goes
    assert [("_cm" in p.__dict__) for p in pres] == [False, True, False, True]
    again = pres[0].component_major()
    assert again is not first
    for a, b in zip(again, first, strict=True):
        np.testing.assert_array_equal(a, b)
    pres[0].drop_component_major()                 # the noise rounds let them go before the selected inverse
    assert "_cm" not in pres[0].__dict__
    for a, b in zip(pres[0].component_major(), first, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_stream_holds_float32_samples_compact_and_reads_them_as_float64() -> None:
    """A float32 log's samples (float64 here, every one exact in float32) are held in float32 and read back as the
    same float64 digits; `replace` and `between` keep the one compact array; samples float32 cannot hold exactly
    (or NaN) stay float64, as given."""
    import pickle
    import warnings
    from dataclasses import replace

    rng = np.random.default_rng(3)
    n = 5000
    t = np.cumsum(rng.uniform(0.002, 0.003, n))
    logged = rng.normal(0.0, 2.0, (n, 3)).astype(np.float32).astype(np.float64)
    s = Stream(Kind.GYROSCOPE, "g", t, logged, "test", "rad/s")
    assert s.stored.dtype == np.float32 and s.stored.nbytes == logged.nbytes // 2
    assert s.values.dtype == np.float64 and not s.values.flags.writeable
    np.testing.assert_array_equal(s.xyz, logged)
    assert replace(s, t=t + 1.0).stored is s.stored
    cut = s.between(t[10], t[20])
    assert np.shares_memory(cut.stored, s.stored) and len(cut) == 11
    np.testing.assert_array_equal(cut.values, logged[10:21])
    back = pickle.loads(pickle.dumps(s))
    assert back.stored.dtype == np.float32 and np.array_equal(back.values, logged)
    wide = logged + 1e-9
    assert Stream(Kind.GYROSCOPE, "g", t, wide, "test", "rad/s").stored.dtype == np.float64
    late = logged.copy()
    late[-1, 2] += 1e-9                                        # exact but for the last sample: float64
    assert Stream(Kind.GYROSCOPE, "g", t, late, "test", "rad/s").stored.dtype == np.float64
    gap = logged.copy()
    gap[7] = np.nan
    assert Stream(Kind.GYROSCOPE, "g", t, gap, "test", "rad/s").stored.dtype == np.float64
    huge = logged.copy()
    huge[-1, 0] = 1e300                                        # a corrupt value beyond float32: no warning, float64
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert Stream(Kind.GYROSCOPE, "g", t, huge, "test", "rad/s").stored.dtype == np.float64


def test_a_rescaled_preintegration_has_the_digits_of_the_scaled_arrays() -> None:
    """`Preintegrated.scaled` keeps the unscaled arrays and applies the factors when read: the digits of scaling
    them at once, factor after factor, with the rotations shared."""
    from magcal_cli.models.gyro import preintegrate

    t, w = _gyro(400, seed=4)
    pre = preintegrate(t, w, t[::7], np.zeros(3), np.full(3, 0.01))
    twice = pre.scaled(1.7).scaled(0.35)
    np.testing.assert_array_equal(twice.cov, pre.cov * 1.7 * 0.35)
    np.testing.assert_array_equal(twice.l_inv, pre.l_inv / np.sqrt(1.7) / np.sqrt(0.35))
    np.testing.assert_array_equal(twice.noise_std, pre.noise_std * np.sqrt(1.7) * np.sqrt(0.35))
    assert twice.delta is pre.delta and twice.cov_base is pre.cov_base


def test_a_preintegration_over_the_samples_a_block_spans_is_the_whole_logs() -> None:
    """A block of epochs preintegrated over its own span of the gyro (`gyro._span`: the samples, the noise scale
    from their first, the whole log's period) gives the digits of the same epochs over the whole log."""
    from magcal_cli.detect import BlockScale
    from magcal_cli.models.gyro import preintegrate

    t, w = _gyro(3000, seed=5)
    scale = BlockScale(np.random.default_rng(6).uniform(1.0, 3.0, (40, 3)), 100)
    epochs = np.linspace(t[1200] + 1e-4, t[1900] - 1e-4, 50)
    whole = preintegrate(t, w, epochs, np.full(3, 0.01), np.full(3, 0.02), scale=scale)
    i0 = int(np.searchsorted(t, epochs[0], side="right")) - 1
    i1 = int(np.searchsorted(t, epochs[-1], side="left")) + 1
    part = preintegrate(t[i0:i1], w[i0:i1], epochs, np.full(3, 0.01), np.full(3, 0.02), scale=scale.from_sample(i0),
                        dt=float(np.median(np.diff(t))))
    for name in ("delta", "d_bias", "cov", "l_inv"):
        np.testing.assert_array_equal(getattr(part, name), getattr(whole, name))
    assert scale.from_sample(i0)[np.arange(3)].tolist() == scale[i0 + np.arange(3)].tolist()


def _noise_scale_whole(x: np.ndarray, level: np.ndarray, size: int) -> np.ndarray:
    """`detect.gyro_noise_scale`'s arithmetic on the whole log at once (its definition before issue 39's blocks)."""
    from magcal_cli.detect import FOURTH

    n = x.shape[0]
    d = np.stack([np.convolve(x[:, i], FOURTH, mode="same") for i in range(3)], axis=1) / np.linalg.norm(FOURTH)
    d[:2], d[-2:] = d[2], d[-3]
    blocks = -(-n // size)
    padded = np.concatenate([d, np.repeat(d[-1:], blocks * size - n, axis=0)]).reshape(blocks, size, 3)
    spread = 1.4826 * np.median(np.abs(padded - np.median(padded, axis=1, keepdims=True)), axis=1)
    return np.maximum(spread / level, 1.0)


@pytest.mark.parametrize("n", [20 * 6, 20 * 6 + 1, 20 * 6 + 2, 20 * 6 + 3, 20 * 5 + 19, 37])
@pytest.mark.parametrize("chunk", [1, 2, 256])
def test_the_gyro_noise_scale_a_chunk_of_blocks_at_a_time_is_the_whole_logs(n: int, chunk: int,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """`gyro_noise_scale` judges NOISE_CHUNK blocks at a time from the float32 samples a stream holds: the digits of
    the whole log's differences at once, whatever the chunk, with a last block or chunk of one to three samples."""
    from magcal_cli import detect

    monkeypatch.setattr(detect, "NOISE_CHUNK", chunk)
    rng = np.random.default_rng(n)
    t = np.arange(n) * 0.05
    w = (np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0) + rng.normal(0, 0.01, (n, 3))).astype(np.float32)
    gyr = Stream(Kind.GYROSCOPE, "g", t, w, "test", "rad/s")
    level = np.array([0.004, 0.005, 0.006])
    still = detect.StillResult((detect.Segment(0, n, 0.0, 3.0, np.zeros(3), np.zeros(3)),), level, level,
                               np.zeros(3), np.ones(n, bool))
    got = detect.gyro_noise_scale(gyr, still, block_s=1.0)                  # 20 samples per block
    assert got is not None and got.size == 20
    np.testing.assert_array_equal(got.values, _noise_scale_whole(w.astype(np.float64), level, 20))


def test_an_imu_logged_in_float32_is_read_in_float32_with_the_same_values() -> None:
    """`logged_columns` keeps float32 columns without a multiplier in float32 (the stream's width: no float64 copy
    beside it), with `stack_columns`'s values; scaled or integer columns stay float64."""
    from magcal_cli.readers.dataflash.format import MessageFormat, Table
    from magcal_cli.readers.dataflash.streams import logged_columns, stack_columns

    rng = np.random.default_rng(3)
    cols = {c: rng.normal(0, 9, 50).astype(np.float32) for c in ("AccX", "AccY", "AccZ")}
    cols["C"] = rng.integers(-900, 900, 50).astype(np.int16)
    table = Table(MessageFormat(1, "IMU", 3 + 12 + 2, "fffc", ("AccX", "AccY", "AccZ", "C")), np.arange(50), cols)
    got = logged_columns(table, ("AccX", "AccY", "AccZ"))
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.astype(np.float64), stack_columns(table, ("AccX", "AccY", "AccZ")))
    scaled = logged_columns(table, ("AccX", "C"))                # 'c' is centi-units: a multiplier, so float64
    assert scaled.dtype == np.float64
    np.testing.assert_array_equal(scaled, stack_columns(table, ("AccX", "C")))


def test_cleaning_float32_samples_keeps_the_rows_float64_keeps() -> None:
    """`sensor_rows` on an IMU held in float32 drops the rows, with the notes, it drops from the same values in float64:
    beyond the limits, a vanished specific force, a saturated axis (its walls found in float64 arithmetic)."""
    from magcal_cli.readers.checks import sensor_rows

    t, v = _messy_imu()
    ok = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    t, v = t[ok], v[ok].astype(np.float32).astype(np.float64)
    v[1000:1030, 4] = np.float32(v[:, 4].max())
    kinds = (Kind.ACCELEROMETER, Kind.GYROSCOPE)
    want = sensor_rows(kinds, t, [v[:, :3].copy(), v[:, 3:].copy()], "IMU[0]")
    got = sensor_rows(kinds, t, [v[:, :3].astype(np.float32), v[:, 3:].astype(np.float32)], "IMU[0]")
    assert want[1] is not None and len(want[2]) >= 3
    assert got[2] == want[2]
    np.testing.assert_array_equal(got[1], want[1])


def test_the_walls_of_a_float32_axis_are_those_of_its_float64_values() -> None:
    """`_walls` judges a float32 axis in float64 arithmetic: readings at float32(0.96), just below the band's edge
    0.96 in float64 but on it in float32, would count inside the band and hide the pile-up at the wall."""
    from magcal_cli.readers.checks import _walls

    rng = np.random.default_rng(2)
    x = rng.uniform(-0.9, 0.9, 4000)
    x[:30], x[30], x[31:39], x[39:42] = 1.0, -1.0, np.linspace(0.961, 0.99, 8), np.float32(0.96)
    x = x.astype(np.float32)
    assert _walls(x) == _walls(x.astype(np.float64)) == [1.0]
