"""The joint MAP method for a whole log (`--method map`): every magnetometer against the IMU, the known physics
of a flight and the diagnosis, assembled into the method's result. The estimator itself is `map/fit.py`."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.config import Config
from magcal_cli.diagnose.parallel import pmap, side_by_side
from magcal_cli.errors import InsufficientDataError, reason
from magcal_cli.findings import Finding, Severity
from magcal_cli.models import consistency
from magcal_cli.models.epochs import BIAS_SCALE, Noise
from magcal_cli.models.gyro import Preintegrated
from magcal_cli.models.map.cost import mag_layout
from magcal_cli.models.map.estimate import MapEstimate
from magcal_cli.models.map.fit import fit_map
from magcal_cli.models.map.joint import fit_joint_or_note
from magcal_cli.models.map.shared import is_shared, shared
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import HeldEntry, ImuFit, MagFit, MethodResult
from magcal_cli.params import BASE, MAG
from magcal_cli.progress import Parts, current
from magcal_cli.streams import Stream

#: progress reports one magnetometer's fit and diagnosis make (log171: 55-70), before one has ended and said so
REPORTS_EACH = 60


def to_fits(est: MapEstimate, stream: Stream) -> MagFit:
    """The magnetometer part of an estimate as a MagFit (D, o in tesla; covariance of vec D, o, dip)."""
    d, o, dip = mag_layout(est.layout).unpack(est.theta)
    c = est.layout.cols(*MAG.names)
    return MagFit(est.mag_id, d, o, dip, est.cov[np.ix_(c, c)], est.residual_rms, int(est.epochs.size),
                  est.iterations, est.converged, est.log, held_entries(est))


def held_entries(est: MapEstimate) -> tuple[HeldEntry, ...]:
    """The estimate's held parameters with their priors in SI (the gyro bias as a total, like theta)."""
    if est.held is None or est.context is None:
        return ()
    si = BASE.si_factors(est.context.ep.scale)
    total = np.zeros(BASE.size)
    total[BASE.slice("gyroscope_bias")] = est.context.pre.bias
    names = est.held.names()
    return tuple(HeldEntry(n, float(est.held.prior_mean[c] * si[c] + total[c]), float(est.held.prior_std[c] * si[c]),
                           s) for n, c, s in zip(names, est.held.cols, est.held.sources, strict=True)
                 if not is_shared(s))             # the shared IMU bias is no partial calibration (map/shared.py)


def with_known_physics(problem: Problem, mag: Stream, loss: str, dip_prior: float | None, start: Noise | None,
                        cache: dict[bytes, Preintegrated], effects: tuple[str, ...], declination: float
                        ) -> tuple[MapEstimate, Problem]:
    """The fit with the problem's base effects (a flight's GPS acceleration), unless the log then determines less
    of the calibration than without them (a GPS that disagrees with the IMU: a lag, glitches, a wrong antenna
    offset): then the fit without, with a finding that says so. Also the problem the fit used."""
    def fit(p: Problem) -> MapEstimate:
        return fit_map(p, mag, loss, dip_prior, imu_start=start, cache=cache, effects=effects,
                       declination=declination)

    if not problem.base_effects:
        return fit(problem), problem

    def partial(e: MapEstimate) -> bool:
        return e.held is not None and e.held.cols.size > 0

    est: MapEstimate | None = None
    try:
        est = fit(problem)
    except InsufficientDataError as exc:
        # the reason alone: its "where" prefix and its advice belong to a refusal, not to this note
        why = f"the fit was refused ({reason(exc, f'{problem.where}: {mag.id}')})"
    else:
        if not partial(est):
            return est, problem
        assert est.held is not None
        why = f"{', '.join(est.held.names())} had to be held at a prior"
    plain = replace(problem, base_effects=())
    try:
        alt = fit(plain)
    except InsufficientDataError:
        if est is None:
            raise
        return est, problem
    if est is not None and partial(alt):              # no better without: the known physics stays
        return est, problem
    note = Finding(Severity.WARNING, "known_physics_dropped",
                   f"{problem.where}: {mag.id}: {', '.join(problem.base_effects)} was not modelled: with it {why}; "
                   "without it the log determines more of the calibration (the log's GPS acceleration disagrees with the "
                   "accelerometer: glitches, a lag beyond the modelled one, or an antenna far from the IMU)",
                   {"sensor": mag.id})
    return replace(alt, findings=(*alt.findings, note)), plain


def without_effects(ests: list[MapEstimate], problem: Problem) -> tuple[Stream, ...]:
    """Each magnetometer's readings (SI) with the effects its fit modelled removed: the consistency check compares
    calibrations, not the motor field one of them sees (log171: 10.7 deg RMS with MAG[1]/MAG[2]'s throttle
    interference left in; effects/correct.py)."""
    from magcal_cli.calibration.effects import entry
    from magcal_cli.effects.correct import remove

    out = []
    for est, s in zip(ests, problem.mags, strict=True):
        entries = [entry(f, None) for f in est.effects if f.sensor == est.mag_id]
        t, y, _ = remove(entries, s.id, problem, s.t, s.xyz)
        out.append(replace(s, t=t, values=y))
    return tuple(out)


def _diagnosed(cfg: Config, problem: Problem, m: Stream, est: MapEstimate, declination: float, loss: str,
               dip_prior: float | None) -> tuple[MapEstimate, dict[str, Any] | None]:
    """The fit with the diagnosis' effects and its report block (None: not diagnosed). A refit the diagnosis needs
    (a fold, an extended model) that fails on a weakly determined log leaves the base calibration standing."""
    if not cfg.diagnose:
        return est, None
    from magcal_cli.diagnose.engine import diagnose

    try:
        found = diagnose(problem, m, est, declination, loss, dip_prior)
    except (InsufficientDataError, np.linalg.LinAlgError) as exc:
        return replace(est, findings=(*est.findings, Finding(
            Severity.WARNING, "diagnosis_failed",
            f"{problem.where}: {m.id}: the mismatch diagnosis could not run ({exc}); the base calibration "
            "is reported without it", {"sensor": m.id}))), None
    return found.estimate, found.block


def run(problem: Problem, cfg: Config) -> MethodResult:
    """Joint MAP for every magnetometer of the problem, each against the IMU (the paper's 30-magnetometer
    setup)."""
    from magcal_cli.wmm import reference_for

    ref = reference_for(cfg)
    dip_prior = None if ref is None else ref.dip
    loss = getattr(cfg, "robust_loss", "l2")
    ests: list[MapEstimate] = []
    cache: dict[bytes, Preintegrated] = {}
    declination = 0.0 if ref is None else ref.declination
    diagnoses: list[dict[str, Any]] = []
    joint, joint_note = fit_joint_or_note(problem, cfg, loss, dip_prior)
    done = {} if joint is None else {e.mag_id: e for e in joint.estimates}
    todo = [m for m in problem.mags if m.id not in done]

    def fitted(m: Stream, start: Noise | None) -> tuple[MapEstimate, Problem]:
        return with_known_physics(problem, m, loss, dip_prior, start, cache, cfg.effects, declination)

    def item(k: int) -> tuple[MapEstimate, dict[str, Any] | None]:
        # later magnetometers start from the first one's IMU noise levels, as its fit found them before its
        # diagnosis: then its diagnosis runs beside their fits and diagnoses (log171's whole fit: 8.7 s with only
        # the folds and replicates side by side, 6.3 s with the magnetometers too), same digits either way
        est, own = (first, mine) if k == 0 else fitted(todo[k], first.noise)
        return _diagnosed(cfg, own, todo[k], est, declination, loss, dip_prior)

    parts = Parts(current(), "magnetometer", len(todo))
    results: list[tuple[MapEstimate, dict[str, Any] | None]] = []
    together = len(todo) > 1 and side_by_side(len(todo))
    if todo:
        with parts.part(0):
            first, mine = fitted(todo[0], None)
            if not together:
                results.append(item(0))
        if together:
            hook, count = current(), len(todo)
            results = pmap(item, range(count), guess=REPORTS_EACH,
                           done=lambda d, n: hook(f"magnetometers 1-{count} side by side", d, n))
        else:
            for k in range(1, len(todo)):
                with parts.part(k):
                    results.append(item(k))
    for est, block in results:
        ests.append(est)
        diagnoses.extend([block] if block is not None else [])
    rest = iter(ests)
    ests = [done[m.id] if m.id in done else next(rest) for m in problem.mags]

    def bias_std(e: MapEstimate) -> float:
        return float(np.sum(np.concatenate([e.std_of("accelerometer_bias"), e.std_of("gyroscope_bias")])
                            / BIAS_SCALE))

    best = min(ests, key=bias_std) if joint is None else joint.estimates[0]     # the joint fit's IMU biases
    if joint is None and len(ests) > 1:                # one IMU, one accelerometer bias (map/shared.py)
        ests = shared(problem, ests, best, loss, dip_prior, declination, pmap)
    imu = ImuFit(problem.imu_id, best.value("accelerometer_bias"), best.value("gyroscope_bias"),
                 best.std_of("accelerometer_bias"), best.std_of("gyroscope_bias"))
    notes: list[str] = []
    findings: list[Finding] = []
    noise: dict[str, list[float]] = {"accelerometer_std": best.noise.acc.tolist(),
                                     "gyroscope_std": best.noise.gyr.tolist()}
    for est, stream in zip(ests, problem.mags, strict=True):
        notes.extend(est.notes)
        findings.extend(est.findings)
        factor = units.from_si(stream.native_unit)
        noise[f"magnetometer_std[{est.mag_id}]"] = (est.noise.mag * factor).tolist()
    if ref is not None:
        notes.append(f"dip initialised from the {ref.model} at the log's position ({ref.dip_deg:.2f} deg); "
                     f"field strength {ref.intensity * 1e6:.2f} uT")
    notes.extend([*([] if joint is None else joint.notes), *([joint_note] if joint_note else [])])
    if joint is None and len(ests) > 1:
        notes.append(f"IMU biases from the fit against {best.mag_id} (smallest bias uncertainty of "
                     f"{len(ests)} magnetometers)")
    fits = tuple(to_fits(e, s) for e, s in zip(ests, problem.mags, strict=True))
    findings.extend(consistency.findings(consistency.measure(fits, without_effects(ests, problem)), problem.where))
    # magnetometer effects from each magnetometer's fit; IMU effects from the fit that gave the IMU biases
    effects = tuple(f for e in ests for f in e.effects if f.sensor == e.mag_id) + \
        tuple(f for f in best.effects if f.sensor == problem.imu_id)
    return MethodResult("map", fits, imu, noise, tuple(notes), tuple(findings), effects, tuple(diagnoses))
