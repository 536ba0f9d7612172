"""What a log leaves undetermined: Fisher-information condition number, poorly observable parameters and the
manoeuvre that would fix them (findings), or an InsufficientDataError when the motion determines nothing
useful.

Works on the marginal covariance of theta = (b_a, b_g, vec D, o, dip) in SI, in `params.BASE` order.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from magcal_cli.errors import InsufficientDataError, UnexplainedError
from magcal_cli.findings import Finding, Severity
from magcal_cli.params import BASE
from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

#: names of the entries of theta
NAMES = BASE.entry_names()
#: beyond this (scaled) condition number the information matrix is numerically singular
SINGULAR_CONDITION = 1e14
#: a parameter whose variance correlation inflates more than this (std x ~30) is confounded with others
CONFOUNDED_VIF = 1e3

TILT_ADVICE = ("tilt the vehicle through large pitch and roll angles -- on each side and, if possible, "
               "upside down -- so that gravity and the field are seen along every body axis")
ROTATE_ADVICE = ("rotate the vehicle about all three axes so that the field sweeps the whole sphere of body "
                 "directions; a flat, yaw-only recording cannot separate the hard-iron offset along the "
                 "vertical axis from the soft-iron column of that axis")
GYRO_ADVICE = "record for longer, or hold the vehicle still for a few seconds at the start and at the end"
DIP_ADVICE = ("tilt the vehicle, or give --location and --date so that the dip starts from the World "
              "Magnetic Model")


class Group(NamedTuple):
    """A parameter group: its slice of theta, a label, the std above which it is poorly determined and above
    which it is not determined at all (in SI, `field`-relative for D and o), the manoeuvre that helps, and the
    unit and factor used to print its std."""

    sl: slice
    label: str
    poor: float
    fatal: float
    relative: bool
    advice: str
    unit: str
    display: float


#: block name -> (poor, fatal, relative, advice, unit, display) of its group
_JUDGED = {
    "accelerometer_bias": (0.05, 1.0, False, TILT_ADVICE, "m/s^2", 1.0),
    "gyroscope_bias": (1e-3, 0.05, False, GYRO_ADVICE, "deg/s", float(np.degrees(1.0))),
    "D": (0.02, 0.1, True, ROTATE_ADVICE, "% of the field", 100.0),
    "o": (0.02, 0.1, True, ROTATE_ADVICE, "% of the field", 100.0),
    "dip": (float(np.deg2rad(1.0)), float(np.deg2rad(20.0)), False, DIP_ADVICE, "deg", float(np.degrees(1.0))),
}
#: block name -> its group, in BASE order; labels are the blocks' observability groups
GROUP_OF = {b.name: Group(BASE.slice(b.name), b.group, *_JUDGED[b.name]) for b in BASE.blocks}
GROUPS = tuple(GROUP_OF.values())
#: the groups only a rotation about all three axes determines: what to advise when nothing is determined
_ROTATION = [GROUP_OF["D"], GROUP_OF["o"]]


def tilt_spread_deg(acc: FloatArray) -> float:
    """95th percentile of the angle (deg) between the measured vertical and its mean direction."""
    v = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    mean = v.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    if norm < 1e-6:
        return 180.0
    ang = np.degrees(np.arccos(np.clip(v @ (mean / norm), -1.0, 1.0)))
    return float(np.percentile(ang, 95))


def scaled_information(cov: FloatArray) -> FloatArray:
    """The Fisher information inv(cov) scaled to unit diagonal (invariant to the units of the parameters)."""
    sd = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sd, sd)
    info = np.linalg.inv(corr)
    d = np.sqrt(np.diag(info))
    return info / np.outer(d, d)


def _fmt(values: FloatArray, names: list[str], unit: str, factor: float = 1.0) -> str:
    """'name std unit' pairs of the worst entries."""
    order = np.argsort(values)[::-1][:3]
    return ", ".join(f"{names[i]} {values[i] * factor:.3g}" for i in order) + f" {unit}"


def _advice(groups: list[Group]) -> str:
    """The manoeuvres that help these groups, most effective first."""
    order = (TILT_ADVICE, ROTATE_ADVICE, DIP_ADVICE, GYRO_ADVICE)
    return "; ".join(a for a in order if any(g.advice == a for g in groups)) + "."


def conditional(cov: FloatArray, held: IntArray) -> tuple[FloatArray, IntArray]:
    """The covariance of the free entries given the held ones (cov_FF - cov_FH cov_HH^-1 cov_HF), and the free
    entries' indices: what the data determine once a partial calibration fixed the rest."""
    free = np.setdiff1d(np.arange(cov.shape[0]), held).astype(np.int64)
    if held.size == 0:
        return cov, free
    c_fh = cov[np.ix_(free, held)]
    return cov[np.ix_(free, free)] - c_fh @ np.linalg.solve(cov[np.ix_(held, held)], c_fh.T), free


#: a partial calibration refused with its uncertainty widened more than this, and the field strength still varying
#: more than NONUNIFORM_SPREAD (relative RMS) after it, is refused for the field, not the motion
NONUNIFORM_WIDENING = 3.0
NONUNIFORM_SPREAD = 0.03
NONUNIFORM_ADVICE = ("record away from steel, magnets and powered electronics (outdoors, or at least 1 m from "
                     "them), keep the sensor in one place while turning it, and")


def check_useful(cov: FloatArray, field: float, held: IntArray, where: str, widening: FloatArray | None = None,
                 spread: float = 0.0) -> None:
    """Refuse a partial calibration whose estimated D or o entries are known no better than the fatal limit once
    the prior's doubt and the correlated residuals are counted (the marginal, widened covariance). With a large
    `widening` (per entry) and calibrated field-strength `spread` the message names a non-uniform field, not the
    motion."""
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None)) / field
    worst = [(i, std[i]) for g in (GROUP_OF["D"], GROUP_OF["o"])
             for i in range(g.sl.start, g.sl.stop) if i not in held and std[i] > g.fatal]
    if worst:
        i, sd = max(worst, key=lambda w: w[1])
        name, wide = NAMES[i], 1.0 if widening is None else float(widening[i])
        if wide > NONUNIFORM_WIDENING and spread > NONUNIFORM_SPREAD:
            msg = (f"{where}: no calibration explains these readings: the calibrated field strength still varies "
                   f"{100 * spread:.0f} % RMS and the residuals drift together in time ({name}'s uncertainty "
                   f"widened {wide:.1f}x, to {100 * sd:.0f} % of the field), so the field around the sensor was "
                   f"not uniform or changed during the log. To fix: {NONUNIFORM_ADVICE} {ROTATE_ADVICE}")
            raise UnexplainedError(msg)
        msg = (f"{where}: the log's motion determines too little for even a partial calibration ({name} is "
               f"uncertain to {100 * sd:.0f} % of the field once the held parameters' doubt and the correlated "
               f"residuals are counted). To fix: {ROTATE_ADVICE}")
        raise InsufficientDataError(msg)


def check_observability(cov: FloatArray, field: float, acc: FloatArray, where: str, held: IntArray | None = None
                        ) -> tuple[float, list[Finding]]:
    """Condition number and findings for a covariance in BASE order (SI); raises when the log cannot determine
    theta. Entries `held` at a prior (partial calibration) are not judged; the others are judged given them."""
    cov, free = conditional(cov, np.zeros(0, np.int64) if held is None else np.asarray(held, np.int64))
    tilt = tilt_spread_deg(acc)
    flat = f" (the measured vertical stayed within {tilt:.0f} deg of its mean direction)" if tilt < 45 else ""
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0.0):
        msg = (f"{where}: the motion in this log cannot determine the calibration (the information matrix is "
               f"singular){flat}. To fix: {_advice(_ROTATION)}")
        raise InsufficientDataError(msg)
    info = scaled_information(cov)
    eig = np.linalg.eigvalsh(info)
    condition = float(eig[-1] / max(eig[0], 1e-300))
    vif = np.full(len(NAMES), 1.0)
    vif[free] = np.diag(np.linalg.inv(info)) if np.isfinite(condition) else np.inf
    std = np.zeros(len(NAMES))
    std[free] = np.sqrt(np.diag(cov))
    fatal, poor = [], []
    for g in GROUPS:
        rel = std[g.sl] / (field if g.relative else 1.0)
        if np.any(rel > g.fatal):
            fatal.append(g)
        elif np.any(rel > g.poor) or np.any(vif[g.sl] > CONFOUNDED_VIF):
            poor.append((g, rel))
    if fatal or condition > SINGULAR_CONDITION:
        what = ", ".join(g.label for g in fatal) or f"calibration (condition number {condition:.2g})"
        msg = (f"{where}: the motion in this log cannot determine the {what}{flat}. To fix: "
               f"{_advice(fatal or _ROTATION)}")
        raise InsufficientDataError(msg)
    worst = int(np.argmax(vif))                     # held entries have vif 1: never the worst
    findings = [Finding(
        Severity.INFO, "fisher_condition",
        f"{where}: the Fisher information of the {free.size} calibration parameters has condition number "
        f"{condition:.3g} (scaled to unit diagonal); the most confounded parameter is {NAMES[worst]} "
        f"(variance inflation {vif[worst]:.3g}).",
        {"condition_number": condition, "max_variance_inflation": float(vif[worst]),
         "parameter": NAMES[worst], "tilt_spread_deg": tilt})]
    for g, rel in poor:
        names = list(NAMES[g.sl])
        findings.append(Finding(
            Severity.WARNING, "poorly_observable",
            f"{where}: this log leaves the {g.label} poorly determined{flat}: std "
            f"{_fmt(rel, names, g.unit, g.display)}"
            f", variance inflated up to {vif[g.sl].max():.3g}x by correlation with other parameters. "
            f"To fix: {g.advice}.",
            {"parameters": names, "std": [float(x) for x in std[g.sl]], "threshold": g.poor,
             "relative_to_field": g.relative, "variance_inflation": [float(x) for x in vif[g.sl]],
             "tilt_spread_deg": tilt}))
    return condition, findings
