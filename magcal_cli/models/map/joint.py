"""One joint MAP fit for every magnetometer on one IMU (issue 14 item 3; Huang et al. 2025's board of 30).

The magnetometers of a log all see the body turn through one orientation trajectory. The separate fits
(`fit.fit_map`, one per magnetometer) each estimate that trajectory again from one magnetometer; here it is
estimated once, from the accelerometer, the gyro and every magnetometer's factors (methods.md section 3 with M
magnetometer factors per epoch). theta = (b_a, db_g, then D, o, dip of each magnetometer): each magnetometer keeps
the separate fit's model, its own dip included, so a disturbed compass cannot pull the others' dip (how far the
magnetometers disagree is reported by `models/consistency.py`), and each has its own noise level (variance
components), which down-weights a noisy one in the shared trajectory.

The magnetometers must read at common epochs (one board, one clock: Huang et al.'s array, the simulator's); then
the coupling of the trajectory with the 6 + 13 M parameters has rank 48 whatever M is, and
`joint_solve.py` eliminates the block-tridiagonal trajectory with 48 right-hand sides instead of 6 + 13 M
(5 minutes of 30 magnetometers: 22 s through `normal.py`'s generic assembly, see docs/results/joint_mags.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.align import interpolate
from magcal_cli.config import Config
from magcal_cli.detect import MIN_STILL_S
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models import consistency
from magcal_cli.models.accel import G
from magcal_cli.models.epochs import MAX_EPOCHS, Epochs, Noise, epochs_for, initial_noise
from magcal_cli.models.factor import Factor
from magcal_cli.models.gyro import Preintegrated, preintegrate_log
from magcal_cli.models.map import init as map_init
from magcal_cli.models.map.cost import held_out
from magcal_cli.models.map.estimate import MapEstimate, widening_note
from magcal_cli.models.map.fit import DIP_BASIN_DEG, REPREINTEGRATE_RAD
from magcal_cli.models.map.joint_cov import factors, joint_variance_ratios, joint_widening
from magcal_cli.models.map.joint_solve import (
    JointData,
    JointSolution,
    at_optimum,
    cost,
    mag_residuals,
    normal,
    solve_joint,
)
from magcal_cli.models.map.noise import NOISE_ROUNDS, noise_step
from magcal_cli.models.normal import one_blas_thread
from magcal_cli.models.observability import check_observability
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MagFit
from magcal_cli.models.solve import Options
from magcal_cli.models.spikes import despike
from magcal_cli.params import ACCEL_BIAS, BASE, D_BLOCK, DIP, GYRO_BIAS, O_BLOCK, Layout
from magcal_cli.progress import current
from magcal_cli.streams import FloatArray, Stream

IntArray = npt.NDArray[np.int64]

#: readings of different magnetometers closer than this share a state (fraction of the IMU period): an autopilot
#: logs its compasses one after another in one loop (log171: 51 of 2,383 epochs microseconds apart), and half an
#: IMU period of motion (1.25 ms at 400 Hz: 0.07 deg at 1 rad/s) is far below a compass's noise
MERGE = 0.5


def joint_layout(n_mags: int) -> Layout:
    """b_a, db_g, then D#i, o#i, dip#i for each magnetometer i (contiguous: one compact Jacobian per factor)."""
    blocks = [ACCEL_BIAS, GYRO_BIAS]
    for i in range(n_mags):
        blocks += [replace(D_BLOCK, name=f"D#{i}"), replace(O_BLOCK, name=f"o#{i}"), replace(DIP, name=f"dip#{i}")]
    return Layout(blocks)


def base_cols(layout: Layout, i: int) -> IntArray:
    """The joint theta's columns of magnetometer i's fit in `params.BASE` order (b_a, b_g, D, o, dip)."""
    return layout.cols("accelerometer_bias", "gyroscope_bias", f"D#{i}", f"o#{i}", f"dip#{i}")


@dataclass(frozen=True, eq=False)
class JointEpochs:
    """The states' times (K,) s (the union of the magnetometers' epochs), the accelerometer interpolated onto them
    (K, 3) with its noise factor (K,), each magnetometer's epochs and the state of each of its readings."""

    t: FloatArray
    acc: FloatArray
    acc_factor: FloatArray
    mags: tuple[Epochs, ...]
    at: tuple[IntArray, ...]


def joint_epochs(problem: Problem, mags: tuple[Stream, ...], scales: list[float]) -> JointEpochs:
    """Every magnetometer's epochs (`epochs_for`) on one time base: readings closer than MERGE IMU periods share a
    state; raises InsufficientDataError when the union exceeds MAX_EPOCHS (the separate fits decimate instead)."""
    eps = tuple(epochs_for(problem, m, s) for m, s in zip(mags, scales, strict=True))
    t_imu = problem.acc.t
    dt = float(np.median(np.diff(t_imu)))
    t_all = np.sort(np.concatenate([e.t for e in eps]))
    t = t_all[np.concatenate([[True], np.diff(t_all) > MERGE * dt])]
    if t.size > MAX_EPOCHS:
        msg = (f"{problem.where}: the magnetometers' readings fall at {t.size} distinct times, more than one fit "
               f"holds ({MAX_EPOCHS})")
        raise InsufficientDataError(msg)
    at = tuple((np.searchsorted(t, e.t, side="right") - 1).astype(np.int64) for e in eps)
    if any(a.size != t.size for a in at):
        msg = (f"{problem.where}: the magnetometers do not read at the same times ({', '.join(str(a.size) for a in at)} "
               f"epochs, {t.size} distinct); the joint fit needs common epochs")
        raise InsufficientDataError(msg)
    j = np.clip(np.searchsorted(t_imu, t, side="right") - 1, 0, t_imu.size - 2)
    w = np.clip((t - t_imu[j]) / (t_imu[j + 1] - t_imu[j]), 0.0, 1.0)
    return JointEpochs(t, interpolate(problem.acc, t), np.sqrt((1.0 - w) ** 2 + w**2), eps, at)


@dataclass(frozen=True)
class JointNoise:
    """Per-sample std per axis: accelerometer (m/s^2), gyro (rad/s), each magnetometer (M, 3) in its own scale."""

    acc: FloatArray
    gyr: FloatArray
    mag: FloatArray

    def levels(self) -> FloatArray:
        """The 4 + 3 M levels in `joint_variance_ratios` order: accelerometer 3, gyro 1, magnetometers 3 each."""
        return np.concatenate([self.acc, self.gyr[:1], self.mag.ravel()])

    def rescaled(self, log_var: FloatArray) -> JointNoise:
        """Variances multiplied by exp(log_var) (levels order)."""
        f = np.exp(0.5 * log_var)
        return JointNoise(self.acc * f[:3], self.gyr * f[3], self.mag * f[4:].reshape(self.mag.shape))


def joint_data(je: JointEpochs, pre: Preintegrated, noise: JointNoise, layout: Layout,
               weights: FloatArray | None) -> JointData:
    """The structured cost's inputs (joint_solve.py); `weights` (K,) zero readings in unmeasured windows."""
    rows = 1.0 / je.acc_factor if weights is None else weights / je.acc_factor
    cols = tuple(layout.cols(f"D#{i}", f"o#{i}", f"dip#{i}") for i in range(len(je.mags)))
    return JointData(je.acc, rows, pre, np.array([e.mag for e in je.mags]), noise.mag, weights, noise.acc, layout,
                     cols)


@dataclass(frozen=True, eq=False)
class JointFit:
    """Each magnetometer's estimate (SI, `params.BASE` layout: the IMU biases are the joint ones), the joint theta
    in SI with its covariance (`layout`), the shared trajectory at the states' times, notes and findings."""

    estimates: tuple[MapEstimate, ...]
    layout: Layout
    theta: FloatArray
    cov: FloatArray
    states: FloatArray
    t: FloatArray
    noise: JointNoise
    iterations: int
    log: tuple[str, ...]
    notes: tuple[str, ...]


def _start(problem: Problem, je: JointEpochs, intr: list[map_init.Intrinsic], noise: JointNoise,
           dip_prior: float | None, layout: Layout) -> tuple[FloatArray, FloatArray, Preintegrated, list[str]]:
    """Start values as `start.initial_state` makes them for one magnetometer (Wu & Luo misalignment per
    magnetometer, the dip, the gyro-integrated or TRIAD trajectory, whichever fits better), for all at once."""
    where = problem.where
    bias = problem.still.gyr_bias if problem.still.segments else np.zeros(3)
    pre = preintegrate_log(problem, je.t, bias, noise.gyr, where)
    cum = np.concatenate([np.eye(3)[None], so3.cumulative_product(pre.delta)])
    theta = layout.zeros()
    anchor = np.full((je.t.size, 3, 3), np.nan)
    dbs = []
    for i, (ep, at, st) in enumerate(zip(je.mags, je.at, intr, strict=True)):
        rel = cum[at[:-1]].transpose(0, 2, 1) @ cum[at[1:]]               # rotation between its own epochs
        dur = np.diff(ep.t)
        h = (ep.mag - st.o0) @ np.linalg.inv(st.D0).T
        window = max(1, int(round(map_init.ALIGNMENT_WINDOW_S / float(np.median(dur)))))
        r_d, db = map_init.wu_luo(h, so3.log_small(rel), dur, window)
        dbs.append(db)
        d0 = st.D0 @ r_d
        m_b = (ep.mag - st.o0) @ np.linalg.inv(d0).T
        dip = dip_prior if dip_prior is not None else map_init.dip_from_data(m_b, ep.acc)
        layout.put(theta, f"D#{i}", d0.ravel(order="F"))
        layout.put(theta, f"o#{i}", st.o0)
        layout.put(theta, f"dip#{i}", dip)
        free = np.isnan(anchor[at, 0, 0])
        anchor[at[free]] = map_init.attitudes(m_b[free], ep.acc[free], dip)
    notes = [f"joint fit of {len(je.mags)} magnetometers on {je.t.size} shared epochs"]
    if not problem.still.segments:
        db = np.median(np.array(dbs), axis=0)
        layout.put(theta, "gyroscope_bias", db)
        notes.append(f"no still segment; gyro bias started from the magnetometers' median Wu & Luo alignment "
                     f"({np.array2string(bias + db, precision=4)} rad/s)")
    delta = pre.delta @ so3.exp(pre.d_bias @ layout.get(theta, "gyroscope_bias"))
    candidates = {"gyro-integrated": map_init.integrated(delta, anchor, pre.broken),
                  "accelerometer/magnetometer": anchor}
    data = joint_data(je, pre, noise, layout, held_out(je.t, problem.unmeasured))
    costs = {k: cost(data, s, theta) for k, s in candidates.items()}
    best = min(costs, key=costs.__getitem__)
    notes.append(f"started from the {best} trajectory")
    return candidates[best], theta, pre, notes


def fit_joint(problem: Problem, loss: str = "l2", dip_prior: float | None = None,
              noise_rounds: int = NOISE_ROUNDS) -> JointFit:
    """The joint MAP calibration of every magnetometer of the problem against its IMU, one trajectory for all."""
    with one_blas_thread():
        return _fit_joint(problem, loss, dip_prior, noise_rounds)


def _fit_joint(problem: Problem, loss: str, dip_prior: float | None, noise_rounds: int) -> JointFit:
    """`fit_joint` without the BLAS thread limit."""
    mags = problem.mags
    intr = [map_init.intrinsic_fit(despike(m.xyz)[0], f"{problem.where}: {m.id}") for m in mags]
    je = joint_epochs(problem, mags, [s.scale for s in intr])
    start = [initial_noise(problem, m, s.scale, s.noise_rms) for m, s in zip(mags, intr, strict=True)]
    still_s = sum(seg.end - seg.start for seg in problem.still.segments)
    dev = np.linalg.norm(je.acc, axis=1) - G
    spread = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
    noise = JointNoise(np.maximum(start[0].acc, spread), start[0].gyr, np.array([s.mag for s in start]))
    floor = JointNoise(start[0].acc, start[0].gyr, noise.mag) if still_s >= MIN_STILL_S else None
    layout = joint_layout(len(mags))
    states, theta, pre, notes = _start(problem, je, intr, noise, dip_prior, layout)
    hold = held_out(je.t, problem.unmeasured)
    bg = layout.slice("gyroscope_bias")
    start_opts = Options(max_iterations=60, cost_tol=1e-4, abs_cost_tol=1e-3, loss=loss)
    first = Options(max_iterations=60, abs_cost_tol=1e-3, loss=loss)
    later = Options(max_iterations=4, abs_cost_tol=1e-3, loss=loss)
    log: list[str] = []
    iters, applied = 0, 0.0
    history: list[tuple[float, float]] = []
    last_step = None
    sol: JointSolution | None = None
    fs_at: JointSolution | None = None
    fs: list[Factor] = []
    hook = current()
    for rnd in range(noise_rounds + 1):
        hook("joint MAP of every magnetometer, noise round", rnd, noise_rounds + 1)
        opts = (start_opts if noise_rounds else first) if rnd == 0 else later
        fs, fs_at, sol = [], None, None         # the last round's go before this round's are made (as fit.py)
        sol = solve_joint(joint_data(je, pre, noise, layout, hold), states, theta, opts)
        states, theta, iters = sol.states, sol.theta.copy(), iters + sol.iterations
        log.extend(f"round {rnd}: {line}" for line in sol.log)
        if float(np.linalg.norm(theta[bg])) * float(pre.duration.max()) > REPREINTEGRATE_RAD:
            pre = preintegrate_log(problem, je.t, pre.bias + theta[bg], noise.gyr, problem.where)
            theta[bg] = 0.0
            log.append(f"round {rnd}: re-preintegrated with the updated gyro bias")
            continue
        if rnd == noise_rounds or not np.all(np.isfinite(sol.cov_theta)):
            break
        fs = factors(joint_data(je, pre, noise, layout, hold), sol.states, sol.theta)
        fs_at = sol
        step = np.log(joint_variance_ratios(sol, fs, loss, opts.loss_scale))
        step, small, measured = noise_step(step, None if floor is None else floor.levels(), noise.levels(), history,
                                           applied)
        if small:
            last_step = step
            break
        history.append((applied, measured))
        applied += float(step[3])
        noise = noise.rescaled(step)
        pre = pre.scaled(float(np.exp(step[3])))
    assert sol is not None
    if not sol.converged:
        fs, fs_at, sol = [], None, None
        sol = solve_joint(joint_data(je, pre, noise, layout, hold), states, theta, first)
        iters += sol.iterations
        log.extend(f"final: {line}" for line in sol.log)
    if fs_at is not sol:              # the factors at the optimum (the last noise round's, unless it moved)
        fs = factors(joint_data(je, pre, noise, layout, hold), sol.states, sol.theta)
    widen = joint_widening(sol, fs, je.t)
    cov = sol.cov_theta
    if last_step is not None:
        # as fit.fit_map: the covariance with the final levels at the same point (one assembly, no iterations)
        noise = noise.rescaled(last_step)
        pre = pre.scaled(float(np.exp(last_step[3])))
        data = joint_data(je, pre, noise, layout, hold)
        cov = at_optimum(normal(data, sol.states, sol.theta)[1], sol.states, sol.theta, sol.cost, 0, True,
                         ()).cov_theta
    data = joint_data(je, pre, noise, layout, hold)
    return _results(problem, je, data, pre, noise, sol, cov, widen, layout, iters, tuple(log), tuple(notes))


def _results(problem: Problem, je: JointEpochs, data: JointData, pre: Preintegrated, noise: JointNoise,
             sol: JointSolution,
             cov: FloatArray, widen: FloatArray, layout: Layout, iters: int, log: tuple[str, ...],
             notes: tuple[str, ...]) -> JointFit:
    """The joint solution in SI and one `MapEstimate` per magnetometer (BASE layout, the marginal of its blocks)."""
    si = np.ones(layout.size)
    for i, ep in enumerate(je.mags):
        names = (f"D#{i}", f"o#{i}", f"dip#{i}")
        si[layout.cols(*names)] = layout.sub(names).si_factors(ep.scale)
    theta = sol.theta * si
    theta[layout.slice("gyroscope_bias")] += pre.bias
    cov = cov * np.outer(si, si)
    states = sol.states
    dips = layout.cols(*(f"dip#{i}" for i in range(len(je.mags))))
    if float(np.median(np.abs(theta[dips]))) > np.pi / 2:
        # `estimate.estimate`'s dip gauge, for all magnetometers at once: they share the trajectory it turns
        theta[dips] = np.angle(np.exp(1j * (np.pi - theta[dips])))
        states = so3.exp([0.0, 0.0, np.pi]) @ states
        cov[dips, :] *= -1.0
        cov[:, dips] *= -1.0
    widened = cov * np.outer(widen, widen)
    resid = mag_residuals(data, sol.states, sol.theta)
    ests = []
    for i, ep in enumerate(je.mags):
        c = base_cols(layout, i)
        where = f"{problem.where}: {ep.mag_id}"
        condition, findings = check_observability(cov[np.ix_(c, c)], ep.scale, ep.acc, where)
        if np.any(widen[c] > 1.0):
            findings.append(widening_note(where, ep.mag_id, float(widen[c].max())))
        r = resid[i]
        rms = float(np.sqrt(np.mean((r * noise.mag[i] * ep.scale) ** 2)))
        ests.append(MapEstimate(ep.mag_id, theta[c], widened[np.ix_(c, c)],
                                Noise(noise.acc, noise.gyr, noise.mag[i] * ep.scale), states[je.at[i]], ep.t,
                                sol.cost, iters, sol.converged, rms, log, tuple(findings),
                                tuple(f"{ep.mag_id}: {n}" for n in ep.notes), condition, BASE))
    return JointFit(tuple(ests), layout, theta, widened, states, je.t, noise, iters, log, notes)


def joint_eligible(problem: Problem, cfg: Config, loss: str) -> bool:
    """The joint fit replaces the separate ones for the base model only: two or more magnetometers, no effects
    (requested, diagnosed or a flight's known physics: those are fitted per magnetometer), the l2 loss."""
    return len(problem.mags) >= 2 and not cfg.diagnose and not cfg.effects and not problem.base_effects \
        and loss == "l2"


def _as_fit(est: MapEstimate) -> MagFit:
    """The D and o of an estimate as a MagFit (for the consistency check)."""
    d = est.value("D").reshape(3, 3, order="F")
    return MagFit(est.mag_id, d, est.value("o"), float(est.value("dip")[0]), est.cov, est.residual_rms,
                  int(est.epochs.size), est.iterations, est.converged)


def fit_joint_or_note(problem: Problem, cfg: Config, loss: str, dip_prior: float | None
                      ) -> tuple[JointFit | None, str]:
    """The joint fit of the magnetometers that agree, and a note; (None, why) when the separate fits must do.

    A magnetometer the consistency check calls an outlier after the joint fit is left out of a second joint fit
    (its disturbance would otherwise enter the shared trajectory) and is fitted on its own by the caller. A joint
    fit the data cannot support gives way to the separate fits, which hold what a log cannot determine per
    magnetometer (partial calibration): no common epochs, too little motion, no convergence, a dip in another
    basin, or magnetometers that still disagree beyond `consistency.agree` (they do not see one field through one
    rotation, so one shared trajectory would bend every calibration toward the others' disturbances).
    """
    if not joint_eligible(problem, cfg, loss):
        return None, ""
    mags = problem.mags
    try:
        fit = fit_joint(problem, loss, dip_prior)
        found = consistency.measure([_as_fit(e) for e in fit.estimates], mags)
        bad = found.outliers if found is not None else ()
        note = ""
        if bad and len(mags) - len(bad) >= 2:
            keep = tuple(m for k, m in enumerate(mags) if k not in bad)
            fit = fit_joint(replace(problem, mags=keep), loss, dip_prior)
            found = consistency.measure([_as_fit(e) for e in fit.estimates], keep)
            note = (f"{', '.join(mags[k].id for k in bad)} disagreed with the other magnetometers after the joint fit "
                    f"and {'was' if len(bad) == 1 else 'were'} fitted on {'its' if len(bad) == 1 else 'their'} own; the "
                    "others share one trajectory")
        elif bad:
            return None, "the magnetometers disagree with each other after a joint fit: each was fitted on its own"
        if not all(e.converged for e in fit.estimates):
            return None, f"the joint fit of the {len(fit.estimates)} magnetometers did not converge: each was fitted on its own"
        if found is not None and not consistency.agree(found):
            ang, norm = consistency.typical(found)
            return None, (f"after a joint fit the magnetometers still disagree by {ang:.1f} deg and {norm:.1f} % RMS, more "
                          "than one field seen through one rigid rotation allows (disturbances near some of them, or "
                          "motion the model leaves out): each was fitted on its own")
        for est in fit.estimates:
            dip = float(est.value("dip")[0])
            if dip_prior is not None and abs(np.degrees(dip - dip_prior)) > DIP_BASIN_DEG:
                msg = f"{est.mag_id}'s dip {np.degrees(dip):.1f} deg is far from the World Magnetic Model's"
                raise InsufficientDataError(msg)
    except (InsufficientDataError, np.linalg.LinAlgError) as exc:
        return None, f"no joint fit of the {len(mags)} magnetometers ({exc}); each was fitted on its own"
    return fit, note
