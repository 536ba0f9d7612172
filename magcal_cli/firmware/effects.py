"""Motor/current interference from a calibration document's modelled effects, in the magnetometer's unit.

calibration-file.md: `current_interference` is y += c I(t) (c in mag unit per ampere), `throttle_interference`
is y += c u(t)^p (c in mag unit at full throttle). An `accepted` entry is exported, else an `ambiguous` one the
fit modelled (it carries c): D and o were fitted with that term, and current and throttle come out ambiguous
exactly when they are proportional in the log, so either compensates flights like it (effects/correct.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.errors import StreamError
from magcal_cli.firmware import FirmwareError
from magcal_cli.streams import FloatArray


def kind_of(effect_id: str) -> str | None:
    """The signal ("current", "throttle") the firmware's compensation multiplies for this effect, from its
    plug-in (None: no firmware knob, or not an effect id)."""
    from magcal_cli.effects import EFFECTS, get

    return get(effect_id).compensates if effect_id in EFFECTS else None


@dataclass(frozen=True, eq=False)
class Interference:
    """c (3) in the magnetometer's unit per ampere ("current") or at full throttle ("throttle"), exponent p."""

    kind: str
    c: FloatArray
    exponent: float
    effect_id: str
    status: str = "accepted"


def _c_in_mag_unit(effect: dict[str, Any], mag: MagCalibration, where: str) -> FloatArray:
    """The effect's c converted to the magnetometer's unit (its `units.c` may name another field unit)."""
    try:
        c = np.asarray(effect["params"]["c"], dtype=np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        msg = f"{where}: params.c is missing or not 3 numbers. Re-create the document with magcal fit"
        raise FirmwareError(msg) from None
    unit = str((effect.get("units") or {}).get("c", mag.unit)).split("/")[0].strip()
    try:
        canonical = units.canonical(unit)
    except StreamError:
        canonical = ""
    if canonical not in units.MAG_UNITS:
        msg = f"{where}: units.c {unit!r} is not a magnetic field unit; expected e.g. '{mag.unit}/ampere'"
        raise FirmwareError(msg)
    return c * units.to_si(canonical) * units.from_si(mag.unit)


def carried(cal: Calibration, mag: MagCalibration) -> tuple[Interference | None, list[str]]:
    """The interference effect of `mag` the calibration carries (accepted, else ambiguous with an estimate;
    current preferred over throttle) and notes on what was left."""
    from magcal_cli.effects import get
    from magcal_cli.effects.correct import has_estimate

    found: dict[str, Interference] = {}
    for status in ("ambiguous", "accepted"):          # an accepted entry replaces an ambiguous one of its kind
        for i, effect in enumerate(cal.effects):
            kind = kind_of(str(effect.get("id")))
            params = effect.get("params") or {}
            if kind is None or effect.get("sensor") != mag.id or effect.get("status") != status:
                continue
            if status == "ambiguous" and not has_estimate(get(str(effect["id"])), params):   # an unmodelled rival
                continue
            where = f"calibration: effects[{i}] ({effect.get('id')}, {mag.id})"
            p = float(params.get("p", 1.0)) if kind == "throttle" else 1.0
            found[kind] = Interference(kind, _c_in_mag_unit(effect, mag, where), p, str(effect["id"]), status)
    notes = []
    if len(found) == 2:
        notes.append(f"{mag.id}: both current and throttle interference are in the calibration; the firmware "
                     "compensates one signal, so the current term is exported and the throttle term is not")
    chosen = found.get("current") or found.get("throttle")
    if chosen is not None and chosen.status == "ambiguous":
        notes.append(f"{mag.id}: {chosen.effect_id} is exported although the diagnosis found it ambiguous (its "
                     "rival explains the same readings in this log): the calibration was fitted with it, and without "
                     "it D and o would not describe the readings")
    if chosen is not None and chosen.kind == "throttle" and abs(chosen.exponent - 1.0) > 1e-6:
        notes.append(f"{mag.id}: the firmware's throttle compensation is linear; the fitted exponent "
                     f"p={chosen.exponent:.2f} is dropped (largest error at u in [0,1]: "
                     f"{np.max(np.abs(np.linspace(0, 1, 101) ** chosen.exponent - np.linspace(0, 1, 101))):.2f}"
                     " x |c|)")
    return chosen, notes


def tested(cal: Calibration, mag_id: str, kind: str) -> bool:
    """True when the diagnosis tested the interference term of `kind` for `mag_id` (any status but not_testable)."""
    return any(kind_of(str(e.get("id"))) == kind and e.get("sensor") == mag_id
               and e.get("status") not in (None, "not_testable") for e in cal.effects)
