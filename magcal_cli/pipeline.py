"""calibrate(path, config) -> RunResult: read, select, detect, estimate, assemble the document. No printing."""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli import __version__, timing, units
from magcal_cli.calibration.types import Calibration, ImuCalibration, MagCalibration, Quality, Source
from magcal_cli.config import Config
from magcal_cli.detect import (
    IMPACT,
    StillResult,
    check_signal,
    detect_still,
    gyro_noise_scale,
    pooled_std,
    unmeasured_windows,
)
from magcal_cli.errors import ConvergenceError, InsufficientDataError, MagcalError, StreamError
from magcal_cli.findings import Finding, Severity
from magcal_cli.models.accel import G
from magcal_cli.models.partial import MagPrior, flown_prior
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MagFit, MethodResult
from magcal_cli.params import MAG
from magcal_cli.progress import Hook, active, current
from magcal_cli.readers import ReadOptions, open_recording
from magcal_cli.readers.checks import normalised_field
from magcal_cli.registry import resolve
from magcal_cli.streams import FloatArray, Kind, Recording, Stream
from magcal_cli.wmm import ReferenceField, reference_for

Progress = Hook
MethodRun = Callable[[Problem, Config], MethodResult]

#: method name -> "module:function(problem, config) -> MethodResult"
METHODS: dict[str, str] = {
    "kok2012": "magcal_cli.models.kok2012:run",
    "map": "magcal_cli.methods.map_run:run",
    "ekf-ml": "magcal_cli.models.ekf.ml:run",
    "ekf-aug": "magcal_cli.models.ekf.aug:run",
    "attitude": "magcal_cli.models.attitude_ref:run",
}


#: the channels effect plug-ins may use, handed to the estimators beside the IMU and magnetometers
AUX_KINDS = frozenset({Kind.BATTERY_CURRENT, Kind.BATTERY_VOLTAGE, Kind.THROTTLE, Kind.TEMPERATURE,
                       Kind.POSITION, Kind.ATTITUDE})


@dataclass(frozen=True, eq=False)
class MagSeries:
    """A magnetometer's readings and calibrated unit field over time, for reports and plots."""

    t: FloatArray
    raw: FloatArray
    calibrated: FloatArray


@dataclass(frozen=True, eq=False)
class RunResult:
    """Everything one `fit` produced: the document, what it was computed from and what was noticed."""

    calibration: Calibration
    recording: Recording
    still: StillResult
    findings: tuple[Finding, ...]
    series: dict[str, MagSeries]


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file, or of a bag directory's files in name order."""
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        with f.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def utc_now() -> str:
    """ISO-8601 UTC timestamp; SOURCE_DATE_EPOCH makes it reproducible (as reproducible builds do)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    stamp = float(epoch) if epoch and epoch.isdigit() else time.time()
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(stamp))


def _known_physics(cfg: Config, aux: tuple[Stream, ...]) -> tuple[str, ...]:
    """Effects `--effects auto` models in every fit: a flight's acceleration where its position measured it."""
    from magcal_cli.effects.nongravity import flying

    return ("nongravity_acceleration",) if cfg.diagnose and flying(aux) else ()


def select_problem(rec: Recording, cfg: Config) -> Problem:
    """Pick the IMU and magnetometers named by the config and cut them to [start, end]."""
    return _select(rec, cfg)[0]


def _select(rec: Recording, cfg: Config) -> tuple[Problem, list[Finding]]:
    """The problem, and warnings for magnetometers left out because they cannot be used (while others can)."""
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
    if not good:
        raise dropped[0][1]
    findings = [Finding(Severity.WARNING, "not_calibrated", f"{m.id} was not calibrated: {exc}", {"sensor": m.id})
                for m, exc in dropped]
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
                   _known_physics(cfg, aux), record, scale), findings


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


def coverage_pct(m_b: FloatArray, cells: int = 100) -> float:
    """Share of `cells` near-equal-area sphere cells (Fibonacci lattice) that the unit field directions visit."""
    k = np.arange(cells) + 0.5
    z = 1.0 - 2.0 * k / cells
    phi = np.pi * (1.0 + np.sqrt(5.0)) * k
    centres = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    u = m_b / np.linalg.norm(m_b, axis=1, keepdims=True)
    hit = np.unique(np.argmax(u[:: max(1, len(u) // 20000)] @ centres.T, axis=1))
    return 100.0 * hit.size / cells


def _with_position(rec: Recording, cfg: Config) -> Config:
    """The config with `location` from the log's position stream and `date` from its clock, when not given."""
    pos = [st.values[np.isfinite(st.values).all(axis=1)] for st in rec.streams if st.kind is Kind.POSITION]
    if cfg.location is None and pos and len(pos[0]):
        lat, lon, alt = np.median(pos[0], axis=0)
        cfg = replace(cfg, location=(float(lat), float(lon), float(alt)))
    utc = rec.utc0 if rec.utc0 is not None else rec.t0 if rec.t0 > 1e9 else None   # t0 may be a Unix time
    if cfg.location is not None and cfg.date is None and utc is not None:
        cfg = replace(cfg, date=time.strftime("%Y-%m-%d", time.gmtime(utc)))
    return cfg


def _mag_calibration(fit: MagFit, stream: Stream, ref: ReferenceField | None = None,
                     effects: tuple[dict[str, object], ...] = (), rec: Recording | None = None
                     ) -> tuple[MagCalibration, MagSeries]:
    """Convert an SI fit to the stream's native unit and measure its quality on every reading, with the
    accepted magnetometer effects removed (the calibration is the base model plus them)."""
    from magcal_cli.effects.correct import remove

    f = units.from_si(stream.native_unit)
    scale = MAG.factors({"field": f, "angle": float(np.rad2deg(1.0))})
    d, o = fit.D * f, fit.o * f
    raw = stream.xyz * f
    t, y = stream.t, raw
    if effects and rec is not None:
        t, y, _ = remove(effects, stream.id, rec, stream.t, raw)
    m_b = (y - o) @ np.linalg.inv(d).T
    used = np.all(np.isfinite(m_b), axis=1)                # excluded (transient) readings are NaN
    norm_err = np.linalg.norm(m_b[used], axis=1) - 1.0
    quality = Quality(len(stream), fit.residual_rms * f, float(100.0 * np.sqrt(np.mean(norm_err**2))),
                      coverage_pct(m_b[used]), bool(fit.converged), int(fit.iterations))
    strength, source = (float(np.cbrt(np.linalg.det(d))), "data") if ref is None else (ref.intensity * f, "wmm")
    cal = MagCalibration(stream.id, units.canonical(stream.native_unit), d, o, float(np.rad2deg(fit.dip)),
                         fit.cov * np.outer(scale, scale), strength, source, quality, held_document(fit, f),
                         fit.reference)
    return cal, MagSeries(t, raw, m_b)


def held_document(fit: MagFit, f: float) -> tuple[dict[str, Any], ...]:
    """The document's `held` entries of a fit: parameter names as the document writes them (D[i][j], o[i],
    dip_deg, imu.accelerometer_bias[i], imu.gyroscope_bias[i]), priors in the magnetometer unit (factor f from
    SI) or degrees, and where the prior came from."""
    out = []
    for h in fit.held:
        block, _, label = h.name.partition(".")
        axis = "xyz".index(label) if label in ("x", "y", "z") else None
        name, k = {"D": (f"D[{label[:1]}][{label[1:]}]", f), "o": (f"o[{axis}]", f),
                   "dip": ("dip_deg", float(np.rad2deg(1.0)))}.get(block, (f"imu.{block}[{axis}]", 1.0))
        out.append({"parameter": name, "held": True, "prior": h.prior * k, "prior_std": h.prior_std * k,
                    "source": h.source})
    return tuple(out)


#: a fitted dip further than this from the World Magnetic Model's says the model missed something
DIP_TOLERANCE_DEG = 5.0


def _dip_check(mags: list[MagCalibration], ref: ReferenceField | None) -> list[Finding]:
    """Warn when a fitted dip disagrees with the WMM: acceleration, a local disturbance or a frame error."""
    if ref is None:
        return []
    out = []
    for m in mags:
        diff = m.dip_deg - float(np.rad2deg(ref.dip))
        if abs(diff) > max(DIP_TOLERANCE_DEG, 3.0 * float(m.std_of("dip"))):
            out.append(Finding(
                Severity.WARNING, "dip_disagrees_with_wmm",
                f"{m.id}: the fitted dip {m.dip_deg:.1f} deg differs from the World Magnetic Model's "
                f"{np.rad2deg(ref.dip):.1f} deg at the log's position by {diff:+.1f} deg: the accelerometer saw "
                "non-gravity acceleration (flight manoeuvres, vibration) or the local field is disturbed; the "
                "attitude the calibration implies is tilted by about that much. Calibrate from a recording "
                "with the vehicle moved by hand, or check the field near the vehicle",
                {"dip_deg": m.dip_deg, "wmm_dip_deg": float(np.rad2deg(ref.dip))}))
    return out


def _findings(rec: Recording, problem: Problem, result: MethodResult, mags: list[MagCalibration]) -> list[Finding]:
    """What the report should tell the user beyond the numbers."""
    out = [Finding(Severity.INFO, "reader_note", note) for note in rec.notes]
    out += [Finding(Severity.INFO, "method_note", note) for note in result.notes]
    out += list(result.findings)
    if result.method == "kok2012":
        out.append(Finding(Severity.INFO, "accel_bias_not_modelled",
                           "Kok 2012 takes the accelerometer as an unbiased vertical; an accelerometer bias b "
                           "tilts every vertical by up to |b|/g rad and shows up in the misalignment and dip."))
    for stream in problem.mags:
        if normalised_field(stream.xyz):
            out.append(Finding(Severity.WARNING, "normalised_field",
                               f"{stream.id}: the log holds the field normalised to a unit vector, not the raw "
                               "readings; the calibration ran, but hard iron is not recoverable in absolute terms "
                               "and the field strength is arbitrary. Log the raw magnetometer.",
                               {"magnitude_si": float(np.median(np.linalg.norm(stream.xyz, axis=1)))}))
    for m in mags:
        q = m.quality
        if q is not None and q.coverage_pct < 30.0:
            out.append(Finding(Severity.WARNING, "low_coverage",
                               f"{m.id}: the field directions cover only {q.coverage_pct:.0f} % of the sphere; "
                               "rotate the vehicle about all three axes (roll it over, pitch it up and down).",
                               {"coverage_pct": q.coverage_pct}))
        if q is not None and not q.converged:
            out.append(Finding(Severity.WARNING, "not_converged",
                               f"{m.id}: the solver stopped before its convergence test passed.",
                               {"iterations": q.iterations}))
    return out


def _method_for(problem: Problem, cfg: Config) -> tuple[str, list[Finding]]:
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


def diagnosis_block(blocks: tuple[dict[str, Any], ...], mags: dict[str, Stream]) -> dict[str, Any]:
    """The document's `diagnosis`: the magnetometer with the strongest mismatch at the top level (the contract's
    single block), every magnetometer's block under `sensors`; SI field values in each one's unit."""
    from magcal_cli.calibration.diagnosis import in_units

    per = [in_units(b, mags[b["sensor"]].native_unit) for b in blocks]
    top = min(per, key=lambda b: float(b["ppc"]["global_p"]))
    return {**top, "summary": " ".join(b["summary"] for b in per), "sensors": per}


def _effect_entries(result: MethodResult, mags: dict[str, Stream]) -> tuple[dict[str, object], ...]:
    """The document's `effects[]`: magnetometer effects in that magnetometer's unit."""
    from magcal_cli.calibration.effects import entry

    return tuple(entry(f, mags[f.sensor].native_unit if f.sensor in mags else None) for f in result.effects)


def _call(run: MethodRun, problem: Problem, cfg: Config, method: str) -> MethodResult:
    """One method run; numerical breakdowns become a ConvergenceError that names the method."""
    try:
        return run(problem, cfg)
    except np.linalg.LinAlgError as exc:                 # singular or non-finite systems: degenerate data
        msg = (f"{problem.where}: the {method} solver failed numerically ({exc}); the data are degenerate for it "
               "(damaged or repeated samples?). Check the log with magcal inspect, or try another --method")
        raise ConvergenceError(msg) from None


def _run_method(run: MethodRun, problem: Problem, cfg: Config, method: str) -> tuple[MethodResult, list[Finding]]:
    """Run the method on every magnetometer; when several are fitted and some cannot be, keep the others.

    A magnetometer that cannot be calibrated (too little motion for it, disturbed, no convergence) must not
    cost the user the others: they are refitted one by one and the failures become warnings. Only when no
    magnetometer can be calibrated is it an error.
    """
    try:
        return _call(run, problem, cfg, method), []
    except (InsufficientDataError, ConvergenceError):
        if len(problem.mags) == 1:
            raise
    parts: list[MethodResult] = []
    failed: list[Finding] = []
    first: MagcalError | None = None
    for m in problem.mags:
        try:
            parts.append(_call(run, replace(problem, mags=(m,)), cfg, method))
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


def _attitude_instead(problem: Problem, cfg: Config, exc: InsufficientDataError
                      ) -> tuple[MethodResult, list[Finding]]:
    """--method auto on a log whose own motion cannot determine the calibration: the vehicle's attitude estimate
    and the World Magnetic Model as the reference, where the log has both (issue 12 item 2); else `exc`."""
    from magcal_cli.models import attitude_ref

    if cfg.method != "auto" or reference_for(cfg) is None:
        raise exc
    try:
        att = attitude_ref.attitude_stream(problem)
        result = attitude_ref.run(problem, cfg)
    except InsufficientDataError:
        raise exc from None
    why = Finding(Severity.WARNING, "attitude_reference",
                  f"the log's own motion cannot determine the calibration ({exc}); it was calibrated against the "
                  f"vehicle's attitude estimate ({att.id}) and the World Magnetic Model instead, so it inherits "
                  "the errors of that estimate (its heading came from the compass calibration it flew with)")
    return result, [why]


def calibrate(path: Path, cfg: Config, fmt: str | None = None, progress: Progress | None = None) -> RunResult:
    """Calibrate every selected magnetometer of one log against its IMU (progress: default the current hook)."""
    path = Path(path)
    progress = progress or current()
    progress(f"reading {path.name}")
    with active(progress):                  # the chunked readers report their fraction through current()
        rec = open_recording(path, fmt, ReadOptions(allow_truncated=cfg.allow_truncated))
    return calibrate_recording(rec, cfg, progress)


def _not_carried(method: str, effects: tuple[str, ...]) -> tuple[str, ...]:
    """The requested effects `method` cannot model: the joint MAP models every effect, the EKFs the additive
    magnetometer terms (models/ekf_effects.py), the other methods none."""
    if method == "map" or not effects:
        return ()
    if method not in ("ekf-ml", "ekf-aug"):
        return effects
    from magcal_cli.models.ekf.effects import not_carried

    return not_carried(effects, method)


def calibrate_recording(rec: Recording, cfg: Config, progress: Progress | None = None) -> RunResult:
    """Calibrate every selected magnetometer of a recording already read (or built in code) against its IMU."""
    path = rec.path
    progress = progress or current()
    problem, dropped = _select(rec, cfg)
    method, chosen = _method_for(problem, cfg)
    cfg = _with_position(rec, cfg)
    if cfg.diagnose and method != "map":
        chosen.append(Finding(Severity.INFO, "diagnosis_skipped",
                              f"the mismatch diagnosis (--effects auto) runs with the joint MAP method only; "
                              f"the {method} method fitted the base model"))
        cfg = replace(cfg, diagnose=False)
    refused = _not_carried(method, cfg.effects)
    if refused:
        from magcal_cli.models.ekf.effects import carried

        what = f"carries only {', '.join(carried(method))}" if method.startswith("ekf") else "has no effect terms"
        msg = (f"{path.name}: --effects {','.join(refused)} is modelled by the joint MAP method only in magcal "
               f"{__version__} (the {method} method {what}); use --method map, or --effects none")
        raise MagcalError(msg)
    target = METHODS.get(method)
    if target is None:
        msg = (f"{path.name}: --method {method} is not available in magcal {__version__}; "
               f"use one of: auto, {', '.join(METHODS)}")
        raise MagcalError(msg)
    progress(f"{len(problem.still.segments)} still segments; fitting {method} "
             f"for {', '.join(m.id for m in problem.mags)}")
    try:
        with active(progress):          # the estimators and the diagnosis report through progress.current()
            result, failed = _run_method(resolve(target, f"the {method} method"), problem, cfg, method)
    except InsufficientDataError as exc:
        result, failed = _attitude_instead(problem, cfg, exc)
    mags, series = [], {}
    ref = reference_for(cfg)
    streams = {m.id: m for m in problem.mags}
    effect_entries = _effect_entries(result, streams)
    for fit in result.mags:
        stream = streams[fit.id]
        cal, ser = _mag_calibration(fit, stream, ref, effect_entries, rec)
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
    findings = chosen + dropped + failed + _findings(rec, problem, result, mags) + _dip_check(mags, ref)
    diagnosis = diagnosis_block(result.diagnosis, streams) if result.diagnosis else None
    doc = Calibration(source, result.method, imu, tuple(mags), __version__, utc_now(), noise,
                      effects=effect_entries, diagnosis=diagnosis, notes=tuple(f.message for f in findings))
    return RunResult(doc, rec, problem.still, tuple(findings), series)
