"""The calibration document assembled from a method's SI result: native units, quality, held entries, findings."""

from __future__ import annotations

from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.run import MagSeries
from magcal_cli.calibration.types import MagCalibration, Quality
from magcal_cli.findings import Finding, Severity
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import MagFit, MethodResult
from magcal_cli.params import MAG
from magcal_cli.readers.checks import normalised_field
from magcal_cli.streams import FloatArray, Recording, Stream
from magcal_cli.wmm import ReferenceField


def coverage_pct(m_b: FloatArray, cells: int = 100) -> float:
    """Share of `cells` near-equal-area sphere cells (Fibonacci lattice) that the unit field directions visit."""
    k = np.arange(cells) + 0.5
    z = 1.0 - 2.0 * k / cells
    phi = np.pi * (1.0 + np.sqrt(5.0)) * k
    centres = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    u = m_b / np.linalg.norm(m_b, axis=1, keepdims=True)
    hit = np.unique(np.argmax(u[:: max(1, len(u) // 20000)] @ centres.T, axis=1))
    return 100.0 * hit.size / cells


def mag_calibration(fit: MagFit, stream: Stream, ref: ReferenceField | None = None,
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
                         fit.reference, fit.method)
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


def dip_check(mags: list[MagCalibration], ref: ReferenceField | None) -> list[Finding]:
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


def findings_for(rec: Recording, problem: Problem, result: MethodResult, mags: list[MagCalibration]) -> list[Finding]:
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


def diagnosis_block(blocks: tuple[dict[str, Any], ...], mags: dict[str, Stream]) -> dict[str, Any]:
    """The document's `diagnosis`: the magnetometer with the strongest mismatch at the top level (the contract's
    single block), every magnetometer's block under `sensors`; SI field values in each one's unit."""
    from magcal_cli.calibration.diagnosis import in_units
    from magcal_cli.diagnose.summary import fold

    per = [in_units(b, mags[b["sensor"]].native_unit) for b in blocks]
    top = min(per, key=lambda b: float(b["ppc"]["global_p"]))
    # the whole log's summary says each explanation once, for all the magnetometers
    return {**top, "summary": " ".join(fold([b["summary"] for b in per])), "sensors": per}


def effect_entries(result: MethodResult, mags: dict[str, Stream]) -> tuple[dict[str, object], ...]:
    """The document's `effects[]`: magnetometer effects in that magnetometer's unit."""
    from magcal_cli.calibration.effects import entry

    return tuple(entry(f, mags[f.sensor].native_unit if f.sensor in mags else None) for f in result.effects)
