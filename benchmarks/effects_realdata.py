"""Effect plug-ins of the joint MAP method on real logs (../shared/realdata/, see its README.md).

1. BROAD fast/slow rotation with `time_offset`: tau and its 95 % CI; heading and field error against the optical
   motion capture before (base model) and after (the time-offset fit, readings re-stamped t - tau); an independent
   delay scan of the base calibration against the mocap, and the mocap-vs-gyro lag (is the mocap on the IMU's
   clock?).
2. ArduPilot log171.bin and the three 2015-10-11_*.log with `current_interference`: c per compass with CI and
   status, what the firmware logged (COMPASS_MOTCT, COMPASS_MOT*, MAG.MOfs*), the firmware-equivalent COMPASS_MOT,
   and the field-norm spread before/after (the document's quality, which leaves the term out, and recomputed
   with c I removed); a cross-check outside magcal (linear least squares against the firmware attitude ATT and
   the WMM field).
3. log171 with `nongravity_acceleration`: dip per compass before/after against the WMM dip, and kappa.

Every fit is timed; failures are recorded (command, error, traceback) rather than stopping the run.

    python benchmarks/effects_realdata.py [--realdata ../shared/realdata] [--out docs/results/effects_realdata]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.run import RunResult
from magcal_cli.config import Config
from magcal_cli.errors import MagcalError
from magcal_cli.firmware.common import Options
from magcal_cli.firmware.export import export
from magcal_cli.pipeline import calibrate
from magcal_cli.readers import open_recording
from magcal_cli.streams import Kind, Recording, Stream
from magcal_cli.wmm import reference_field

ROOT = Path(__file__).resolve().parents[1]
BROAD = ("06_undisturbed_fast_rotation_A.mat", "01_undisturbed_slow_rotation_A.mat")
ARDU_CURRENT = ("log171.bin", "2015-10-11_19-53-46.log", "2015-10-11_19-59-09.log", "2015-10-11_20-17-22.log")
GPS_EPOCH = dt.date(1980, 1, 6)


# ----------------------------------------------------------------------------------------------------- fitting
def fit(path: Path, effects: tuple[str, ...], log: list[dict[str, Any]]) -> RunResult | None:
    """One timed MAP fit; a failure is recorded with the equivalent CLI command and returns None."""
    try:
        shown = os.path.relpath(path)
    except ValueError:
        shown = str(path)
    cmd = f"magcal fit {shown} --method map --effects {','.join(effects) or 'none'} --json"
    t0 = time.perf_counter()
    entry: dict[str, Any] = {"log": path.name, "effects": list(effects) or ["none"], "command": cmd}
    try:
        res = calibrate(path, Config(method="map", effects=effects))
    except MagcalError as exc:
        entry.update(ok=False, seconds=time.perf_counter() - t0, kind="clean error (MagcalError, CLI exit 1)",
                     error=f"{type(exc).__name__}: {exc}")
        log.append(entry)
        print(f"  FAILED {cmd}: {exc}", flush=True)
        return None
    except Exception as exc:  # noqa: BLE001 -- a crash is a finding, not the end of the benchmark
        entry.update(ok=False, seconds=time.perf_counter() - t0, kind="crash (traceback)",
                     error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
        log.append(entry)
        print(f"  CRASHED {cmd}: {exc}", flush=True)
        return None
    entry.update(ok=True, seconds=time.perf_counter() - t0)
    log.append(entry)
    print(f"  {entry['seconds']:5.1f} s  {path.name} --effects {','.join(effects) or 'none'}", flush=True)
    return res


def effect_entry(res: RunResult, effect: str, sensor: str | None = None) -> dict[str, Any] | None:
    """The document's effects[] entry of `effect` (for `sensor`, when given)."""
    for e in res.calibration.effects:
        if e["id"] == effect and (sensor is None or e["sensor"] == sensor):
            return dict(e)
    return None


# ------------------------------------------------------------------------------------------ part 1: BROAD time
class Mocap:
    """The mocap attitude (IMU -> NED) on its uniform grid k / rate, with gaps where tracking was lost."""

    def __init__(self, att: Stream, rate: float, n: int) -> None:
        self.rate = rate
        self.rot = np.tile(np.eye(3), (n, 1, 1))
        self.valid = np.zeros(n, dtype=bool)
        k = np.rint(att.t * rate).astype(int)
        keep = (k >= 0) & (k < n)
        self.rot[k[keep]] = so3.from_quat(att.values[keep])
        self.valid[k[keep]] = True
        step = np.einsum("nji,njk->nik", self.rot[:-1], self.rot[1:])       # R_k^T R_k+1
        self.step = so3.log(step)                                          # (n-1, 3) rad, body frame
        self.step_ok = self.valid[:-1] & self.valid[1:]

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations at times t (geodesic interpolation between grid samples) and where both neighbours exist."""
        x = t * self.rate
        k = np.floor(x).astype(int)
        ok = (k >= 0) & (k < self.rot.shape[0] - 1)
        k = np.clip(k, 0, self.rot.shape[0] - 2)
        ok &= self.step_ok[k]
        frac = (x - k)[:, None]
        return self.rot[k] @ so3.exp(self.step[k] * frac), ok


def heading_stats(m_b: np.ndarray, rot: np.ndarray, ok: np.ndarray) -> dict[str, float]:
    """Heading RMS (deg) about its circular mean, and the field residual against the mean nav-frame field."""
    m_n = np.einsum("nij,nj->ni", rot[ok], m_b[ok])
    h = np.arctan2(m_n[:, 1], m_n[:, 0])
    mean = np.angle(np.mean(np.exp(1j * h)))
    err = np.angle(np.exp(1j * (h - mean)))
    ref = m_n.mean(axis=0)                                   # the constant field the mocap frame should see
    res = m_n - ref
    cosang = np.clip(m_n @ ref / (np.linalg.norm(m_n, axis=1) * np.linalg.norm(ref)), -1.0, 1.0)
    return {"heading_rms_deg": float(np.degrees(np.sqrt(np.mean(err**2)))),
            "heading_p95_deg": float(np.degrees(np.percentile(np.abs(err), 95))),
            "field_residual_rms": float(np.sqrt(np.mean(np.sum(res**2, axis=1)))),
            "direction_rms_deg": float(np.degrees(np.sqrt(np.mean(np.arccos(cosang) ** 2)))),
            "samples": int(ok.sum())}


def parabola_min(x: np.ndarray, y: np.ndarray) -> float:
    """The grid minimum refined by a parabola through it and its neighbours."""
    i = int(np.argmin(y))
    if 0 < i < len(x) - 1:
        a, b, _ = np.polyfit(x[i - 1:i + 2], y[i - 1:i + 2], 2)
        if a > 0:
            return float(-b / (2 * a))
    return float(x[i])


def mocap_lag_ms(mocap: Mocap, gyr: Stream) -> float:
    """L (ms) such that the mocap's body rate stamped t matches the gyro stamped t - L (L > 0: mocap lags)."""
    dt_s = 1.0 / mocap.rate
    idx = np.flatnonzero(mocap.step_ok)
    w_mocap = mocap.step[idx] / dt_s
    t_mid = (idx + 0.5) * dt_s
    lags = np.arange(-30.0, 30.01, 0.5)
    cost = []
    for lag in lags:
        g = np.stack([np.interp(t_mid - lag * 1e-3, gyr.t, gyr.values[:, i]) for i in range(3)], axis=1)
        d = w_mocap - g
        d -= np.median(d, axis=0)                            # gyro bias
        cost.append(float(np.mean(np.sum(d**2, axis=1))))
    return parabola_min(lags, np.asarray(cost))


def broad_trial(path: Path, log: list[dict[str, Any]]) -> dict[str, Any]:
    """Base and time-offset fits of one BROAD trial scored against the mocap."""
    out: dict[str, Any] = {"trial": path.name}
    base = fit(path, (), log)
    with_tau = fit(path, ("time_offset",), log)
    out["seconds_none"] = log[-2]["seconds"]
    out["seconds_time_offset"] = log[-1]["seconds"]
    if base is None or with_tau is None:
        out["error"] = "fit failed (see Problems found)"
        return out
    rec = base.recording
    mag_b = base.calibration.magnetometers[0]
    mag_t = with_tau.calibration.magnetometers[0]
    ser_b, ser_t = base.series[mag_b.id], with_tau.series[mag_t.id]
    gyr = rec.select(Kind.GYROSCOPE)
    rate = 1.0 / float(np.median(np.diff(gyr.t)))
    mocap = Mocap(rec.select(Kind.ATTITUDE, "opt_quat"), rate, len(gyr))
    eff = effect_entry(with_tau, "time_offset") or {}
    tau = float(eff.get("params", {}).get("tau_s", 0.0)) if eff.get("status") != "not_testable" else 0.0
    out.update(status=eff.get("status"), tau_ms=1e3 * tau,
               tau_ci95_ms=[1e3 * v for v in eff.get("ci95", {}).get("tau_s", [np.nan, np.nan])],
               tau_std_ms=1e3 * float(eff.get("std", {}).get("tau_s", np.nan)),
               p_value=eff.get("test", {}).get("p_value"),
               field_uT=mag_b.field_strength, units=mag_b.unit,
               fit_residual_rms_none=mag_b.quality.residual_rms if mag_b.quality else None,
               fit_residual_rms_time_offset=mag_t.quality.residual_rms if mag_t.quality else None,
               norm_rms_pct_none=mag_b.quality.field_norm_rms_pct if mag_b.quality else None,
               norm_rms_pct_time_offset=mag_t.quality.field_norm_rms_pct if mag_t.quality else None,
               dip_none=mag_b.dip_deg, dip_time_offset=mag_t.dip_deg,
               misalignment_deg_none=float(np.degrees(so3.angle(mag_b.misalignment))),
               misalignment_deg_time_offset=float(np.degrees(so3.angle(mag_t.misalignment))))
    m_none = ser_b.calibrated * mag_b.field_strength                    # uT, the base calibration
    m_tau = ser_t.calibrated * mag_t.field_strength                     # uT, the time-offset fit's D, o
    t = ser_b.t
    raw = ser_b.raw
    variants = {
        "raw (factory calibration), stamp t": (raw, 0.0),
        "before: base fit, stamp t": (m_none, 0.0),
        "base fit, re-stamped t - tau": (m_none, tau),
        "time-offset fit's D, o, stamp t": (m_tau, 0.0),
        "after: time-offset fit, re-stamped t - tau": (m_tau, tau),
    }
    lag = mocap_lag_ms(mocap, gyr) * 1e-3
    out["mocap_lag_vs_gyro_ms"] = 1e3 * lag
    # tau is the lag behind the IMU; the mocap itself is L behind the IMU, so on the mocap's clock the
    # magnetometer lags by tau - L
    variants["after, on the mocap's clock: re-stamped t - (tau - L)"] = (m_tau, tau - lag)
    scores = {}
    for name, (m_b, shift) in variants.items():
        rot, ok = mocap.at(t - shift)
        scores[name] = heading_stats(m_b, rot, ok)
    out["scores"] = scores
    # independent estimate: the delay of the base-calibrated field against the mocap that minimises the error
    delays = np.arange(-20.0, 40.01, 0.5)
    for label, m_b in (("base", m_none), ("time_offset", m_tau)):
        h_rms, f_rms = [], []
        for d in delays:
            rot, ok = mocap.at(t - d * 1e-3)
            s = heading_stats(m_b, rot, ok)
            h_rms.append(s["heading_rms_deg"])
            f_rms.append(s["field_residual_rms"])
        out[f"scan_{label}"] = {"delay_heading_ms": parabola_min(delays, np.asarray(h_rms)),
                                "delay_field_ms": parabola_min(delays, np.asarray(f_rms)),
                                "heading_rms_at_best_deg": float(np.min(h_rms)),
                                "field_residual_rms_at_best": float(np.min(f_rms))}
    return out


# ------------------------------------------------------------------------------------- part 2 and 3: ArduPilot
def firmware_motor(path: Path) -> dict[str, Any]:
    """What the firmware logged about motor compensation: every PARM value of COMPASS_MOT*/PMOT*, and the range
    of the MAG records' motor-offset fields (pymavlink, independent of magcal's reader)."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path))
    params: dict[str, list[float]] = {}
    mo: dict[str, list[float]] = {}
    gps_date = None
    while True:
        msg = conn.recv_match(type=["PARM", "MAG", "MAG2", "MAG3", "GPS"])
        if msg is None:
            break
        kind = msg.get_type()
        if kind == "PARM":
            if msg.Name.startswith(("COMPASS_MOT", "COMPASS_PMOT")):
                vals = params.setdefault(msg.Name, [])
                if msg.Value not in vals:
                    vals.append(float(msg.Value))
        elif kind == "GPS":
            if gps_date is None and getattr(msg, "Status", 0) >= 3:
                week = getattr(msg, "GWk", getattr(msg, "Week", None))
                ms = getattr(msg, "GMS", getattr(msg, "TimeMS", None))
                if week:
                    gps_date = GPS_EPOCH + dt.timedelta(weeks=int(week), milliseconds=float(ms or 0))
        else:
            d = msg.to_dict()
            for c in ("MOfsX", "MOfsY", "MOfsZ", "MOX", "MOY", "MOZ"):
                if c in d:
                    lo_hi = mo.setdefault(f"{kind}.{c}", [np.inf, -np.inf])
                    lo_hi[0], lo_hi[1] = min(lo_hi[0], d[c]), max(lo_hi[1], d[c])
    return {"params": params, "motor_offset_fields": {k: [float(v[0]), float(v[1])] for k, v in mo.items()},
            "gps_date": gps_date.isoformat() if gps_date else None}


def norm_rms_pct(m_b: np.ndarray) -> float:
    """As quality.field_norm_rms_pct: RMS of |m_b| - 1 in %."""
    return float(100.0 * np.sqrt(np.mean((np.linalg.norm(m_b, axis=1) - 1.0) ** 2)))


def current_at(rec: Recording, channel: str, t: np.ndarray) -> np.ndarray:
    """The battery current (A) of stream `channel` linearly interpolated at t."""
    s = next(s for s in rec.of_kind(Kind.BATTERY_CURRENT) if s.id == channel)
    return np.asarray(np.interp(t, s.t, s.values[:, 0]), dtype=np.float64)


def wmm_for(rec: Recording, date: dt.date) -> Any:
    """The WMM field at the median GPS position on `date` (magcal itself uses the log's clock date, else today)."""
    pos = rec.of_kind(Kind.POSITION)
    if not pos:
        return None
    v = pos[0].values[np.isfinite(pos[0].values).all(axis=1)]
    lat, lon, alt = np.median(v, axis=0)
    return reference_field(float(lat), float(lon), float(alt), date)


def cross_check_current(rec: Recording, mag: Stream, ref: Any) -> dict[str, Any] | None:
    """Outside magcal: y = D R^T m_n + o + c I by linear least squares, R from the firmware's EKF attitude (ATT,
    body -> true NED), m_n the WMM field (true NED, mG), D (3x3), o, c free. ATT's yaw used the compass, so the
    interference leaks into it; a rough, independent order-of-magnitude check."""
    if ref is None:
        return None
    att = next((s for s in rec.of_kind(Kind.ATTITUDE) if s.id == "ATT"), None)
    cur = rec.of_kind(Kind.BATTERY_CURRENT)
    if att is None or not cur:
        return None
    t = mag.t
    j = np.clip(np.searchsorted(att.t, t), 1, len(att) - 1)
    j -= (t - att.t[j - 1]) < (att.t[j] - t)
    ok = np.abs(att.t[j] - t) < 0.06
    f = ref.intensity * 1e7                                      # tesla -> milligauss
    m_n = f * np.array([np.cos(ref.dip) * np.cos(ref.declination), np.cos(ref.dip) * np.sin(ref.declination),
                        np.sin(ref.dip)])
    v = np.einsum("nji,j->ni", so3.from_quat(att.values[j[ok]]), m_n)
    i_a = np.interp(t[ok], cur[0].t, cur[0].values[:, 0])
    y = mag.xyz[ok] * 1e7
    x = np.column_stack([v, np.ones(ok.sum()), i_a])             # per axis: D row (3), o (1), c (1)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ coef
    sigma2 = np.sum(resid**2, axis=0) / (len(y) - x.shape[1])
    cov_c = np.linalg.inv(x.T @ x)[4, 4]
    return {"c": coef[4].tolist(), "std": np.sqrt(sigma2 * cov_c).tolist(),
            "residual_rms": float(np.sqrt(np.mean(resid**2))), "samples": int(ok.sum())}


def ardupilot_current(path: Path, log: list[dict[str, Any]]) -> tuple[dict[str, Any], RunResult | None]:
    """Base and current-interference fits of one ArduPilot log, per compass (and the base fit, for part 3)."""
    out: dict[str, Any] = {"log": path.name, "firmware": firmware_motor(path)}
    base = fit(path, (), log)
    out["seconds_none"] = log[-1]["seconds"]
    with_c = fit(path, ("current_interference",), log)
    out["seconds_current"] = log[-1]["seconds"]
    rec = base.recording if base is not None else (with_c.recording if with_c is not None else open_recording(path))
    cur = rec.of_kind(Kind.BATTERY_CURRENT)
    if cur:
        out["current_A"] = {"min": float(cur[0].values.min()), "max": float(cur[0].values.max()),
                            "std": float(cur[0].values.std())}
    att = next((a for a in rec.of_kind(Kind.ATTITUDE) if a.id == "ATT"), None)
    if att is not None:
        rpy = np.degrees(so3.as_rpy(so3.from_quat(att.values)))
        out["tilt_p1_p99_deg"] = {"roll": np.percentile(rpy[:, 0], [1, 99]).tolist(),
                                  "pitch": np.percentile(rpy[:, 1], [1, 99]).tolist()}
    gps_date = out["firmware"]["gps_date"]
    ref = wmm_for(rec, dt.date.fromisoformat(gps_date) if gps_date else dt.date.today())
    out["wmm_field_mG"] = None if ref is None else ref.intensity * 1e7
    params = rec.params
    out["COMPASS_MOTCT"] = params.get("COMPASS_MOTCT")
    comp: list[dict[str, Any]] = []
    for k, mag in enumerate(rec.of_kind(Kind.MAGNETOMETER)):
        suffix = ("", "2", "3")[k] if k < 3 else str(k + 1)
        ext = params.get(("COMPASS_EXTERNAL", "COMPASS_EXTERN2", "COMPASS_EXTERN3")[k]) if k < 3 else None
        row: dict[str, Any] = {"id": mag.id, "external": None if ext is None else bool(ext),
                               "firmware_MOT": [params.get(f"COMPASS_MOT{suffix}_{a}") for a in "XYZ"],
                               "cross_check": cross_check_current(rec, mag, ref)}
        if base is not None:
            m0 = next((m for m in base.calibration.magnetometers if m.id == mag.id), None)
            if m0 is not None and m0.quality is not None:
                row["norm_rms_pct_none"] = m0.quality.field_norm_rms_pct
                row["residual_rms_none"] = m0.quality.residual_rms
                row["dip_none"] = m0.dip_deg
        if with_c is not None:
            m1 = next((m for m in with_c.calibration.magnetometers if m.id == mag.id), None)
            e = effect_entry(with_c, "current_interference", mag.id)
            if m1 is not None and m1.quality is not None:
                row["norm_rms_pct_with_doc"] = m1.quality.field_norm_rms_pct
                row["residual_rms_with"] = m1.quality.residual_rms
                row["dip_with"] = m1.dip_deg
            if e is not None:
                row.update(status=e["status"], channels=e.get("channels"), reason=e.get("reason"))
                if e["status"] != "not_testable" and m1 is not None:
                    c = np.asarray(e["params"]["c"], dtype=float)
                    row.update(c=c.tolist(), c_std=e["std"]["c"], c_ci95=e["ci95"]["c"],
                               p_value=e.get("test", {}).get("p_value"), units=e["units"]["c"])
                    ser = with_c.series[mag.id]
                    i_a = current_at(rec, e["channels"][0], ser.t)
                    row["norm_rms_pct_with_term_removed"] = norm_rms_pct(m1.apply(ser.raw - i_a[:, None] * c))
                    row["norm_rms_pct_with_doc_check"] = norm_rms_pct(m1.apply(ser.raw))
                    # firmware-export.md section 3: COMPASS_MOT = -A k with A = F D^-1 (mG/A)
                    row["MOT_equivalent"] = (-(m1.field_strength * m1.A) @ c).tolist()
                    row["max_interference_mG"] = float(np.linalg.norm(c) * np.max(np.abs(i_a)))
                    row["max_interference_pct_field"] = 100.0 * row["max_interference_mG"] / m1.field_strength
        comp.append(row)
    if with_c is not None:                    # what `magcal export`/the fit's ardupilot.param writes
        try:
            exp = export(with_c.calibration, "ardupilot", rec.params, Options(skip_refused=True))
            for row in comp:
                sfx = next((e.slot.removeprefix("COMPASS_*") for e in exp.mags if e.mag_id == row["id"]), None)
                if sfx is not None and f"COMPASS_MOT{sfx}_X" in exp.params:
                    row["exported_MOT"] = [exp.params[f"COMPASS_MOT{sfx}_{a}"] for a in "XYZ"]
            out["exported_MOTCT"] = exp.params.get("COMPASS_MOTCT")
        except Exception as exc:  # noqa: BLE001 -- recorded, not fatal
            out["export_error"] = f"{type(exc).__name__}: {exc}"
    out["compasses"] = comp
    return out, base


def nongravity(path: Path, log: list[dict[str, Any]], base: RunResult | None) -> dict[str, Any]:
    """log171: dip per compass with and without the non-gravity acceleration term, against the WMM."""
    out: dict[str, Any] = {"log": path.name}
    fits = {"none": base, "nongravity_acceleration": fit(path, ("nongravity_acceleration",), log)}
    out["seconds_nongravity"] = log[-1]["seconds"]
    fits["nongravity_acceleration+current_interference"] = fit(
        path, ("nongravity_acceleration", "current_interference"), log)
    out["seconds_both"] = log[-1]["seconds"]
    rec = next((r.recording for r in fits.values() if r is not None), None)
    if rec is None:
        out["error"] = "fit failed (see Problems found)"
        return out
    fw = firmware_motor(path)
    gps_date = dt.date.fromisoformat(fw["gps_date"]) if fw["gps_date"] else None
    today = dt.datetime.now(dt.timezone.utc).date()
    ref_log = wmm_for(rec, gps_date) if gps_date else None
    ref_today = wmm_for(rec, today)
    out["gps_date"] = fw["gps_date"]
    out["wmm_dip_log_date"] = ref_log.dip_deg if ref_log else None
    out["wmm_dip_today"] = ref_today.dip_deg if ref_today else None
    out["wmm_model_today"] = ref_today.model if ref_today else None
    dips: dict[str, dict[str, Any]] = {}
    for name, res in fits.items():
        if res is None:
            continue
        dips[name] = {m.id: {"dip": m.dip_deg, "dip_std": float(m.std_of("dip")),
                             "residual_rms": m.quality.residual_rms if m.quality else None}
                      for m in res.calibration.magnetometers}
        warned = sorted(f.message.split(":")[0] for f in res.findings if f.code == "dip_disagrees_with_wmm")
        e = effect_entry(res, "nongravity_acceleration")
        dips[name]["dip_warnings"] = warned
        if e is not None:
            dips[name]["kappa"] = {k: e.get(k) for k in ("status", "params", "std", "ci95", "test", "reason")}
    out["fits"] = dips
    return out


# ------------------------------------------------------------------------------------------------------ report
def fmt(x: Any, spec: str = ".2f") -> str:
    """A number, or '-' when missing."""
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return format(x, spec)


def vec(v: Any, spec: str = "+.2f") -> str:
    """A 3-vector as (x, y, z)."""
    return "-" if v is None else "(" + ", ".join(fmt(a, spec) for a in v) + ")"


HOW_HEADING = """\
**How heading was scored.** BROAD's `opt_quat` is the optical motion capture's IMU→ENU attitude on the same
285.714 Hz sample grid as the IMU (the reader turns it into IMU→NED and drops samples where tracking was lost).
For a magnetometer sample stamped t the mocap attitude is taken at t' (geodesic interpolation
R_k·Exp(f·Log(R_kᵀR_k+1)) between the two neighbouring grid samples, used only where both are tracked), and the
calibrated body field m_b = F·A·(y − b) (µT, from the fitted document) is rotated into the mocap's level frame,
m_n = R(t')·m_b. Heading = atan2(m_n,E, m_n,N). The mocap frame's x axis is not magnetic north, so the error is
the heading minus its circular mean over the trial; the table gives its RMS and 95th percentile. The field
residual is the RMS of |m_n − mean(m_n)| (µT): in a homogeneous field the mocap-predicted body field is
R(t')ᵀ·mean(m_n), so this is the calibrated field against the mocap-predicted field; the direction RMS is the
angle between m_n and mean(m_n). "Before" is the base fit (`--effects none`) with t' = t; "after" is the
`time_offset` fit with the re-stamping its `apply` does, t' = t − tau. The two middle rows separate the
re-stamping from the change of D and o. tau is the lag behind the *IMU*; the mocap is not exactly on the IMU's
clock (its lag L behind the gyro is measured by matching the mocap's finite-difference body rate to the gyro
over ±30 ms), so the last row re-stamps onto the mocap's clock, t' = t − (tau − L). Independent check: the
delay of the calibrated field against the mocap that minimises the heading (or field) error, scanned over
−20…40 ms in 0.5 ms steps with a parabolic refinement; on the IMU's clock it implies tau ≈ scan + L."""


def write_md(path: Path, res: dict[str, Any]) -> None:
    """The results as Markdown: tables, how they were measured, what they say and what failed."""
    lines = ["# Effects on real logs", "",
             f"`python benchmarks/effects_realdata.py --out {path.with_suffix('')}`; {res['total_s']:.0f} s in "
             f"total for {len(res['fits'])} fits (Python API `calibrate(path, Config(method='map', effects=...))`, "
             "one process). Data: `../shared/realdata/` (README.md there); raw numbers in the JSON next to this "
             "file.", ""]
    # ---------------------------------------------------------------------------------------------- part 1
    lines += ["## 1 `time_offset` on BROAD, scored against the motion capture", "",
              "| trial | tau ms | 95 % CI ms | p | status | mocap lag L vs gyro ms | mocap delay scan, base fit "
              "(heading / field) ms | implied tau = scan + L ms | fit residual RMS µT none / with | dip deg none "
              "/ with | misalignment deg none / with | fit s none / with |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for b in res["broad"]:
        if "error" in b:
            lines.append(f"| {b['trial']} | {b['error']} |||||||||||")
            continue
        ci, sc, lag = b["tau_ci95_ms"], b["scan_base"], b["mocap_lag_vs_gyro_ms"]
        lines.append(
            f"| {b['trial']} | {b['tau_ms']:.2f} | [{ci[0]:.2f}, {ci[1]:.2f}] | {b['p_value']:.2g} | {b['status']} | "
            f"{lag:+.2f} | {sc['delay_heading_ms']:.2f} / {sc['delay_field_ms']:.2f} | "
            f"{sc['delay_heading_ms'] + lag:.2f} / {sc['delay_field_ms'] + lag:.2f} | "
            f"{fmt(b['fit_residual_rms_none'], '.3f')} / {fmt(b['fit_residual_rms_time_offset'], '.3f')} | "
            f"{b['dip_none']:.2f} / {b['dip_time_offset']:.2f} | {b['misalignment_deg_none']:.2f} / "
            f"{b['misalignment_deg_time_offset']:.2f} | {b['seconds_none']:.1f} / "
            f"{b['seconds_time_offset']:.1f} |")
    lines += ["", "Heading and field against the mocap (every tracked sample of the trial):", "",
              "| trial | variant | heading RMS deg | heading p95 deg | field residual RMS µT | direction RMS deg |",
              "|---|---|---|---|---|---|"]
    for b in res["broad"]:
        for name, s in b.get("scores", {}).items():
            bold = "**" if name.startswith(("before", "after:")) else ""
            lines.append(f"| {b['trial'][:2]} | {bold}{name}{bold} | {bold}{s['heading_rms_deg']:.2f}{bold} | "
                         f"{s['heading_p95_deg']:.2f} | {bold}{s['field_residual_rms']:.2f}{bold} | "
                         f"{s['direction_rms_deg']:.2f} |")
        if "scan_base" in b:
            lines.append(f"| {b['trial'][:2]} | best delay of the scan (base fit) | "
                         f"{b['scan_base']['heading_rms_at_best_deg']:.2f} | | "
                         f"{b['scan_base']['field_residual_rms_at_best']:.2f} | |")
    lines += ["", HOW_HEADING, ""]
    # ---------------------------------------------------------------------------------------------- part 2
    lines += ["## 2 `current_interference` on ArduPilot logs", "",
              "| log | compass | status (p) | c mG/A | 95 % CI mG/A | firmware COMPASS_MOT{,2,3} (MOTCT) | "
              "MOT this c implies, −F·A·c mG/A | COMPASS_MOT magcal exports | max \\|c\\|·I, % of field | field-norm RMS %: none / with (document) "
              "/ with, c·I removed | cross-check c, ATT+WMM LS | fit s none / with |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for a in res["ardupilot"]:
        for c in a["compasses"]:
            ci = "-" if "c_ci95" not in c else ", ".join(f"[{lo:+.1f}, {hi:+.1f}]" for lo, hi in c["c_ci95"])
            xc = c.get("cross_check")
            xcs = "-" if not xc else vec(xc["c"], "+.1f")
            st = c.get("status", "fit failed")
            st += f" ({c['p_value']:.2g})" if c.get("p_value") is not None else ""
            lines.append(
                f"| {a['log']} | {c['id']} | {st} | {vec(c.get('c'))} | {ci} | "
                f"{vec(c['firmware_MOT'], 'g')} ({fmt(a['COMPASS_MOTCT'], 'g')}) | {vec(c.get('MOT_equivalent'))} | "
                f"{vec(c.get('exported_MOT'))} | "
                f"{fmt(c.get('max_interference_pct_field'), '.1f')} | {fmt(c.get('norm_rms_pct_none'))} / "
                f"{fmt(c.get('norm_rms_pct_with_doc'))} / {fmt(c.get('norm_rms_pct_with_term_removed'))} | "
                f"{xcs} | {a['seconds_none']:.1f} / {a['seconds_current']:.1f} |")
    lines += ["", "What the firmware logged (pymavlink, every PARM and MAG record, independent of magcal's reader):", ""]
    for a in res["ardupilot"]:
        fw = a["firmware"]
        nonzero = {k: v for k, v in fw["params"].items() if any(x != 0 for x in v)}
        mo = {k: v for k, v in fw["motor_offset_fields"].items() if v != [0.0, 0.0]}
        cur = a.get("current_A", {})
        tilt = a.get("tilt_p1_p99_deg")
        tilt_s = "" if not tilt else (f"; ATT roll {tilt['roll'][0]:.0f}…{tilt['roll'][1]:.0f}°, pitch "
                                      f"{tilt['pitch'][0]:.0f}…{tilt['pitch'][1]:.0f}° (1st–99th percentile)")
        lines.append(f"- {a['log']}: {len(fw['params'])} COMPASS_MOT*/PMOT* parameters, "
                     f"{'all zero in every PARM record' if not nonzero else 'non-zero: ' + json.dumps(nonzero)}; "
                     f"MAG motor-offset fields "
                     f"{', '.join(sorted({k.split('.')[1] for k in fw['motor_offset_fields']})) or 'absent'}: "
                     f"{'zero in every record' if not mo else json.dumps(mo)}; current "
                     f"{fmt(cur.get('min'), '.1f')}–{fmt(cur.get('max'), '.1f')} A (std {fmt(cur.get('std'), '.1f')} A)"
                     f"{tilt_s}; GPS date {fw['gps_date']}.")
    lines += ["", """\
**Conventions.** c is the field the current adds to the *raw* reading (mG/A): magcal's ArduPilot reader
undoes the firmware correction, motor offsets included (all zero here), so y is the pre-correction body-frame
field. ArduPilot's COMPASS_MOT is the negative of the interference and is added after the iron matrix, so the
value to export is MOT = −A·c with A = F·D⁻¹ (design/firmware-export.md §1 and §3); the column "MOT this c
implies" is that. The firmware had no compensation in any of these logs (COMPASS_MOTCT = 0, MOT = 0, MOfs = 0),
so there is no firmware estimate to compare with: the firmware's numbers are zero, and the fitted c is what
compassmot would have had to learn.

**Norm spread.** `quality.field_norm_rms_pct` in the document is RMS(|A·(y − b − terms)| − 1) with the accepted
magnetometer effects removed (an earlier version left them in, which made an accepted `current_interference`
look worse than the base model). The last number of that column recomputes it here from the document and the
log: RMS(|A·(y − b − c·I)| − 1), I = the log's battery current (`BAT[0]`) linearly interpolated at the
magnetometer times; the two agree.

**Cross-check outside magcal** (rough, independent): per axis, linear least squares
y = D·R_ATTᵀ·m_WMM + o + c·I with R_ATT the firmware's EKF attitude (ATT, body→true NED), m_WMM the WMM field
vector (declination included) at the median GPS position on the log's GPS date, D, o, c free. ATT's yaw came
from the compass, so interference and calibration errors leak into it; its formal std (~0.1 mG/A) is far too
small to mean anything. It runs on the 2015 logs too, where magcal refuses to fit.""", ""]
    # ---------------------------------------------------------------------------------------------- part 3
    n = res["nongravity"]
    lines += ["## 3 `nongravity_acceleration` on log171", "",
              f"WMM dip at the median GPS position: {fmt(n.get('wmm_dip_log_date'))}° on the log's GPS date "
              f"({n.get('gps_date')}), {fmt(n.get('wmm_dip_today'))}° today ({n.get('wmm_model_today')}; magcal "
              "dates a boot-clock DataFlash log from its GPS week and time, so it uses the log's date).", "",
              "| fit | kappa | kappa 95 % CI | status | " + " | ".join(
                  f"{m} dip deg ± std (− WMM)" for m in ("MAG[0]", "MAG[1]", "MAG[2]")) + " | fit s |",
              "|---|---|---|---|---|---|---|---|"]
    secs = {"none": next((a["seconds_none"] for a in res["ardupilot"] if a["log"] == "log171.bin"), None),
            "nongravity_acceleration": n.get("seconds_nongravity"),
            "nongravity_acceleration+current_interference": n.get("seconds_both")}
    wmm = n.get("wmm_dip_log_date") or n.get("wmm_dip_today") or 0.0
    for name, f in n.get("fits", {}).items():
        k = f.get("kappa") or {}
        kv = (k.get("params") or {}).get("kappa")
        kci = (k.get("ci95") or {}).get("kappa")
        dips = " | ".join(f"{f[m]['dip']:.2f} ± {f[m]['dip_std']:.2f} ({f[m]['dip'] - wmm:+.2f})" if m in f else "-"
                          for m in ("MAG[0]", "MAG[1]", "MAG[2]"))
        lines.append(f"| {name} | {fmt(kv, '.3f')} | {'-' if not kci else f'[{kci[0]:.3f}, {kci[1]:.3f}]'} | "
                     f"{k.get('status', '-')} | {dips} | {fmt(secs.get(name), '.1f')} |")
    lines += ["", "kappa scales the NED acceleration from the GPS position differentiated twice (Savitzky-Golay, "
              "order 7 over 2 s at 10 Hz, cubic-spline resampling), evaluated delay_s later (the position's latency, "
              "fitted); 1 = the GPS acceleration is right.", ""]
    # ------------------------------------------------------------------------------------------ findings
    lines += ["## Findings", ""] + findings(res) + [""]
    lines += ["## Fits and timings", "", "| log | effects | ok | s | command |", "|---|---|---|---|---|"]
    for f in res["fits"]:
        lines.append(f"| {f['log']} | {','.join(f['effects'])} | {'yes' if f['ok'] else 'NO'} | {f['seconds']:.2f} | "
                     f"`{f['command']}` |")
    lines += ["", "## Problems found", ""] + problems(res) + [""]
    path.write_text("\n".join(lines) + "\n")


def findings(res: dict[str, Any]) -> list[str]:
    """Plain statements of what the numbers say, with the numbers filled in."""
    out: list[str] = []
    by = {b["trial"][:2]: b for b in res["broad"] if "scores" in b}
    if "06" in by:
        b = by["06"]
        s = b["scores"]
        bef, aft = s["before: base fit, stamp t"], s["after: time-offset fit, re-stamped t - tau"]
        rest = s["base fit, re-stamped t - tau"]
        mc = next(v for k, v in s.items() if k.startswith("after, on the mocap"))
        implied = b["scan_base"]["delay_heading_ms"] + b["mocap_lag_vs_gyro_ms"]
        out.append(
            f"- **Time offset, fast rotation (06):** tau = {b['tau_ms']:.2f} ms (95 % CI {b['tau_ci95_ms'][0]:.2f}–"
            f"{b['tau_ci95_ms'][1]:.2f}), accepted: the magnetometer lags the IMU. Against the mocap the heading RMS "
            f"drops from {bef['heading_rms_deg']:.2f}° to {aft['heading_rms_deg']:.2f}° and the field residual from "
            f"{bef['field_residual_rms']:.2f} to {aft['field_residual_rms']:.2f} µT; the re-stamping does almost "
            f"all of it (base fit re-stamped: {rest['heading_rms_deg']:.2f}°), the change of D and o little. On the "
            f"mocap's clock (t − (tau − L)) it is {mc['heading_rms_deg']:.2f}°. The fit's own residual drops "
            f"{b['fit_residual_rms_none']:.2f} → {b['fit_residual_rms_time_offset']:.2f} µT.")
        out.append(
            f"- **The delay is real; its CI is too narrow.** The mocap alone says the magnetometer lags the IMU by "
            f"about {implied:.1f} ms (delay scan {b['scan_base']['delay_heading_ms']:.1f} ms against the mocap, "
            f"mocap {b['mocap_lag_vs_gyro_ms']:+.1f} ms against the gyro in both trials): same sign and size as tau, "
            f"but {abs(implied - b['tau_ms']):.1f} ms away, about "
            f"{abs(implied - b['tau_ms']) / b['tau_std_ms']:.0f} standard deviations of tau.")
    if "01" in by and "06" in by:
        b1, b6 = by["01"], by["06"]
        out.append(
            f"- **Slow rotation (01):** tau = {b1['tau_ms']:.2f} ms (CI {b1['tau_ci95_ms'][0]:.2f}–"
            f"{b1['tau_ci95_ms'][1]:.2f}, p = {b1['p_value']:.2g}) is `{b1['status']}` at magcal's 1 % level"
            f"{' although the 95 % CI excludes 0' if b1['status'] == 'rejected' else ''}; the mocap implies "
            f"{b1['scan_base']['delay_heading_ms'] + b1['mocap_lag_vs_gyro_ms']:.1f} ms. Heading "
            f"{b1['scores']['before: base fit, stamp t']['heading_rms_deg']:.2f}° → "
            f"{b1['scores']['after: time-offset fit, re-stamped t - tau']['heading_rms_deg']:.2f}° (slow motion: a "
            f"few ms hardly matter). The same board gives {b1['tau_ms']:.1f} ms slow and {b6['tau_ms']:.1f} ms fast "
            "(each CI excludes the other value) and the mocap scan shows the same difference, so the apparent lag "
            "depends on the motion (cause not identified: sensor dynamics, or the dataset's synchronisation). A "
            "tau from one recording should not be trusted to better than a few ms on another, whatever its CI.")
        raw6 = b6["scores"]["raw (factory calibration), stamp t"]
        raw1 = b1["scores"]["raw (factory calibration), stamp t"]
        out.append(
            f"- Against the mocap the factory-calibrated readings score {raw6['heading_rms_deg']:.2f}° (06) and "
            f"{raw1['heading_rms_deg']:.2f}° (01) in heading; the base MAP fit is slightly worse in heading "
            f"({b6['scores']['before: base fit, stamp t']['heading_rms_deg']:.2f}°, "
            f"{b1['scores']['before: base fit, stamp t']['heading_rms_deg']:.2f}°) but better in field residual. "
            f"The fit rotates the field by {b6['misalignment_deg_none']:.1f}° (06) / {b1['misalignment_deg_none']:.1f}° "
            "(01) into the frame of the IMU's gyro and accelerometer; whether the mocap's body frame is that frame "
            "or the magnetometer's is not known, so this comparison does not rank the calibrations. About "
            f"{min(v['heading_rms_deg'] for v in b6['scores'].values()):.1f}–"
            f"{max(b1['scores'][k]['heading_rms_deg'] for k in b1['scores'] if not k.startswith('raw')):.1f}° of "
            "heading RMS remains in every variant: the time offset is not the dominant heading error in BROAD.")
    for a in res["ardupilot"]:
        acc = [c for c in a["compasses"] if c.get("status") == "accepted"]
        rej = [c for c in a["compasses"] if c.get("status") == "rejected"]
        if not acc and not rej:
            continue
        parts = [f"{c['id']} c = {vec(c['c'], '+.1f')} mG/A, up to {c['max_interference_pct_field']:.0f} % of the "
                 f"field at the peak current (norm RMS {c['norm_rms_pct_none']:.1f} % → "
                 f"{c['norm_rms_pct_with_term_removed']:.1f} % with c·I removed, {c['norm_rms_pct_with_doc']:.1f} % "
                 "in the document)" for c in acc]
        xc = "; ".join(f"{c['id']} z {c['c'][2]:+.1f} vs {c['cross_check']['c'][2]:+.1f}, x {c['c'][0]:+.1f} vs "
                       f"{c['cross_check']['c'][0]:+.1f}, y {c['c'][1]:+.1f} vs {c['cross_check']['c'][1]:+.1f}"
                       for c in acc if c.get("cross_check"))
        exported = [c for c in acc if c.get("exported_MOT") and c.get("MOT_equivalent")]
        out.append(
            f"- **Current, {a['log']}:** accepted for " + "; ".join(parts) + ". " +
            ("Rejected for " + ", ".join(f"{c['id']} (p = {c['p_value']:.2g})" for c in rej) + ". " if rej else "")
            + ("Mounting (COMPASS_EXTERNAL/EXTERN2/EXTERN3): " + ", ".join(
                f"{c['id']} {'external' if c['external'] else 'internal'}"
                for c in acc + rej if c.get("external") is not None) + ". "
               if any(c.get("external") is not None for c in acc + rej) else "")
            + "The firmware had COMPASS_MOTCT = 0 and every MOT/MOfs zero: no compensation, nothing to compare "
            "against but zero. "
            + (f"The ATT+WMM cross-check (magcal vs cross-check, mG/A): {xc}: it agrees on z, where the EKF's "
               "compass-derived yaw matters least, and differs by a few mG/A in the horizontal axes. " if xc else "")
            + ("magcal's own ArduPilot export writes COMPASS_MOT = " + "; ".join(
                f"{c['id']} {vec(c['exported_MOT'], '+.2f')}" for c in exported)
               + " (sign opposite to c, as firmware-export.md says; it is −A_held·c with the part of A the "
               "ArduPilot parameters can hold, firmware/ardupilot.py, hence the difference from −F·A·c)."
               if exported else ""))
    fails = [a for a in res["ardupilot"] if all("status" not in c for c in a["compasses"])]
    if fails:
        worst = max((np.linalg.norm(c["cross_check"]["c"]) * a["current_A"]["max"] / a["wmm_field_mG"], a["log"])
                    for a in fails for c in a["compasses"] if c.get("cross_check") and a.get("wmm_field_mG"))
        biggest = max(abs(x) for a in fails for c in a["compasses"] if c.get("cross_check")
                      for x in c["cross_check"]["c"])
        out.append(f"- **Current, {', '.join(a['log'] for a in fails)}:** no magcal result: the base fit itself "
                   "is refused (see Problems found). The cross-check puts the interference at ≤ "
                   f"{biggest:.1f} mG/A per axis, at most {100 * worst[0]:.0f} % of the field at the peak current.")
    n = res["nongravity"]
    if n.get("fits"):
        f0, f1 = n["fits"].get("none", {}), n["fits"].get("nongravity_acceleration", {})
        f2 = n["fits"].get("nongravity_acceleration+current_interference", {})
        wmm = n.get("wmm_dip_log_date") or n.get("wmm_dip_today")
        k = (f1.get("kappa") or {})
        kv, kci = (k.get("params") or {}).get("kappa"), (k.get("ci95") or {}).get("kappa")
        if kv is not None and f0 and wmm is not None:
            mags = [m for m in f0 if m.startswith("MAG")]
            gap0 = np.mean([f0[m]["dip"] - wmm for m in mags])
            gap1 = np.mean([f1[m]["dip"] - wmm for m in mags if m in f1])
            std = np.mean([f1[m]["dip_std"] for m in mags if m in f1])
            extra = [abs(f2[m]["dip"] - f1[m]["dip"]) for m in mags if m in f2 and m in f1]
            ci_text = f"95 % CI {kci[0]:.2f}–{kci[1]:.2f}, " if kci else ""
            out.append(
                f"- **Non-gravity acceleration, log171:** kappa = {kv:.2f} ({ci_text}"
                f"{k.get('status')}; 1 is {'inside' if kci and kci[0] <= 1 <= kci[1] else 'outside'} the CI). The dip moves toward the WMM's {wmm:.1f}° by only "
                f"{abs(gap0 - gap1):.1f}° on average (mean gap {gap0:+.1f}° → {gap1:+.1f}°, about "
                f"{abs(gap1) / std:.1f} dip std): the vehicle's acceleration explains a small part of the "
                "disagreement, most of it remains"
                + (f"; adding current_interference moves the dips by another {min(extra):.1f}–{max(extra):.1f}°"
                   if extra else "")
                + f". `dip_disagrees_with_wmm` still fires for {', '.join(f1.get('dip_warnings', [])) or 'none'} "
                "with the term.")
    return out


def problems(res: dict[str, Any]) -> list[str]:
    """Failed fits with the command and error, and the issues seen in the numbers, with a diagnosis."""
    out: list[str] = []
    failed = [f for f in res["fits"] if not f["ok"]]
    crashes = [f for f in failed if "traceback" in f]
    clean = [f for f in failed if "traceback" not in f]
    for f in crashes:
        out += [f"- **Crash:** `{f['command']}`: {f['error']}", "", "```", f["traceback"].rstrip(), "```", ""]
    if clean:
        out.append("- **Fits refused (clean error, CLI exit 1, no traceback):**")
        out += [f"  - `{f['command']}` → {f['error']}" for f in clean]
        if any("ellipsoid" in f["error"] for f in clean):
            tilts = [f"{a['log'][:19]} roll {a['tilt_p1_p99_deg']['roll'][0]:.0f}…"
                     f"{a['tilt_p1_p99_deg']['roll'][1]:.0f}°, pitch {a['tilt_p1_p99_deg']['pitch'][0]:.0f}…"
                     f"{a['tilt_p1_p99_deg']['pitch'][1]:.0f}°"
                     for a in res["ardupilot"] if a.get("tilt_p1_p99_deg") and
                     all("status" not in c for c in a["compasses"])]
            out.append(
                "  - *Diagnosis:* flights with yaw through 360° but little tilt ("
                + "; ".join(tilts) + ", 1st–99th percentile of ATT). The readings lie near a tilted circle, and "
                "the algebraic ellipsoid fit that starts the MAP method (models/map/init.intrinsic_fit → "
                "ellipsoid.fit_ellipsoid) returns a degenerate quadric (by hand: two of its three "
                "eigenvalues ≈ 0, i.e. a pair of planes), so its Cholesky step fails and the fit stops before the "
                "joint MAP, and before any effect, is reached. The base model fails identically (`--effects none`), "
                "as do `--method auto`, `--method kok2012` and `--mag MAG[1]` alone (checked by hand). The joint "
                "MAP has the IMU attitude and could in principle fit such a flight from another start (the "
                "firmware's own OFS/DIA, or a sphere fit with D ≈ F·I), as ArduPilot's in-flight learning does; "
                "the message (\"rotate the sensor through more orientations\") suits a handheld calibration but "
                "leaves a flight log with no way forward. Not fixed here (package not edited).")
    bad_q = [(a["log"], c) for a in res["ardupilot"] for c in a["compasses"]
             if c.get("status") == "accepted" and c.get("norm_rms_pct_with_doc", 0) >
             c.get("norm_rms_pct_none", np.inf)]
    if bad_q:
        out.append(
            "- **The quality numbers ignore an accepted effect.** `magnetometers[].quality.field_norm_rms_pct` (and "
            "`coverage_pct`, and `RunResult.series[].calibrated`) are computed from A·(y − b) without the effect "
            "term (calibration/assemble.mag_calibration), so an accepted current_interference makes the "
            "calibration look worse than the base fit: " + "; ".join(
                f"{log} {c['id']} {c['norm_rms_pct_none']:.1f} % (none) → {c['norm_rms_pct_with_doc']:.1f} % in "
                f"the document, {c['norm_rms_pct_with_term_removed']:.1f} % with c·I removed" for log, c in bad_q)
            + ". The number feeds `--fail-on field_norm_rms_pct>…`, the report's advice (\"> 1 %: something the "
            "model leaves out…\") and the one-line summary of `magcal fit`. Checked by hand: `magcal fit "
            "../shared/realdata/ardupilot/log171.bin --method map --mag 'MAG[1]' --fail-on "
            "'field_norm_rms_pct>6' --effects current_interference` exits 3 (9.72 %), the same with `--effects "
            "none` exits 0 (5.85 %). Compute the quality with the accepted terms removed (the effects' `correct`), "
            "or report both.")
    b6 = next((b for b in res["broad"] if b["trial"].startswith("06") and "scan_base" in b), None)
    if b6 is not None:
        implied = b6["scan_base"]["delay_heading_ms"] + b6["mocap_lag_vs_gyro_ms"]
        if abs(implied - b6["tau_ms"]) > 3 * b6["tau_std_ms"]:
            slow = next((b["tau_ms"] for b in res["broad"] if b["trial"].startswith("01")), float("nan"))
            out.append(
                f"- **The time_offset CI understates the error on real data** (not a bug: the CI is the posterior "
                f"under the model): 06 gives tau = {b6['tau_ms']:.2f} ± {b6['tau_std_ms']:.2f} ms (std), the mocap "
                f"implies {implied:.1f} ms, and trial 01 of the same board gives {slow:.1f} ms. Worth a caveat "
                "where tau is documented.")
    n = res.get("nongravity", {})
    if n.get("wmm_dip_log_date") is not None and n.get("wmm_dip_today") is not None:
        out.append(
            f"- *Minor:* for log171 magcal evaluates the WMM on today's date (dip {n['wmm_dip_today']:.2f}°) because "
            "the log's clock is time since boot, although its GPS records (week and ms of week) give the date "
            f"{n['gps_date']} (dip {n['wmm_dip_log_date']:.2f}°). Negligible here; decades-old logs would differ more.")
    return out or ["None."]


def main() -> int:
    """Run everything and write <out>.json and <out>.md."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--out", type=Path, default=None, help="path prefix for .json and .md (default: print only)")
    args = ap.parse_args()
    if not args.realdata.is_dir():
        print(f"skipped: {args.realdata} is absent (the real logs are not part of the project; see "
              "../shared/realdata/README.md)")
        return 0
    t0 = time.perf_counter()
    log: list[dict[str, Any]] = []
    res: dict[str, Any] = {"broad": [], "ardupilot": [], "nongravity": {}}
    print("1 BROAD time_offset", flush=True)
    for name in BROAD:
        p = args.realdata / "broad" / name
        if p.exists():
            res["broad"].append(broad_trial(p, log))
        else:
            print(f"  {name} missing")
    print("2 ArduPilot current_interference", flush=True)
    base171 = None
    for name in ARDU_CURRENT:
        p = args.realdata / "ardupilot" / name
        if not p.exists():
            print(f"  {name} missing")
            continue
        row, base = ardupilot_current(p, log)
        res["ardupilot"].append(row)
        if name == "log171.bin":
            base171 = base
    print("3 log171 nongravity_acceleration", flush=True)
    p171 = args.realdata / "ardupilot" / "log171.bin"
    if p171.exists():
        res["nongravity"] = nongravity(p171, log, base171)
    res["fits"] = log
    res["total_s"] = time.perf_counter() - t0
    text = json.dumps(res, indent=1, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o))
    if args.out is None:
        print(text)
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(text + "\n")
    write_md(args.out.with_suffix(".md"), res)
    print(f"wrote {args.out.with_suffix('.json')} and {args.out.with_suffix('.md')} ({res['total_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
