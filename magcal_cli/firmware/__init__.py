"""Firmware knowledge: ArduPilot and PX4 rotation enums, the split of a calibration into what each firmware can
hold, parameter names, limits and file formats, and the post-flight check.

The conventions (correction order, signs, units, frames, slot mapping) are those of
`../shared/design/firmware-export.md`; docs/firmware-export.md says what magcal writes and what is lost.
"""

from __future__ import annotations

from magcal_cli.errors import MagcalError


class FirmwareError(MagcalError):
    """A calibration cannot be written as firmware parameters (slot, rotation, unit or document problem)."""


class NotExportableError(FirmwareError):
    """One magnetometer cannot be exported (its values or its data); `fit`'s writers leave it out and say so."""


class FirmwareLimitError(NotExportableError):
    """An exported value lies outside what the firmware accepts; the message names the parameter and limit."""
