"""PX4's magnetometer delay (EKF2_MAG_DELAY) and thermal compensation (TC_M*) from a calibration's effects, and
what ArduPilot cannot hold of them.

EKF2_MAG_DELAY [S32]: "Magnetometer measurement delay relative to IMU measurements", ms, 0..300, one value for every
magnetometer; the EKF re-stamps each magnetometer sample at `time_us - mag_delay_ms * 1000` before fusing it
(EstimatorInterface::setMagData [S33]), which is the `time_offset` effect's own correction t -> t - tau_s (tau_s > 0:
the magnetometer lags the IMU). So EKF2_MAG_DELAY = 1000 tau_s.

TC_M* [S34]: with TC_M_ENABLE = 1 (reboot), the slot j whose TC_Mj_ID is the magnetometer's device id gives the
offset o_T(T) = X0 + X1 dT + X2 dT^2 + X3 dT^3 per sensor axis i (TC_Mj_Xp_i), dT = clip(T, TMIN, TMAX) - TREF, T the
magnetometer's own temperature, subtracted from the raw sensor-frame reading in gauss like CAL_MAGn_OFF. The
`temperature_drift` effect y += k (T - T0) (k in the raw frame) is then TREF = T0, X1 = k (gauss/degC), X0 = X2 = X3
= 0, and TMIN/TMAX the temperatures the fit saw (its `T_min`/`T_max`), so the firmware never extrapolates the slope.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.errors import StreamError
from magcal_cli.firmware.common import Extras
from magcal_cli.streams import FloatArray

#: EKF2_MAG_DELAY's @min/@max (ms) [S32]
DELAY_RANGE_MS = (0.0, 300.0)
#: TC_Mj slots (MAG_COUNT_MAX) [S34]
TC_SLOTS = range(4)
AXES = "XYZ"
#: two-sided 95 % normal quantile: lags whose difference exceeds it times its std disagree
Z95 = 1.959963984540054


def carried(cal: Calibration, mag_id: str, effect_id: str) -> dict[str, Any] | None:
    """The entry of `effect_id` for `mag_id` the calibration carries (accepted, or ambiguous with an estimate)."""
    from magcal_cli.effects.correct import terms

    return next((e for e, eff in terms(cal.effects, mag_id) if eff.id == effect_id), None)


def _lag(entry: dict[str, Any]) -> tuple[float, float]:
    """(tau_s, its std; inf when the entry has none)."""
    std = (entry.get("std") or {}).get("tau_s")
    return float(entry["params"]["tau_s"]), float(std) if std is not None else float("inf")


def delay(cal: Calibration, slots: Sequence[tuple[MagCalibration, int]], params: Mapping[str, float]) -> Extras:
    """EKF2_MAG_DELAY from the primary magnetometer's lag: the exported one with the highest CAL_MAGn_PRIO (the
    document's order among equals). The others' lags are compared with it: outside each other's 95 % intervals,
    a warning (the EKF fuses the selected magnetometer; after a switch the delay would be wrong)."""
    out = Extras()
    lags = {mag.id: _lag(e) for mag, _ in slots if (e := carried(cal, mag.id, "time_offset")) is not None}
    if not lags:
        return out
    order = sorted(range(len(slots)), key=lambda i: -params.get(f"CAL_MAG{slots[i][1]}_PRIO", 0.0))
    primary = slots[order[0]][0].id
    if primary not in lags:
        out.notes.append(f"EKF2_MAG_DELAY not written: the primary magnetometer {primary} carries no time_offset "
                         f"(only {', '.join(lags)} do); the vehicle keeps its own value")
        return out
    tau, std = lags[primary]
    for other, (t2, s2) in lags.items():
        if other != primary and abs(t2 - tau) > Z95 * float(np.hypot(std, s2)):
            out.warnings.append(f"{other} lags by {t2 * 1e3:.1f} ms, {primary} (the primary, written) by "
                                f"{tau * 1e3:.1f} ms: EKF2_MAG_DELAY is one value for all magnetometers, so after a "
                                f"switch to {other} the EKF would use the wrong delay")
    ms = tau * 1e3
    if ms < DELAY_RANGE_MS[0]:
        out.warnings.append(f"{primary} leads the IMU by {-ms:.1f} ms (time_offset {tau * 1e3:.1f} ms); "
                            "EKF2_MAG_DELAY cannot be negative (0..300 ms), so it is not written")
        return out
    if ms > DELAY_RANGE_MS[1]:
        out.warnings.append(f"{primary} lags by {ms:.1f} ms, beyond EKF2_MAG_DELAY's 300 ms: 300 is written; "
                            "check the log's time stamps")
        ms = DELAY_RANGE_MS[1]
    out.params["EKF2_MAG_DELAY"] = float(ms)
    was = params.get("EKF2_MAG_DELAY")
    out.notes.append(f"EKF2_MAG_DELAY = {ms:.1f} ms from {primary}'s time_offset ({tau * 1e3:.1f} ± "
                     f"{std * 1e3:.1f} ms)" + (f"; the vehicle had {was:g} ms" if was is not None else "")
                     + " (reboot needed)")
    return out


def _k_gauss(entry: dict[str, Any], mag: MagCalibration) -> FloatArray | None:
    """The drift k (3) in gauss/degC, or None when its unit is not a field unit per degC."""
    unit = str((entry.get("units") or {}).get("k", f"{mag.unit}/degC")).split("/")[0].strip()
    try:
        canonical = units.canonical(unit)
    except StreamError:
        return None
    if canonical not in units.MAG_UNITS:
        return None
    k: FloatArray = np.asarray(entry["params"]["k"], dtype=np.float64).reshape(3)
    return k * units.to_si(canonical) * units.from_si("gauss")


def _tc_slot(dev: int, params: Mapping[str, float], taken: set[int]) -> int | None:
    """The TC_Mj slot whose ID is the device, else the first without an ID (None: all four hold other devices)."""
    ids = {j: int(params.get(f"TC_M{j}_ID", 0.0)) for j in TC_SLOTS}
    match = [j for j in TC_SLOTS if ids[j] == dev]
    if match:
        return match[0]
    free = [j for j in TC_SLOTS if ids[j] == 0 and j not in taken]
    return free[0] if free else None


def thermal(cal: Calibration, slots: Sequence[tuple[MagCalibration, int]], params: Mapping[str, float]) -> Extras:
    """TC_M_ENABLE and TC_Mj_* of every exported magnetometer that carries a temperature drift."""
    out = Extras()
    taken: set[int] = set()
    for mag, _ in slots:
        entry = carried(cal, mag.id, "temperature_drift")
        if entry is None:
            continue
        p = entry.get("params") or {}
        dev = int(params.get(f"{mag.id}.device_id", 0.0))
        k = _k_gauss(entry, mag)
        why = ("the document has no T_min/T_max (fitted before magcal recorded the temperature range; fit again)"
               if "T_min" not in p or "T_max" not in p else
               "its units.k is not a field unit per degC" if k is None else
               "its device id is unknown (TC_Mj_ID must name it; log sensor_mag with device_id)" if not dev else "")
        j = None if why else _tc_slot(dev, params, taken)
        if not why and j is None:
            why = "all four TC_Mj slots hold other devices"
        if why or k is None or j is None:
            out.warnings.append(f"{mag.id}: temperature_drift not exported to TC_M*: {why}")
            continue
        taken.add(j)
        q = f"TC_M{j}_"
        out.params |= {f"{q}ID": float(dev), f"{q}TREF": float(p["T0"]), f"{q}TMIN": float(p["T_min"]),
                       f"{q}TMAX": float(p["T_max"])}
        for i in range(3):
            out.params |= {f"{q}X0_{i}": 0.0, f"{q}X1_{i}": float(k[i]), f"{q}X2_{i}": 0.0, f"{q}X3_{i}": 0.0}
        out.integers.add(f"{q}ID")
        out.notes.append(f"{mag.id}: temperature drift -> {q}* (TREF {p['T0']:.2f} degC, clamped by the firmware to "
                         f"the log's {p['T_min']:.2f}..{p['T_max']:.2f} degC)")
        chans = [str(c) for c in entry.get("channels") or []]
        if chans and mag.id not in chans:
            out.notes.append(f"{mag.id}: the drift was fitted against {', '.join(chans)}; PX4 compensates with the "
                             "magnetometer's own temperature (sensor_mag.temperature)")
    if out.params:
        out.params["TC_M_ENABLE"] = 1.0
        out.integers.add("TC_M_ENABLE")
        out.notes.append("TC_M_ENABLE = 1 turns magnetometer thermal compensation on (reboot needed); other TC_Mj "
                         "slots keep the vehicle's values")
    return out


#: ArduPilot's EKF3 assumes a fixed magnetometer delay (AP_NavEKF3_core.h `const uint16_t magDelay_ms = 60`) [S35]
AP_MAG_DELAY_MS = 60.0


def not_held(cal: Calibration, mags: Sequence[MagCalibration], firmware: str) -> list[str]:
    """What an export leaves out for want of a parameter: on ArduPilot a lag (EKF3's delay is a constant) and a
    temperature drift (no compass thermal compensation); on PX4 per-motor fields (no per-motor compensation)."""
    if firmware == "px4":
        return [f"{m.id}: its per-motor interference is not exported: PX4 has no per-motor compass compensation"
                for m in mags if carried(cal, m.id, "motor_interference") is not None]
    notes = []
    for mag in mags:
        if (e := carried(cal, mag.id, "time_offset")) is not None:
            notes.append(f"{mag.id}: its {_lag(e)[0] * 1e3:.1f} ms lag is not exported: ArduPilot's EKF3 assumes a "
                         f"fixed {AP_MAG_DELAY_MS:.0f} ms magnetometer delay and has no parameter for it")
        if carried(cal, mag.id, "temperature_drift") is not None:
            notes.append(f"{mag.id}: its temperature drift is not exported: ArduPilot has no compass thermal "
                         "compensation parameters")
    return notes


def pmot(cal: Calibration, mag: MagCalibration, suffix: str, held: FloatArray, k: float,
         params: Mapping[str, float]) -> tuple[dict[str, float], set[str], list[str], list[str]]:
    """COMPASS_PMOT_EN/EXP/PMOTn_X.. of a carried `motor_interference`: the firmware adds
    sum_n PMOTn (u_n V)^EXP after the iron matrix, to the first compass only (AP_Compass_Backend correct_field,
    Compass_PerMotor::compensate [S3][S7]), so PMOTn = -A_fw c_n in mGauss (A_fw = `held`, c_n in the document's unit
    times `k`), the sign and frame of COMPASS_MOT. Returns (parameters, integer names, notes, what is not held)."""
    entry = carried(cal, mag.id, "motor_interference")
    if entry is None:
        return {}, set(), [], []
    if suffix != "":
        return {}, set(), [], [f"{mag.id}: its per-motor interference is not exported: ArduPilot's per-motor "
                               "compensation applies to the first compass (COMPASS_*, slot 1) only"]
    if params and "COMPASS_PMOT_EN" not in params:
        return {}, set(), [], [f"{mag.id}: its per-motor interference is not exported: this firmware has no "
                               "per-motor compass compensation (no COMPASS_PMOT_EN in its parameters; added in "
                               "ArduCopter 3.6)"]
    p = entry["params"]
    out = {"COMPASS_PMOT_EN": 1.0, "COMPASS_PMOT_EXP": float(p.get("expo", 0.65))}
    for n in range(1, 5):
        v = -held @ (np.asarray(p[f"c{n}"], dtype=np.float64) * k)
        out |= {f"COMPASS_PMOT{n}_{a}": float(v[i]) for i, a in enumerate(AXES)}
    notes = [f"{mag.id}: per-motor interference -> COMPASS_PMOT1..4 (COMPASS_PMOT_EN=1; the firmware then uses them "
             "instead of COMPASS_MOT for this compass); they assume its outputs scale as (PWM fraction x battery "
             "voltage)^COMPASS_PMOT_EXP (Compass_PerMotor.cpp of 3.6-4.x); newer variants read scale motor thrust by "
             "battery current: check the firmware's Compass_PerMotor before flying"]
    return out, {"COMPASS_PMOT_EN"}, notes, []


def extras(cal: Calibration, slots: Sequence[tuple[MagCalibration, int]], params: Mapping[str, float]) -> Extras:
    """Both: the delay and the thermal terms."""
    out = delay(cal, slots, params)
    out.absorb(thermal(cal, slots, params))
    return out
