"""A diagnosis block with its SI field values in a magnetometer's unit (keys ending in `_si` lose the suffix)."""

from __future__ import annotations

from typing import Any

from magcal_cli import units


def in_units(block: dict[str, Any], unit: str) -> dict[str, Any]:
    """The block (nested dicts too) with every `*_si` value converted to `unit` and renamed, plus the unit."""
    f = units.from_si(unit)

    def conv(d: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            if isinstance(v, dict):
                out[k] = conv(v)
            elif k.endswith("_si"):
                out[k[:-3]] = v * f
            else:
                out[k] = v
        return out

    return {**conv(block), "unit": units.canonical(unit)}
