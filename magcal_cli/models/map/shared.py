"""One IMU, one accelerometer bias: the magnetometers of a log fitted one by one share the IMU's bias.

Each separate fit (with effects, or when the joint fit cannot run) estimates the IMU's biases again, and a
magnetometer's own misfit can move them: on log171 MAG[1]'s fit put the accelerometer bias at x = 0.33 +- 0.07
m/s^2 against 0.07 and 0.13 in the other two, a 1.5 deg tilt of its vertical, and its dip followed (-63.6 deg
against the WMM's -66.0). The document reports one IMU, the biases of the fit that determines them best; the
other magnetometers are refitted from their own optimum with the accelerometer bias held there (pinned while
fitting; the reference's std carried into their covariance, as a partial calibration's prior). The gyro biases
agree across fits (within 0.5 mrad/s on log171) and stay free.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from magcal_cli.effects.correct import MODELLED
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.map.estimate import MapEstimate
from magcal_cli.models.map.fit import fit_map
from magcal_cli.models.partial import Held
from magcal_cli.models.problem import Problem
from magcal_cli.params import BASE
from magcal_cli.streams import Stream

#: the block the magnetometers share, and how its hold names its source: not a partial calibration (the log does
#: determine it), so the document's `held` list leaves it out (`is_shared`) and a note says what was done
SHARED = "accelerometer_bias"
TAG = "one IMU, one bias"
#: a map over independent items, in order ([fn(x) for x in items], or on threads)
Each = Callable[[Callable[[Any], MapEstimate], Sequence[Any]], list[MapEstimate]]


def is_shared(source: str) -> bool:
    """Whether a held entry's source is the shared IMU bias (`held_at`), not a partial calibration's prior."""
    return source.endswith(f"({TAG})")


def held_at(est: MapEstimate, ref: MapEstimate) -> Held:
    """`est`'s hold (if any) with the accelerometer bias held at `ref`'s value and std (internal units: m/s^2)."""
    assert est.context is not None
    base = est.context.held or Held(np.zeros(0, np.int64), BASE.zeros(), BASE.zeros(), ("",) * BASE.size)
    cols = BASE.cols(SHARED)
    mean, std, src = base.prior_mean.copy(), base.prior_std.copy(), list(base.prior_sources)
    mean[cols], std[cols] = ref.value(SHARED), ref.std_of(SHARED)
    for c in cols:
        src[int(c)] = f"the IMU's bias from {ref.mag_id}'s fit ({TAG})"
    return replace(base, cols=np.union1d(base.cols, cols).astype(np.int64), prior_mean=mean, prior_std=std,
                   prior_sources=tuple(src)).placed(est.context.layout)


def refit(problem: Problem, mag: Stream, est: MapEstimate, ref: MapEstimate, loss: str, dip_prior: float | None,
          declination: float) -> MapEstimate:
    """`est` refitted from its optimum with the accelerometer bias held at `ref`'s, its effect verdicts kept with
    the new estimates; `est` itself when it has no context or the refit fails."""
    if est.context is None:
        return est
    modelled = tuple(f.id for f in est.effects if f.status in MODELLED and f.estimate is not None
                     and f.id not in problem.base_effects)
    try:
        full = fit_map(problem, mag, loss, dip_prior, effects=modelled, declination=declination,
                       warm=replace(est.context, held=held_at(est, ref)))
    except (InsufficientDataError, np.linalg.LinAlgError):
        return est
    fitted = {(f.id, f.sensor): f for f in full.effects}
    verdicts = tuple(replace(v, estimate=fitted[v.id, v.sensor].estimate, statistic=fitted[v.id, v.sensor].statistic,
                             p_value=fitted[v.id, v.sensor].p_value)
                     if (v.id, v.sensor) in fitted and v.estimate is not None else v for v in est.effects)
    own = np.array2string(est.value(SHARED), precision=3)
    note = (f"{mag.id}: fitted with the IMU's accelerometer bias held at {ref.mag_id}'s fit's "
            f"({np.array2string(ref.value(SHARED), precision=3)} m/s^2; its own fit put it at {own}): {TAG}")
    codes = {f.code for f in full.findings}
    return replace(full, effects=verdicts, notes=(*est.notes, note),
                   findings=(*full.findings, *(f for f in est.findings if f.code not in codes)))


def shared(problem: Problem, ests: list[MapEstimate], ref: MapEstimate, loss: str, dip_prior: float | None,
           declination: float, each: Each | None = None) -> list[MapEstimate]:
    """Every estimate but `ref` refitted with `ref`'s accelerometer bias (`refit`); `each` maps the independent
    refits (diagnose.parallel.pmap runs them side by side: log171's two take 0.8 s one after the other)."""
    def one(em: tuple[MapEstimate, Stream]) -> MapEstimate:
        e, m = em
        return e if e is ref else refit(problem, m, e, ref, loss, dip_prior, declination)

    items = list(zip(ests, problem.mags, strict=True))
    return [one(x) for x in items] if each is None else each(one, items)
