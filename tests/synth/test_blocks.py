"""The simulator's fine grid made a block at a time (issue 39): the same bits as the whole grid, in bounded memory."""

from __future__ import annotations

import tracemalloc

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.streams import FloatArray
from magcal_cli.synth.motion import BLOCK, Motion, Trajectory, _integrate, hermite_pieces

DT = 1e-3


def _knots(n: int) -> FloatArray:
    """A wandering attitude: n knots (n, 3, 3)."""
    out: FloatArray = so3.exp(np.cumsum(np.random.default_rng(1).normal(0.0, 0.01, (n, 3)), axis=0))
    return out


def test_sparse_intervals_give_the_whole_grids_coefficients_bit_for_bit() -> None:
    """Intervals gathered from their four knots (every tenth, as IMU stamps on a 10x grid) give exactly the
    coefficients of the whole grid: the ends one-sided, and einsum's operand in C order (a Fortran-ordered one
    summed in another order and moved rows by 1e-17)."""
    knots = _knots(20_001)
    whole = hermite_pieces(knots, DT)[1]
    traj = Trajectory.from_knots(knots, DT)
    for u in (np.arange(0, 20_000, 10), np.array([0, 1, 19_998, 19_999]), np.arange(5, 20_000, 7)):
        got_knots, got = traj._pieces(u)
        assert np.array_equal(got, whole[u])
        assert np.array_equal(got_knots, knots[u])


def test_motion_from_kept_knots_matches_one_running_sum() -> None:
    """Velocity and position integrated on from every BLOCK-th knot equal one running sum over the whole grid,
    for dense and for sparse queries (GNSS fixes far apart)."""
    n = 3 * BLOCK + 123
    a = np.random.default_rng(2).normal(size=(n, 3))
    v, p = _integrate(a, DT, np.array([0.3, -0.1, 0.0]), np.zeros(3))
    motion = Motion.from_acceleration(a, DT, (0.3, -0.1, 0.0))
    for k in (np.arange(0, n - 1, 3), np.array([n - 2, 5, BLOCK, 2 * BLOCK + 7, 1])):
        t = (k + 0.25) * DT
        s = (t - k * DT)[:, None]
        jerk = (a[k + 1] - a[k]) / DT
        assert np.array_equal(motion.position(t), p[k] + s * (v[k] + s * (0.5 * a[k] + s * jerk / 6.0)))
        assert np.array_equal(motion.acceleration(t), a[k] + s * jerk)


def test_a_motion_made_on_demand_keeps_no_block_alive() -> None:
    """Integrating 4 M knots from a source holds a block at a time (the kept velocity once was a view that held
    its whole block until the end: 0.7 GB for an hour at 400 Hz; here 190 MB)."""
    n = 4_000_000

    def source(idx: npt.NDArray[np.int64]) -> FloatArray:
        out: FloatArray = np.sin(idx[:, None] * np.array([1e-5, 2e-5, 3e-5]))
        return out

    tracemalloc.start()
    try:
        motion = Motion.from_source(source, n, DT)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 40e6, f"{peak / 1e6:.0f} MB at the peak"
    assert motion.v.shape == (n // BLOCK + 2, 3)
