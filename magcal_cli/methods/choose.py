"""Which method runs (auto's choice), what it cannot carry, and its run over every magnetometer with fallbacks."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from magcal_cli.config import Config
from magcal_cli.errors import ConvergenceError, InsufficientDataError, MagcalError, UnexplainedError, reason
from magcal_cli.findings import Finding, Severity
from magcal_cli.methods.table import METHODS
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MethodResult, Refusal
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


#: disturbances a compass's readings are judged with before it is refused: magnetometer terms driven by a channel
#: the log may hold (issue 38 item 2: a field strength that follows the current is current interference)
DISTURBANCES = ("current_interference", "throttle_interference", "motor_interference", "temperature_drift")

Progress = Callable[[str], None]


#: what to record instead, for a refusal whose message carries no advice of its own
RECORD_AGAIN = "record again, turning the vehicle slowly about all three axes away from iron and power wiring"


def refusal(where: str, mag_id: str, exc: MagcalError) -> Refusal:
    """The refusal of one magnetometer from the error that refused it: its `To fix:` advice, else the last sentence
    of a `where: what. How` message, else RECORD_AGAIN."""
    text = str(exc)
    why = reason(exc, f"{where}: {mag_id}").removeprefix(f"{where}: ")
    if " To fix:" in text:
        return Refusal(mag_id, why, text.split(" To fix:", 1)[1].strip().rstrip("."))
    what, _, how = why.rpartition(". ")
    return Refusal(mag_id, what, how[:1].lower() + how[1:]) if what else Refusal(mag_id, why, RECORD_AGAIN)


def refused_finding(r: Refusal) -> Finding:
    """The warning that names a refused magnetometer, its reason and its advice."""
    return Finding(Severity.WARNING, "not_calibrated", f"{r.id} was not calibrated: {r.reason}. To fix: {r.advice}",
                   {"sensor": r.id})


def _disturbed(run: MethodRun, problem: Problem, cfg: Config, method: str, exc: UnexplainedError,
               progress: Progress) -> tuple[MethodResult, list[Finding]] | None:
    """The base fit left one magnetometer's readings unexplained: the fit with one disturbance the log has a channel
    for, the first of current, throttle, motors and temperature (the usual size of each on a vehicle) that explains
    the readings; None when none does. Only where the effects are the diagnosis's to choose (`--effects auto`) and the method
    models them. The first, not the best: a refused fit costs as much as a whole one, and the rivals are told
    apart by the diagnosis of a log that a base model explains."""
    if not (cfg.diagnose and METHODS[method].carries == "all"):
        return None
    from magcal_cli.effects import get

    kinds = {s.kind for s in problem.aux}
    mag = problem.mags[0]
    for eid in DISTURBANCES:
        if not set(get(eid).channels) <= kinds:
            continue
        progress(f"{mag.id}: the base model was refused; fitting it with {eid}")
        try:
            got = call(run, problem, replace(cfg, effects=(eid,), diagnose=False), method)
        except (InsufficientDataError, ConvergenceError):
            continue
        break
    else:
        return None
    note = Finding(Severity.WARNING, "disturbance_modelled",
                   f"{mag.id}: the base model was refused ({reason(exc, f'{problem.where}: {mag.id}')}); with "
                   f"{eid} modelled the readings are explained, so it was calibrated with it (the mismatch "
                   "diagnosis did not run for this magnetometer)", {"sensor": mag.id, "effect": eid})
    return got, [note]


def one_compass(run: MethodRun, problem: Problem, cfg: Config, method: str, exc: MagcalError,
                progress: Progress) -> tuple[MethodResult | None, list[Finding], Refusal | None]:
    """A magnetometer the method refused (`exc`), given the strongest calibration its own data support: the method
    with the disturbances the log can explain, then the vehicle's attitude and the WMM (auto only), else refused."""
    m = problem.mags[0]
    if isinstance(exc, UnexplainedError):        # not for too little motion: that no disturbance explains
        got = _disturbed(run, problem, cfg, method, exc, progress)
        if got is not None:
            return got[0], got[1], None
    try:
        result, why = attitude_instead(problem, cfg, exc, progress)
    except (InsufficientDataError, ConvergenceError):
        return None, [], refusal(problem.where, m.id, exc)
    return result, why, None


def run_method(run: MethodRun, problem: Problem, cfg: Config, method: str, progress: Progress = lambda _: None
               ) -> tuple[MethodResult, list[Finding]]:
    """Run the method on every magnetometer; when one cannot be calibrated, give each its strongest fallback.

    A magnetometer that cannot be calibrated (too little motion for it, disturbed, no convergence) must not
    cost the user the others, and none may vanish: each is refitted alone (`one_compass`: as `--mag` alone would)
    and either calibrated, by the method that could, or listed in `refused` with its reason. Only when no
    magnetometer can be calibrated is it an error, which names each.
    """
    try:
        return call(run, problem, cfg, method), []
    except (InsufficientDataError, ConvergenceError) as exc:
        whole: MagcalError = exc
    parts: list[MethodResult] = []
    found: list[Finding] = []
    refused: list[Refusal] = []
    errors: list[MagcalError] = []
    for m in problem.mags:
        one = replace(problem, mags=(m,))
        try:
            if len(problem.mags) == 1:
                raise whole
            parts.append(call(run, one, cfg, method))
            continue
        except (InsufficientDataError, ConvergenceError) as exc:
            got, why, no = one_compass(run, one, cfg, method, exc, progress)
            errors.append(exc)
        found.extend(why)
        if got is not None:
            parts.append(got)
        else:
            assert no is not None
            refused.append(no)
    if not parts:
        raise _all_refused(problem.where, refused, errors)
    merged = merge(parts)
    return replace(merged, refused=tuple(refused)), found + [refused_finding(r) for r in refused]


def _all_refused(where: str, refused: list[Refusal], errors: list[MagcalError]) -> MagcalError:
    """The error of a log none of whose magnetometers could be calibrated: the one error, or one naming each."""
    if len(errors) == 1:
        return errors[0]
    kind = type(errors[0]) if all(type(e) is type(errors[0]) for e in errors) else InsufficientDataError
    return kind(none_calibrated(where, refused, "could be calibrated"))


def none_calibrated(where: str, refused: Sequence[Refusal], verb: str) -> str:
    """One sentence for a log none of whose magnetometers is calibrated: each by name with its reason, then the
    advice of all of them, each piece once."""
    each = "; ".join(f"{r.id}, {r.reason}" for r in refused)
    advice: list[str] = []
    for a in dict.fromkeys(r.advice for r in refused if r.advice != RECORD_AGAIN):
        if not any(a in b for b in advice):
            advice = [b for b in advice if b not in a] + [a]
    return f"{where}: none of the {len(refused)} magnetometers {verb}: {each}" + \
        (f". To fix: {'; '.join(advice)}" if advice else "")


def merge(parts: list[MethodResult]) -> MethodResult:
    """Results of single magnetometers as one: each fit keeps its method, the IMU biases come from the part that
    determined them best."""
    imu = min((p.imu for p in parts), key=lambda i: float(np.sum(i.accel_bias_std)) if i.accel_bias_std is not None
              else np.inf)
    noise = {k: v for p in parts for k, v in p.noise.items()}
    mag_ids = {f.id for p in parts for f in p.mags}
    # magnetometer effects from every part, IMU effects from the part whose IMU biases are kept
    effects = tuple(e for p in parts for e in p.effects if e.sensor in mag_ids) + \
        tuple(e for p in parts if p.imu is imu for e in p.effects if e.sensor not in mag_ids)
    fits = tuple(replace(f, method=f.method or p.method) for p in parts for f in p.mags)
    return MethodResult(parts[0].method, fits, imu, noise, tuple(n for p in parts for n in p.notes),
                        tuple(f for p in parts for f in p.findings), effects,
                        tuple(d for p in parts for d in p.diagnosis), tuple(r for p in parts for r in p.refused))


def attitude_instead(problem: Problem, cfg: Config, exc: MagcalError,
                     progress: Progress = lambda _: None) -> tuple[MethodResult, list[Finding]]:
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
                  "from the compass calibration the vehicle flew with",
                  {"sensor": problem.mags[0].id} if len(problem.mags) == 1 else {})
    return result, [why]
