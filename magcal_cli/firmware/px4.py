"""PX4 magnetometer calibration parameters (CAL_MAGn_*, CAL_MAG_COMP_TYP) from a calibration.

PX4's correction (firmware-export.md section 2, Magnetometer.cpp [S16]) on the raw sensor_mag reading in gauss:
m_body = R S ((raw + P COMP) - OFF), R = Dcm(Euler(SENS_BOARD_X/Y/Z_OFF)) rot(CAL_MAGn_ROT) for an external
magnetometer, rot(SENS_BOARD_ROT) in place of rot(CAL_MAGn_ROT) for an internal one (CAL_MAGn_ROT = -1). For a
magcal calibration b = A (y - o - c p): S = sym(R^T A), OFF = o, COMP = -c (G/kA for current) (section 3).
The slot n is the one whose CAL_MAGn_ID is the sensor's device id.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.firmware import FirmwareError, NotExportableError, rotations
from magcal_cli.firmware.common import (
    Collected,
    Export,
    MagExport,
    Options,
    check_limits,
    correction,
    determined,
    select_mags,
    shared_signal,
    soft_range,
)
from magcal_cli.firmware.effects import carried
from magcal_cli.firmware.extras import extras, not_held
from magcal_cli.firmware.split import choose_rotation, split_symmetric_first
from magcal_cli.streams import FloatArray

UNIT = "gauss"
SLOTS = range(4)
AXES = "XYZ"
#: CAL_MAGn_xSCALE min/max of module.yaml [S20]
SCALE_LIMITS = (0.1, 3.0)
#: mag_calibration warns above this offset (gauss) [S18]
OFF_WARN = 1.3
#: ROTATION_CUSTOM == MAV_SENSOR_ROTATION_CUSTOM (static_assert in PX4's mavlink_messages.cpp)
CUSTOM = 100
#: current in battery_status is in A; COMP is per kA (P = current_a / 1000) [S16]
KILO = 1000.0


def level(params: Mapping[str, float]) -> FloatArray:
    """Dcm(Euler(SENS_BOARD_X_OFF, _Y_OFF, _Z_OFF)), the board levelling rotation (degrees in the parameters)."""
    return so3.from_rpy(np.deg2rad([params.get(f"SENS_BOARD_{a}_OFF", 0.0) for a in AXES]))


def rotation_of(params: Mapping[str, float], n: int) -> FloatArray:
    """R of slot n as the firmware builds it (board rotation for internal magnetometers)."""
    rot = int(params.get(f"CAL_MAG{n}_ROT", -1))
    if rot == CUSTOM:
        inner = so3.from_rpy(np.deg2rad([params.get(f"CAL_MAG{n}_{a}", 0.0) for a in ("ROLL", "PITCH", "YAW")]))
    elif rot < 0:
        inner = rotations.matrix("px4", int(params.get("SENS_BOARD_ROT", 0)))
    else:
        inner = rotations.matrix("px4", rot)
    return level(params) @ inner


def slot_of(mag_id: str, position: int, params: Mapping[str, float], requested: int | None
            ) -> tuple[int, int | None, list[str]]:
    """(slot n, device id or None, notes): the CAL_MAGn_ID that is the sensor's device id [S17][S21]."""
    dev = int(params[f"{mag_id}.device_id"]) if params.get(f"{mag_id}.device_id") else None
    ids = {n: int(params[f"CAL_MAG{n}_ID"]) for n in SLOTS if f"CAL_MAG{n}_ID" in params}
    if requested is not None:
        if requested not in SLOTS:
            msg = f"export: --slot {requested} does not exist; PX4 has magnetometer slots 0 to 3"
            raise FirmwareError(msg)
        if dev and ids.get(requested) not in (None, 0, dev):
            msg = (f"export: --slot {requested} holds CAL_MAG{requested}_ID={ids[requested]}, but {mag_id} is "
                   f"device_id {dev}. Drop --slot to write to the slot that holds it")
            raise FirmwareError(msg)
        return requested, dev, []
    if dev:
        match = [n for n, v in ids.items() if v == dev]
        if match:
            return match[0], dev, []
        free = [n for n in SLOTS if not ids.get(n)]
        if not free:
            msg = (f"export: {mag_id} (device_id {dev}) has no CAL_MAGn_ID and all four slots are taken. "
                   "Pass --slot to overwrite one")
            raise FirmwareError(msg)
        return free[0], dev, [f"{mag_id}: device_id {dev} had no calibration slot; CAL_MAG{free[0]}_ID is set"]
    m = re.fullmatch(r"sensor_mag\[(\d)\]", mag_id)
    n = int(m.group(1)) if m else position
    if n not in SLOTS:
        msg = f"export: {mag_id} would need slot {n}; PX4 has slots 0 to 3. Use --mag and --slot"
        raise FirmwareError(msg)
    return n, None, [f"{mag_id}: no device id known, so slot {n} is assumed (the log index need not be the "
                     "calibration slot); check CAL_MAGn_ID or pass --slot"]


def _rotation_why(external: bool, kind: str, params: Mapping[str, float], options: Options, p: str) -> str:
    """Why a misalignment stays in the residual: the reason PX4 cannot take a custom rotation here."""
    if not external:
        return (f"an internal magnetometer ({p}ROT=-1) takes the board's SENS_BOARD_ROT, so its misalignment to the "
                "IMU cannot be exported; use an external magnetometer or SENS_BOARD_X/Y/Z_OFF for the whole board")
    if kind == "custom":
        return ""
    if options.rotation == "enum":
        return f"--rotation enum asked for the nearest {p}ROT value"
    if f"{p}ROLL" not in params:
        return (f"custom Euler angles need a PX4 version with {p}ROLL/PITCH/YAW (newer PX4 releases); this vehicle's "
                f"parameters have none, so the nearest {p}ROT enum is written")
    return ""


def _export_one(cal: Calibration, mag: MagCalibration, position: int, params: Mapping[str, float],
                options: Options) -> tuple[MagExport, set[str], str | None]:
    """One magnetometer: its parameters, the integer-valued names and the interference kind it needs."""
    if cal.source.format in ("ulog", "px4log") and not re.fullmatch(r"sensor_mag\[\d\]", mag.id):
        msg = (f"export {mag.id} (PX4): this field was already corrected by the firmware (no raw sensor_mag in the "
               "log), so its calibration is relative to the parameters flown and cannot be written as CAL_MAG "
               "parameters. Log sensor_mag (SDLOG_PROFILE) and calibrate again")
        raise NotExportableError(msg)
    n, dev, notes = slot_of(mag.id, position, params, options.slot)
    A, o, k = correction(mag, UNIT)
    p = f"CAL_MAG{n}_"
    if f"{p}ROT" in params:
        external = params[f"{p}ROT"] >= 0
    else:
        external = bool(options.external)
        notes.append(f"{mag.id}: {p}ROT unknown; treated as {'external' if external else 'internal'} "
                     "(--external/--internal)")
    lev = level(params)
    wanted = lev.T @ so3.polar(A)[0]
    custom_ok = options.rotation != "enum" and f"{p}ROLL" in params
    if external and options.rotation == "custom" and not custom_ok:
        msg = (f"export: {mag.id}: --rotation custom needs a PX4 version with {p}ROLL/PITCH/YAW (absent from the "
               "vehicle parameters); use --rotation enum")
        raise FirmwareError(msg)
    board = rotations.matrix("px4", int(params.get("SENS_BOARD_ROT", 0)))
    rot = choose_rotation("px4", wanted, fixed=None if external else board, custom=custom_ok,
                          custom_above_deg=0.0 if options.rotation == "custom" else options.custom_above_deg)
    sp = split_symmetric_first(A, lev @ rot.matrix, rot, wanted)
    s = sp.symmetric
    out: dict[str, float] = {}
    for i, a in enumerate(AXES):
        out[f"{p}{a}OFF"] = float(o[i])
        out[f"{p}{a}SCALE"] = float(s[i, i])
    for (i, j), a in zip(((0, 1), (0, 2), (1, 2)), AXES, strict=True):
        out[f"{p}{a}ODIAG"] = float(s[i, j])
    integers = {f"{p}ROT"}
    rot_value = {"enum": rot.enum_id, "custom": CUSTOM}.get(rot.kind)
    out[f"{p}ROT"] = float(-1 if rot_value is None else rot_value)
    if rot.kind == "custom":
        out |= {f"{p}{ax}": v for ax, v in zip(("ROLL", "PITCH", "YAW"), rot.rpy_deg or (), strict=True)}
        notes.append(f"{mag.id}: the nearest rotation enum misses by {rot.enum_residual_deg:.2f} deg; custom Euler "
                     f"angles {p}ROLL/PITCH/YAW used")
    elif f"{p}ROLL" in params:          # non-zero custom angles would force ROT to custom [S16b]
        out |= {f"{p}{ax}": 0.0 for ax in ("ROLL", "PITCH", "YAW")}
    if dev:
        out[f"{p}ID"] = float(dev)
        integers.add(f"{p}ID")
    kind = None
    inter, inter_notes = carried(cal, mag)
    notes += inter_notes
    if inter is not None:
        comp = -inter.c * k * (KILO if inter.kind == "current" else 1.0)
        out |= {f"{p}{a}COMP": float(comp[i]) for i, a in enumerate(AXES)}
        kind = inter.kind
    errors = [f"{mag.id}: {p}{a}SCALE = {s[i, i]:.4g} is outside {SCALE_LIMITS[0]:g}..{SCALE_LIMITS[1]:g} "
              "(CAL_MAGn_xSCALE range); check the field strength and the fit"
              for i, a in enumerate(AXES) if not SCALE_LIMITS[0] <= s[i, i] <= SCALE_LIMITS[1]]
    check_limits(f"export {mag.id} (PX4)", errors)
    warnings = [f"{mag.id}: {w}" for i, a in enumerate(AXES)
                for w in soft_range(f"{p}{a}OFF", o[i], -OFF_WARN, OFF_WARN, "PX4's calibration warns")]
    exp = MagExport(mag.id, f"CAL_MAG{n}_*", out, sp, mag.dip_deg, external, tuple(notes), tuple(warnings),
                    _rotation_why(external, rot.kind, params, options, p))
    return exp, integers, kind


def export_px4(cal: Calibration, params: Mapping[str, float], options: Options | None = None,
               mag_ids: Sequence[str] | None = None) -> Export:
    """CAL_MAGn_* parameters of the selected magnetometers; COMP and CAL_MAG_COMP_TYP from accepted effects;
    EKF2_MAG_DELAY and TC_M* from a carried time offset and temperature drift (firmware/extras.py)."""
    options = options or Options()
    mags = select_mags(cal, mag_ids, options)
    acc = Collected()
    kinds: dict[str, str] = {}
    slots: dict[str, int] = {}
    for i, mag in enumerate(mags):
        try:
            exp, integers, kind = _export_one(cal, mag, i, params, options)
        except NotExportableError as exc:
            if not options.skip_refused or len(mags) == 1:
                raise
            acc.warnings.append(f"{mag.id} not exported: {exc}")
            continue
        n = int(exp.slot[7])
        if n in slots.values():
            msg = (f"export: {mag.id} and {[m for m, s in slots.items() if s == n][0]} map to slot {n}; export them "
                   "one at a time with --mag and --slot")
            raise FirmwareError(msg)
        slots[mag.id] = n
        acc.add(determined(exp, mag), integers)
        if kind:
            kinds[mag.id] = kind
    acc.require_any()
    if kinds:
        kind = shared_signal(kinds)
        for mag_id, n in slots.items():
            if kinds.get(mag_id) != kind:
                acc.params |= {f"CAL_MAG{n}_{a}COMP": 0.0 for a in AXES}
        acc.params["CAL_MAG_COMP_TYP"] = 2.0 if kind == "current" else 1.0   # 2 = current of battery 0
        acc.integers.add("CAL_MAG_COMP_TYP")
    else:
        acc.notes.append("no accepted current or throttle interference in the document: CAL_MAGn_xCOMP and "
                         "CAL_MAG_COMP_TYP are left as the vehicle has them")
    acc.absorb(extras(cal, [(cal.magnetometer(m.mag_id), int(m.slot[7])) for m in acc.mags], params))
    acc.not_held += not_held(cal, [cal.magnetometer(m.mag_id) for m in acc.mags], "px4")
    if any(k.startswith("SENS_MAG0_") for k in params):
        acc.notes.append("this PX4 keeps rotations in SENS_MAGn_* configuration parameters; magcal writes the "
                         "CAL_MAGn_* layout, so set the rotation there by hand")
    return Export("px4", tuple(acc.mags), acc.params, frozenset(acc.integers), tuple(acc.notes),
                  tuple(acc.warnings), cal.source.path, tuple(acc.not_held))


def correct(raw: FloatArray, params: Mapping[str, float], n: int, signal: FloatArray | None) -> FloatArray:
    """PX4's Magnetometer correction of raw sensor_mag readings (N, 3) gauss with slot n (for `check`).

    `signal` is throttle (0..1, CAL_MAG_COMP_TYP 1) or current (A, types 2 and 3; converted to kA here).
    """
    p = f"CAL_MAG{n}_"
    off = np.array([params.get(f"{p}{a}OFF", 0.0) for a in AXES])
    d = [params.get(f"{p}{a}SCALE", 1.0) for a in AXES]
    od = [params.get(f"{p}{a}ODIAG", 0.0) for a in AXES]
    s = np.array([[d[0], od[0], od[1]], [od[0], d[1], od[2]], [od[1], od[2], d[2]]])
    comp = np.array([params.get(f"{p}{a}COMP", 0.0) for a in AXES])
    typ = int(params.get("CAL_MAG_COMP_TYP", 0))
    x = np.asarray(raw, dtype=np.float64)
    if typ in (1, 2, 3) and signal is not None:
        x = x + (signal / (KILO if typ >= 2 else 1.0))[:, None] * comp
    out: FloatArray = (x - off) @ s.T @ rotation_of(params, n).T
    return out
