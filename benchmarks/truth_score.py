"""Score a calibration document against a truth document (calibration-file.md shape): z = error / reported std.

Used by `tests/test_independent.py` and the benchmarks that fit simulated logs. Magnetometers are matched by id or
by the truth's `aliases`; the IMU by id (or the truth's `imus` list); D and o in the log's unit, dip in degrees.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np


class Z(NamedTuple):
    """One estimate against its truth: where, what, error / std."""

    sensor: str
    name: str
    z: float


def _by_alias(truth: dict[str, Any]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for m in truth.get("magnetometers", []):
        for name in (m["id"], *m.get("aliases", [])):
            out[name] = m
    return out


def truth_offset(doc: dict[str, Any], truth: dict[str, Any], mag_id: str, o: Any) -> Any:
    """The truth's offset o at the fit's reference temperature: a temperature drift's offset is at its T0, which
    the fit takes from the log (its mean temperature) and the simulator from its own (25 degC)."""
    fit = next((e for e in doc.get("effects", []) if e["id"] == "temperature_drift" and e.get("sensor") == mag_id
                and "T0" in (e.get("params") or {}) and "k" in (e.get("params") or {})), None)
    true = next((e for e in truth.get("effects", []) if e["id"] == "temperature_drift"
                 and e.get("sensor") in (mag_id, None)), None)
    if fit is None or true is None:
        return o
    k = np.asarray(true["params"]["k"], dtype=float)
    return np.asarray(o, dtype=float) + k * (float(fit["params"]["T0"]) - float(true["params"]["T0"]))


def z_scores(doc: dict[str, Any], truth: dict[str, Any]) -> list[Z]:
    """Every estimate of D, o, dip and the IMU biases as an error over its reported std (held entries skipped)."""
    out: list[Z] = []
    mags = _by_alias(truth)
    for m in doc.get("magnetometers", []):
        t = mags.get(m["id"])
        if t is None:
            continue
        held = {h["parameter"] for h in m.get("held", [])}
        for key in ("D", "o"):
            true = truth_offset(doc, truth, m["id"], t["o"]) if key == "o" else t["D"]
            err = (np.asarray(m[key], dtype=float) - np.asarray(true, dtype=float)).ravel()
            std = np.asarray(m["std"][key], dtype=float).ravel()
            names = [f"{key}.{i}{j}" for i in range(3) for j in range(3)] if key == "D" else \
                [f"o.{a}" for a in "xyz"]
            out += [Z(m["id"], n, float(e / s)) for n, e, s in zip(names, err, std, strict=True)
                    if n not in held and s > 0]
        if "dip" not in held and m["std"].get("dip_deg"):
            out.append(Z(m["id"], "dip", (m["dip_deg"] - t["dip_deg"]) / m["std"]["dip_deg"]))
    imus = {i["id"]: i for i in truth.get("imus", [])}
    imu = doc.get("imu") or {}
    ti = imus.get(imu.get("id"), truth.get("imu"))
    for key in ("accelerometer_bias", "gyroscope_bias"):
        if imu.get(key) is None or ti is None or imu.get("std", {}).get(key) is None:
            continue
        err = np.asarray(imu[key], dtype=float) - np.asarray(ti[key], dtype=float)
        std = np.asarray(imu["std"][key], dtype=float)
        out += [Z(imu["id"], f"{key}.{a}", float(e / s)) for a, e, s in zip("xyz", err, std, strict=True) if s > 0]
    return out


def covers(entry: dict[str, Any], truth_entry: dict[str, Any]) -> dict[str, bool]:
    """Whether each scalar of the truth's effect parameters lies inside the entry's ci95 (component by component)."""
    out: dict[str, bool] = {}
    for name, value in truth_entry.get("params", {}).items():
        ci = entry.get("ci95", {}).get(name)
        if ci is None or isinstance(value, str):
            continue
        lo_hi = np.asarray(ci, dtype=float).reshape(-1, 2)
        v = np.atleast_1d(np.asarray(value, dtype=float))
        for i, (x, (lo, hi)) in enumerate(zip(v, lo_hi, strict=True)):
            out[f"{name}[{i}]" if v.size > 1 else name] = bool(lo <= x <= hi)
    return out


def heading_errors(doc: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Per magnetometer: the largest heading error (deg) over a level 360 deg turn at the true dip, the fitted
    calibration applied to the readings the true one produces (the accuracy that matters to a vehicle)."""
    mags = _by_alias(truth)
    frame = str((truth.get("imu") or {}).get("frame", "FRD")).upper()
    down = -1.0 if frame == "FLU" else 1.0                   # the body's z axis points up in ROS (FLU)
    psi = np.deg2rad(np.arange(0.0, 360.0, 1.0))
    out: dict[str, float] = {}
    for m in doc.get("magnetometers", []):
        t = mags.get(m["id"])
        if t is None:
            continue
        dip = np.deg2rad(float(t["dip_deg"]))
        # level body, heading psi: x forward; y right (FRD) or left (FLU); z along gravity (FRD) or against (FLU)
        m_b = np.stack([np.cos(dip) * np.cos(psi), -down * np.cos(dip) * np.sin(psi),
                        np.full_like(psi, down * np.sin(dip))], axis=1)
        y = m_b @ np.asarray(t["D"], dtype=float).T + np.asarray(truth_offset(doc, truth, m["id"], t["o"]), dtype=float)
        fitted = (y - np.asarray(m["o"], dtype=float)) @ np.linalg.inv(np.asarray(m["D"], dtype=float)).T
        heading = np.arctan2(-down * fitted[:, 1], fitted[:, 0])
        out[m["id"]] = float(np.degrees(np.max(np.abs(np.angle(np.exp(1j * (heading - psi)))))))
    return out
