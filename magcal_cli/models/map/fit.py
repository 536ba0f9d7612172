"""Huang et al. 2025: joint MAP calibration of magnetometer, accelerometer and gyro biases (`--method map`).

Unknowns (methods.md section 3): theta = (b_a, db_g, vec D, o, dip) (19) and the orientations R_k at the
magnetometer epochs. Factors: accelerometer and magnetometer at every epoch, gyro preintegration between
consecutive epochs. The one solver (`solve.py`) eliminates the block-tridiagonal trajectory; the marginal
covariance of theta is the inverse Schur complement. The noise levels are re-estimated from the residuals with
leverage-corrected degrees of freedom (variance components), so the reported covariance matches the data.

Internally the magnetometer is expressed in units of its ellipsoid-fit scale (D ~ I); results are in SI.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from magcal_cli import so3
from magcal_cli.detect import MIN_STILL_S
from magcal_cli.effects import get
from magcal_cli.effects.base import Point, Target
from magcal_cli.errors import InsufficientDataError
from magcal_cli.findings import Finding, Severity
from magcal_cli.models import partial
from magcal_cli.models.accel import G, accel_factor
from magcal_cli.models.epochs import Epochs, Noise, epochs_for, initial_noise
from magcal_cli.models.gyro import Preintegrated, gyro_factor, preintegrate_log
from magcal_cli.models.mag import MagLayout, field_nav, mag_factor
from magcal_cli.models.map import init as map_init
from magcal_cli.models.map.effects import (
    Bound,
    bind,
    gyro_extra,
    layout_for,
    prior_factor,
    results,
    row_weights,
    terms,
    with_terms,
)
from magcal_cli.models.observability import ROTATE_ADVICE, check_observability, check_useful
from magcal_cli.models.partial import Held
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit
from magcal_cli.models.sandwich import factor_clusters, time_clusters, widening
from magcal_cli.models.solve import (
    Factor,
    Linearize,
    Options,
    Solution,
    information,
    marginal_covariance,
    one_blas_thread,
    solve,
)
from magcal_cli.params import BASE, Layout
from magcal_cli.progress import current
from magcal_cli.streams import FloatArray, Stream

#: theta layout: accelerometer bias, gyro bias correction, then D (column-major), o, dip
#: rounds of (solve, re-estimate the noise levels); stop when no level changes by more than NOISE_TOL
NOISE_ROUNDS = 6
NOISE_TOL = 0.03
#: slope of the gyro's variance-factor fixed point (d log factor / d log variance) assumed for the first step
FIRST_GYRO_SLOPE = -0.7
#: a partial calibration's covariance damps the trajectory blocks by this trace: a flat log's nearly rigid
#: trajectory otherwise cancels theta's information in the Schur complement (models/solve.py `information`)
TRAJECTORY_DAMPING = 1e-9
#: the gyro variance never drops below this factor (log) of its start value (100x lower std)
MIN_GYRO_LOG_VARIANCE = float(np.log(1e-4))
#: re-preintegrate when the first-order bias correction rotates an interval by more than this (rad)
REPREINTEGRATE_RAD = 0.01
@dataclass(frozen=True, eq=False)
class FitContext:
    """What the solver saw at the optimum, in its internal (scaled) units: the diagnosis re-evaluates, extends
    and simulates the fit from here (diagnose/)."""

    ep: Epochs
    pre: Preintegrated
    noise: Noise
    layout: Layout
    bound: tuple[Bound, ...]
    states: FloatArray
    theta: FloatArray
    holdout: FloatArray | None = None
    held: Held | None = None
    #: (K,) 0 at readings inside windows the IMU did not measure (Problem.unmeasured): never part of any cost
    excluded: FloatArray | None = None

    def linearize(self, layout: Layout | None = None, bound: tuple[Bound, ...] | None = None,
                  ep: Epochs | None = None, pre: Preintegrated | None = None,
                  holdout: FloatArray | None = None) -> Linearize:
        """The fit's cost, optionally with another layout and effects, data or held-out weights."""
        w = self.excluded if holdout is None else holdout if self.excluded is None else holdout * self.excluded
        return make_linearize(self.ep if ep is None else ep, self.pre if pre is None else pre, self.noise,
                              self.layout if layout is None else layout, self.bound if bound is None else bound,
                              w, self.held)


@dataclass(frozen=True, eq=False)
class MapEstimate:
    """One magnetometer's joint MAP result in SI: theta in `layout` (b_a, b_g, D, o, dip and any effect blocks)
    with the *total* gyro bias, its covariance, the noise levels used (SI), the trajectory and the solver's
    record, and the effects fitted or found not testable."""

    mag_id: str
    theta: FloatArray
    cov: FloatArray
    noise: Noise
    states: FloatArray
    epochs: FloatArray
    cost: float
    iterations: int
    converged: bool
    residual_rms: float
    log: tuple[str, ...]
    findings: tuple[Finding, ...] = ()
    notes: tuple[str, ...] = ()
    condition: float = float("nan")
    layout: Layout = BASE
    effects: tuple[EffectFit, ...] = ()
    context: FitContext | None = None
    #: entries the log could not determine, held at a prior (partial calibration, models/partial.py)
    held: Held | None = None

    @property
    def std(self) -> FloatArray:
        """Marginal standard deviations of theta (SI)."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def value(self, name: str) -> FloatArray:
        """Block `name` of theta (SI)."""
        return self.layout.get(self.theta, name)

    def std_of(self, name: str) -> FloatArray:
        """Marginal standard deviations of block `name` (SI)."""
        return self.std[self.layout.slice(name)]

    def base(self) -> tuple[FloatArray, FloatArray]:
        """theta and covariance of the base blocks only, in BASE order."""
        c = self.layout.cols(*BASE.names)
        return self.theta[c], self.cov[np.ix_(c, c)]


def _scaled(f: Factor, s: FloatArray) -> Factor:
    """A factor's rows multiplied by s (M,)."""
    def mul(a: FloatArray | None) -> FloatArray | None:
        return None if a is None else a * s.reshape((-1,) + (1,) * (a.ndim - 1))
    return Factor(f.name, f.r * s[:, None], f.idx, mul(f.J_x), mul(f.J_next), mul(f.J_theta), f.theta_cols)


def mag_layout(layout: Layout) -> MagLayout:
    """Where the magnetometer factor finds D, o and the dip in theta."""
    return MagLayout(layout.slice("D").start, layout.slice("o").start, layout.slice("dip").start)


def point_at(states: FloatArray, theta: FloatArray, layout: Layout, pre: Preintegrated) -> Point:
    """The model at an iterate, as the effect terms see it (effects/base.py `Point`)."""
    d, _, dip = mag_layout(layout).unpack(theta)
    return Point(states, np.einsum("mji,j->mi", states, field_nav(dip)),
                 np.einsum("mji,j->mi", states, np.array([-np.sin(dip), 0.0, np.cos(dip)])),
                 G * states[:, 2, :], d, pre)


def make_linearize(ep: Epochs, pre: Preintegrated, noise: Noise, layout: Layout = BASE,
                   bound: tuple[Bound, ...] = (), holdout: FloatArray | None = None,
                   held: Held | None = None) -> Linearize:
    """Accelerometer, magnetometer and gyro-preintegration factors of the MAP cost (methods.md section 3), with
    the terms of the bound effects added to the factors they enter (map_effects.py). `holdout` (K,) weights
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

    def linearize(states: FloatArray, theta: FloatArray, jac: bool) -> list[Factor]:
        fa = accel_factor(states, ep.acc, l_acc, theta, ba, idx, jacobians=jac, compact=True)
        fm = mag_factor(states, ep.mag, l_mag, theta, ml, idx, jac, compact=True)
        extra = None
        if bound:
            at = point_at(states, theta, layout, pre)
            fa = with_terms(fa, l_acc, terms(bound, layout, theta, at, Target.ACCEL), layout)
            fm = with_terms(fm, l_mag, terms(bound, layout, theta, at, Target.MAG), layout)
            extra = gyro_extra(bound, layout, theta, at)
        if interpolated:
            fa = _scaled(fa, s_acc)
        if w_mag is not None:
            fm = _scaled(fm, w_mag)
        out = [fa, fm, gyro_factor(states, theta, pre, bg, jac, extra)]   # gyro noise is in pre.l_inv
        prior = prior_factor(bound, layout, theta, jac)
        out = out if prior is None else [*out, prior]
        return out if held is None else [*out, held.factor(theta, jac)]

    return linearize


def variance_ratios(sol: Solution, loss: str = "l2", c: float = 3.0) -> FloatArray:
    """Variance factors sum(r^2) / (rows - leverage): accelerometer (3 axes), gyro (1), magnetometer (3).

    The leverage (trace of the hat matrix over a group's rows) counts the degrees of freedom the unknowns take
    from that group (Foerstner's variance-component estimation); a factor of 1 means the assumed noise level
    fits. With a robust loss each row's |r|^2 is truncated at c^2 and divided by its expectation under the
    model (E min(chi2_m, c^2) / m), one factor per group: outliers then cannot inflate the levels.
    """
    marg = sol.marginals()
    out = {f.name: group_ratio(f, sol.leverage(f, marg).sum(axis=0), loss, c) for f in sol.factors}
    return np.concatenate([out["accel"], out["gyro"], out["mag"]])


def group_ratio(f: Factor, leverage: FloatArray, loss: str = "l2", c: float = 3.0) -> FloatArray:
    """One factor group's variance factor per axis (one for the gyro), sum(r^2) / (rows - leverage), from its
    leverage summed over rows per axis (`variance_ratios`)."""
    m = f.r.shape[1]
    # rows weighted to zero (excluded readings) carry no information and no residual: do not count them
    rows = f.r.shape[0] if f.J_theta is None else int(np.count_nonzero(np.any(f.J_theta != 0.0, axis=(1, 2))))
    if loss != "l2":
        s2 = np.minimum(np.sum(f.r**2, axis=1), c * c)
        # E[min(X, c^2)] for X ~ chi2_m: m F_(m+2)(c^2) + c^2 (1 - F_m(c^2))
        kappa = (m * stats.chi2.cdf(c * c, m + 2) + c * c * stats.chi2.sf(c * c, m)) / m
        width = 1 if f.name == "gyro" else m
        ss = np.full(width, s2.sum() / kappa / m)
        dof = np.full(width, (rows * m - leverage.sum()) / m)
    else:
        ss, dof = np.sum(f.r**2, axis=0), rows - leverage
        if f.name == "gyro":
            ss, dof = ss.sum(keepdims=True), dof.sum(keepdims=True)
    out: FloatArray = np.where(dof > 10.0, ss / np.maximum(dof, 1e-300), 1.0)
    return out


def _levels(noise: Noise) -> FloatArray:
    """The 7 noise levels in variance_ratios order (accelerometer 3, gyro 1, magnetometer 3)."""
    return np.concatenate([noise.acc, noise.gyr[:1], noise.mag])


def _secant(history: list[tuple[float, float]], x: float, f: float) -> float:
    """Next step for the gyro log-variance x whose fixed-point residual is f (the log variance factor).

    The plain update x += f converges linearly with rate 1 + slope, slowly for the weakly determined gyro
    level; a secant step on f(x) = 0 (slope clipped to [-1, -0.1], so at most 10 plain steps) converges in a
    few rounds. The first step assumes the slope the paper protocol shows from below (FIRST_GYRO_SLOPE).
    """
    slope = FIRST_GYRO_SLOPE
    if history:
        x0, f0 = history[-1]
        if abs(x - x0) > 1e-12:
            slope = (f - f0) / (x - x0)
    if slope > -0.1:           # not a fixed-point slope: the other levels moved the factor (coupling)
        slope = FIRST_GYRO_SLOPE
    return -f / float(max(slope, -1.0))


def noise_step(step: FloatArray, floor: FloatArray | None, levels: FloatArray, history: list[tuple[float, float]],
               applied: float) -> tuple[FloatArray, bool, float]:
    """One noise round's log-variance step (gyro at index 3) from the measured factors `step`: whether it is small
    enough to stop, and the gyro's measured factor (for the secant history)."""
    if floor is not None:
        # still data measured the sensors' white noise: levels never go below it, and the gyro keeps it; where it
        # moves, the gyro's own noise is measured sample by sample (Problem.gyr_scale: a flight's vibration).
        # Estimated from the residuals instead, the gyro level absorbs every misfit of the other factors and runs
        # away (x 280 on the x-io log), docs/method-map.md
        step[3] = 0.0
        step = np.maximum(step, 2.0 * np.log(floor / levels))
    small = float(np.max(np.abs(step))) < 2.0 * NOISE_TOL
    measured = float(step[3])
    step[3] = _secant(history, applied, measured) if floor is None else 0.0
    # without still data the gyro level is weakly determined: when the other factors misfit (flight, too
    # little rotation) its fixed point runs away toward zero and the trajectory becomes numerically rigid
    step[3] = max(step[3], MIN_GYRO_LOG_VARIANCE - applied)
    return step, small, measured


def rescaled(noise: Noise, pre: Preintegrated, log_var: FloatArray) -> tuple[Noise, Preintegrated]:
    """Noise levels (and the preintegration whitening) with variances multiplied by exp(log_var) (7,)."""
    f = np.exp(0.5 * log_var)
    new = Noise(noise.acc * f[:3], noise.gyr * f[3], noise.mag * f[4:])
    return new, pre.scaled(float(np.exp(log_var[3])))


def _preintegrated(problem: Problem, ep: Epochs, bias: FloatArray, noise: Noise,
                   cache: dict[bytes, Preintegrated], scale_jacobian: bool = False) -> Preintegrated:
    """Preintegrate between the epochs (with the gyro-scale Jacobian when asked), or rescale a cached
    preintegration of the same epochs and bias."""
    key = ep.t.tobytes() + np.asarray(bias, dtype=np.float64).tobytes() + bytes([scale_jacobian])
    hit = cache.get(key)
    if hit is not None:
        ratio = noise.gyr / hit.noise_std
        if np.allclose(ratio, ratio[0], rtol=1e-12):
            return hit.scaled(float(ratio[0]) ** 2)
    pre = preintegrate_log(problem, ep.t, bias, noise.gyr, f"{problem.where}: {ep.mag_id}", scale_jacobian)
    cache[key] = pre
    return pre


def _initial_state(problem: Problem, ep: Epochs, intr: map_init.Intrinsic, noise: Noise,
                   dip_prior: float | None, cache: dict[bytes, Preintegrated], align: bool = True,
                   scale_jacobian: bool = False) -> tuple[FloatArray, FloatArray, Preintegrated, list[str]]:
    """Start values (states, theta, preintegration) as in Sec. III-D; the trajectory that fits better wins.
    Without `align` the start D stays in the body frame (a prior calibration: a flat log cannot align);
    `scale_jacobian`: a gyro effect will need the preintegration's scale Jacobian (integrate once, not twice)."""
    notes = []
    if problem.still.segments:
        bias = problem.still.gyr_bias
        notes.append(f"{ep.mag_id}: gyro bias started from {len(problem.still.segments)} still segments")
    else:
        bias = np.zeros(3)
    pre = _preintegrated(problem, ep, bias, noise, cache, scale_jacobian)
    h = (ep.mag - intr.o0) @ np.linalg.inv(intr.D0).T
    window = max(1, int(round(map_init.ALIGNMENT_WINDOW_S / float(np.median(pre.duration)))))
    r_d, db = map_init.wu_luo(h, so3.log_small(pre.delta), pre.duration, window) if align else (np.eye(3), np.zeros(3))
    db = db if not problem.still.segments else np.zeros(3)
    if not problem.still.segments and align:           # the first-order bias correction carries db (no re-integration)
        notes.append(f"{ep.mag_id}: no still segment; gyro bias started from the Wu & Luo alignment "
                     f"({np.array2string(bias + db, precision=4)} rad/s)")
    d0 = intr.D0 @ r_d
    m_b = (ep.mag - intr.o0) @ np.linalg.inv(d0).T
    dip = dip_prior if dip_prior is not None else map_init.dip_from_data(m_b, ep.acc)
    theta = BASE.zeros()
    BASE.put(theta, "gyroscope_bias", db)
    BASE.put(theta, "D", d0.ravel(order="F"))
    BASE.put(theta, "o", intr.o0)
    BASE.put(theta, "dip", dip)
    att = map_init.attitudes(m_b, ep.acc, dip)
    delta = pre.delta @ so3.exp(pre.d_bias @ db)
    candidates = {"gyro-integrated": map_init.integrated(delta, att, pre.broken),
                  "accelerometer/magnetometer": att}
    lin = make_linearize(ep, pre, noise, holdout=held_out(ep.t, problem.unmeasured))
    costs = {k: sum(float(np.sum(f.r**2)) for f in lin(s, theta, False)) for k, s in candidates.items()}
    best = min(costs, key=costs.__getitem__)
    notes.append(f"{ep.mag_id}: started from the {best} trajectory")
    return candidates[best], theta, pre, notes


def fit_map(problem: Problem, mag: Stream, loss: str = "l2", dip_prior: float | None = None,
            noise_rounds: int = NOISE_ROUNDS, imu_start: Noise | None = None,
            cache: dict[bytes, Preintegrated] | None = None, effects: tuple[str, ...] = (),
            declination: float = 0.0, holdout: tuple[tuple[float, float], ...] = (),
            warm: FitContext | None = None) -> MapEstimate:
    """The joint MAP calibration of one magnetometer against the problem's IMU.

    `imu_start`: accelerometer and gyro noise levels to start from (another magnetometer's fit, same IMU);
    `cache`: preintegrations shared between magnetometers with the same epochs; `effects`: ids of the effect
    plug-ins to model (those the log cannot test come back as not_testable); `declination` (rad): turns the
    log's true-north vectors into the model's magnetic-north frame; `holdout`: time windows (s) whose
    accelerometer and magnetometer readings the fit must not see (validation); `warm`: a fit of the same
    magnetometer to start from (its trajectory, parameters and noise levels).
    """
    effects = (*problem.base_effects, *(e for e in effects if e not in problem.base_effects))
    cache = {} if cache is None else cache
    args = (problem, mag, loss, dip_prior, noise_rounds, imu_start, cache, effects,
            declination, holdout, warm)
    with one_blas_thread():       # small dense blocks: BLAS threads only cost
        try:
            return _plausible(_fit_map(*args), dip_prior, problem.where)
        except InsufficientDataError as refused:
            if warm is not None:
                raise
            # the motion cannot determine everything: hold what it cannot at a prior (models/partial.py)
            prior = _with_coverage(problem, mag, partial.priors_by_id(problem.priors, mag.id, mag.xyz), dip_prior,
                                   cache)
            try:
                return _fit_map(*args, prior=prior)
            except InsufficientDataError as exc:          # not even that: say why the partial fit failed
                turned = prior.yaw_deg is not None and prior.yaw_deg >= partial.OFFSETS_YAW_DEG
                for level in (1, 2) if turned else ():    # unless a half turn still gives the offsets
                    try:
                        return _fit_map(*args, prior=replace(prior, fallback=level))
                    except (InsufficientDataError, np.linalg.LinAlgError):
                        continue
                raise exc from refused
            except np.linalg.LinAlgError:
                msg = (f"{problem.where}: {mag.id}: the log's motion determines too little for even a partial "
                       f"calibration (the fit with D held at {prior.source} is numerically singular). To fix: "
                       f"{ROTATE_ADVICE}")
                raise InsufficientDataError(msg) from refused


#: a full fit whose dip is further than this from the World Magnetic Model's converged to another basin (a flat
#: log's mirror solution: the sign of D's vertical column against the dip's, ~2x the dip away) and is redone from
#: the prior. Not tighter: flight acceleration alone moves a fitted dip 10 deg (log171), and simulated logs whose
#: drawn dip is not the WMM's at their GPS position must not be pushed off their truth
DIP_BASIN_DEG = 45.0


def _plausible(est: MapEstimate, dip_ref: float | None, where: str) -> MapEstimate:
    """The estimate, or InsufficientDataError (which starts the partial path from the prior) when its dip is
    further than DIP_BASIN_DEG from the reference."""
    dip = float(est.value("dip")[0])
    if dip_ref is not None and abs(np.degrees(dip - dip_ref)) > DIP_BASIN_DEG:
        msg = (f"{where}: {est.mag_id}: the fit converged to a dip of {np.degrees(dip):.1f} deg, "
               f"{abs(np.degrees(dip - dip_ref)):.0f} deg from the World Magnetic Model's")
        raise InsufficientDataError(msg)
    return est


def _with_effects(problem: Problem, mag: Stream, ep: Epochs, pre: Preintegrated, theta: FloatArray,
                  effects: tuple[str, ...], declination: float
                  ) -> tuple[Layout, tuple[Bound, ...], list[EffectFit], FloatArray, Preintegrated]:
    """Bind the effects at the start values: the extended layout and theta, and a preintegration with the scale
    Jacobian when a gyro effect needs it."""
    bias = pre.bias + BASE.get(theta, "gyroscope_bias")
    bound, untestable = bind(problem, mag, ep.t, bias, effects, declination)
    layout = layout_for(bound)
    full = layout.zeros()
    layout.carry(full, BASE, theta)
    for b in bound:
        full[layout.cols(*b.names())] = b.effect.start()
    if any(b.effect.target.value == "gyro" for b in bound) and pre.d_scale is None:
        pre = preintegrate_log(problem, ep.t, pre.bias, pre.noise_std, f"{problem.where}: {mag.id}", True)
    return layout, tuple(bound), untestable, full, pre


def _with_coverage(problem: Problem, mag: Stream, prior: partial.MagPrior, dip: float | None,
                   cache: dict[bytes, Preintegrated]) -> partial.MagPrior:
    """The prior with what the motion shows of the field (`partial.covered`): from the gyro-integrated attitude
    levelled by the accelerometer, never from the readings about the prior."""
    ep = epochs_for(problem, mag, 1.0)
    bias = problem.still.gyr_bias if problem.still.segments else np.zeros(3)
    pre = _preintegrated(problem, ep, bias, Noise(np.ones(3), np.full(3, 1e-3), np.ones(3)), cache)
    return partial.covered(prior, pre.delta, ep.acc, dip, ep.mag)


def held_out(t: FloatArray, windows: tuple[tuple[float, float], ...]) -> FloatArray | None:
    """Row weights at epochs t: 0 inside the held-out windows, 1 elsewhere (None without windows)."""
    if not windows:
        return None
    w = np.ones(t.size)
    for t0, t1 in windows:
        w[(t >= t0) & (t < t1)] = 0.0
    return w


def _fit_map(problem: Problem, mag: Stream, loss: str, dip_prior: float | None, noise_rounds: int,
             imu_start: Noise | None, cache: dict[bytes, Preintegrated], effects: tuple[str, ...] = (),
             declination: float = 0.0, holdout: tuple[tuple[float, float], ...] = (),
             warm: FitContext | None = None, prior: partial.MagPrior | None = None) -> MapEstimate:
    """`fit_map` without the BLAS thread limit; with a `prior`, a partial calibration starts from it and holds
    at it what the motion cannot determine."""
    where = f"{problem.where}: {mag.id}"
    clean, spikes = map_init.despike(mag.xyz)            # outliers would wreck the algebraic start values
    if prior is not None:
        intr = map_init.from_prior(clean, prior.D, prior.o)
    elif warm is not None:                # the fit to start from may be a partial one: no ellipsoid needed
        d, o, _ = mag_layout(warm.layout).unpack(warm.theta)
        intr = map_init.from_prior(clean, d * warm.ep.scale, o * warm.ep.scale)
    else:
        intr = map_init.intrinsic_fit(clean, where)
    ep = epochs_for(problem, mag, intr.scale)
    noise = initial_noise(problem, mag, intr.scale, intr.noise_rms)
    still_s = sum(seg.end - seg.start for seg in problem.still.segments)
    floor = noise if still_s >= MIN_STILL_S else None
    if imu_start is not None:                  # already estimated on this IMU (floors still apply below)
        noise = Noise(imu_start.acc, imu_start.gyr, noise.mag)
    else:
        # in motion the accelerometer also sees linear acceleration: start from the spread of |a| about g
        dev = np.linalg.norm(ep.acc, axis=1) - G
        spread = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
        noise = Noise(np.maximum(noise.acc, spread), noise.gyr, noise.mag)
    if warm is not None:                  # same magnetometer, same epochs: start where that fit ended
        ep, noise, pre, states = warm.ep, warm.noise, warm.pre, warm.states
        notes: list[str] = []
        theta = BASE.zeros()
        BASE.carry(theta, warm.layout, warm.theta)
    else:
        clean_ep = replace(ep, mag=clean[ep.index] / intr.scale, notes=(), index=np.zeros(0, np.int64))
        gyro_effect = any(get(e).target is Target.GYRO for e in effects)
        states, theta, pre, notes = _initial_state(problem, clean_ep, intr, noise, dip_prior, cache, prior is None,
                                                   gyro_effect)
    layout, bound, untestable, theta, pre = _with_effects(problem, mag, ep, pre, theta, effects, declination)
    if warm is not None:                  # the effect blocks that fit also had
        layout.carry(theta, warm.layout, warm.theta)
    hold = held_out(ep.t, holdout + problem.unmeasured)
    held = warm.held if warm is not None else None
    if prior is not None:
        held = _rechoose(partial.prior_of(layout, theta, prior, ep.scale, dip_prior),
                          make_linearize(ep, pre, noise, layout, bound, hold), states, theta, where)
        theta[held.theta_cols] = held.mean
    held = None if held is None else held.placed(layout)      # a warm start's hold, in this fit's layout
    scale_jac = pre.d_scale is not None
    bg = layout.slice("gyroscope_bias")
    if floor is not None and any(b.effect.target.value == "mag" and b.effect.params for b in bound):
        # a magnetometer effect also acts while the vehicle is still (current, temperature): the still
        # readings' spread is not the sensor's white noise then, so it is no floor for the magnetometer level
        floor = Noise(floor.acc, floor.gyr, np.full(3, 1e-12))
    if spikes:
        notes.append(f"{mag.id}: {spikes} isolated spikes in the readings were smoothed for the start values "
                     "only" + ("" if loss != "l2" else "; consider --robust-loss huber"))
    # a step that lowers the whitened cost by < 1e-3 moved the estimate by ~0.03 sigma: converged. After a
    # noise round the optimum moves little (weights change by a few per cent): 1-2 Gauss-Newton steps
    first = Options(max_iterations=60, abs_cost_tol=1e-3, loss=loss)
    # the noise levels will change after round 0: a relative cost change of 1e-4 is close enough there
    start = Options(max_iterations=60, cost_tol=1e-4, abs_cost_tol=1e-3, loss=loss)
    opts_scale = first.loss_scale
    later = Options(max_iterations=4, abs_cost_tol=1e-3, loss=loss)
    log: list[str] = []
    iters = 0
    sol = None
    history: list[tuple[float, float]] = []      # (gyro log-variance applied so far, log factor found there)
    applied = 0.0
    last_step = None
    hook = current()
    for rnd in range(noise_rounds + 1):
        hook(f"{mag.id}: joint MAP, noise round", rnd, noise_rounds + 1)
        opts = (start if noise_rounds else first) if rnd == 0 else later
        sol = solve(make_linearize(ep, pre, noise, layout, bound, hold, held), states, theta, opts)
        states, theta, iters = sol.states, sol.theta.copy(), iters + sol.iterations
        log.extend(f"round {rnd}: {line}" for line in sol.log)
        db = theta[bg]
        if float(np.linalg.norm(db)) * float(pre.duration.max()) > REPREINTEGRATE_RAD:
            pre = preintegrate_log(problem, ep.t, pre.bias + db, noise.gyr, where, scale_jac)
            theta[bg] = 0.0
            log.append(f"round {rnd}: re-preintegrated with the updated gyro bias")
            continue
        if rnd == noise_rounds or not np.all(np.isfinite(sol.cov_theta)):
            break
        step = np.log(variance_ratios(sol, loss, opts_scale))
        log.append(f"round {rnd}: noise variance factors {np.array2string(np.exp(step), precision=3)}")
        step, small, measured = noise_step(step, None if floor is None else _levels(floor), _levels(noise),
                                           history, applied)
        if small:
            last_step = step
            break
        history.append((applied, measured))
        applied += float(step[3])
        noise, pre = rescaled(noise, pre, step)
    # round 0's loose relative tolerance is no convergence test when the noise levels then stay: a slow direction
    # (throttle's exponent from its start at 1, where c = 0 gives it no gradient) had stopped 2 std short
    if sol is not None and (not sol.converged or opts is start):
        sol = solve(make_linearize(ep, pre, noise, layout, bound, hold, held), states, theta, first)
        iters += sol.iterations
        log.extend(f"final: {line}" for line in sol.log)
    assert sol is not None
    for rnd in range(3 if prior is not None else 0):
        # the start trajectory is rougher than the fitted one and shows more (or less) than the data hold:
        # choose again at the optimum (from scratch the first time, then only adding, which must settle: what is
        # held changes the residuals' correlation and so the widening)
        assert held is not None
        widen = widening(sol, factor_clusters(sol.factors, time_clusters(ep.t)))
        more = _rechoose(held, make_linearize(ep, pre, noise, layout, bound, hold), sol.states, sol.theta, where,
                         widen, keep=rnd > 0)
        if np.array_equal(more.cols, held.cols):
            break
        held, theta = more, sol.theta.copy()
        theta[held.theta_cols] = held.mean
        sol = solve(make_linearize(ep, pre, noise, layout, bound, hold, held), sol.states, theta, first)
        iters += sol.iterations
        log.extend(f"held {', '.join(held.names())}: {line}" for line in sol.log)
    if held is not None and held.cols.size and warm is None:
        notes.append(f"{mag.id}: the motion cannot determine {', '.join(held.names())}: held at "
                     f"{'; '.join(sorted(set(held.sources)))}")
    cov = None
    if last_step is not None:
        # the last small change of the levels moves the optimum negligibly but the covariance proportionally:
        # report the covariance with the final levels at the same point (one assembly, no iterations)
        noise, pre = rescaled(noise, pre, last_step)
    if last_step is not None or held is not None:
        # held entries are pinned during the fit; the covariance carries their prior's doubt (a soft prior)
        cov = marginal_covariance(make_linearize(ep, pre, noise, layout, bound, hold, held and held.soft()),
                                  sol.states, sol.theta, 0.0 if held is None else TRAJECTORY_DAMPING)
    # residuals correlated in time beyond the white-noise model (quantised still readings, unmodelled motion
    # or disturbances) make the information overstate what the data know: widen where the data say so
    ids = time_clusters(ep.t)
    widen = widening(sol, factor_clusters(sol.factors, ids))
    if held is not None:
        widen[held.theta_cols] = 1.0            # a held entry's std is its prior's doubt, not the data's
        _explains(ep, sol.theta, layout, where)
    est = _estimate(problem, ep, pre, noise, sol, iters, tuple(log), tuple(notes) + ep.notes, cov, widen, layout,
                    held)
    fitted = results(bound, layout, est.theta, est.cov, mag.id, problem.imu_id)
    ctx = FitContext(ep, pre, noise, layout, bound, sol.states, sol.theta, hold, held,
                     held_out(ep.t, problem.unmeasured))
    return replace(est, effects=tuple(fitted + untestable), context=ctx, held=held)


#: a partial calibration that leaves the field strength varying more than this (RMS, relative) explains nothing
PARTIAL_MAX_NORM_RMS = 0.15


def norm_spread(ep: Epochs, theta: FloatArray, layout: Layout) -> float:
    """RMS of the calibrated field strength about 1 (relative): how far the calibration leaves the readings from a
    sphere."""
    d, o, _ = mag_layout(layout).unpack(theta)
    return float(np.sqrt(np.mean((np.linalg.norm((ep.mag - o) @ np.linalg.inv(d).T, axis=1) - 1.0) ** 2)))


def _explains(ep: Epochs, theta: FloatArray, layout: Layout, where: str) -> None:
    """Refuse a partial calibration that does not explain the readings: the calibrated field strength must stay
    within PARTIAL_MAX_NORM_RMS of constant (a full fit is judged by its quality numbers instead)."""
    spread = norm_spread(ep, theta, layout)
    if spread > PARTIAL_MAX_NORM_RMS:
        msg = (f"{where}: even a partial calibration does not explain the readings (the calibrated field strength "
               f"still varies {100 * spread:.0f} % RMS): the log's motion determines too little, or a disturbance "
               f"dominates. To fix: {ROTATE_ADVICE}")
        raise InsufficientDataError(msg)


def _rechoose(held: Held, data: Linearize, states: FloatArray, theta: FloatArray, where: str,
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
        more = held.holding(partial.choose(info, held.prior_std, np.union1d(pinned, held.cols) if keep else pinned),
                            pinned)
    except np.linalg.LinAlgError:
        more = held.holding(BASE.cols(*BASE.names), pinned)
    if more.undetermined():
        msg = (f"{where}: the motion in this log determines no part of the magnetometer calibration, not even the "
               f"offsets with D held at {held.prior_sources[BASE.slice('D').start]} (the field turned through "
               f"too few directions). To fix: {ROTATE_ADVICE}")
        raise InsufficientDataError(msg)
    return more


def _estimate(problem: Problem, ep: Epochs, pre: Preintegrated, noise: Noise, sol: Solution, iters: int,
              log: tuple[str, ...], notes: tuple[str, ...], cov_theta: FloatArray | None = None,
              widen: FloatArray | None = None, layout: Layout = BASE, held: Held | None = None) -> MapEstimate:
    """Convert the scaled solution to SI, with the total gyro bias and the observability findings."""
    s = ep.scale
    jac = layout.si_factors(s)
    theta = sol.theta * jac
    bg, dip_at = layout.slice("gyroscope_bias"), layout.slice("dip")
    theta[bg] += pre.bias
    cov = (sol.cov_theta if cov_theta is None else cov_theta) * np.outer(jac, jac)
    states = sol.states
    dip = float(theta[dip_at][0])
    if abs(dip) > np.pi / 2:
        # (dip, R_k) and (pi - dip, Rz(pi) R_k) explain the data alike (north is only fixed by m_n): report
        # the representative with |dip| <= 90 deg; d dip'/d dip = -1 flips the dip's covariances
        theta[dip_at] = float(np.angle(np.exp(1j * (np.pi - dip))))
        states = so3.exp([0.0, 0.0, np.pi]) @ states
        cov[dip_at, :] *= -1.0
        cov[:, dip_at] *= -1.0
    fm = sol.factors[1]
    resid = fm.r * noise.mag * s
    noise_si = Noise(noise.acc, noise.gyr, noise.mag * s)
    where = f"{problem.where}: {ep.mag_id}"
    # observability is a property of the motion: judge it on the model information of the base blocks, then
    # widen for honesty
    base = layout.cols(*BASE.names)
    condition, findings = check_observability(cov[np.ix_(base, base)], s, ep.acc, where,
                                              None if held is None else held.cols)
    if widen is not None and np.any(widen > 1.0):
        cov = cov * np.outer(widen, widen)
        names = [n for n, c in layout.groups().items() if np.any(widen[c] > 1.0)]
        findings.append(Finding(
            Severity.WARNING, "correlated_residuals",
            f"{where}: the residuals are correlated in time beyond the noise model (quantised readings, "
            f"unmodelled motion or a disturbance); the uncertainty of {', '.join(names)} was widened up to "
            f"{float(widen.max()):.1f}x (time-clustered sandwich estimate)", {"max_factor": float(widen.max())}))
    if held is not None:
        check_useful(cov[np.ix_(base, base)], s, held.cols, where,
                     None if widen is None else widen[base], norm_spread(ep, sol.theta, layout))
    return MapEstimate(ep.mag_id, theta, cov, noise_si, states, ep.t, sol.cost, iters, sol.converged,
                       float(np.sqrt(np.mean(resid**2))), log, tuple(findings), notes, condition, layout)


def information_at(problem: Problem, mag: Stream, states: FloatArray, theta_si: FloatArray,
                   noise_si: Noise) -> FloatArray:
    """Inverse Fisher information of the base theta (SI, BASE order, total gyro bias) at given states and
    theta: the CRLB."""
    d = BASE.get(theta_si, "D").reshape(3, 3, order="F")
    scale = float(np.cbrt(abs(np.linalg.det(d))))
    ep = epochs_for(problem, mag, scale)
    pre = preintegrate_log(problem, ep.t, BASE.get(theta_si, "gyroscope_bias"), noise_si.gyr)
    jac = BASE.si_factors(scale)
    theta = theta_si / jac
    BASE.put(theta, "gyroscope_bias", 0.0)
    noise = Noise(noise_si.acc, noise_si.gyr, noise_si.mag / scale)
    return marginal_covariance(make_linearize(ep, pre, noise), states, theta) * np.outer(jac, jac)
