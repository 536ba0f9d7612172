"""Time alignment: interpolation onto the IMU time base, gaps, attitude slerp, clean_time and sample checks."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.align import clean_time, common_window, interpolate, onto
from magcal_cli.errors import StreamError
from magcal_cli.readers.checks import drop_held, normalised_field
from magcal_cli.streams import Kind, Stream


def ramp(t: np.ndarray, kind: Kind = Kind.MAGNETOMETER) -> Stream:
    """A three-axis signal linear in time: (t, 2t, -t) + (1, 0, 3)."""
    values = np.column_stack([t + 1.0, 2.0 * t, 3.0 - t])
    return Stream(kind, "s", t, values, "test#s", "tesla")


def test_interpolation_onto_the_imu_epochs_adds_no_time_offset() -> None:
    """A 50 Hz stream starting 3 ms late, read at the 100 Hz IMU epochs: exact for a linear signal.

    Nearest-sample lookup would be off by up to half a period times the slope (here up to 0.01).
    """
    mag = ramp(0.003 + np.arange(100) / 50.0)
    imu_t = np.arange(200) / 100.0
    mask, values = onto(mag, imu_t)
    assert mask.sum() == 198 and not mask[0] and not mask[-1]     # epochs outside the span are not invented
    np.testing.assert_allclose(values, ramp(imu_t[mask]).values, atol=1e-12)
    nearest = mag.values[np.abs(mag.t[None, :] - imu_t[mask][:, None]).argmin(axis=1)]
    assert np.abs(nearest - values).max() > 5e-3                   # what the test guards against


def test_onto_never_bridges_a_dropout() -> None:
    """Epochs inside a gap longer than 4 sample periods are masked; epochs on samples stay."""
    t = np.concatenate([np.arange(0, 1, 0.02), np.arange(2, 3, 0.02)])
    mask, values = onto(ramp(t), np.arange(0, 3, 0.01))
    epochs = np.arange(0, 3, 0.01)[mask]
    assert not np.any((epochs > t[49] + 1e-9) & (epochs < 2.0 - 1e-9))
    assert np.any(np.isclose(epochs, t[49])) and np.any(np.isclose(epochs, 2.0))
    np.testing.assert_allclose(values, ramp(epochs).values, atol=1e-12)
    mask, _ = onto(ramp(t), np.arange(0, 3, 0.01), max_gap_s=2.0)
    assert mask.sum() == np.sum(np.arange(0, 3, 0.01) <= t[-1])


def test_onto_a_stream_of_one_sample_is_empty() -> None:
    """One sample cannot be interpolated: no epoch is usable."""
    mask, values = onto(ramp(np.array([0.5])), np.arange(0, 1, 0.1))
    assert not mask.any() and values.shape == (0, 3)


def test_attitude_is_slerped() -> None:
    """A constant-rate turn sampled at 10 Hz, read at 100 Hz, is exact; a sign flip between samples is harmless."""
    rate = np.array([0.3, -0.2, 1.0])
    t = np.arange(0, 2.0, 0.1)
    q = so3.as_quat(so3.exp(t[:, None] * rate))
    q[1::2] *= -1.0                                               # q and -q are the same rotation
    att = Stream(Kind.ATTITUDE, "att", t, q, "test#att", "1")
    tq = np.arange(0, 1.9, 0.01)
    got = so3.from_quat(interpolate(att, tq))
    np.testing.assert_allclose(got, so3.exp(tq[:, None] * rate), atol=1e-12)


def test_interpolation_errors() -> None:
    """Asking outside the span, or of a single sample, says what to do."""
    s = ramp(np.arange(10) * 0.1)
    with pytest.raises(StreamError, match=r"test#s: asked for times 0.000..1.000 s outside the stream's "
                                          r"0.000..0.900 s; cut the other streams to the common window first"):
        interpolate(s, [0.0, 1.0])
    with pytest.raises(StreamError, match=r"test#s: needs at least two samples to interpolate, has 1"):
        interpolate(ramp(np.array([0.0])), [0.0])
    with pytest.raises(StreamError, match=r"test#s, test#s: the streams do not overlap in time"):
        common_window(s, ramp(np.arange(10) * 0.1 + 5.0))
    start, end = common_window(s, ramp(np.arange(10) * 0.1 + 0.25))
    assert (start, end) == pytest.approx((0.25, 0.9))


def test_clean_time_sorts_drops_and_reports() -> None:
    """NaN rows, backwards stamps and repeated stamps are handled and each is reported with its count."""
    t = np.array([0.0, 0.2, 0.1, 0.1, 0.3, np.nan, 0.4])
    v = np.array([[0.0], [2.0], [1.0], [9.0], [np.nan], [5.0], [4.0]])
    t2, v2, notes = clean_time(t, v, "/imu/mag")
    assert t2.tolist() == [0.0, 0.1, 0.2, 0.4]
    assert v2[:, 0].tolist() == [0.0, 1.0, 2.0, 4.0]                # the first of two equal stamps is kept
    assert notes == ["/imu/mag: dropped 2 samples with NaN or inf",
                     "/imu/mag: 1 timestamps went backwards; samples were sorted by time",
                     "/imu/mag: dropped 1 samples with duplicated timestamps"]
    assert clean_time(np.arange(3.0), np.ones((3, 3)), "x")[2] == []


def test_normalised_field_detection() -> None:
    """Constant magnitude (1e-4 T unit vectors) is detected; a real field with 0.3 % noise is not."""
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 3))
    unit = u / np.linalg.norm(u, axis=1, keepdims=True)
    assert normalised_field(unit * 1e-4)
    assert not normalised_field(unit * 50e-6 * (1 + 0.003 * rng.standard_normal((200, 1))))
    assert not normalised_field(unit[:5])                         # too few readings to tell


def test_held_values_dropped_only_when_most_repeat() -> None:
    """Most readings repeating = a held (stale) source: keep the changes; a few repeats = quantisation: keep all."""
    t = np.arange(20, dtype=np.float64) * 0.01
    held = np.repeat(np.arange(5.0), 4)[:, None] * np.ones(3)
    t2, v2, notes = drop_held(t, held, "mag")
    assert t2.tolist() == pytest.approx([0.0, 0.04, 0.08, 0.12, 0.16]) and v2[:, 0].tolist() == [0, 1, 2, 3, 4]
    assert notes == ["mag: 15 of 20 readings repeat the previous one exactly (the source holds its last value "
                     "between updates); kept the 5 that changed"]
    few = np.arange(20.0)[:, None] * np.ones(3)
    few[5] = few[4]
    assert drop_held(t, few, "mag")[2] == [] and len(drop_held(t, few, "mag")[0]) == 20
