"""The calibration document `magcal.calibration/1` (spec/calibration-file.md): to and from plain dicts."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magcal_cli import so3
from magcal_cli.calibration.types import (
    MAG_PARAMS,
    Calibration,
    ImuCalibration,
    MagCalibration,
    Quality,
    Source,
)
from magcal_cli.errors import CalibrationFileError

#: `covariance.order` of documents written before the order became a list of [block, size, unit kind]
LEGACY_ORDER = "vec(D) column-major (9), o (3), dip_deg (1)"


def _list(a: Any) -> Any:
    """Plain Python lists/floats for JSON and YAML (None stays None)."""
    return None if a is None else np.asarray(a, dtype=np.float64).tolist()


def mag_to_dict(m: MagCalibration) -> dict[str, Any]:
    """One `magnetometers[]` entry."""
    u = m.misalignment
    w_cov = m.misalignment_cov()
    out: dict[str, Any] = {
        "id": m.id, "status": "calibrated", "method": m.method, "units": m.unit,
        "D": _list(m.D), "o": _list(m.o), "A": _list(m.A), "b": _list(m.b),
        "dip_deg": m.dip_deg,
        "field_strength": m.field_strength, "field_strength_source": m.field_strength_source,
        "misalignment": {"rotation": _list(u), "angle_deg": float(np.rad2deg(so3.angle(u))),
                         "rpy_deg": _list(np.rad2deg(so3.as_rpy(u)))},
        "soft_iron": _list(m.soft_iron),
        "std": {"D": _list(m.std_of("D")), "o": _list(m.std_of("o")), "dip_deg": float(m.std_of("dip")),
                "misalignment_deg": float(np.rad2deg(np.sqrt(max(np.trace(w_cov), 0.0))))},
        "quality": None if m.quality is None else dict(m.quality.__dict__),
        "held": [dict(h) for h in m.held],
        "reference": m.reference,
        "covariance": {"order": MAG_PARAMS.to_order(), "matrix": _list(m.cov)},
    }
    if m.heading_check is not None:         # only where measured: documents without it stay as they were
        out["heading_check"] = m.heading_check
    return out


def imu_to_dict(imu: ImuCalibration) -> dict[str, Any]:
    """The `imu` section; biases not estimated by the method are null."""
    return {"id": imu.id, "accelerometer_bias": _list(imu.accelerometer_bias),
            "gyroscope_bias": _list(imu.gyroscope_bias),
            "std": {"accelerometer_bias": _list(imu.accelerometer_bias_std),
                    "gyroscope_bias": _list(imu.gyroscope_bias_std)}}


def to_dict(cal: Calibration) -> dict[str, Any]:
    """The whole document as plain data, keys in the order of the schema."""
    doc: dict[str, Any] = {
        "schema": Calibration.SCHEMA, "magcal_version": cal.magcal_version, "created_utc": cal.created_utc,
        "source": {k: v for k, v in cal.source.__dict__.items() if v or k != "timing"},   # no timing: older
        "method": cal.method, "imu": imu_to_dict(cal.imu),
        "magnetometers": [mag_to_dict(m) for m in cal.magnetometers],
        "refused": [dict(r) for r in cal.refused],
        "effects": list(cal.effects), "diagnosis": cal.diagnosis, "noise": cal.noise, "notes": list(cal.notes),
    }
    doc.update({k: v for k, v in cal.extra.items() if k not in doc})
    return doc


_KNOWN = {"schema", "magcal_version", "created_utc", "source", "method", "imu", "magnetometers", "refused",
          "effects", "diagnosis", "noise", "notes"}


def _arr(d: dict[str, Any], key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    """A float array of the given shape from d[key], or CalibrationFileError naming the key."""
    try:
        return np.asarray(d[key], dtype=np.float64).reshape(shape)
    except (KeyError, TypeError, ValueError):
        msg = f"{where}: '{key}' is missing or not a {'x'.join(map(str, shape))} array of numbers"
        raise CalibrationFileError(msg) from None


def _covariance(m: dict[str, Any], where: str) -> np.ndarray:
    """The magnetometer covariance in MAG_PARAMS order (NaN when absent); its `order` must be MAG_PARAMS's.

    `order` is [[block, size, unit kind], ...] (`Layout.to_order`); documents written before that carry the
    string LEGACY_ORDER, which names the same layout.
    """
    size = MAG_PARAMS.size
    cov = m.get("covariance") or {}
    if not isinstance(cov, dict):
        msg = f"{where}: 'covariance' is not a mapping with 'order' and 'matrix'"
        raise CalibrationFileError(msg)
    order = cov.get("order")
    expected = MAG_PARAMS.to_order()
    if isinstance(order, list):
        try:
            known = [[str(n), int(k), str(u)] for n, k, u in order] == expected
        except (TypeError, ValueError):
            known = False
    else:
        known = order is None or order == LEGACY_ORDER
    if not known:
        msg = (f"{where}: covariance.order is {order!r}, but this magcal reads only {expected!r} (blocks D, o, "
               f"dip: name, size, unit kind). Re-create the calibration with magcal fit")
        raise CalibrationFileError(msg)
    if cov.get("matrix") is None:
        return np.full((size, size), np.nan)
    return _arr(cov, "matrix", (size, size), f"{where}: covariance")


def from_dict(doc: dict[str, Any], where: str = "calibration") -> Calibration:
    """Parse a document; only `magcal.calibration/1` is understood."""
    if not isinstance(doc, dict) or doc.get("schema") != Calibration.SCHEMA:
        got = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        msg = f"{where}: not a magcal calibration document (schema {got!r}, expected {Calibration.SCHEMA!r})"
        raise CalibrationFileError(msg)
    try:
        mags = []
        for i, m in enumerate(doc["magnetometers"]):
            w = f"{where}: magnetometers[{i}]"
            q = m.get("quality")
            mags.append(MagCalibration(
                id=str(m["id"]), unit=str(m["units"]), D=_arr(m, "D", (3, 3), w), o=_arr(m, "o", (3,), w),
                dip_deg=float(m["dip_deg"]),
                cov=_covariance(m, w),
                field_strength=float(m["field_strength"]),
                field_strength_source=str(m.get("field_strength_source", "data")),
                quality=None if q is None else Quality(**q), held=tuple(m.get("held") or ()),
                reference=str(m.get("reference", "motion")), method=str(m.get("method", doc.get("method", ""))),
                heading_check=m.get("heading_check")))
        imu_d = doc["imu"]
        std = imu_d.get("std", {})
        imu = ImuCalibration(str(imu_d["id"]), imu_d.get("accelerometer_bias"), imu_d.get("gyroscope_bias"),
                             std.get("accelerometer_bias"), std.get("gyroscope_bias"))
        extra = {k: v for k, v in doc.items() if k not in _KNOWN}
        return Calibration(Source(**doc["source"]), str(doc["method"]), imu, tuple(mags),
                           str(doc["magcal_version"]), str(doc["created_utc"]), dict(doc.get("noise") or {}),
                           tuple(doc.get("effects") or ()), doc.get("diagnosis"), tuple(doc.get("notes") or ()),
                           extra, tuple(dict(r) for r in doc.get("refused") or ()))
    except CalibrationFileError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        msg = f"{where}: malformed calibration document ({type(exc).__name__}: {exc}). Re-create it with magcal fit"
        raise CalibrationFileError(msg) from None


def dumps_json(cal: Calibration) -> str:
    """The document as indented JSON."""
    return json.dumps(to_dict(cal), indent=2) + "\n"


def dumps_yaml(cal: Calibration) -> str:
    """The document as block-style YAML with the schema's key order."""
    return str(yaml.safe_dump(to_dict(cal), sort_keys=False, default_flow_style=None, width=120))


def load(path: Path) -> Calibration:
    """Read a calibration document from .json or .yaml/.yml."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        msg = f"{path}: cannot read the calibration ({exc.strerror or exc}). Check the path"
        raise CalibrationFileError(msg) from None
    except UnicodeDecodeError:
        msg = f"{path}: not a calibration document (binary data, not JSON or YAML). Give the file magcal fit wrote"
        raise CalibrationFileError(msg) from None
    try:
        doc = yaml.safe_load(text) if path.suffix.lower() in (".yaml", ".yml") else json.loads(text)
    except (yaml.YAMLError, json.JSONDecodeError) as exc:
        msg = f"{path}: not valid {'YAML' if path.suffix.lower() in ('.yaml', '.yml') else 'JSON'} ({exc})"
        raise CalibrationFileError(msg.splitlines()[0]) from None
    return from_dict(doc, str(path))
