"""Change detection on one parameter's series of flights, using each flight's reported std (docs/fleet.md).

A flight's std is what its fit reports; flights are overconfident (an unmodelled effect, a field that differs
from flight to flight), so the std is first scaled by the observed flight-to-flight scatter (`inflation`):
the standardised differences of consecutive flights, d_i = (x_i - x_(i-1)) / sqrt(s_i^2 + s_(i-1)^2), are N(0, 1)
when the stds are honest, and a robust scale of them (the median of d^2 over that of chi^2_1, pooled over the
fleet's vehicles, so that the rare steps do not count) is the factor, at least 1.

Each flight is then compared with the reference, the inverse-variance mean of the flights since the last change:
z_i = (x_i - ref) / sqrt(s_i^2 + var_ref). A two-sided CUSUM (Page 1954) accumulates g+ = max(0, g+ + z - k) and
g- = max(0, g- - z - k); when either exceeds h the series alarms at that flight, the change is placed where that
sum last left zero, and the reference restarts there. With k = 1.25 and h = 2.75, one flight 4 reference-stds
off, or two flights 2.65 off each, alarm; a steady parameter alarms on about 4 flights in 10,000, and a 5-std step
is found within 2 flights 99 % of the time (Gaussian series of 20 flights; tests/history/test_detect.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli.streams import FloatArray

#: CUSUM slack k and threshold h, in reference standard deviations
SLACK, THRESHOLD = 1.25, 2.75
#: the median of a chi-square variable with one degree of freedom: median(d^2) of honest standardised differences
CHI2_1_MEDIAN = 0.454936
#: fewest consecutive-flight differences that make an inflation estimate (fewer: 1)
MIN_DIFFERENCES = 5


@dataclass(frozen=True)
class Alarm:
    """A detected change: the flight it alarmed at, the first flight after the change, and the step (the new
    segment's first flight minus the old reference) in the parameter's unit and in combined stds."""

    at: int
    start: int
    step: float
    z: float


def standardised_differences(x: npt.ArrayLike, s: npt.ArrayLike) -> FloatArray:
    """(x_i - x_(i-1)) / sqrt(s_i^2 + s_(i-1)^2) over consecutive flights with finite values and positive std."""
    xa, sa = np.asarray(x, dtype=np.float64), np.asarray(s, dtype=np.float64)
    ok = np.isfinite(xa) & np.isfinite(sa) & (sa > 0)
    xa, sa = xa[ok], sa[ok]
    d: FloatArray = np.diff(xa) / np.sqrt(sa[1:] ** 2 + sa[:-1] ** 2)
    return d


def inflation(differences: npt.ArrayLike) -> float:
    """The factor the reported stds need to match the observed scatter (at least 1; 1 with too few)."""
    d = np.asarray(differences, dtype=np.float64)
    if d.size < MIN_DIFFERENCES:
        return 1.0
    return max(1.0, float(np.sqrt(np.median(d**2) / CHI2_1_MEDIAN)))


def cusum(x: npt.ArrayLike, s: npt.ArrayLike, slack: float = SLACK, threshold: float = THRESHOLD) -> list[Alarm]:
    """The alarms of a two-sided CUSUM on a series `x` with stds `s` (already inflated); flights without a finite
    value or a positive std are passed over."""
    x, s = np.asarray(x, dtype=np.float64), np.asarray(s, dtype=np.float64)
    good = [i for i in range(x.size) if np.isfinite(x[i]) and np.isfinite(s[i]) and s[i] > 0]
    alarms: list[Alarm] = []
    start = 0                                       # position in `good` where the current segment begins
    pos = 1
    g_hi = g_lo = 0.0
    left_hi = left_lo = 1                           # where each sum last left zero (positions in `good`)
    while pos < len(good):
        seg = good[start:pos]
        w = 1.0 / s[seg] ** 2
        ref, var_ref = float(np.sum(w * x[seg]) / np.sum(w)), float(1.0 / np.sum(w))
        i = good[pos]
        z = (x[i] - ref) / np.sqrt(s[i] ** 2 + var_ref)
        if g_hi == 0.0:
            left_hi = pos
        if g_lo == 0.0:
            left_lo = pos
        g_hi, g_lo = max(0.0, g_hi + z - slack), max(0.0, g_lo - z - slack)
        if max(g_hi, g_lo) > threshold:
            first = left_hi if g_hi >= g_lo else left_lo
            j = good[first]
            alarms.append(Alarm(i, j, float(x[j] - ref), float((x[j] - ref) / np.sqrt(s[j] ** 2 + var_ref))))
            start, pos, g_hi, g_lo = first, first + 1, 0.0, 0.0
            continue
        pos += 1
    return alarms
