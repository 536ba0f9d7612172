"""Which method runs (auto's choice), what it cannot carry, and its run over every magnetometer with fallbacks."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from magcal_cli.config import Config
from magcal_cli.errors import ConvergenceError, InsufficientDataError, MagcalError
from magcal_cli.findings import Finding, Severity
from magcal_cli.methods.table import METHODS
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MethodResult
from magcal_cli.readers.checks import normalised_field
from magcal_cli.wmm import reference_for

MethodRun = Callable[[Problem, Config], MethodResult]


def choose(problem: Problem, cfg: Config) -> tuple[str, list[Finding]]:
    """The method to run: auto picks MAP when there is gyro data, but Kok 2012 for a field normalised upstream,
    whose magnitude the joint model needs (Kok 2012 uses only directions); MAP on such a field is refused."""
    normalised = [m.id for m in problem.mags if normalised_field(m.xyz)]
    if normalised and cfg.method in ("auto", "map") and len(problem.gyr):
        ids = ", ".join(normalised)
        if cfg.method == "map":
            msg = (f"{problem.where}: {ids}: the field was normalised to unit length upstream, so --method map cannot "
                   "determine the calibration (it needs the raw field's magnitude); use --method kok2012 for the "
                   "misalignment and dip only, or log the raw magnetometer readings")
            raise InsufficientDataError(msg)
        return "kok2012", [Finding(Severity.WARNING, "method_choice",
                                   f"{ids}: the field was normalised to unit length upstream, so auto chose Kok 2012 "
                                   "(directions only) over the joint MAP method (which needs the field's magnitude); "
                                   "only the misalignment and dip are meaningful")]
    return (("map" if len(problem.gyr) else "kok2012") if cfg.method == "auto" else cfg.method), []


def not_carried(method: str, effects: tuple[str, ...]) -> tuple[str, ...]:
    """The requested effects `method` cannot model: the joint MAP models every effect, the EKFs the additive
    magnetometer terms (models/ekf/effects.py), the other methods none."""
    carries = METHODS[method].carries if method in METHODS else "none"
    if carries == "all" or not effects:
        return ()
    if carries == "none":
        return effects
    from magcal_cli.models.ekf.effects import not_carried

    return not_carried(effects, method)


def call(run: MethodRun, problem: Problem, cfg: Config, method: str) -> MethodResult:
    """One method run; numerical breakdowns become a ConvergenceError that names the method."""
    try:
        return run(problem, cfg)
    except np.linalg.LinAlgError as exc:                 # singular or non-finite systems: degenerate data
        msg = (f"{problem.where}: the {method} solver failed numerically ({exc}); the data are degenerate for it "
               "(damaged or repeated samples?). Check the log with magcal inspect, or try another --method")
        raise ConvergenceError(msg) from None


def run_method(run: MethodRun, problem: Problem, cfg: Config, method: str) -> tuple[MethodResult, list[Finding]]:
    """Run the method on every magnetometer; when several are fitted and some cannot be, keep the others.

    A magnetometer that cannot be calibrated (too little motion for it, disturbed, no convergence) must not
    cost the user the others: they are refitted one by one and the failures become warnings. Only when no
    magnetometer can be calibrated is it an error.
    """
    try:
        return call(run, problem, cfg, method), []
    except (InsufficientDataError, ConvergenceError):
        if len(problem.mags) == 1:
            raise
    parts: list[MethodResult] = []
    failed: list[Finding] = []
    first: MagcalError | None = None
    for m in problem.mags:
        try:
            parts.append(call(run, replace(problem, mags=(m,)), cfg, method))
        except (InsufficientDataError, ConvergenceError) as exc:
            first = first or exc
            failed.append(Finding(Severity.WARNING, "not_calibrated", f"{m.id} was not calibrated: {exc}",
                                  {"sensor": m.id}))
    if not parts:
        assert first is not None
        raise first
    imu = min((p.imu for p in parts), key=lambda i: float(np.sum(i.accel_bias_std)) if i.accel_bias_std is not None
              else np.inf)
    noise = {k: v for p in parts for k, v in p.noise.items()}
    mag_ids = {f.id for p in parts for f in p.mags}
    # magnetometer effects from every part, IMU effects from the part whose IMU biases are kept
    effects = tuple(e for p in parts for e in p.effects if e.sensor in mag_ids) + \
        tuple(e for p in parts if p.imu is imu for e in p.effects if e.sensor not in mag_ids)
    merged = MethodResult(parts[0].method, tuple(f for p in parts for f in p.mags), imu, noise,
                          tuple(n for p in parts for n in p.notes), tuple(f for p in parts for f in p.findings),
                          effects, tuple(d for p in parts for d in p.diagnosis))
    return merged, failed


def attitude_instead(problem: Problem, cfg: Config, exc: InsufficientDataError,
                     progress: Callable[[str], None] = lambda _: None) -> tuple[MethodResult, list[Finding]]:
    """--method auto on a log whose own motion cannot determine the calibration: the vehicle's attitude estimate
    and the World Magnetic Model as the reference, where the log has both (issue 12 item 2); else `exc`. The
    progress line then names the method that runs."""
    from magcal_cli.models import attitude_ref

    if cfg.method != "auto" or reference_for(cfg) is None:
        raise exc
    try:
        att = attitude_ref.attitude_stream(problem)
        progress(f"the log's own motion cannot determine the calibration; fitting attitude (against {att.id} and "
                 f"the World Magnetic Model) for {', '.join(m.id for m in problem.mags)}")
        result = attitude_ref.run(problem, cfg)
    except InsufficientDataError:
        raise exc from None
    why = Finding(Severity.WARNING, "attitude_reference",
                  f"{str(exc).rstrip('.')}. It was calibrated against the vehicle's attitude estimate {att.id} and "
                  "the World Magnetic Model instead, so it inherits the errors of that estimate, whose heading came "
                  "from the compass calibration the vehicle flew with")
    return result, [why]
