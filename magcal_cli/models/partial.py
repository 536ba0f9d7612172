"""Partial calibration: hold at a prior what the log's motion cannot determine, estimate the rest (issue 12).

A level flight turns the field about one body axis only: the column of D along that axis and the offset along
it act alike (D[:, z] sin(dip) + o), and the dip trades against the horizontal scale of D. Such a log still
determines the offsets and the horizontal part of D, which is what heading needs. Held entries get a Gaussian
prior (mean: the prior's value; std: how far the prior may be off), so the reported uncertainty carries the
prior's doubt into the free entries it is confounded with.

Which entries: the data's own information about theta (Schur complement, trajectory eliminated) decides,
greedily. The entry the data know least relative to its prior is held, and so on until every free entry is
known better than its prior would know it. Ties go by preference (dip, D, IMU biases, offsets): a log that
cannot separate a column of D from the offset along it keeps the offset.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.models.factor import Factor, gaussian_factor
from magcal_cli.models.spikes import despike
from magcal_cli.params import BASE, Layout
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

#: how far a prior may be off, relative to the field: the vehicle's own calibration, or a sphere fit
ONBOARD_REL_STD = 0.05
SPHERE_REL_STD = 0.10
#: the dip from the World Magnetic Model (local anomalies, a few tenths of a degree) or from the data alone
DIP_REF_STD = float(np.deg2rad(1.0))
DIP_DATA_STD = float(np.deg2rad(10.0))
#: IMU biases: none beyond the factory calibration (m/s^2) and the still segments' gyro bias (rad/s)
ACCEL_BIAS_STD = 0.3
GYRO_BIAS_STD = 0.02
#: a free IMU bias or dip further than this many prior stds from its prior is not a measurement but the fit
#: using it to absorb what the log cannot separate (flight acceleration, too little rotation): it is held too
IMPLAUSIBLE_SIGMAS = 5.0
#: while fitting, a held entry's std is this fraction of its prior's: the estimate stays at the prior
PIN = 1e-3
#: which block gives way first when the data cannot separate two entries
PREFERENCE = {"dip": 0, "D": 1, "accelerometer_bias": 2, "gyroscope_bias": 3, "o": 4}
#: how far the modelled field directions may be off (rad, or relative to the field) whatever the log's length: the
#: attitude a vehicle IMU gives in motion (half a degree) and the sensor's own nonlinearity. Averaging does not
#: shrink it, so it decides what a narrow cap of directions can determine (`cap_needs`)
DIRECTION_ERROR = 0.01
#: the std (relative to the field) beyond which an estimated offset is not determined (observability's fatal limit)
OFFSET_FATAL = 0.1
#: the dip assumed for the field's body directions when the log gives no position for the World Magnetic Model
DIP_TYPICAL = float(np.deg2rad(60.0))
#: a vehicle turned through at least this much heading (deg) gets at least its offsets, whatever its prior: the
#: horizontal field swept half a circle, whose centre the offsets are (issue 25)
OFFSETS_YAW_DEG = 180.0
#: a prior source reads FLOWN + DETAIL + where it was found, then PINNED + why the motion cannot determine the entry
#: (`cap_pins`) when it is pinned: one sentence, no brackets within brackets
FLOWN = "the calibration the vehicle flew with"
DETAIL = ": "
PINNED = "; "


def source_parts(source: str) -> tuple[str, str]:
    """A prior source's short name ('the calibration the vehicle flew with') and why it was pinned ('' if not)."""
    head, _, why = source.partition(PINNED)
    return head.split(DETAIL, 1)[0].split(", rescaled", 1)[0], why


@dataclass(frozen=True, eq=False)
class MagPrior:
    """A magnetometer's prior calibration, y = D m_b + o (tesla), where it came from and how far it may be off."""

    D: FloatArray
    o: FloatArray
    source: str
    rel_std: float
    #: RMS angles (rad, largest first) the field directions spread about their mean along their principal axes
    #: (`motion_coverage`); None when not measured
    spread: FloatArray | None = None
    #: the heading (deg) the vehicle turned through (`motion_coverage`); None when not measured
    yaw_deg: float | None = None
    #: the body axis (0-2) the field directions spread least along (a level flight's vertical); None: not measured
    flat_axis: int | None = None
    #: after a refused fit, what a half turn still determines: 1 holds D's column along `flat_axis`, 2 all of D
    fallback: int = 0
    #: a fit to the log's own readings (a sphere), not a calibration the vehicle flew with
    from_readings: bool = False
    #: where the offsets came from when not from `source` (a flown calibration that does not fit its sensor)
    offset_source: str | None = None


@dataclass(frozen=True, eq=False)
class Held:
    """Base-theta entries held at a prior: their columns, and every base entry's prior mean and std (internal
    units) and source (`prior_of`)."""

    cols: IntArray
    prior_mean: FloatArray
    prior_std: FloatArray
    prior_sources: tuple[str, ...]
    #: entries held because the fit drove them implausibly far (`implausible`): they stay held
    pinned: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    #: the held factor's std relative to the prior's: pinned while fitting, the prior's own for the covariance
    stiffness: float = PIN
    #: where each base entry sits in the fitted theta (`placed`): effect blocks may come before the base ones
    at: IntArray = field(default_factory=lambda: BASE.cols(*BASE.names))
    #: entries never held whatever the information says: the horizontal offsets of a vehicle that turned through
    #: OFFSETS_YAW_DEG of heading (`turned_offsets`)
    free: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))

    def placed(self, layout: Layout) -> Held:
        """The same hold for a theta in `layout` (cols stay base indices; `theta_cols` follow the layout)."""
        return replace(self, at=layout.cols(*BASE.names))

    @property
    def theta_cols(self) -> IntArray:
        """The held entries' columns in the fitted theta."""
        out: IntArray = self.at[self.cols]
        return out

    @property
    def mean(self) -> FloatArray:
        """The held entries' prior means."""
        return self.prior_mean[self.cols]

    @property
    def std(self) -> FloatArray:
        """The held entries' prior stds."""
        return self.prior_std[self.cols]

    @property
    def sources(self) -> tuple[str, ...]:
        """Where each held entry's prior came from."""
        return tuple(self.prior_sources[int(c)] for c in self.cols)

    def holding(self, cols: IntArray, pinned: IntArray) -> Held:
        """The same priors holding these columns (and pinning those)."""
        return replace(self, cols=np.asarray(cols, np.int64), pinned=np.asarray(pinned, np.int64))

    def soft(self) -> Held:
        """The same hold as a prior with the prior's own std: its covariance carries the prior's doubt into the
        free entries confounded with the held ones."""
        return replace(self, stiffness=1.0)

    def undetermined(self) -> bool:
        """True when nothing useful is left to estimate: every entry of D and of o is held."""
        return bool(np.isin(BASE.cols("D", "o"), self.cols).all())

    def choosable_std(self) -> FloatArray:
        """The prior stds `choose` judges by: infinite for the entries never held (their ratio is then 0)."""
        out = self.prior_std.copy()
        out[self.free] = np.inf
        return out

    def factor(self, theta: FloatArray, jacobians: bool) -> Factor:
        """(theta_c - mean) / (std x stiffness) for the held columns."""
        return gaussian_factor("held", self.theta_cols, self.mean, self.std * self.stiffness, theta, jacobians)

    def names(self) -> list[str]:
        """The held entries' names ('D.02', 'o.z', 'dip', ...)."""
        labels = BASE.entry_names()
        return [labels[int(c)] for c in self.cols]


def sphere_prior(y: FloatArray) -> MagPrior:
    """D = r I and o = the centre of the least-squares sphere through the readings (N, 3) in tesla; a small ridge
    keeps the centre finite when the readings lie near a circle (level motion)."""
    mu = y.mean(axis=0)
    x = y - mu
    s = float(np.sqrt(np.mean(np.sum(x * x, axis=1)))) or 1.0
    x = x / s
    # |x|^2 = 2 x.c + k, linear in (c, k)
    a = np.column_stack([2.0 * x, np.ones(len(x))])
    rhs = np.sum(x * x, axis=1)
    sol = np.linalg.solve(a.T @ a + 1e-3 * len(x) * np.diag([1.0, 1.0, 1.0, 0.0]), a.T @ rhs)
    centre = sol[:3]
    radius = float(np.sqrt(max(sol[3] + centre @ centre, 1e-12)))
    return MagPrior(np.eye(3) * radius * s, mu + centre * s, "a sphere fit to the readings", SPHERE_REL_STD,
                    from_readings=True)


def flown_prior(raw: FloatArray, field: FloatArray, to_si: float, slot: str) -> MagPrior | None:
    """The calibration the vehicle flew with as y = D m_b + o: the affine map raw -> corrected field (N, 3) (least
    squares; motor compensation averages in) inverted, with |field| as the field strength."""
    ok = np.all(np.isfinite(raw), axis=1) & np.all(np.isfinite(field), axis=1)
    if ok.sum() < 12:
        return None
    a = np.column_stack([raw[ok], np.ones(int(ok.sum()))])
    coef, *_ = np.linalg.lstsq(a, field[ok], rcond=None)
    m, t = coef[:3].T, coef[3]
    if not np.all(np.isfinite(m)) or abs(float(np.linalg.det(m))) < 1e-9:
        return None
    norm = np.linalg.norm(field[ok], axis=1)
    strength = float(np.median(norm))
    # a calibration whose corrected field strength varies by 15 % RMS is off by about that much: its doubt is at
    # least twice its own misfit (a flown calibration that fits gets ONBOARD_REL_STD)
    misfit = float(np.sqrt(np.mean((norm / strength - 1.0) ** 2))) if strength > 0 else 1.0
    m_inv = np.linalg.inv(m)
    return MagPrior(strength * m_inv * to_si, -m_inv @ t * to_si,
                    f"{FLOWN}{DETAIL}{slot}", min(max(ONBOARD_REL_STD, 2.0 * misfit), 1.0))


def motion_coverage(delta: FloatArray, acc: FloatArray, dip: float | None) -> tuple[FloatArray, float, int]:
    """What the motion shows of the field: the RMS spread (rad, largest first) of the Earth field's body-frame
    directions about their mean along their principal axes, the heading (deg) turned through, and the body axis
    nearest the direction of least spread.

    Judged from the attitude alone, never from the readings (a prior off by more than the field would make any
    motion look like a narrow cap): the gyro-integrated trajectory (`delta` (K-1, 3, 3), consecutive epochs)
    levelled by the mean vertical the accelerometer (K, 3) measured along it, and the field at `dip` (rad; the
    World Magnetic Model's, else DIP_TYPICAL). The heading's origin is arbitrary: the spread of a turn about the
    vertical does not depend on it.
    """
    rel = np.concatenate([np.eye(3)[None], so3.cumulative_product(delta)])          # body k -> body 0
    up = np.einsum("kij,kj->ki", rel, acc / np.linalg.norm(acc, axis=1, keepdims=True))
    v = up.mean(axis=0)
    v = v / (np.linalg.norm(v) or 1.0)
    axis = np.cross(v, [0.0, 0.0, -1.0])                        # body-0's vertical onto NED up
    s, c = float(np.linalg.norm(axis)), float(-v[2])
    if s > 1e-12:
        level = so3.exp(axis / s * np.arctan2(s, c))
    else:                                                       # already vertical: upright, or upside down
        level = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    rot = level @ rel
    d = DIP_TYPICAL if dip is None else dip
    m_b = np.einsum("kji,j->ki", rot, [np.cos(d), 0.0, np.sin(d)])
    x = m_b - m_b.mean(axis=0)
    var, axes = np.linalg.eigh(x.T @ x / len(x))
    spread: FloatArray = np.sqrt(np.clip(var, 0.0, None))[::-1]
    heading = np.unwrap(np.arctan2(rot[:, 1, 0], rot[:, 0, 0]))
    return spread, float(np.degrees(np.ptp(heading))), int(np.argmax(np.abs(axes[:, 0])))


#: a prior whose field strength differs from the one the motion shows by more than this (relative, or 3 of its
#: stds) is no calibration of this sensor (an uncalibrated compass's 'identity' through its hard iron)
SCALE_MISMATCH = 0.3
#: the field directions must spread this much (rad RMS, across the second direction) for that strength to be judged
SCALE_SPREAD = 0.1


def covered(prior: MagPrior, delta: FloatArray, acc: FloatArray, dip: float | None, y: FloatArray) -> MagPrior:
    """The prior with the motion's coverage (`motion_coverage`); a flown calibration's D rescaled when its strength is
    not the one the readings (N, 3) show for that motion (the readings' spread about their own mean over the unit
    field's, two largest principal spreads, which no prior enters), and its offsets then where they centre."""
    spread, yaw, flat = motion_coverage(delta, acc, dip)
    clean, _ = despike(y)                    # an isolated spike would inflate the readings' spread
    x = clean - clean.mean(axis=0)
    seen = np.sqrt(np.clip(np.linalg.eigvalsh(x.T @ x / len(x)), 0.0, None))[::-1]
    out = replace(prior, spread=spread, yaw_deg=yaw, flat_axis=flat)
    if spread[1] < SCALE_SPREAD or prior.from_readings:
        # a narrow cap shows no strength to compare with; a sphere through the readings is already their scale
        return out
    strength = float(np.sqrt(seen[0] * seen[1] / (spread[0] * spread[1])))
    held = float(np.cbrt(abs(np.linalg.det(prior.D))))
    if abs(held / strength - 1.0) <= max(SCALE_MISMATCH, 3.0 * prior.rel_std):
        return out
    # no calibration of this sensor: its offsets are where the readings centre, its scale what the motion shows
    return replace(out, D=prior.D * (strength / held), o=sphere_prior(y).o, rel_std=max(prior.rel_std, SPHERE_REL_STD),
                   source=f"{prior.source}, rescaled by {strength / held:.2f} to the field strength the motion shows "
                          "(as flown it does not fit this sensor)",
                   offset_source="the centre of the readings (the calibration the vehicle flew with does not fit this "
                                 "sensor)")


def cap_needs(rel_std: float) -> tuple[float, float]:
    """The RMS spreads (rad) of the field directions below which a cap cannot determine a plane of D better than a
    prior of this doubt, and the offsets at all (with D held).

    Over a cap, y = (D u0 + o) + D (u - u0): D's action on the directions the cap spreads along is measured with a
    lever of the spread s, so a direction error e that no averaging removes (DIRECTION_ERROR) becomes an error e / s
    of D there: a plane of D needs s2 >= e / rel_std. With D held, the offsets follow from where in the body the
    field points (its dip and heading at the cap), which the gyro-measured turning fixes to e / s1 of the field:
    they need s1 >= e / OFFSET_FATAL."""
    return DIRECTION_ERROR / rel_std, DIRECTION_ERROR / OFFSET_FATAL


def cap_pins(prior: MagPrior) -> tuple[IntArray, str]:
    """The base columns a narrow cap of field directions cannot determine (`cap_needs`): every entry of D when no
    plane of it is determined (an offsets-only fit), D and o when not even the offsets are; and why."""
    if prior.spread is None:
        return np.zeros(0, np.int64), ""
    plane, offsets = cap_needs(prior.rel_std)
    s1, s2 = np.degrees(prior.spread[:2])
    arc = float(np.sqrt(12.0))           # a uniform sweep through an arc of angle a spreads a / sqrt(12) RMS
    turned = prior.yaw_deg is not None and prior.yaw_deg >= OFFSETS_YAW_DEG
    if prior.fallback and turned:
        column = prior.fallback == 1 and prior.flat_axis is not None
        axis = 0 if prior.flat_axis is None else prior.flat_axis
        cols = BASE.cols("D")[3 * axis:3 * axis + 3] if column else BASE.cols("D")
        what = f"D's column along body axis {'xyz'[axis]}" if column else "D"
        return cols, (f"the full calibration could not be determined; the vehicle turned through {prior.yaw_deg:.0f} "
                      f"deg of heading, so the offsets are estimated with {what} held")
    if prior.spread[0] < offsets and not turned:
        return BASE.cols("D", "o"), (
            f"the field directions moved through an arc of only {arc * s1:.0f} deg ({s1:.1f} deg RMS about their "
            f"mean); the offsets need {arc * np.degrees(offsets):.0f} deg: turn the vehicle through at least that "
            "about an axis away from the field, e.g. a full turn about the vertical")
    if prior.spread[1] < plane and prior.rel_std >= SPHERE_REL_STD and not turned:
        return BASE.cols("D", "o"), (
            f"the field directions stayed in a narrow cap ({s1:.1f} x {s2:.1f} deg RMS): the offsets alone would need D "
            f"from the calibration the vehicle flew with, and a sphere through such a cap is none (a plane of D needs "
            f"{np.degrees(plane):.0f} deg RMS across two directions)")
    if prior.spread[1] < plane or prior.spread[0] < offsets:
        turn = f"; the vehicle turned through {prior.yaw_deg:.0f} deg of heading, so the offsets are estimated" \
            if turned else ""
        return BASE.cols("D"), (
            f"the field directions stayed in a narrow cap ({s1:.1f} x {s2:.1f} deg RMS), which cannot determine D "
            f"(that needs {np.degrees(plane):.0f} deg RMS across two directions){turn}")
    return np.zeros(0, np.int64), ""


#: the field directions' third principal spread (rad RMS) below which the motion was a vehicle's, turning about one
#: body axis near the vertical (the issue's 3-compass flight, tilt within 16 deg: 0.03); a hand-held half sphere
#: (x-io's sensor_data.csv: 0.14) has no heading whose turn fixes the offsets, and what it fixes the information says
LEVEL_SPREAD = 0.1


def turned_offsets(prior: MagPrior) -> IntArray:
    """The base columns of the horizontal offsets (those off the body axis nearest the vertical) when the vehicle
    turned through at least OFFSETS_YAW_DEG of heading while staying near level (LEVEL_SPREAD), else none: the horizontal field then swept at least half a
    circle about that axis, whose centre they are (issue 25 item 5, issue 38 item 3). The information may still say
    the data know them worse than their prior (residuals correlated in time widen it): they are then estimated with
    that larger std, not pinned at a prior that the turn itself contradicts."""
    tumbled = prior.spread is not None and float(prior.spread[2]) > LEVEL_SPREAD
    if prior.yaw_deg is None or prior.yaw_deg < OFFSETS_YAW_DEG or tumbled:
        return np.zeros(0, np.int64)
    vertical = 2 if prior.flat_axis is None else prior.flat_axis
    return np.array([c for i, c in enumerate(BASE.cols("o")) if i != vertical], np.int64)


def prior_of(layout: Layout, theta: FloatArray, prior: MagPrior, scale: float, dip_ref: float | None) -> Held:
    """Prior mean, std and source of every base entry in internal units (D and o divided by `scale`, tesla),
    holding nothing yet but pinning what the cap of field directions cannot determine (`cap_pins`)."""
    mean = BASE.zeros()
    std = BASE.zeros()
    src = [""] * BASE.size
    for name, value, sd, why in (
            ("accelerometer_bias", np.zeros(3), ACCEL_BIAS_STD, "no bias beyond the factory calibration"),
            ("gyroscope_bias", np.zeros(3), GYRO_BIAS_STD, "the still segments' gyro bias (zero without any)"),
            ("D", prior.D.ravel(order="F") / scale, prior.rel_std, prior.source),
            ("o", prior.o / scale, prior.rel_std, prior.offset_source or prior.source),
            ("dip", np.atleast_1d(layout.get(theta, "dip")[0] if dip_ref is None else dip_ref),
             DIP_DATA_STD if dip_ref is None else DIP_REF_STD,
             "the data's start value (no position for the World Magnetic Model)" if dip_ref is None else
             "the World Magnetic Model")):
        sl = BASE.slice(name)
        mean[sl], std[sl] = value, sd
        src[sl] = [why] * (sl.stop - sl.start)
    pins, why = cap_pins(prior)
    for c in pins:
        src[c] = f"{src[c]}{PINNED}{why}"
    o = BASE.slice("o")
    if pins.size and not np.isin(BASE.cols("o"), pins).any():
        # an offsets-only fit: what goes stale in a flown calibration is the offsets (a new payload, wiring), so they
        # are estimated unless the data know them worse than an undetermined offset, D's doubt included
        std[o] = np.maximum(std[o], OFFSET_FATAL)
    return replace(Held(np.zeros(0, np.int64), mean, std, tuple(src), pins).placed(layout),
                   free=np.setdiff1d(turned_offsets(prior), pins).astype(np.int64))


def implausible(theta: FloatArray, held: Held) -> IntArray:
    """Free IMU-bias and dip entries more than IMPLAUSIBLE_SIGMAS prior stds from their priors."""
    cols = BASE.cols("accelerometer_bias", "gyroscope_bias", "dip")
    far = np.abs(theta[held.at[cols]] - held.prior_mean[cols]) > IMPLAUSIBLE_SIGMAS * held.prior_std[cols]
    return np.setdiff1d(cols[far], held.cols).astype(np.int64)


def posterior_std(info: FloatArray, prior_std: FloatArray, held: IntArray) -> FloatArray:
    """Standard deviations of every entry when the `held` ones carry their priors (the data's information plus
    1/std^2 on the held entries), from an information matrix that may be singular (scaled to unit diagonal,
    then a tiny ridge: undetermined entries come out huge, not NaN). The held entries' doubt reaches the free
    entries confounded with them, as in the reported covariance."""
    full = info.copy()
    held = np.asarray(held, np.int64)
    full[held, held] += 1.0 / prior_std[held] ** 2
    d = np.diag(full).copy()
    none = d <= 0.0
    d[none] = 1.0
    js = 1.0 / np.sqrt(d)
    scaled = js[:, None] * full * js[None, :]
    scaled[np.ix_(none, none)] = np.eye(int(none.sum()))
    var = np.diag(np.linalg.inv(scaled + 1e-12 * np.eye(d.size))) * js**2
    return np.where(none, np.inf, np.sqrt(np.clip(var, 0.0, None)))


def _excess(info: FloatArray, prior_std: FloatArray, held: list[int]) -> tuple[FloatArray, IntArray, float]:
    """Each free base entry's posterior std / prior std, the free base columns, and the total log excess over 1
    (effect columns, which have no prior, are never judged)."""
    free = np.array([c for c in range(prior_std.size) if c not in held], np.int64)
    sd = posterior_std(info, prior_std, np.array(held, np.int64))
    ratio = sd[free] / prior_std[free]
    return ratio, free, float(np.sum(np.log(np.maximum(ratio, 1.0))))


def choose(info: FloatArray, prior_std: FloatArray, already: IntArray | None = None,
           rank: IntArray | None = None) -> IntArray:
    """The base columns to hold besides `already`, until every free base entry's std (the held entries' doubt
    included) is below its prior std: holding it then loses nothing the data knew.

    Each step holds the over-threshold entry whose holding leaves the least total excess (sum of log std/prior
    over the free entries): a rotation of D about the one axis a flat log turns about is fixed by one entry
    that changes to first order (D.10), not by the diagonal one. PREFERENCE breaks ties (a column of D before
    the offset it is confounded with). `info` covers the whole theta (base blocks first, then any effect
    blocks, which stay free). Another parameter vector (the attitude method's per-axis coefficients) gives its own
    `rank` (PREFERENCE's order per entry) and `prior_std` (inf: never held)."""
    if rank is None:
        rank = np.concatenate([np.full(b.size, PREFERENCE.get(b.name, 9)) for b in BASE.blocks])
    held = [] if already is None else [int(c) for c in already]
    while True:
        ratio, free, _ = _excess(info, prior_std, held)
        over = free[ratio > 1.0]
        if over.size == 0:
            return np.array(sorted(held), np.int64)
        left = [_excess(info, prior_std, [*held, int(c)])[2] + 1e-3 * rank[c] for c in over]
        held.append(int(over[int(np.argmin(left))]))


def priors_by_id(priors: Mapping[str, MagPrior], mag_id: str, y: FloatArray) -> MagPrior:
    """The vehicle's own calibration of this magnetometer where the log has one, else a sphere fit to the readings
    (N, 3) tesla; the motion's coverage is measured by the fit (`motion_coverage`)."""
    return priors.get(mag_id) or sphere_prior(y)
