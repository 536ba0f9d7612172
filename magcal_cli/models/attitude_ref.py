"""The vehicle's attitude as the reference (issue 12 item 2; `--method attitude`).

Where the autopilot logged its attitude estimate R_k (body -> true-north NED; ArduPilot ATT, PX4
vehicle_attitude) and a position, the field the compass should read is known: y_k = D R_k^T m + o with m the
World Magnetic Model's direction (declination and dip) at the log's position and date. The model is linear in
(D, o), so each sensor axis is one small least-squares problem (ArduPilot WebTools MAGFit and pymavlink's
magfit_WMM.py fit the same model with an iterative optimiser). What the attitude does not vary (the body-z
field of a level flight) is held at the prior the partial calibration uses (the onboard calibration, else a
sphere): as in the joint MAP (`partial.choose`), an entry the data, their correlation in time counted, know no
better than its prior is held there, and the entries it is confounded with are estimated around it. The EKF's
attitude errors are correlated in time, so the uncertainty is a block sandwich (10 s blocks) and never below the
model-based one.

Before issue 30 the held entries were only named after the fit (posterior std above half the prior's): their values
were the data's, which a level flight's small tilts (and the EKF's correlated attitude errors) pull along the
direction the data cannot see. 01_07_59.px4log's MAG[0] ended with "held" offsets at -82 and +85 mG against a
prior of 0 +- 28 mG, each with the z column of D moved the opposite way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import align, so3
from magcal_cli.config import Config
from magcal_cli.effects.base import NotTestable
from magcal_cli.effects.current import Current, varying_current
from magcal_cli.errors import InsufficientDataError, UnexplainedError
from magcal_cli.models import partial
from magcal_cli.models.kok2012 import gyro_bias_from_still
from magcal_cli.models.map.effects import ALPHA
from magcal_cli.models.map.hold import PARTIAL_MAX_NORM_RMS as MAX_NORM_RMS
from magcal_cli.models.observability import NONUNIFORM_ADVICE
from magcal_cli.models.partial import MagPrior, sphere_prior
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit, HeldEntry, MagFit, MethodResult
from magcal_cli.params import MAG, Estimate, Layout
from magcal_cli.streams import FloatArray, Kind, Stream
from magcal_cli.wmm import ReferenceField, reference_for

#: attitude streams whose nav frame is NED with x to true north (ArduPilot, PX4); a mocap or ROS frame is not
NED_ATTITUDES = ("ATT", "vehicle_attitude", "AHR2")
#: the WMM's stated 1-sigma error of the inclination (WMM2020 report, Table 5): 0.21 deg
WMM_DIP_STD = np.deg2rad(0.21)
#: block length (s) of the sandwich: the EKF's attitude error wanders over seconds
BLOCK_S = 10.0
#: which entry of an axis [D_i0, D_i1, D_i2, o_i, c_i] gives way first when the data cannot separate two (a column
#: of D before the offset it is confounded with, as `partial.PREFERENCE`); the interference has no prior, never held
AXIS_RANK = np.array([partial.PREFERENCE["D"]] * 3 + [partial.PREFERENCE["o"], 9])
#: Huber threshold (robust std) for readings the attitude or the field do not explain (spikes, transients)
HUBER_K = 3.0
#: a battery current that varies less than this (A, std) cannot separate interference from the offsets
MIN_CURRENT_STD = 1.0


def current_at(problem: Problem, t: FloatArray) -> tuple[FloatArray, str] | None:
    """The battery current (A) at times t where the log's varies enough to fit interference (magfit_WMM's
    --cmot), with its channel id; else None."""
    for s in problem.channels(Kind.BATTERY_CURRENT):
        try:
            return varying_current(s, t, MIN_CURRENT_STD), s.id
        except NotTestable:
            continue
    return None


def attitude_stream(problem: Problem) -> Stream:
    """The autopilot's attitude estimate among the problem's channels, in a true-north NED frame."""
    found = {s.id: s for s in problem.channels(Kind.ATTITUDE)}
    for sid in NED_ATTITUDES:
        if sid in found:
            return found[sid]
    have = f" (it has {', '.join(found)}, whose frame is not known to be north-east-down)" if found else ""
    msg = (f"{problem.where}: --method attitude needs the autopilot's attitude estimate (ArduPilot ATT, PX4 "
           f"vehicle_attitude){have}; use --method auto")
    raise InsufficientDataError(msg)


@dataclass(frozen=True, eq=False)
class AxisFit:
    """One sensor axis fitted: the coefficients, their covariance (block sandwich, never below the model's), the
    noise std, the residuals, and the data's information about the coefficients narrowed by the sandwich's widening
    (what the data know, their correlation in time counted; without the prior)."""

    beta: FloatArray
    cov: FloatArray
    sigma: float
    r: FloatArray
    info: FloatArray


def _solve_axis(x: FloatArray, y: FloatArray, prior_mean: FloatArray, prior_var: FloatArray,
                blocks: npt.NDArray[np.int64], held: npt.NDArray[np.int64] | None = None) -> AxisFit:
    """Robust MAP of y = x beta (+ Gaussian prior), its covariance and the data's information.

    The `held` coefficients are pinned at their prior means (`partial.PIN`) while fitting; the covariance carries
    their prior's own doubt (a soft prior) into the free ones, as the joint MAP's does. The widening is one factor
    for every coefficient, the largest sandwich / model variance ratio of a free one (the sandwich taken with the
    held ones fixed: their scores at the pinned value are the prior's pull, not noise).
    """
    held = np.zeros(0, np.int64) if held is None else held
    free = np.setdiff1d(np.arange(x.shape[1]), held)
    w = np.ones(y.size)
    beta = np.linalg.lstsq(x, y, rcond=None)[0]
    p = 1.0 / prior_var
    p_fit = p.copy()
    p_fit[held] = p[held] / partial.PIN**2
    for _ in range(4):                                            # Huber IRLS: a few rounds settle it
        r = y - x @ beta
        sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-15)
        w = np.minimum(1.0, HUBER_K * sigma / np.maximum(np.abs(r), 1e-300))
        data = (x * (w / sigma**2)[:, None]).T @ x
        beta = np.linalg.solve(data + np.diag(p_fit), (x * (w / sigma**2)[:, None]).T @ y + p_fit * prior_mean)
    r = y - x @ beta
    # the sandwich of the free coefficients with the held ones fixed (the model's, conditional on them)
    ff = np.ix_(free, free)
    model = np.linalg.inv(data[ff] + np.diag(p[free]))
    score = x[:, free] * (w * r / sigma**2)[:, None]
    per_block = np.zeros((int(blocks.max()) + 1, free.size))
    np.add.at(per_block, blocks, score)
    meat = per_block.T @ per_block + np.diag(p[free])
    sandwich = model @ meat @ model
    ratio = np.maximum(np.diag(sandwich) / np.diag(model), 1.0)
    most = float(np.max(ratio, initial=1.0))
    cov = np.asarray(np.linalg.inv(data + np.diag(p)) * most, dtype=np.float64)
    if held.size:
        # a held coefficient reports its prior's std (issue 38), not the soft prior's widened posterior: its rows and
        # columns are scaled, which keeps the correlations and the free block
        f = np.ones(x.shape[1])
        f[held] = np.sqrt(prior_var[held] / np.diag(cov)[held])
        cov = cov * np.outer(f, f)
    widen = np.full(x.shape[1], np.sqrt(most))
    widen[free] = np.sqrt(ratio)
    return AxisFit(np.asarray(beta, dtype=np.float64), cov, sigma, r, data / np.outer(widen, widen))


def _held_fit(x: FloatArray, y: FloatArray, prior_mean: FloatArray, prior_var: FloatArray,
              blocks: npt.NDArray[np.int64], free: tuple[int, ...] = ()) -> tuple[AxisFit, npt.NDArray[np.int64]]:
    """The axis fitted with what the data, their correlation in time counted, know no better than the prior held
    at it (`partial.choose`, as the joint MAP holds its entries), rather than left to wander along the direction
    the attitude does not vary; and the coefficients held. Holding changes the residuals and so the widening: the
    choice is redone at the new fit, keeping what is held, until it stays. The `free` coefficients are never held
    (a horizontal axis's offset after a half turn of heading: `turned_axes`)."""
    fitted = _solve_axis(x, y, prior_mean, prior_var, blocks)
    held = np.zeros(0, np.int64)
    judged = np.sqrt(prior_var)
    judged[list(free)] = np.inf                   # choose: an infinite prior std is never held
    for _ in range(x.shape[1]):
        more = partial.choose(fitted.info, judged, held, AXIS_RANK[:x.shape[1]])
        if more.size == held.size:
            break
        held = more
        fitted = _solve_axis(x, y, prior_mean, prior_var, blocks, held)
    return fitted, held


def turned_axes(rot: FloatArray) -> tuple[int, ...]:
    """The body axes whose offsets a turn of the attitude (N, 3, 3) body -> NED determines whatever their prior:
    those off the axis nearest the mean vertical, when the heading turned through at least
    `partial.OFFSETS_YAW_DEG` (issue 25 item 5, issue 38 item 3), else none."""
    heading = np.unwrap(np.arctan2(rot[:, 1, 0], rot[:, 0, 0]))
    if np.degrees(np.ptp(heading)) < partial.OFFSETS_YAW_DEG:
        return ()
    vertical = int(np.argmax(np.abs(rot[:, 2, :].mean(axis=0))))      # R^T e_z: NED down in the body
    return tuple(i for i in range(3) if i != vertical)


def fit_attitude(problem: Problem, mag: Stream, att: Stream, ref: ReferenceField,
                 prior: MagPrior | None) -> tuple[MagFit, EffectFit | None]:
    """D and o of one magnetometer against the vehicle's attitude and the WMM field (SI), with the current
    interference c (y += c I) where the log's current varies."""
    # scipy.stats.chi2.sf computes it so, and importing scipy.stats costs 0.2-1.2 s (issue 27)
    from scipy.special import chdtrc

    where = f"{problem.where}: {mag.id}"
    ok, q = align.onto(att, mag.t)                    # slerped, inside the attitude's span, no gap bridged
    rot = np.full((mag.t.size, 3, 3), np.nan)
    rot[ok] = so3.from_quat(q)
    for a, b in problem.unmeasured:
        ok &= ~((mag.t >= a) & (mag.t <= b))
    ok &= np.all(np.isfinite(mag.xyz), axis=1)
    if ok.sum() < 50:
        msg = (f"{where}: only {int(ok.sum())} readings lie inside the attitude estimate's time span; "
               "--method attitude needs the autopilot's attitude over the flight")
        raise InsufficientDataError(msg)
    c, s = np.cos(ref.dip), np.sin(ref.dip)
    m_true = np.array([c * np.cos(ref.declination), c * np.sin(ref.declination), s])
    u = np.einsum("nji,j->ni", rot[ok], m_true)                     # R^T m: the unit field in the body frame
    y, t = mag.xyz[ok], mag.t[ok]
    prior = prior or sphere_prior(y)
    scale = float(np.cbrt(abs(np.linalg.det(prior.D)))) or float(np.median(np.linalg.norm(y, axis=1)))
    sd = prior.rel_std * scale
    current = current_at(problem, t)
    x = np.column_stack([u, np.ones(len(u))] + ([] if current is None else [current[0]]))
    blocks = np.floor((t - t[0]) / BLOCK_S).astype(np.int64)
    d, o, c_i = np.zeros((3, 3)), np.zeros(3), np.zeros(3)
    c_var = np.zeros(3)
    cov = np.zeros((MAG.size, MAG.size))
    held: list[HeldEntry] = []
    horizontal = turned_axes(rot[ok])
    rms = []
    for i in range(3):
        mean = np.append(prior.D[i], prior.o[i])
        var = np.full(4, sd**2)
        if current is not None:                                   # no prior on the interference: free
            mean, var = np.append(mean, 0.0), np.append(var, np.inf)
        fitted, hold = _held_fit(x, y[:, i], mean, var, blocks, (3,) if i in horizontal else ())
        beta, cv, r = fitted.beta, fitted.cov, fitted.r
        d[i], o[i] = beta[:3], beta[3]
        if current is not None:
            c_i[i], c_var[i] = beta[4], cv[4, 4]
            cv = cv[:4, :4]
        rms.append(float(np.sqrt(np.mean(r**2))))
        cols = [MAG.cols("D")[i + 3 * j] for j in range(3)] + [MAG.cols("o")[i]]
        cov[np.ix_(cols, cols)] = cv
        names = [f"D.{i}{k}" for k in range(3)] + [f"o.{'xyz'[i]}"]
        held.extend(HeldEntry(names[j], float(mean[j]), sd, prior.source) for j in hold)
    # a compass no calibration explains is refused, not passed on (issue 38): judged by the residual against the
    # reference field, which a held column of D cannot inflate as it can the calibrated field strength
    misfit = float(np.sqrt(np.sum(np.square(rms)))) / scale
    if misfit > MAX_NORM_RMS:
        msg = (f"{where}: no calibration against the vehicle's attitude explains these readings either (they miss "
               f"the reference field by {100 * misfit:.0f} % of its strength RMS): the sensor is faulty, or the field "
               f"around it changed during the log. To fix: {NONUNIFORM_ADVICE}")
        raise UnexplainedError(msg)
    dip_col = MAG.cols("dip")[0]
    cov[dip_col, dip_col] = WMM_DIP_STD**2
    log = (f"{mag.id}: reference: the vehicle's attitude ({att.id}) and the {ref.model} field at "
           f"{ref.latitude:.4f}, {ref.longitude:.4f} on {ref.date} (dip {ref.dip_deg:.2f} deg, declination "
           f"{np.rad2deg(ref.declination):.2f} deg); {int(ok.sum())} readings",)
    fit = MagFit(mag.id, d, o, ref.dip, cov, float(np.sqrt(np.mean(np.square(rms)))), int(ok.sum()), 4, True,
                 log, tuple(held), reference=f"vehicle attitude ({att.id}) + {ref.model}")
    if current is None:
        return fit, None
    # the axes are fitted separately: their c are independent to this order (the sandwich keeps the widening)
    est = Estimate(Layout(Current.params), c_i, np.diag(c_var))
    stat = float(np.sum(c_i**2 / c_var))
    p = float(chdtrc(3, stat))
    return fit, EffectFit(Current.id, mag.id, "accepted" if p < ALPHA else "rejected", est, (current[1],), stat, 3, p)


def run(problem: Problem, cfg: Config) -> MethodResult:
    """Every magnetometer of the problem against the vehicle's attitude and the WMM."""
    att = attitude_stream(problem)
    ref = reference_for(cfg)
    if ref is None:
        msg = (f"{problem.where}: --method attitude needs the log's position (GPS) or --location LAT,LON for the "
               "World Magnetic Model's field; use --method auto")
        raise InsufficientDataError(msg)
    done = [fit_attitude(problem, m, att, ref, problem.priors.get(m.id)) for m in problem.mags]
    fits = tuple(f for f, _ in done)
    notes = tuple(line for f in fits for line in f.log)
    effects = tuple(e for _, e in done if e is not None)
    return MethodResult("attitude", fits, gyro_bias_from_still(problem), {}, notes, effects=effects)
