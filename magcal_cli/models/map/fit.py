"""Huang et al. 2025: joint MAP calibration of magnetometer, accelerometer and gyro biases (`--method map`).

Unknowns (methods.md section 3): theta = (b_a, db_g, vec D, o, dip) (19) and the orientations R_k at the
magnetometer epochs. Factors: accelerometer and magnetometer at every epoch, gyro preintegration between
consecutive epochs. The one solver (`solve.py`) eliminates the block-tridiagonal trajectory; the marginal
covariance of theta is the inverse Schur complement. The noise levels are re-estimated from the residuals with
leverage-corrected degrees of freedom (variance components), so the reported covariance matches the data.

Internally the magnetometer is expressed in units of its ellipsoid-fit scale (D ~ I); results are in SI.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from magcal_cli.errors import InsufficientDataError
from magcal_cli.models import partial
from magcal_cli.models.epochs import Noise, epochs_for
from magcal_cli.models.gyro import Preintegrated, preintegrate_epochs
from magcal_cli.models.map.cost import held_out, make_linearize
from magcal_cli.models.map.effects import results
from magcal_cli.models.map.estimate import FitContext, MapEstimate, Record, estimate
from magcal_cli.models.map.hold import explains, rechoose, undisturbed, with_prior_doubt
from magcal_cli.models.map.noise import NOISE_ROUNDS, as_levels, noise_step, rescaled, variance_ratios
from magcal_cli.models.map.start import FitSettings, Run, prepare, with_coverage
from magcal_cli.models.normal import marginal_covariance, one_blas_thread
from magcal_cli.models.observability import ROTATE_ADVICE
from magcal_cli.models.problem import Problem
from magcal_cli.models.sandwich import factor_clusters, time_clusters, widening
from magcal_cli.models.solve import LAMBDA_FLOOR, Options, Solution, solve
from magcal_cli.params import BASE
from magcal_cli.progress import current
from magcal_cli.streams import FloatArray, Stream

#: a partial calibration's covariance damps the trajectory blocks by this trace: a flat log's nearly rigid
#: trajectory otherwise cancels theta's information in the Schur complement (models/normal.py `information`)
TRAJECTORY_DAMPING = 1e-9
#: a fit with held-out windows (a cross-validation fold) stops when a step lowers the cost by less than this: its
#: tail of slow steps along barely determined directions cost a quarter of the folds' iterations (log171 179 ->
#: 136, BROAD 06 74 -> 61 from 1e-2) and moved the held-out gain's interval in its fourth digit
HELDOUT_COST_TOL = 1e-1
#: re-preintegrate when the first-order bias correction rotates an interval by more than this (rad)
REPREINTEGRATE_RAD = 0.01


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
    cfg = FitSettings(loss, dip_prior, noise_rounds, imu_start, effects, declination, holdout, warm)
    with one_blas_thread():       # small dense blocks: BLAS threads only cost
        try:
            return _plausible(_fit(problem, mag, cfg, cache), dip_prior, problem.where)
        except InsufficientDataError as refused:
            if warm is not None:
                raise
            # the motion cannot determine everything: hold what it cannot at a prior (models/partial.py)
            prior = with_coverage(problem, mag, partial.priors_by_id(problem.priors, mag.id, mag.xyz), dip_prior,
                                  cache)
            try:
                return _fit(problem, mag, replace(cfg, prior=prior), cache)
            except InsufficientDataError as exc:          # not even that: say why the partial fit failed
                turned = prior.yaw_deg is not None and prior.yaw_deg >= partial.OFFSETS_YAW_DEG
                for level in (1, 2) if turned else ():    # unless a half turn still gives the offsets
                    try:
                        return _fit(problem, mag, replace(cfg, prior=replace(prior, fallback=level)), cache)
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


def _fit(problem: Problem, mag: Stream, cfg: FitSettings, cache: dict[bytes, Preintegrated]) -> MapEstimate:
    """`fit_map` without the BLAS thread limit; with `cfg.prior`, a partial calibration starts from it and holds
    at it what the motion cannot determine."""
    run = prepare(problem, mag, cfg, cache)
    sol, last_step = _rounds(problem, run, cfg)
    if cfg.prior is not None:
        sol = _hold_again(run, sol, cfg.loss)
    if run.held is not None and run.held.cols.size and cfg.warm is None:
        run.notes.append(f"{mag.id}: the motion cannot determine {', '.join(run.held.names())}: held at "
                         f"{'; '.join(sorted(set(run.held.sources)))}")
    # residuals correlated in time beyond the white-noise model (quantised still readings, unmodelled motion
    # or disturbances) make the information overstate what the data know: widen where the data say so
    widen = widening(sol, factor_clusters(sol.factors, time_clusters(run.ep.t)))
    # then the Jacobians go, before the covariance at the final noise levels makes its own (issue 39)
    sol = sol.residuals_only()
    return _finish(problem, run, sol, last_step, widen)


def _to_convergence(loss: str, warm: bool = False) -> Options:
    """The solver's rules for a fit to convergence: a step that lowers the whitened cost by < 1e-3 moved the
    estimate by ~0.03 sigma. A `warm` solve starts near an optimum (where the solve before it stopped, or a fit
    of a training fold of the same log, or with one effect more): its first step is nearly Gauss-Newton's. The
    default damping (1e-6, relative) held such a solve to steps ~3x longer each iteration along the
    accelerometer-bias/tilt direction, which real logs barely determine (BROAD 06: 10-20 iterations where 4-7
    reach the same optimum, within 0.004 std)."""
    return Options(max_iterations=60, abs_cost_tol=1e-3, loss=loss, lambda0=LAMBDA_FLOOR if warm else 1e-6)


def _rounds(problem: Problem, run: Run, cfg: FitSettings) -> tuple[Solution, FloatArray | None]:
    """Rounds of (solve, re-estimate the noise levels from the residuals), re-preintegrating when the gyro bias
    moved far, then a solve to convergence; the solution and the last, small change of the levels (if the
    rounds stopped on one)."""
    loss, noise_rounds = cfg.loss, cfg.noise_rounds
    scale_jac = run.pre.d_scale is not None
    bg = run.layout.slice("gyroscope_bias")
    # a partial calibration keeps the default damping throughout: what it holds, priors alone hold, and undamped
    # steps along those directions took the phidgets bag to a point where nothing looked determined, so it was
    # refused for its motion instead of for the non-uniform field the log shows (tests/readers/test_rosbag.py)
    partial_fit = cfg.prior is not None or (run.held is not None and run.held.cols.size > 0)
    first = _to_convergence(loss, cfg.warm is not None and not partial_fit)
    if cfg.holdout:                 # a cross-validation fold: only its held-out likelihood is used
        first = replace(first, abs_cost_tol=HELDOUT_COST_TOL)
    # the noise levels will change after round 0: a relative cost change of 1e-4 is close enough there
    round0 = replace(first, cost_tol=1e-4)
    opts_scale = first.loss_scale
    # every later solve resumes where the one before stopped, near the optimum: it starts at the damping floor
    resumed = first if partial_fit else replace(first, lambda0=LAMBDA_FLOOR)
    # after a noise round the optimum moves little (weights change by a few per cent): 1-2 Gauss-Newton steps
    later = replace(resumed, max_iterations=4)
    sol = None
    history: list[tuple[float, float]] = []      # (gyro log-variance applied so far, log factor found there)
    applied = 0.0
    last_step = None
    hook = current()
    for rnd in range(noise_rounds + 1):
        hook(f"{run.mag_id}: joint MAP, noise round", rnd, noise_rounds + 1)
        opts = (round0 if noise_rounds else first) if rnd == 0 else later
        # the last round's solution (every factor's Jacobians, the covariance) goes before this round's is made:
        # two at once were a 60-min flight's peak (issue 39)
        sol = None
        sol = solve(run.cost(run.held), run.states, run.theta, opts)
        run.states, run.theta, run.iters = sol.states, sol.theta.copy(), run.iters + sol.iterations
        run.log.extend(f"round {rnd}: {line}" for line in sol.log)
        db = run.theta[bg]
        if float(np.linalg.norm(db)) * float(run.pre.duration.max()) > REPREINTEGRATE_RAD:
            run.pre = preintegrate_epochs(problem, run.ep, run.pre.bias + db, run.noise.gyr, run.where, scale_jac)
            run.theta[bg] = 0.0
            run.log.append(f"round {rnd}: re-preintegrated with the updated gyro bias")
            continue
        if rnd == noise_rounds or not np.all(np.isfinite(sol.cov_theta)):
            break
        # the leverage needs no gyro stacks, and a rescaled preintegration makes its own: 13 MB of a 60-min flight's
        # peak, which the selected inverse reaches here (issue 39)
        run.pre.drop_component_major()
        step = np.log(variance_ratios(sol, loss, opts_scale))
        run.log.append(f"round {rnd}: noise variance factors {np.array2string(np.exp(step), precision=3)}")
        step, small, measured = noise_step(step, None if run.floor is None else as_levels(run.floor),
                                           as_levels(run.noise), history, applied)
        if small:
            last_step = step
            break
        history.append((applied, measured))
        applied += float(step[3])
        run.noise, run.pre = rescaled(run.noise, run.pre, step)
    # round 0's loose relative tolerance is no convergence test when the noise levels then stay: a slow direction
    # (throttle's exponent from its start at 1, where c = 0 gives it no gradient) had stopped 2 std short
    if sol is not None and (not sol.converged or opts is round0):
        sol = None                                      # as in the rounds: one solution at a time
        sol = solve(run.cost(run.held), run.states, run.theta, resumed)
        run.iters += sol.iterations
        run.log.extend(f"final: {line}" for line in sol.log)
    assert sol is not None
    return sol, last_step


def _hold_again(run: Run, sol: Solution, loss: str) -> Solution:
    """A partial calibration's choice of what to hold, made again at the optimum (up to three times)."""
    held = run.held
    for rnd in range(3):
        # the start trajectory is rougher than the fitted one and shows more (or less) than the data hold:
        # choose again at the optimum (from scratch the first time, then only adding, which must settle: what is
        # held changes the residuals' correlation and so the widening)
        assert held is not None
        widen = widening(sol, factor_clusters(sol.factors, time_clusters(run.ep.t)))
        more = rechoose(held, run.cost(None), sol.states, sol.theta, run.where, widen, keep=rnd > 0)
        if np.array_equal(more.cols, held.cols):
            break
        held, theta = more, sol.theta.copy()
        theta[held.theta_cols] = held.mean
        run.held, run.theta = held, theta
        sol = solve(run.cost(held), sol.states, theta, _to_convergence(loss))
        run.iters += sol.iterations
        run.log.extend(f"held {', '.join(held.names())}: {line}" for line in sol.log)
    return sol


def _finish(problem: Problem, run: Run, sol: Solution, last_step: FloatArray | None, widen: FloatArray
            ) -> MapEstimate:
    """The estimate in SI with its covariance (at the final noise levels, widened by `widen` where the residuals
    are correlated in time), its effects and the context it was fitted in."""
    cov = None
    if last_step is not None:
        # the last small change of the levels moves the optimum negligibly but the covariance proportionally:
        # report the covariance with the final levels at the same point (one assembly, no iterations)
        run.noise, run.pre = rescaled(run.noise, run.pre, last_step)
    held = run.held
    if last_step is not None or held is not None:
        # held entries are pinned during the fit; the covariance carries their prior's doubt (a soft prior)
        cov = marginal_covariance(run.cost(held and held.soft()), sol.states, sol.theta,
                                  0.0 if held is None else TRAJECTORY_DAMPING)
        if held is not None:
            cov = with_prior_doubt(cov, held)
    if held is not None:
        widen[held.theta_cols] = 1.0            # a held entry's std is its prior's doubt, not the data's
    # a full fit too: one that leaves the field strength varying by 30 % calibrated a failing sensor (issue 38)
    spread = explains(run.ep, sol.theta, run.layout, run.where,
                      undisturbed(run.ep, sol.theta, run.layout, run.bound, sol.states, run.pre))
    # the context's preintegration shares the arrays but not the component-major stacks this fit made: an estimate
    # outlives its fit (the diagnosis runs beside it), and they are made again when it is linearised (issue 39)
    ctx = FitContext(run.ep, replace(run.pre), run.noise, run.layout, run.bound, sol.states, sol.theta, run.hold,
                     held, held_out(run.ep.t, problem.unmeasured))
    record = Record(run.iters, tuple(run.log), tuple(run.notes) + run.ep.notes)
    est = estimate(problem, ctx, sol, record, cov, widen, spread)
    fitted = results(run.bound, run.layout, est.theta, est.cov, run.mag_id, problem.imu_id)
    return replace(est, effects=tuple(fitted + run.untestable))


def information_at(problem: Problem, mag: Stream, states: FloatArray, theta_si: FloatArray,
                   noise_si: Noise) -> FloatArray:
    """Inverse Fisher information of the base theta (SI, BASE order, total gyro bias) at given states and
    theta: the CRLB."""
    d = BASE.get(theta_si, "D").reshape(3, 3, order="F")
    scale = float(np.cbrt(abs(np.linalg.det(d))))
    ep = epochs_for(problem, mag, scale, average=True)
    pre = preintegrate_epochs(problem, ep, BASE.get(theta_si, "gyroscope_bias"), noise_si.gyr)
    jac = BASE.si_factors(scale)
    theta = theta_si / jac
    BASE.put(theta, "gyroscope_bias", 0.0)
    noise = Noise(noise_si.acc, noise_si.gyr, noise_si.mag / scale)
    return marginal_covariance(make_linearize(ep, pre, noise), states, theta) * np.outer(jac, jac)
