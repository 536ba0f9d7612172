"""The MAP cost of one magnetometer: accelerometer, magnetometer and gyro factors, effect terms and priors."""

from __future__ import annotations

import numpy as np

from magcal_cli.effects.base import Point, Target
from magcal_cli.models.accel import G, accel_factor
from magcal_cli.models.epochs import Epochs, Noise
from magcal_cli.models.factor import Factor, Linearize, scale_rows
from magcal_cli.models.gyro import Preintegrated, gyro_factor
from magcal_cli.models.mag import MagLayout, field_nav, mag_factor
from magcal_cli.models.map.effects import Bound, gyro_extra, prior_factor, row_weights, terms, with_terms
from magcal_cli.models.map.within import averaged
from magcal_cli.models.partial import Held
from magcal_cli.params import BASE, Layout
from magcal_cli.streams import FloatArray


def mag_layout(layout: Layout) -> MagLayout:
    """Where the magnetometer factor finds D, o and the dip in theta."""
    return MagLayout(layout.slice("D").start, layout.slice("o").start, layout.slice("dip").start)


def point_at(states: FloatArray, theta: FloatArray, layout: Layout, pre: Preintegrated) -> Point:
    """The model at an iterate, as the effect terms see it (effects/base.py `Point`): for epochs that average
    readings (`pre.within`), the groups' means (map/within.py)."""
    d, _, dip = mag_layout(layout).unpack(theta)
    at = Point(states, np.einsum("mji,j->mi", states, field_nav(dip)),
               np.einsum("mji,j->mi", states, np.array([-np.sin(dip), 0.0, np.cos(dip)])),
               G * states[:, 2, :], d, pre)
    if pre.within is None:
        return at
    return averaged(at, pre.within.mixed(theta[layout.slice("gyroscope_bias")]))


def held_out(t: FloatArray, windows: tuple[tuple[float, float], ...]) -> FloatArray | None:
    """Row weights at epochs t: 0 inside the held-out windows, 1 elsewhere (None without windows)."""
    if not windows:
        return None
    w = np.ones(t.size)
    for t0, t1 in windows:
        w[(t >= t0) & (t < t1)] = 0.0
    return w


def make_linearize(ep: Epochs, pre: Preintegrated, noise: Noise, layout: Layout = BASE,
                   bound: tuple[Bound, ...] = (), holdout: FloatArray | None = None,
                   held: Held | None = None) -> Linearize:
    """Accelerometer, magnetometer and gyro-preintegration factors of the MAP cost (methods.md section 3), with
    the terms of the bound effects added to the factors they enter (map/effects.py). `holdout` (K,) weights
    the accelerometer and magnetometer rows (0: held out for validation; the gyro still carries the
    trajectory through). `held`: base entries held at a prior (partial calibration)."""
    l_acc, l_mag = np.diag(1.0 / noise.acc), np.diag(1.0 / noise.mag)
    idx = np.arange(ep.t.size)
    s_acc = 1.0 / ep.acc_factor
    interpolated = bool(np.any(ep.acc_factor < 1.0 - 1e-12))
    ml = mag_layout(layout)
    ba, bg = layout.slice("accelerometer_bias").start, layout.slice("gyroscope_bias").start
    w_mag = row_weights(bound)
    w_acc = row_weights(bound, Target.ACCEL)
    held = None if held is None else held.placed(layout)
    if w_acc is not None:
        s_acc = s_acc * w_acc
        interpolated = True
    if holdout is not None:
        w_mag = holdout if w_mag is None else w_mag * holdout
        s_acc = s_acc * holdout
        interpolated = True
    if ep.mag_factor is not None:           # a group's mean reading: its noise std shrinks with the count
        w_mag = 1.0 / ep.mag_factor if w_mag is None else w_mag / ep.mag_factor
    within = pre.within                     # epochs that average readings: the factors predict the groups' means

    def linearize(states: FloatArray, theta: FloatArray, jac: bool) -> list[Factor]:
        fa = accel_factor(states, ep.acc, l_acc, theta, ba, idx, jacobians=jac, compact=True, within=within)
        fm = mag_factor(states, ep.mag, l_mag, theta, ml, idx, jac, compact=True, within=within, bias_at=bg)
        extra = None
        if bound:
            at = point_at(states, theta, layout, pre)
            fa = with_terms(fa, l_acc, terms(bound, layout, theta, at, Target.ACCEL), layout)
            fm = with_terms(fm, l_mag, terms(bound, layout, theta, at, Target.MAG), layout)
            extra = gyro_extra(bound, layout, theta, at)
        if interpolated:
            fa = scale_rows(fa, s_acc, in_place=True)          # fa and fm are this call's own
        if w_mag is not None:
            fm = scale_rows(fm, w_mag, in_place=True)
        out = [fa, fm, gyro_factor(states, theta, pre, bg, jac, extra)]   # gyro noise is in pre.l_inv
        prior = prior_factor(bound, layout, theta, jac)
        out = out if prior is None else [*out, prior]
        return out if held is None else [*out, held.factor(theta, jac)]

    return linearize
