"""calibrate(path, config) -> RunResult: read, select, detect, estimate, assemble the document. No printing."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from magcal_cli import __version__, timing, units
from magcal_cli.calibration.assemble import (
    diagnosis_block,
    dip_check,
    effect_entries,
    findings_for,
    mag_calibration,
)
from magcal_cli.calibration.run import RunResult, sha256, utc_now
from magcal_cli.calibration.types import Calibration, ImuCalibration, Source
from magcal_cli.config import Config
from magcal_cli.detect import (
    IMPACT,
    check_dead,
    check_signal,
    detect_still,
    gyro_noise_scale,
    pooled_std,
    unmeasured_windows,
)
from magcal_cli.errors import InsufficientDataError, MagcalError, StreamError
from magcal_cli.findings import Finding, Severity
from magcal_cli.firmware.heading import heading_checks
from magcal_cli.methods.choose import (
    choose,
    none_calibrated,
    not_carried,
    refusal,
    refused_finding,
    run_method,
)
from magcal_cli.methods.table import METHODS
from magcal_cli.models.partial import MagPrior, flown_prior
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MethodResult, Refusal
from magcal_cli.progress import Hook, active, current
from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.registry import resolve
from magcal_cli.streams import Kind, Recording, Sampling, Stream
from magcal_cli.units import G
from magcal_cli.wmm import reference_for

#: the channels effect plug-ins may use, handed to the estimators beside the IMU and magnetometers
AUX_KINDS = frozenset({Kind.BATTERY_CURRENT, Kind.BATTERY_VOLTAGE, Kind.THROTTLE, Kind.TEMPERATURE,
                       Kind.POSITION, Kind.ATTITUDE, Kind.MOTOR_OUTPUT})


def _known_physics(cfg: Config, aux: tuple[Stream, ...]) -> tuple[str, ...]:
    """Effects `--effects auto` models in every fit: a flight's acceleration where its position measured it."""
    if not cfg.diagnose:
        return ()
    from magcal_cli.effects.nongravity import flying  # on use: scipy.signal brings scipy.stats (issue 27)

    return ("nongravity_acceleration",) if flying(aux) else ()


def select_problem(rec: Recording, cfg: Config) -> Problem:
    """Pick the IMU and magnetometers named by the config and cut them to [start, end]."""
    return select_streams(rec, cfg)[0]


def select_streams(rec: Recording, cfg: Config) -> tuple[Problem, list[Finding], tuple[Refusal, ...]]:
    """The problem, and the warnings and refusals of magnetometers left out because they cannot be used (while
    others can)."""
    where = rec.path.name
    gyro_ids = set(rec.ids(Kind.GYROSCOPE))
    if cfg.imu is None:
        candidates = [i for i in rec.ids(Kind.ACCELEROMETER) if i in gyro_ids]
        imu_id = candidates[0] if candidates else None
    else:
        imu_id = cfg.imu
    acc = rec.select(Kind.ACCELEROMETER, imu_id, "--imu")
    gyr = rec.select(Kind.GYROSCOPE, acc.id, "--imu")
    mag_ids: list[str | None] = list(rec.ids(Kind.MAGNETOMETER)) if cfg.mag == "all" else \
        [m.strip() for m in cfg.mag.split(",")]
    mags = tuple(rec.select(Kind.MAGNETOMETER, m or None, "--mag").between(cfg.start_s, cfg.end_s)
                 for m in (mag_ids or [None]))
    acc, gyr = acc.between(cfg.start_s, cfg.end_s), gyr.between(cfg.start_s, cfg.end_s)
    windowed = cfg.start_s is not None or cfg.end_s is not None

    def usable(s: Stream) -> None:
        check_dead(s, rec.dead.get(s.id) if s.kind is Kind.MAGNETOMETER else None, where)
        if len(s) < 10:
            span = f" ({s.t[-1] - s.t[0]:.1f} s)" if len(s) > 1 else ""
            msg = (f"{where}: {s.kind.value} {s.id} has only {len(s)} samples between --start and --end; "
                   "widen the time window" if windowed else
                   f"{where}: {s.kind.value} {s.id} has only {len(s)} samples{span}; a calibration needs a "
                   "recording of at least a minute with the vehicle turned through many orientations")
            raise StreamError(msg)
        check_signal(s)

    for s in (acc, gyr):
        usable(s)
    good, dropped = [], []
    for m in mags:                      # one unusable magnetometer must not cost the user the others
        try:
            usable(m)
            good.append(m)
        except (StreamError, InsufficientDataError) as exc:
            if len(mags) == 1:
                raise
            dropped.append((m, exc))
    refused = [refusal(where, m.id, exc) for m, exc in dropped]
    if not good:
        raise dropped[0][1] if len(dropped) == 1 else InsufficientDataError(
            none_calibrated(where, refused, "can be used"))
    findings = [refused_finding(r) for r in refused]
    aux = tuple(st.between(cfg.start_s, cfg.end_s) for st in rec.streams if st.kind in AUX_KINDS)
    still = detect_still(acc, gyr, cfg.still, tuple(good))
    unmeasured = unmeasured_windows(acc, gyr)
    if unmeasured:
        spans = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in unmeasured)
        findings.append(Finding(Severity.WARNING, "unmeasured_motion",
                                f"{acc.id}: the IMU did not measure the motion at {spans} (an impact above "
                                f"{IMPACT / G:.0f} g or the gyro at the top of its range, "
                                f"{np.degrees(np.abs(gyr.xyz).max()):.0f} deg/s): the trajectory is not carried "
                                "through, and the samples there are not used", {"windows_s": unmeasured}))
    aux = tuple(st for st in aux if len(st) >= 2)
    # still segments and impacts are found on the samples as logged (one IMU time base); the estimators take
    # them in their own time convention (timing.py)
    scale = gyro_noise_scale(gyr, still)
    acc, gyr, mags_est, record = timing.for_estimator(acc, gyr, tuple(good), cfg.imu_timing, cfg.mag_timing)
    return Problem(where, acc.id, acc, gyr, mags_est, still, aux, onboard_priors(rec, good), unmeasured,
                   _known_physics(cfg, aux), record, scale), findings, tuple(refused)


def onboard_priors(rec: Recording, mags: list[Stream]) -> dict[str, MagPrior]:
    """The calibration each magnetometer flew with, from the log's own parameters (ArduPilot COMPASS_*, PX4
    CAL_MAGn_*; a firmware-corrected stream is its own): the prior of a partial calibration. None without
    parameters."""
    from magcal_cli.firmware import FirmwareError
    from magcal_cli.firmware.flown import flown_fields

    try:
        flown, source = flown_fields(rec, [m.id for m in mags], None, None)
    except (FirmwareError, MagcalError):
        return {}
    out = {}
    for f, m in zip(flown, mags, strict=True):
        p = flown_prior(f.raw, f.field, units.to_si(f.unit), f"{f.slot} in {source}")
        if p is not None:
            out[m.id] = p
    return out


def with_position(rec: Recording, cfg: Config) -> Config:
    """The config with `location` from the log's position stream and `date` from its clock, when not given."""
    pos = [st.values[np.isfinite(st.values).all(axis=1)] for st in rec.streams if st.kind is Kind.POSITION]
    if cfg.location is None and pos and len(pos[0]):
        lat, lon, alt = np.median(pos[0], axis=0)
        cfg = replace(cfg, location=(float(lat), float(lon), float(alt)))
    utc = rec.utc0 if rec.utc0 is not None else rec.t0 if rec.t0 > 1e9 else None   # t0 may be a Unix time
    if cfg.location is not None and cfg.date is None and utc is not None:
        cfg = replace(cfg, date=time.strftime("%Y-%m-%d", time.gmtime(utc)))
    return cfg


def command_config(mag: str = "all", imu: str | None = None, *, method: str = "auto",
                   effects: tuple[str, ...] | None = None, start_s: float | None = None, end_s: float | None = None,
                   strict: bool = False, imu_timing: Sampling | None = None, mag_timing: Sampling | None = None
                   ) -> Config:
    """The Config `fit`, `diagnose` and `check`'s refit calibrate a log with, from the options they share.

    One function, so the three commands read the same records, select the same streams, choose the same method and
    reach the same observability verdict for the same log (issue 30): `diagnose` used to force the joint MAP method
    and refused 01_07_59.px4log, which `fit` calibrated with the attitude method auto fell back to; it and `check`'s
    refit also refused a cut log (Config's default), which `fit` reads up to its last complete record. `method` auto
    picks as `methods.choose` does; `effects` None is --effects auto (the mismatch diagnosis chooses the effects, and
    a flight's known physics is modelled), a tuple models exactly those effects; `strict` refuses a cut log.
    `fit` adds its own options (location, date, robust loss) with `dataclasses.replace`.
    """
    return Config(method=method, mag=mag, imu=imu, start_s=start_s, end_s=end_s, allow_truncated=not strict,
                  effects=() if effects is None else effects, diagnose=effects is None, imu_timing=imu_timing,
                  mag_timing=mag_timing)


def not_diagnosable(why: str) -> Finding:
    """The finding that the mismatch diagnosis did not run: `why` says which method calibrated the log instead."""
    return Finding(Severity.INFO, "diagnosis_skipped",
                   f"not diagnosed: the mismatch diagnosis runs with the joint MAP method only, and {why}")


def skipped_diagnoses(result: MethodResult, found: list[Finding]) -> list[Finding]:
    """Which magnetometers the mismatch diagnosis did not run for, and why: those another method calibrated, and
    those calibrated only with a disturbance modelled (methods/choose.py); each finding names its sensors, none
    when the finding is about them all."""
    other = [f.id for f in result.mags if f.method != "map"]
    disturbed = {str(f.evidence["sensor"]): str(f.evidence["effect"]) for f in found
                 if f.code == "disturbance_modelled"}
    out = []
    if other:
        methods = " and ".join(dict.fromkeys(f.method for f in result.mags if f.method != "map"))
        why = not_diagnosable(f"this log's own motion cannot determine the joint MAP calibration, so the {methods} "
                              f"method calibrated it")
        out.append(why if len(other) == len(result.mags) else replace(why, evidence={"sensors": other}))
    for mag_id, eid in disturbed.items():
        out.append(Finding(Severity.INFO, "diagnosis_skipped",
                           f"not diagnosed: the base model left the readings unexplained, so {eid} was modelled "
                           "without the diagnosis", {"sensors": [mag_id]}))
    return out


def not_diagnosed(result: RunResult) -> str | None:
    """Why the mismatch diagnosis did not run on a result fitted with the diagnosis asked for (`command_config`
    with effects None), in one sentence for `diagnose` to print as its result; None when it ran, or when the
    diagnosis was not asked for."""
    return next((f.message for f in result.findings if f.code == "diagnosis_skipped"), None)


def calibrate(path: Path, cfg: Config, fmt: str | None = None, progress: Hook | None = None) -> RunResult:
    """Calibrate every selected magnetometer of one log against its IMU (progress: default the current hook)."""
    path = Path(path)
    progress = progress or current()
    progress(f"reading {path.name}")
    with active(progress):                  # the chunked readers report their fraction through current()
        rec = open_recording(path, fmt, ReadOptions(allow_truncated=cfg.allow_truncated))
    return calibrate_recording(rec, cfg, progress)


def calibrate_recording(rec: Recording, cfg: Config, progress: Hook | None = None) -> RunResult:
    """Calibrate every selected magnetometer of a recording already read (or built in code) against its IMU."""
    path = rec.path
    progress = progress or current()
    problem, dropped, unusable = select_streams(rec, cfg)
    method, chosen = choose(problem, cfg)
    cfg = with_position(rec, cfg)
    if cfg.diagnose and method != "map":
        chosen.append(not_diagnosable(f"auto chose the {method} method for this log" if cfg.method == "auto" else
                                      f"--method {method} calibrated it"))
        cfg = replace(cfg, diagnose=False)
    uncarried = not_carried(method, cfg.effects)
    if uncarried:
        from magcal_cli.models.ekf.effects import carried

        what = f"carries only {', '.join(carried(method))}" if method.startswith("ekf") else "has no effect terms"
        msg = (f"{path.name}: --effects {','.join(uncarried)} is modelled by the joint MAP method only in magcal "
               f"{__version__} (the {method} method {what}); use --method map, or --effects none")
        raise MagcalError(msg)
    target = METHODS.get(method)
    if target is None:
        msg = (f"{path.name}: --method {method} is not available in magcal {__version__}; "
               f"use one of: auto, {', '.join(METHODS)}")
        raise MagcalError(msg)
    progress(f"{len(problem.still.segments)} still segments; fitting {method} "
             f"for {', '.join(m.id for m in problem.mags)}")
    with active(progress):              # the estimators and the diagnosis report through progress.current()
        result, failed = run_method(resolve(target.run, f"the {method} method"), problem, cfg, method, progress)
    result = replace(result, mags=tuple(replace(f, method=f.method or result.method) for f in result.mags))
    if cfg.diagnose:
        failed += skipped_diagnoses(result, failed)
    mags, series = [], {}
    ref = reference_for(cfg)
    streams = {m.id: m for m in problem.mags}
    entries = effect_entries(result, streams)
    for fit in result.mags:
        stream = streams[fit.id]
        cal, ser = mag_calibration(fit, stream, ref, entries, rec)
        mags.append(cal)
        series[stream.id] = ser
    imu = ImuCalibration(result.imu.id, result.imu.accel_bias, result.imu.gyro_bias,
                         result.imu.accel_bias_std, result.imu.gyro_bias_std)
    segs = problem.still.segments
    noise = {"accelerometer_std": problem.still.acc_noise.tolist(), "gyroscope_std": problem.still.gyr_noise.tolist(),
             "source": "quietest windows of the IMU (detect.noise_std)"}
    for m in mags:
        if segs:
            stream = streams[m.id]
            noise[f"magnetometer_std[{m.id}]"] = (pooled_std(stream, segs) * units.from_si(stream.native_unit)).tolist()
    if result.noise:                     # the levels the method estimated and used replace the detector's
        noise.update(result.noise)
        noise["source"] = f"estimated by {result.method} from its residuals (variance components)"
    t_used = np.concatenate([problem.acc.t, *[m.t for m in problem.mags]])
    digest = sha256(path) if path.exists() else ""
    stored = path.resolve() if path.exists() else path         # absolute: later commands work from any directory
    source = Source(str(stored), rec.format, digest, float(t_used.min()), float(t_used.max()),
                    dict(problem.timing))
    findings = chosen + dropped + failed + findings_for(rec, problem, result, mags) + dip_check(mags, ref)
    diagnosis = diagnosis_block(result.diagnosis, streams) if result.diagnosis else None
    refused = tuple({"id": r.id, "status": "refused", "reason": r.reason, "advice": r.advice}
                    for r in (*unusable, *result.refused))
    doc = Calibration(source, result.method, imu, tuple(mags), __version__, utc_now(), noise,
                      effects=entries, diagnosis=diagnosis, notes=tuple(f.message for f in findings), refused=refused)
    doc, worse = heading_checks(rec, doc, findings, ref, cfg.export_worse)     # never silently worse (issue 38)
    doc, findings = replace(doc, notes=(*doc.notes, *(f.message for f in worse))), findings + worse
    return RunResult(doc, rec, problem.still, tuple(findings), series)
