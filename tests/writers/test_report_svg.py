"""The report's SVG figures: decimation to what a pixel column can show, ticks, and the drawn document.

Modules it covers (the mirrored test file aside): magcal_cli.writers.report.plots, magcal_cli.writers.report.svg.
"""

from __future__ import annotations

import base64
import re
from xml.etree import ElementTree

import numpy as np
import pytest

from magcal_cli.writers.report.data import EffectView
from magcal_cli.writers.report.plots import effect_grid
from magcal_cli.writers.report.svg import Figure, envelope, nice_ticks, tick_labels


def _vertices(svg: str) -> list[int]:
    """The number of points of every path in an SVG document."""
    return [len(re.findall(r"[ML]", d)) for d in re.findall(r" d='([^']*)'", svg)]


def test_envelope_keeps_every_column_extreme() -> None:
    """Min/max decimation (issue 27): at most two samples per pixel column, and each column's lowest and highest
    reading survive, so a one-sample spike is still drawn."""
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 300.0, 300_001)
    y = rng.normal(size=t.size)
    y[123_457], y[222_222] = 40.0, -35.0                     # single-sample spikes
    xs, ys = envelope(t, y, 800)
    assert xs.size <= 1600 and np.all(np.diff(xs) >= 0)
    assert ys.max() == 40.0 and ys.min() == -35.0
    col = np.minimum((t / 300.0 * 800).astype(int), 799)
    col_d = np.minimum((xs / 300.0 * 800).astype(int), 799)
    for k in (0, 17, 411, 799):                                # every column's extremes, not only the spikes'
        assert ys[col_d == k].max() == y[col == k].max() and ys[col_d == k].min() == y[col == k].min()


def test_envelope_leaves_short_series_and_marks_gaps() -> None:
    """A series that already fits is unchanged; a column with no finite reading becomes a NaN (a gap)."""
    t = np.arange(10.0)
    assert np.array_equal(envelope(t, t ** 2, 800)[1], t ** 2)
    t = np.linspace(0.0, 1.0, 10_000)
    y = np.sin(t)
    y[4000:6000] = np.nan
    xs, ys = envelope(t, y, 100)
    assert np.isnan(ys).sum() >= 15 and np.nanmax(ys) == y[np.isfinite(y)].max()


def test_a_long_line_costs_what_the_panel_is_wide() -> None:
    """A million samples draw as at most two vertices per pixel column; 10^5 identical dots as one."""
    fig = Figure(400, 200)
    (row,) = fig.grid(1, 1, {"left": 0.1, "right": 0.9, "bottom": 0.1, "top": 0.9, "wspace": 0, "hspace": 0})
    t = np.linspace(0, 1, 1_000_000)
    row[0].line(t, np.sin(50 * t), "#000")
    row[0].dots(np.zeros(100_000), np.zeros(100_000), "#f00")
    svg = fig.svg()
    ElementTree.fromstring(svg)
    assert max(_vertices(svg)) <= 2 * 320 + 1
    assert "M" in svg and svg.count("h0") == 1


def test_ticks_are_round_numbers() -> None:
    """Ticks step by 1, 2, 2.5 or 5 times a power of ten inside the range; labels carry the digits they need."""
    assert np.allclose(nice_ticks(-0.93, 0.97), [-0.5, 0.0, 0.5])
    assert np.array_equal(nice_ticks(0.0, 117.0), [0.0, 25.0, 50.0, 75.0, 100.0])
    assert np.array_equal(nice_ticks(-2.3, 2.4, 5), [-2.0, 0.0, 2.0])
    assert tick_labels(np.array([-0.05, 0.0, 0.05])) == ["-0.05", "0.00", "0.05"]
    assert tick_labels(np.array([0.0, 2.5, 5.0])) == ["0.0", "2.5", "5.0"]


@pytest.mark.parametrize(("n_views", "panels"), [(1, 1), (3, 3), (5, 5)])
def test_effect_grid_draws_one_panel_per_view(n_views: int, panels: int) -> None:
    """The effect grid: one titled panel per view in rows of two, the rest of the last row left empty."""
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, 5000)
    views = [EffectView(f"e{k}", "accepted", "x", "y", x, x + rng.normal(size=x.size), rng.normal(size=x.size))
             for k in range(n_views)]
    plot = effect_grid(views, 2, "Modelled effects", "caption")
    assert plot is not None and plot.uri.startswith("data:image/svg+xml;base64,")
    svg = base64.b64decode(plot.uri.split(",", 1)[1]).decode("utf-8")
    titles = re.findall(r">(e\d) \(accepted\)<", svg)
    assert titles == [f"e{k}" for k in range(panels)]
    assert effect_grid([], 2, "t", "c") is None
