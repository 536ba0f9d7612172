"""The not-a-knot cubic spline (magcal_cli/effects/spline.py) against scipy's CubicSpline, which it replaces."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from magcal_cli.effects import spline


@pytest.mark.parametrize("n", [2, 3, 4, 5, 64, 2000])
@pytest.mark.parametrize("trailing", [(), (3,)])
def test_values_and_slopes_equal_scipys_to_the_last_digit(n: int, trailing: tuple[int, ...]) -> None:
    """Same knots and samples: identical values and slopes inside, on the knots, beyond both ends and at NaN."""
    rng = np.random.default_rng(n)
    x = np.cumsum(rng.uniform(0.01, 1.0, n))
    y = rng.normal(size=(n, *trailing))
    t = np.concatenate([rng.uniform(x[0] - 1.0, x[-1] + 1.0, 3000), x, [np.nan]])
    mine, theirs = spline.cubic(x, y), CubicSpline(x, y, axis=0)
    for deriv in (0, 1):
        got, want = mine(t, deriv), theirs(t, deriv)
        assert got.shape == want.shape
        assert np.array_equal(got, want, equal_nan=True)


def test_interpolates_a_cubic_exactly() -> None:
    """A cubic is its own not-a-knot spline: the value and slope anywhere are the cubic's."""
    x = np.array([0.0, 0.3, 1.1, 1.5, 2.9, 4.0])
    f = lambda t: 2.0 * t**3 - t**2 + 0.5 * t - 3.0   # noqa: E731
    t = np.linspace(-1.0, 5.0, 61)
    curve = spline.cubic(x, f(x))
    np.testing.assert_allclose(curve(t), f(t), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(curve(t, 1), 6.0 * t**2 - 2.0 * t + 0.5, rtol=1e-12, atol=1e-10)


@pytest.mark.parametrize(("x", "y"), [([0.0], [1.0]), ([0.0, 1.0, 1.0], [1.0, 2.0, 3.0]), ([0.0, 1.0], [1.0]),
                                      ([0.0, np.inf], [1.0, 2.0]), ([0.0, 1.0, 2.0], [1.0, np.nan, 3.0])])
def test_bad_knots_are_refused(x: list[float], y: list[float]) -> None:
    """Fewer than two knots, a repeated or infinite knot, a sample count that is not the knot count, or a NaN
    sample: ValueError, where scipy's CubicSpline raised one too."""
    with pytest.raises(ValueError, match="a spline needs"):
        spline.cubic(x, y)
    with pytest.raises(ValueError):
        CubicSpline(x, y)


def test_only_values_and_slopes() -> None:
    """A second derivative is not offered: asking for one is an error, not a silent zero."""
    with pytest.raises(ValueError, match="deriv"):
        spline.cubic([0.0, 1.0, 2.0], [0.0, 1.0, 0.0])(0.5, 2)
