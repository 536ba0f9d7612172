"""The raw field of each ArduPilot compass: the logged (corrected) field with the correction in force undone.

The correction itself (iron matrix, offsets, motor compensation) and the evidence for int16 truncation are in
`compass`; here the MAG records are selected, timed and scaled, and each compass's correction is undone.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magcal_cli.readers.checks import dead_field
from magcal_cli.readers.dataflash.compass import (
    ROUNDED_EVIDENCE,
    Correction,
    ParamHistory,
    compass_correction,
    motor_cast_evidence,
    motor_product,
    offset_cast_evidence,
    offsets_in_force,
    param_suffix,
    truncation_evidence,
    undo_correction,
)
from magcal_cli.readers.dataflash.format import RawLog, Table
from magcal_cli.readers.dataflash.load import MAG_NAMES
from magcal_cli.readers.dataflash.streams import Clock, instance_tag, instances, stack_columns, time_of
from magcal_cli.streams import FloatArray

Series = tuple[FloatArray, FloatArray]


def firmware_version(raw: RawLog) -> tuple[int, int] | None:
    """(major, minor) from the VER record or a MSG banner such as 'APM:Copter V3.3-dev'."""
    ver = raw.table("VER")
    if ver is not None and ver.fmt.has("Maj", "Min"):
        return int(ver.num("Maj")[0]), int(ver.num("Min")[0])
    msgs = raw.table("MSG")
    for text in msgs.text("Message") if msgs is not None and msgs.fmt.has("Message") else []:
        m = re.search(r"\bV(\d+)\.(\d+)", text)
        if m:
            return int(m.group(1)), int(m.group(2))
    return None


def _raw_resolution(corr: Correction, count: float) -> FloatArray | None:
    """Quantisation std per raw axis (mG): one count's uniform error (count/sqrt 12) through the undone matrix."""
    if not len(corr.scale):
        return None
    i = len(corr.scale) // 2
    inv = np.linalg.inv(corr.matrix[i]) / corr.scale[i]
    out: FloatArray = count / np.sqrt(12.0) * np.sqrt(np.sum(inv**2, axis=1))
    return out


def _mag_factor(table: Table) -> float:
    """Logged field to milligauss: FMTU says Gauss times 1e-3; old logs mean mGauss by convention."""
    unit, mult = table.fmt.units.get("MagX", ""), table.fmt.mults.get("MagX")
    if unit in ("G", "Gauss") and mult:
        return mult * 1000.0
    return 1.0


def _interp(t: FloatArray, series: Series | None) -> FloatArray | None:
    """A (t, v) series linearly interpolated at t (held at the ends), or None."""
    if series is None or series[0].size == 0:
        return None
    order = np.argsort(series[0], kind="stable")
    return np.interp(t, series[0][order], series[1][order])


def sample_time(time_us: FloatArray, s_us: FloatArray) -> FloatArray:
    """Seconds of MAG.S, unwrapped against TimeUS; TimeUS where S is unset or more than 1 s older."""
    delay = np.mod(time_us - s_us, 2.0**32)
    return np.where((s_us > 0) & (delay < 1e6), time_us - delay, time_us) * 1e-6


@dataclass(frozen=True, eq=False)
class MagReconstruction:
    """One compass: times (s, boot clock), logged and reconstructed raw field (N, 3) mG, the correction."""

    instance: int
    source: str
    t: FloatArray
    logged: FloatArray
    raw: FloatArray
    correction: Correction
    notes: tuple[str, ...]
    resolution: FloatArray | None = None      # per-axis quantisation std of `raw` (mG), integer fields only
    #: why the compass measures no field as logged (checks.dead_field, Health 0 throughout); then `raw` is `logged`
    dead: str | None = None


def reconstruct(path: Path, raw: RawLog, clock: Clock, hist: ParamHistory,
                throttle: Series | None, current: Series | None, rotated: bool = False) -> list[MagReconstruction]:
    """Every logged compass with the firmware correction in force at each sample undone; a dead or stuck one
    (judged on the field as logged; `rotated`: the IMU shows the vehicle turning) as logged, with why."""
    version = firmware_version(raw)
    after = version is None or version >= (3, 6)
    params = hist.last()
    out: list[MagReconstruction] = []
    bad_instances: list[str] = []
    found = [(i, tb) for i, tb in instances(raw, MAG_NAMES, notes=bad_instances, limit=3)
             if tb.fmt.has("MagX", "MagY", "MagZ")]
    compasses = [_compass(inst, table, clock, rotated) for inst, table in found]
    # a dead compass's zeros would read as a pile-up in the zero bin: its cast is not evidence
    truncated, cast = _int16_cast([c for c in compasses if c.dead is None], hist, throttle, current)
    for c in compasses:
        if c.dead is not None:
            # undoing the correction would add COMPASS_MOT x current and the offsets back to a field that is not
            # there, and turn a dead sensor into a varying one the pipeline would calibrate (issue 38)
            src = f"{path.name}#{c.table.fmt.name}{instance_tag(c.table.fmt, c.inst)}.MagX/MagY/MagZ (as logged)"
            notes = [*c.notes, f"MAG[{c.inst}]: dead or stuck as logged ({c.dead}); the firmware correction was "
                     "not undone"]
            out.append(MagReconstruction(c.inst, src, c.t, c.logged, c.logged, _no_correction(len(c.t)),
                                         tuple(bad_instances * (not out) + notes), None, c.dead))
            continue
        inst, table, t, notes = c.inst, c.table, c.t, list(c.notes)
        f, k, logged = table.fmt, c.factor, c.logged
        field = logged
        if c.integer and truncated:
            # AP_Compass logs (int16_t)field: the cast truncates toward zero, so the field was on average half
            # a count further out; left in, it shrinks D by ~0.5 count / |field| (0.2 % at 270 mG)
            field = logged + 0.5 * k * np.sign(logged)
            notes.append(f"MAG[{inst}]: added back half a count ({0.5 * k:g} mG) lost to the firmware's int16 "
                         "truncation toward zero")
        elif c.integer:
            notes.append(f"MAG[{inst}]: the logged integers were rounded, not truncated as AP_Compass's cast does "
                         f"({cast}); no half count added back")
        suffix, slot_note = param_suffix(inst, params)
        corr, desc = compass_correction(hist, suffix, t, c.ofs, c.motor, after, _interp(t, throttle),
                                        _interp(t, current))
        ext = {"": "COMPASS_EXTERNAL", "2": "COMPASS_EXTERN2", "3": "COMPASS_EXTERN3"}[suffix]
        frame = (f"COMPASS_ORIENT{suffix}={params.get(f'COMPASS_ORIENT{suffix}', 0):.0f}" if params.get(ext)
                 else f"AHRS_ORIENTATION={params.get('AHRS_ORIENTATION', 0):.0f}")
        notes += [slot_note] if slot_note else []
        notes.append(f"MAG[{inst}]: undid the firmware correction of the logged field ({desc}); the raw "
                     f"field stays in the body frame ({frame} already applied by the firmware)")
        if not after and np.any(corr.motor != 0):
            notes.append(f"MAG[{inst}]: motor offsets undone before the iron matrix, where firmware "
                         f"{version[0]}.{version[1]} added them" if version else "")
        if version is None and np.any(corr.motor != 0):
            notes.append(f"MAG[{inst}]: firmware version unknown; motor offsets taken as added after the "
                         "iron matrix")
        src = f"{path.name}#{f.name}{instance_tag(f, inst)}.MagX/MagY/MagZ (raw, reconstructed)"
        out.append(MagReconstruction(inst, src, t, logged, undo_correction(field, corr), corr,
                                     tuple(bad_instances * (not out) + notes),
                                     _raw_resolution(corr, k) if c.integer else None))
    return out


@dataclass(frozen=True, eq=False)
class _Compass:
    """One compass's healthy MAG records before the correction is undone: times (s), field and motor offsets (mG)."""

    inst: int
    table: Table
    t: FloatArray
    factor: float
    logged: FloatArray
    motor: FloatArray | None
    integer: bool
    notes: tuple[str, ...]
    ofs: FloatArray | None = None
    dead: str | None = None


def _no_correction(n: int) -> Correction:
    """The identity correction of n samples: what a dead compass's readings are kept with."""
    return Correction(np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.ones(n), np.zeros((n, 3)))


def _compass(inst: int, table: Table, clock: Clock, rotated: bool = False) -> _Compass:
    """The healthy records of one compass (all of them, with a note, when the firmware marked none healthy), and
    whether it is dead or stuck as logged."""
    f = table.fmt
    notes: list[str] = []
    t = time_of(table, clock)
    if f.has("S", "TimeUS"):          # 4.x: S (uint32 us, wraps) is when the sample was taken
        t = sample_time(table.num("TimeUS"), table.num("S"))
    keep = table.num("Health") != 0 if f.has("Health") else np.ones(len(table), dtype=bool)
    unhealthy = not keep.any()
    if unhealthy:               # a compass that never worked: kept whole, to be refused by name
        notes.append(f"MAG[{inst}]: the firmware marked all {len(keep)} samples unhealthy")
        keep[:] = True
    elif not keep.all():
        notes.append(f"MAG[{inst}]: dropped {int((~keep).sum())} samples the firmware marked unhealthy")
    table, t = table.where(keep), t[keep]
    k = _mag_factor(table)
    mo_cols = next((c for c in (("MOfsX", "MOfsY", "MOfsZ"), ("MOX", "MOY", "MOZ")) if f.has(*c)), None)
    logged = stack_columns(table, ("MagX", "MagY", "MagZ"), k)
    integer = f.char("MagX") in "bBhHiIqQ"
    dead = dead_field(logged, "milligauss", k if integer else None, rotated)
    if unhealthy:
        dead = f"{dead} and Health 0 throughout" if dead else "Health 0 throughout"
    return _Compass(inst, table, t, k, logged, stack_columns(table, mo_cols, k) if mo_cols else None, integer,
                    tuple(notes),
                    stack_columns(table, ("OfsX", "OfsY", "OfsZ"), k) if f.has("OfsX", "OfsY", "OfsZ") else None,
                    dead)


def _int16_cast(compasses: list[_Compass], hist: ParamHistory, throttle: Series | None,
                current: Series | None) -> tuple[bool, str]:
    """Whether the log's integer fields were truncated toward zero (AP_Compass's cast) or rounded, and the evidence:
    the logged motor offsets against the COMPASS_MOT product they were cast from, and the field's zero bin."""
    params = hist.last()
    ints = [c for c in compasses if c.integer]
    zero_bin = truncation_evidence([c.logged / c.factor for c in ints], [c.t for c in ints]) if ints else 0.0
    motor = offset = 0.0
    for c in ints:
        suffix = param_suffix(c.inst, params)[0]
        if c.motor is not None:
            product = motor_product(hist, suffix, c.t, _interp(c.t, throttle), _interp(c.t, current))[0]
            motor += motor_cast_evidence(c.motor / c.factor, product / c.factor)
        in_force = offsets_in_force(hist, suffix, c.t)
        if c.ofs is not None and in_force is not None:
            offset += offset_cast_evidence(c.ofs / c.factor, in_force / c.factor)
    evidence = zero_bin + motor + offset
    decades = -evidence / np.log(10.0)
    ratio = f"1e{decades:.0f}" if decades > 6 else f"{10.0 ** decades:.3g}"
    why = f"likelihood ratio {ratio} from the zero bin" + (", the offsets against COMPASS_OFS" if offset else "") + (
        ", the motor offsets against COMPASS_MOT" if motor else "")
    return evidence > -np.log(ROUNDED_EVIDENCE), why
