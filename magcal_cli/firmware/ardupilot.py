"""ArduPilot compass parameters (COMPASS_OFS/DIA/ODI/SCALE/ORIENT/MOT, CUST_ROT) from a calibration.

correct_field (firmware-export.md section 1, AP_Compass_Backend.cpp [S3]) works on the body-frame field after
rotate_field: x = raw + OFS; x *= SCALE (only within 0.85..1.4); x = M x; x += MOT * signal (after M). For a
magcal calibration b = A (y - o - c p): with the orientation change V (new COMPASS_ORIENT times the flown one's
inverse; identity for internal compasses, whose rotation AHRS_ORIENTATION fixes), SCALE x M = sym(A V^T),
OFS = -V o, MOT = -A_fw c (section 3).
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
from magcal_cli.firmware.extras import not_held, pmot
from magcal_cli.firmware.split import choose_rotation, split_rotation_first
from magcal_cli.readers.dataflash.compass import correct_field, effective_scale, iron_matrix, param_suffix
from magcal_cli.streams import FloatArray

UNIT = "milligauss"
SUFFIXES = ("", "2", "3")
EXTERNAL = {"": "COMPASS_EXTERNAL", "2": "COMPASS_EXTERN2", "3": "COMPASS_EXTERN3"}
AXES = "XYZ"
#: COMPASS_OFFS_MAX default of the version read [S4]; the pre-arm check compares |OFS| with it
OFFS_MAX_DEFAULT = 1800.0
#: the onboard calibrator's acceptance of a fit (CompassCalibrator.cpp [S1]): 0.2 < DIA < 5, |ODI| < 1
DIA_LIMITS = (0.2, 5.0)
ODI_LIMIT = 1.0
#: SCALE is applied only within 0.85..1.4 (have_scale_factor [S4]); its documented range ends at 1.3
SCALE_CHOICE = (0.85, 1.3)
#: COMPASS_ORIENT values that select custom rotations: 100 = 4.1-and-older COMPASS_CUS_*, 101/102 = CUST_ROTn
CUSTOM_OLD, CUSTOM_1 = 100, 101


def suffix_of(slot: int) -> str:
    """Parameter suffix of slot 1..3: "", "2", "3"."""
    return SUFFIXES[slot - 1]


def orientation(params: Mapping[str, float], value: float) -> FloatArray:
    """The matrix of a COMPASS_ORIENTn / AHRS_ORIENTATION value, custom rotations included [S10]."""
    v = int(value)
    names: tuple[str, ...]
    if v == CUSTOM_OLD:
        names = ("COMPASS_CUS_ROLL", "COMPASS_CUS_PIT", "COMPASS_CUS_YAW")
    elif v in (CUSTOM_1, CUSTOM_1 + 1):
        names = tuple(f"CUST_ROT{v - 100}_{a}" for a in ("ROLL", "PITCH", "YAW"))
    else:
        return rotations.matrix("ardupilot", v)
    return so3.from_rpy(np.deg2rad([params.get(n, 0.0) for n in names]))


def _slot(mag_id: str, position: int, params: Mapping[str, float], requested: int | None) -> tuple[str, list[str]]:
    """The parameter suffix for a magnetometer, checked against COMPASS_PRIOn_ID / COMPASS_DEV_IDn."""
    m = re.fullmatch(r"MAG\[(\d)\]", mag_id)
    inst = int(m.group(1)) if m else None
    if requested is not None:
        if not 1 <= requested <= 3:
            msg = f"export: --slot {requested} does not exist; ArduPilot has compass slots 1, 2 and 3"
            raise FirmwareError(msg)
        suffix = suffix_of(requested)
        prio_name = f"COMPASS_PRIO{inst + 1}_ID" if inst is not None else ""
        prio, dev = params.get(prio_name, 0.0), params.get(f"COMPASS_DEV_ID{suffix}")
        if prio and dev is not None and dev != prio:
            msg = (f"export: --slot {requested} holds COMPASS_DEV_ID{suffix}={dev:.0f}, but {mag_id} is the device "
                   f"{prio_name}={prio:.0f}. Drop --slot to write to the slot that holds it")
            raise FirmwareError(msg)
        return suffix, []
    notes: list[str] = []
    if inst is None:
        inst = position
        notes.append(f"{mag_id}: not an ArduPilot compass id; written to slot {position + 1} "
                     f"(COMPASS_*{suffix_of(position + 1) if position < 3 else '?'}); use --slot to choose")
    if inst > 2:
        msg = f"export: {mag_id} would need compass slot {inst + 1}; ArduPilot has 3. Use --mag and --slot"
        raise FirmwareError(msg)
    suffix, note = param_suffix(inst, dict(params))
    return suffix, notes + ([note] if note else [])


def _custom_slots(params: Mapping[str, float], exported: set[str]) -> list[int]:
    """CUST_ROT slots (1, 2) not used by AHRS_ORIENTATION or by compasses this export leaves alone."""
    used = {int(params.get("AHRS_ORIENTATION", 0))}
    used |= {int(params.get(f"COMPASS_ORIENT{s}", 0)) for s in SUFFIXES if s not in exported}
    return [n for n in (1, 2) if CUSTOM_1 - 1 + n not in used]


def _limits(mag_id: str, suffix: str, p: dict[str, float], offs_max: float) -> list[str]:
    """Hard-limit violations of one compass's parameters (each names the parameter and the limit)."""
    errors = []
    ofs = np.array([p[f"COMPASS_OFS{suffix}_{a}"] for a in AXES])
    if np.linalg.norm(ofs) >= offs_max:
        errors.append(f"|COMPASS_OFS{suffix}| = {np.linalg.norm(ofs):.0f} mGauss is not below COMPASS_OFFS_MAX = "
                      f"{offs_max:.0f} (pre-arm 'compass offsets too high'); move the compass away from magnetised "
                      "parts or raise COMPASS_OFFS_MAX (up to 3000)")
    for a in AXES:
        dia, odi = p[f"COMPASS_DIA{suffix}_{a}"], p[f"COMPASS_ODI{suffix}_{a}"]
        if not DIA_LIMITS[0] < dia < DIA_LIMITS[1]:
            errors.append(f"COMPASS_DIA{suffix}_{a} = {dia:.4g} is outside {DIA_LIMITS[0]:g}..{DIA_LIMITS[1]:g} "
                          "(the firmware's own calibration rejects it); check the field strength and the fit")
        if not abs(odi) < ODI_LIMIT:
            errors.append(f"COMPASS_ODI{suffix}_{a} = {odi:.4g} is outside -1..1 (the firmware's own calibration "
                          "rejects it); check the fit")
    return [f"{mag_id}: {e}" for e in errors]


def _warnings(mag_id: str, suffix: str, p: dict[str, float]) -> list[str]:
    """Values outside the typical ranges WebTools MAGFit warns about [S15] (written anyway)."""
    out: list[str] = []
    for a in AXES:
        out += soft_range(f"COMPASS_OFS{suffix}_{a}", p[f"COMPASS_OFS{suffix}_{a}"], -1500, 1500, "large hard iron")
        out += soft_range(f"COMPASS_DIA{suffix}_{a}", p[f"COMPASS_DIA{suffix}_{a}"], 0.8, 1.2, "large soft iron")
        out += soft_range(f"COMPASS_ODI{suffix}_{a}", p[f"COMPASS_ODI{suffix}_{a}"], -0.2, 0.2, "large soft iron")
        if f"COMPASS_MOT{suffix}_{a}" in p:
            out += soft_range(f"COMPASS_MOT{suffix}_{a}", p[f"COMPASS_MOT{suffix}_{a}"], -1000, 1000,
                              "documented range")
    return [f"{mag_id}: {w}" for w in out]


def _rotation_why(external: bool, kind: str, params: Mapping[str, float], options: Options, free: bool,
                  suffix: str) -> str:
    """Why a misalignment stays in the residual: the reason ArduPilot cannot take a custom rotation here."""
    if not external:
        return ("an internal compass takes the board's AHRS_ORIENTATION, and COMPASS_ORIENT applies to external "
                "compasses only, so its misalignment to the IMU cannot be exported; mount the board square or use "
                "an external compass")
    if kind == "custom":
        return ""
    if options.rotation == "enum":
        return "--rotation enum asked for the nearest COMPASS_ORIENT value"
    if not params:
        return "no vehicle parameters, so no custom rotation (pass --params with the vehicle's parameters)"
    if "CUST_ROT_ENABLE" not in params:
        return (f"custom rotations need ArduPilot 4.3 or newer (CUST_ROT_ENABLE, then COMPASS_ORIENT{suffix}=101); "
                "this vehicle's parameters have none, so the nearest orientation enum is written")
    if not free:
        return "both custom rotations CUST_ROT1/2 are used by AHRS_ORIENTATION or other compasses"
    return ""


def _export_one(cal: Calibration, mag: MagCalibration, position: int, params: Mapping[str, float],
                options: Options, custom_free: list[int]) -> tuple[MagExport, set[str], str | None]:
    """One compass: its parameters, the integer-valued names and the interference kind it needs."""
    known = bool(params)
    suffix, notes = _slot(mag.id, position, params, options.slot)
    A, o, k = correction(mag, UNIT)
    ext_name = EXTERNAL[suffix]
    if ext_name in params:
        external = params[ext_name] >= 1
    else:
        external = bool(options.external)
        notes.append(f"{mag.id}: {ext_name} unknown; treated as {'external' if external else 'internal'} "
                     "(--external/--internal)")
    flown = orientation(params, params.get(f"COMPASS_ORIENT{suffix}", 0.0)) if external else np.eye(3)
    wanted = so3.polar(A)[0] @ flown                                   # the new absolute orientation
    custom_ok = options.rotation != "enum" and "CUST_ROT_ENABLE" in params and bool(custom_free)
    if external and options.rotation == "custom" and not custom_ok:
        msg = (f"export: {mag.id}: --rotation custom needs ArduPilot 4.3 or newer with a free CUST_ROT slot "
               "(CUST_ROT_ENABLE in the vehicle parameters); use --rotation enum")
        raise FirmwareError(msg)
    threshold = 0.0 if options.rotation == "custom" else options.custom_above_deg
    rot = choose_rotation("ardupilot", wanted, fixed=None if external else flown, custom=custom_ok,
                          custom_above_deg=threshold)
    effective = rot.matrix @ flown.T if external else np.eye(3)
    sp = split_rotation_first(A, effective, rot, wanted)
    out: dict[str, float] = {}
    integers: set[str] = set()
    has_scale = f"COMPASS_SCALE{suffix}" in params or not known
    s = float(np.clip(np.mean(np.diag(sp.symmetric)), *SCALE_CHOICE)) if f"COMPASS_SCALE{suffix}" in params else 1.0
    m = sp.symmetric / s
    ofs = -effective @ o
    for i, a in enumerate(AXES):
        out[f"COMPASS_OFS{suffix}_{a}"] = float(ofs[i])
        out[f"COMPASS_DIA{suffix}_{a}"] = float(m[i, i])
    for (i, j), a in zip(((0, 1), (0, 2), (1, 2)), AXES, strict=True):
        out[f"COMPASS_ODI{suffix}_{a}"] = float(m[i, j])
    if has_scale:
        out[f"COMPASS_SCALE{suffix}"] = s
    if external:
        if rot.kind == "custom":
            n = custom_free.pop(0)
            out[f"COMPASS_ORIENT{suffix}"] = CUSTOM_1 - 1 + n
            out["CUST_ROT_ENABLE"] = 1
            out |= {f"CUST_ROT{n}_{ax}": v for ax, v in zip(("ROLL", "PITCH", "YAW"), rot.rpy_deg or (), strict=True)}
            integers |= {"CUST_ROT_ENABLE"}
            notes.append(f"{mag.id}: the nearest orientation enum misses by {rot.enum_residual_deg:.2f} deg; "
                         f"custom rotation CUST_ROT{n} used: COMPASS_ORIENT{suffix}={CUSTOM_1 - 1 + n:.0f} selects "
                         "it and CUST_ROT_ENABLE=1 enables it (reboot needed)")
        else:
            out[f"COMPASS_ORIENT{suffix}"] = float(rot.enum_id)  # type: ignore[arg-type]
        integers.add(f"COMPASS_ORIENT{suffix}")
    kind = None
    inter, inter_notes = carried(cal, mag)
    notes += inter_notes
    if inter is not None:
        mot = -sp.held @ (inter.c * k)
        out |= {f"COMPASS_MOT{suffix}_{a}": float(mot[i]) for i, a in enumerate(AXES)}
        kind = inter.kind
    per_motor, per_motor_ints, per_motor_notes, lost = pmot(cal, mag, suffix, sp.held, k, params)
    out |= per_motor
    integers |= per_motor_ints
    notes += per_motor_notes
    warnings = _warnings(mag.id, suffix, out)
    offs_max = params.get("COMPASS_OFFS_MAX", OFFS_MAX_DEFAULT)
    check_limits(f"export {mag.id} (ArduPilot)", _limits(mag.id, suffix, out, offs_max))
    exp = MagExport(mag.id, f"COMPASS_*{suffix}", out, sp, mag.dip_deg, external, tuple(notes), tuple(warnings),
                    _rotation_why(external, rot.kind, params, options, bool(custom_free), suffix), tuple(lost))
    return exp, integers, kind


def export_ardupilot(cal: Calibration, params: Mapping[str, float], options: Options | None = None,
                     mag_ids: Sequence[str] | None = None) -> Export:
    """COMPASS_* parameters of the selected magnetometers; MOT* and MOTCT from the interference effects the
    calibration carries (firmware/effects.py)."""
    options = options or Options()
    mags = select_mags(cal, mag_ids, options)
    suffixes = {_slot(m.id, i, params, options.slot)[0] for i, m in enumerate(mags)}
    if len(suffixes) != len(mags):
        msg = (f"export: {', '.join(m.id for m in mags)} map to the same compass slot; export them one at a time "
               "with --mag and --slot")
        raise FirmwareError(msg)
    custom_free = _custom_slots(params, suffixes)
    acc = Collected()
    kinds: dict[str, str] = {}
    for i, mag in enumerate(mags):
        try:
            exp, integers, kind = _export_one(cal, mag, i, params, options, custom_free)
        except NotExportableError as exc:
            if not options.skip_refused or len(mags) == 1:
                raise
            acc.warnings.append(f"{mag.id} not exported: {exc}")
            continue
        acc.add(determined(exp, mag), integers)
        if kind:
            kinds[mag.id] = kind
    acc.require_any()
    if kinds:
        kind = shared_signal(kinds)
        dropped = [m for m, k in kinds.items() if k != kind]
        for e in acc.mags:                        # MOTCT is global: every compass uses the same signal [S15]
            sfx = e.slot.removeprefix("COMPASS_*")
            if e.mag_id in dropped or e.mag_id not in kinds:
                acc.params |= {f"COMPASS_MOT{sfx}_{a}": 0.0 for a in AXES}
        if dropped:
            acc.notes.append(f"{', '.join(dropped)}: {'throttle' if kind == 'current' else 'current'} interference "
                             f"not exported; COMPASS_MOTCT is one signal for all compasses and more of them need "
                             f"{kind}")
        acc.params["COMPASS_MOTCT"] = 2.0 if kind == "current" else 1.0
        acc.integers.add("COMPASS_MOTCT")
    else:
        acc.notes.append("no accepted current or throttle interference in the document: COMPASS_MOT* and "
                         "COMPASS_MOTCT are left as the vehicle has them")
    acc.not_held += not_held(cal, [cal.magnetometer(m.mag_id) for m in acc.mags], "ardupilot")
    if not params:
        acc.notes.append("no vehicle parameters: slots from the magnetometer ids, COMPASS_SCALE written as 1, "
                         "no custom rotations (pass --params with the vehicle's parameter file or its log)")
    return Export("ardupilot", tuple(acc.mags), acc.params, frozenset(acc.integers), tuple(acc.notes),
                  tuple(acc.warnings), cal.source.path, tuple(acc.not_held))


def correct(raw: FloatArray, params: Mapping[str, float], suffix: str, signal: FloatArray | None) -> FloatArray:
    """correct_field of body-frame raw readings (N, 3) mGauss with the slot's parameters (for `check`).

    `signal` is throttle (0..1) or current (A) at the samples, as COMPASS_MOTCT selects; MOT is added after M.
    """
    def vec(stem: str) -> FloatArray:
        return np.array([[params.get(f"COMPASS_{stem}{suffix}_{a}", 0.0) for a in AXES]])

    m = iron_matrix(vec("DIA"), vec("ODI"))[0]
    scale = float(effective_scale(np.array([params.get(f"COMPASS_SCALE{suffix}", 0.0)]))[0])
    motct = int(params.get("COMPASS_MOTCT", 0))
    motor = signal[:, None] * vec("MOT") if motct in (1, 2) and signal is not None else None
    return correct_field(raw, vec("OFS"), scale, m, motor)
