"""What both firmware exporters share: options, results, the correction in the firmware's unit and limits."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.firmware import FirmwareError, FirmwareLimitError, NotExportableError
from magcal_cli.firmware.split import Split
from magcal_cli.streams import FloatArray


@dataclass(frozen=True)
class Options:
    """Export choices: rotation policy, the custom-rotation threshold, --external/--internal, --slot."""

    rotation: str = "auto"              # auto: enum unless it misses by more than custom_above_deg; enum; custom
    custom_above_deg: float = 1.0
    external: bool | None = None        # used only when the vehicle parameters do not say
    slot: int | None = None             # ArduPilot 1..3, PX4 0..3; one magnetometer only
    skip_refused: bool = False          # leave out (and say so) magnetometers beyond the limits, not fail


@dataclass(frozen=True, eq=False)
class MagExport:
    """One magnetometer's parameters, the split behind them and what the firmware cannot hold."""

    mag_id: str
    slot: str                           # e.g. "COMPASS_*2" or "CAL_MAG1_*"
    params: dict[str, float]
    split: Split
    dip_deg: float
    external: bool
    notes: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    rotation_why: str = ""              # why the firmware cannot take the misalignment (said when some is lost)
    not_held: tuple[str, ...] = ()      # effects it carries that this firmware cannot hold

    def lost(self) -> dict[str, float]:
        """Residual misalignment (deg), largest field error (%) and level heading error (deg) the export keeps."""
        return {"residual_misalignment_deg": self.split.residual_angle_deg,
                "max_field_error_pct": self.split.max_error_pct,
                "heading_error_deg": self.split.heading_error_deg(self.dip_deg)}

    def lost_text(self) -> str:
        """One line: what the firmware cannot hold of this calibration."""
        lost = self.lost()
        how = {"enum": f"orientation {self.split.rotation.enum_id}", "custom": "a custom orientation",
               "fixed": "the board orientation (internal compass)"}[self.split.rotation.kind]
        if lost["max_field_error_pct"] < 0.1:
            return f"{self.mag_id} -> {self.slot}: exported exactly with {how} (field error below 0.1 %)"
        why = f": {self.rotation_why}" if self.rotation_why and lost["residual_misalignment_deg"] >= 0.5 else ""
        return (f"{self.mag_id} -> {self.slot}: with {how}, {lost['residual_misalignment_deg']:.2f} deg of "
                f"misalignment is not representable (field error up to {lost['max_field_error_pct']:.2f} %, "
                f"level heading error up to {lost['heading_error_deg']:.2f} deg){why}")


@dataclass(frozen=True, eq=False)
class Export:
    """A whole parameter file: every magnetometer's parameters plus the global ones."""

    firmware: str
    mags: tuple[MagExport, ...]
    params: dict[str, float]
    integers: frozenset[str] = frozenset()
    notes: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    source: str = ""
    #: effects the calibration carries that this firmware has no parameter for (a lag on ArduPilot, ...)
    not_held: tuple[str, ...] = ()

    def header(self) -> list[str]:
        """Comment lines for the file: origin, what is lost per magnetometer, effects not held, warnings."""
        lines = [f"magcal {self.firmware} compass parameters from {self.source}" if self.source else
                 f"magcal {self.firmware} compass parameters"]
        lines += [m.lost_text() for m in self.mags]
        lines += [f"not held: {n}" for n in self.not_held]
        lines += [f"warning: {w}" for w in self.warnings]
        return lines


def correction(mag: MagCalibration, unit: str) -> tuple[FloatArray, FloatArray, float]:
    """(A = F D^-1 dimensionless, o in `unit`, factor from the document's unit to `unit`)."""
    if mag.unit not in units.MAG_UNITS:
        msg = f"calibration: {mag.id} has unit {mag.unit!r}, not a magnetic field unit. Re-create it with magcal fit"
        raise FirmwareError(msg)
    if not np.all(np.isfinite(mag.D)) or abs(np.linalg.det(mag.D)) < 1e-300 or not np.isfinite(mag.field_strength):
        msg = f"calibration: {mag.id} has a singular or non-finite D. Re-create it with magcal fit"
        raise FirmwareError(msg)
    k = units.to_si(mag.unit) * units.from_si(unit)
    return mag.field_strength * mag.A, mag.o * k, k


def check_limits(where: str, errors: list[str]) -> None:
    """Refuse (FirmwareLimitError) when any value is outside what the firmware accepts."""
    if errors:
        msg = f"{where}: {'; '.join(errors)}"
        raise FirmwareLimitError(msg)


def soft_range(name: str, value: float, lo: float, hi: float, why: str) -> list[str]:
    """A warning when `value` lies outside a typical range (flagged, still written)."""
    if lo <= value <= hi:
        return []
    return [f"{name}={value:.4g} is outside the typical {lo:g}..{hi:g} ({why})"]


def select_mags(cal: Calibration, mag_ids: Sequence[str] | None, options: Options) -> list[MagCalibration]:
    """The magnetometers to export (all by default); --slot needs exactly one."""
    mags = list(cal.magnetometers) if not mag_ids else [cal.magnetometer(m) for m in mag_ids]
    if options.slot is not None and len(mags) != 1:
        msg = (f"export: --slot applies to one magnetometer, but {len(mags)} are selected "
               f"({', '.join(m.id for m in mags)}). Add --mag ID")
        raise FirmwareError(msg)
    return mags


#: parameters that come from D (iron matrix, scale, orientation) and, axis by axis, from o
_FROM_D = re.compile(r"COMPASS_(DIA|ODI)\d?_[XYZ]|COMPASS_SCALE\d?|COMPASS_ORIENT\d?|CUST_ROT.*"
                     r"|CAL_MAG\d_([XYZ](SCALE|ODIAG)|ROT|ROLL|PITCH|YAW)")
_OFFSET = re.compile(r"COMPASS_OFS\d?_([XYZ])|CAL_MAG\d_([XYZ])OFF")


def determined(m: MagExport, mag: MagCalibration) -> MagExport:
    """Only the parameters the log determined: where a partial calibration held D (any entry), the iron
    matrix, scale and orientation are left as the vehicle has them; where it held an offset, that axis's
    offset too. Says so in a note."""
    held = sorted(str(h["parameter"]) for h in mag.held)
    d_held = any(p.startswith("D[") for p in held)
    axes = {"XYZ"[int(p[2])] for p in held if p.startswith("o[")}

    def keep(name: str) -> bool:
        offset = _OFFSET.fullmatch(name)
        if offset:
            return (offset.group(1) or offset.group(2)) not in axes
        return not (d_held and _FROM_D.fullmatch(name))

    params = {k: v for k, v in m.params.items() if keep(k)}
    dropped = sorted(set(m.params) - set(params))
    if not dropped:
        return m
    note = (f"{m.mag_id}: this log could not determine {', '.join(held)} (held at a prior, see the report), so "
            f"{', '.join(dropped)} are not written and the vehicle keeps its own values")
    return replace(m, params=params, notes=(*m.notes, note))


@dataclass
class Extras:
    """Parameters, integer-valued names, notes and warnings an export gathers."""

    params: dict[str, float] = field(default_factory=dict)
    integers: set[str] = field(default_factory=set)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def absorb(self, more: Extras) -> None:
        """Add `more`'s parameters, integer names, notes and warnings to these."""
        self.params |= more.params
        self.integers |= more.integers
        self.notes += more.notes
        self.warnings += more.warnings


@dataclass
class Collected(Extras):
    """Accumulates the parameters, notes and warnings of several magnetometers."""

    mags: list[MagExport] = field(default_factory=list)
    not_held: list[str] = field(default_factory=list)

    def add(self, m: MagExport, integers: set[str]) -> None:
        """Add one magnetometer's export."""
        self.mags.append(m)
        self.params.update(m.params)
        self.integers |= integers
        self.notes += m.notes
        self.warnings += m.warnings
        self.not_held += m.not_held

    def require_any(self) -> None:
        """Raise NotExportableError with every magnetometer's reason when none could be exported."""
        if not self.mags:
            msg = "; ".join(self.warnings)
            raise NotExportableError(msg)


def shared_signal(kinds: Mapping[str, str]) -> str:
    """The one interference signal a firmware applies to every compass (COMPASS_MOTCT, CAL_MAG_COMP_TYP are
    global): the one most magnetometers' carried effects follow, current on a tie (it follows the load itself).
    "Current when any" dropped two compasses' throttle terms for one compass's current (log171, where each
    compass carries one of an ambiguous current/throttle pair)."""
    values = list(kinds.values())
    return "current" if values.count("current") >= values.count("throttle") else "throttle"
