"""A partial MAP calibration: which base entries the motion cannot determine and are held at a prior."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from magcal_cli.effects.base import Target
from magcal_cli.errors import InsufficientDataError, UnexplainedError
from magcal_cli.models import partial
from magcal_cli.models.epochs import Epochs
from magcal_cli.models.factor import Linearize
from magcal_cli.models.gyro import Preintegrated
from magcal_cli.models.map.cost import mag_layout, point_at
from magcal_cli.models.map.effects import Bound, terms
from magcal_cli.models.normal import information
from magcal_cli.models.observability import ROTATE_ADVICE
from magcal_cli.models.partial import Held
from magcal_cli.params import BASE, Layout
from magcal_cli.streams import FloatArray

#: a partial calibration that leaves the field strength varying more than this (RMS, relative) explains nothing
PARTIAL_MAX_NORM_RMS = 0.15


def norm_spread(ep: Epochs, theta: FloatArray, layout: Layout, mag: FloatArray | None = None) -> float:
    """RMS of the calibrated field strength about 1 (relative): how far the calibration leaves the readings (`mag`,
    default the epochs' own) from a sphere."""
    d, o, _ = mag_layout(layout).unpack(theta)
    y = ep.mag if mag is None else mag
    return float(np.sqrt(np.mean((np.linalg.norm((y - o) @ np.linalg.inv(d).T, axis=1) - 1.0) ** 2)))


def undisturbed(ep: Epochs, theta: FloatArray, layout: Layout, bound: Sequence[Bound], states: FloatArray,
                pre: Preintegrated) -> FloatArray:
    """The readings with the fitted magnetometer effect terms taken out: a compass is judged after the disturbances
    the fit models (issue 38: a field strength that follows the current is current interference, not a compass
    no calibration explains)."""
    if not any(b.effect.target is Target.MAG for b in bound):
        return ep.mag
    found = terms(bound, layout, theta, point_at(states, theta, layout, pre), Target.MAG)
    out: FloatArray = ep.mag - np.sum([term.value for term, _ in found], axis=0)
    return out


def explains(ep: Epochs, theta: FloatArray, layout: Layout, where: str, mag: FloatArray | None = None) -> float:
    """The calibrated field strength's spread (`norm_spread` of `mag`, the readings with the modelled disturbances
    taken out); refuses a calibration that does not explain the readings: beyond PARTIAL_MAX_NORM_RMS."""
    spread = norm_spread(ep, theta, layout, mag)
    if spread > PARTIAL_MAX_NORM_RMS:
        msg = (f"{where}: no calibration explains the readings (the calibrated field strength "
               f"still varies {100 * spread:.0f} % RMS): the log's motion determines too little, or a disturbance "
               f"dominates. To fix: {ROTATE_ADVICE}")
        raise UnexplainedError(msg)
    return spread


def rechoose(held: Held, data: Linearize, states: FloatArray, theta: FloatArray, where: str,
             widen: FloatArray | None = None, keep: bool = False) -> Held:
    """The base entries the data's information at this point cannot determine better than their priors (the
    information narrowed by the sandwich's widening factors, when given: residuals correlated in time know less
    than the white-noise model says), plus the pinned implausible ones; refuses when D and o would be held
    entirely. With `keep`, what is held stays held."""
    pinned = np.union1d(held.pinned, partial.implausible(theta, held)).astype(np.int64)
    try:
        info = information(data, states, theta)
        if widen is not None:
            info = info / np.outer(widen, widen)
        # `choose` wants the base entries first: accelerometer effect blocks come before them in the layout
        order = np.concatenate([held.at, np.setdiff1d(np.arange(theta.size), held.at)])
        info = info[np.ix_(order, order)]
        # the horizontal offsets of a vehicle that turned through a half circle are never held (`turned_offsets`)
        more = held.holding(partial.choose(info, held.choosable_std(),
                                           np.union1d(pinned, held.cols) if keep else pinned), pinned)
    except np.linalg.LinAlgError:
        more = held.holding(np.setdiff1d(BASE.cols(*BASE.names), held.free), pinned)
    if more.undetermined():
        # why the offsets could not be pinned down, else what the motion left of D: one clause, not a bracket
        prior, d_why = partial.source_parts(held.prior_sources[BASE.slice("D").start])
        _, o_why = partial.source_parts(held.prior_sources[BASE.slice("o").start])
        msg = (f"{where}: the motion in this log determines no part of the magnetometer calibration, not even the "
               f"offsets with D held at {prior}, as {o_why or d_why or 'the field turned through too few directions'}. "
               f"To fix: {ROTATE_ADVICE}")
        raise InsufficientDataError(msg)
    return more


def with_prior_doubt(cov: FloatArray, held: Held) -> FloatArray:
    """The covariance with each held entry's std set to its prior's (issue 38: "held ... with its doubt as their
    std"). The soft prior's marginal is the data's information plus the prior's, smaller than the prior whenever the
    white-noise information knows anything of the entry, though `choose` found the data (widened) know it no better
    than the prior. The held rows and columns are scaled, which keeps every correlation and the matrix positive
    semi-definite; the free entries' block, which carries the held entries' doubt, is unchanged."""
    cols = held.theta_cols
    if cols.size == 0:
        return cov
    sd = np.sqrt(np.clip(np.diag(cov)[cols], 0.0, None))
    factor = np.ones(cov.shape[0])
    factor[cols] = np.where(sd > 0, held.std / np.where(sd > 0, sd, 1.0), 1.0)
    out: FloatArray = cov * np.outer(factor, factor)
    out[cols, cols] = held.std**2                       # exact, and where the marginal was zero
    return out
