"""One history entry per calibrated magnetometer of a fit: plain JSON-able data, made where the fit ran (a batch
worker, a Dask task) and written to the store once, by the process that owns it (the client).

Every tracked parameter is a scalar with its reported std, in the document's units:
- `hard_iron.x|y|z`: o (the magnetometer unit);
- `soft_iron.xx|yy|zz|xy|xz|yz`: the symmetric factor P of D = U P over the field strength (unitless); its std
  is cov(vec D) propagated through the polar decomposition by a finite-difference Jacobian;
- `orientation.x|y|z`: U's rotation vector (deg), std from `MagCalibration.misalignment_cov`;
- `<effect>.<param>.x|y|z`: each effect estimated for this magnetometer (e.g. `current_interference.c.x`);
- `dip_deg`: the field's dip, shown but not watched (it changes with the place).
"""

from __future__ import annotations

import datetime as dt
from typing import Any

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.run import RunResult, utc_now
from magcal_cli.calibration.types import MagCalibration
from magcal_cli.history.identity import sensor_of, vehicle_of
from magcal_cli.streams import FloatArray

XYZ = ("x", "y", "z")
SYM = (("xx", 0, 0), ("yy", 1, 1), ("zz", 2, 2), ("xy", 0, 1), ("xz", 0, 2), ("yz", 1, 2))
#: relative step of the finite-difference Jacobian of the soft iron in D
FD_STEP = 1e-6
#: Unix times before this are boot clocks, not dates
EPOCH_2000 = 946_684_800.0


def _soft_iron(mag: MagCalibration) -> tuple[FloatArray, FloatArray]:
    """The 6 unique soft-iron elements and their std (first order in vec(D), the field strength held)."""
    def unique(d: FloatArray) -> FloatArray:
        p = so3.polar(d)[1] / mag.field_strength
        return np.array([p[i, j] for _, i, j in SYM])

    base = unique(mag.D)
    h = FD_STEP * float(np.abs(mag.D).max())
    jac = np.zeros((6, 9))
    for col in range(9):
        dd = np.zeros(9)
        dd[col] = h
        jac[:, col] = (unique(mag.D + dd.reshape(3, 3, order="F")) - base) / h   # vec(D) is column-major
    cov = jac @ mag.cov_of("D") @ jac.T
    return base, np.sqrt(np.clip(np.diag(cov), 0.0, None))


def _number(x: Any) -> float | None:
    """A finite float, or None (JSON has no NaN)."""
    v = float(x)
    return v if np.isfinite(v) else None


def parameters(mag: MagCalibration, effects: tuple[dict[str, Any], ...]) -> dict[str, list[float | None]]:
    """name -> [value, std] of every tracked parameter of one magnetometer."""
    out: dict[str, list[float | None]] = {}
    o_std = mag.std_of("o")
    for k, axis in enumerate(XYZ):
        out[f"hard_iron.{axis}"] = [_number(mag.o[k]), _number(o_std[k])]
    soft, soft_std = _soft_iron(mag)
    for k, (name, _, _) in enumerate(SYM):
        out[f"soft_iron.{name}"] = [_number(soft[k]), _number(soft_std[k])]
    rot = np.rad2deg(so3.log(mag.misalignment))
    rot_std = np.rad2deg(np.sqrt(np.clip(np.diag(mag.misalignment_cov()), 0.0, None)))
    for k, axis in enumerate(XYZ):
        out[f"orientation.{axis}"] = [_number(rot[k]), _number(rot_std[k])]
    out["dip_deg"] = [_number(mag.dip_deg), _number(mag.std_of("dip"))]
    for e in effects:
        if e.get("sensor") != mag.id or not e.get("params") or e.get("status") not in ("accepted", "ambiguous"):
            continue
        for pname, value in e["params"].items():
            std = e.get("std", {}).get(pname)
            values, stds = np.atleast_1d(np.asarray(value, float)), np.atleast_1d(np.asarray(std, float))
            if std is None or values.shape != stds.shape or values.ndim != 1:
                continue
            names = XYZ if values.size == 3 else tuple(str(i) for i in range(values.size))
            for k, axis in enumerate(names):
                out[f"{e['id']}.{pname}.{axis}"] = [_number(values[k]), _number(stds[k])]
    return out


def log_utc(result: RunResult) -> float | None:
    """The log's start as a Unix time, where the log states a date."""
    rec = result.recording
    if rec.utc0 is not None:
        return float(rec.utc0)
    return float(rec.t0) if rec.t0 > EPOCH_2000 else None


def entries(result: RunResult, vehicle: str | None = None) -> list[dict[str, Any]]:
    """One entry per calibrated magnetometer of `result`; `vehicle` overrides the log's own identity."""
    from magcal_cli.firmware.metrics import heading_std_deg

    cal, rec = result.calibration, result.recording
    who = vehicle_of(rec, vehicle, tuple(m.id for m in cal.magnetometers))
    when = log_utc(result)
    out = []
    for mag in cal.magnetometers:
        q = mag.quality
        quality = {} if q is None else {k: _number(v) if isinstance(v, float) else v for k, v in q.__dict__.items()}
        quality["heading_std_deg"] = heading_std_deg(mag)
        out.append({
            "sha256": cal.source.sha256, "mag_id": mag.id, "vehicle": who.vehicle, "vehicle_source": who.source,
            "sensor": sensor_of(rec, mag.id), "log_utc": when, "path": cal.source.path, "format": cal.source.format,
            "method": cal.method, "unit": mag.unit, "magcal_version": cal.magcal_version, "recorded_utc": utc_now(),
            "params": parameters(mag, cal.effects), "quality": quality,
            "covariance": {"std_D": [_number(v) for v in mag.std_of("D").ravel(order="F")],
                           "std_o": [_number(v) for v in mag.std_of("o")],
                           "max_abs_correlation": _max_correlation(mag.cov)},
            "effects": [{k: e[k] for k in ("id", "status", "params", "std", "units") if k in e}
                        for e in cal.effects if e.get("sensor") == mag.id],
        })
    return out


def _max_correlation(cov: FloatArray) -> float | None:
    """The largest |correlation| between two parameters: how far the covariance is from diagonal."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    ok = sd > 0
    if ok.sum() < 2:
        return None
    corr = cov[np.ix_(ok, ok)] / np.outer(sd[ok], sd[ok])
    np.fill_diagonal(corr, 0.0)
    return _number(np.abs(corr).max())


def utc_text(when: float | None) -> str:
    """A Unix time as ISO-8601 UTC (minutes), '-' when unknown."""
    if when is None:
        return "-"
    return dt.datetime.fromtimestamp(when, dt.timezone.utc).strftime("%Y-%m-%d %H:%M")
