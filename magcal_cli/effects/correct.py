"""Modelled magnetometer effects removed from readings: what `apply` writes and what the quality figures see.

The calibration is the base model plus every effect the final fit carried: an `accepted` one, and an
`ambiguous` one the fit modelled (it carries an estimate; its rival, which explains the same readings, does not).
D and o were fitted with that term in the model: without it they can describe the readings worse than the
calibration the vehicle flew with (log171 MAG[1]: yaw RMS against ATT 26.5 deg without its throttle term, 11.4
deg with it, 19.4 deg flown; docs/decisions.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from magcal_cli.effects import EFFECTS, get
from magcal_cli.effects.base import Effect, Target, resample
from magcal_cli.effects.motor import motor_streams
from magcal_cli.streams import FloatArray, Kind, Stream

#: the statuses whose fitted entries are part of the calibration
MODELLED = ("accepted", "ambiguous")


class Channels(Protocol):
    """Where an effect's channels (current, throttle, temperature) are found: a Recording, or a Problem's aux."""

    def of_kind(self, kind: Kind) -> list[Stream]:
        """All streams of one kind."""


def has_estimate(eff: Effect, params: dict[str, Any]) -> bool:
    """Whether an entry carries the estimate of every parameter that vanishes under the base model (an exponent
    with a prior, like throttle's p, may be left out: `correct` then uses its default)."""
    prior = eff.prior()
    std = np.full(sum(b.size for b in eff.params), np.inf) if prior is None else prior[1]
    start = 0
    for b in eff.params:
        if not np.all(np.isfinite(std[start:start + b.size])) and b.name not in params:
            return False
        start += b.size
    return True


def terms(effects: Sequence[dict[str, Any]], mag_id: str, statuses: tuple[str, ...] = MODELLED
          ) -> list[tuple[dict[str, Any], Effect]]:
    """The entries of `mag_id`'s magnetometer effects with an estimate, with their plug-ins: what the calibration
    carries. An entry without one (an ambiguous rival the fit did not model) may still carry constants such as a
    reference temperature: it is left out."""
    out = []
    for e in effects:
        eid = str(e.get("id"))
        if e.get("sensor") != mag_id or e.get("status") not in statuses or eid not in EFFECTS:
            continue
        eff = get(eid)
        if eff.target is Target.MAG and has_estimate(eff, e.get("params") or {}):
            out.append((e, eff))
    return out


def remove(effects: Sequence[dict[str, Any]], mag_id: str, rec: Channels | Mapping[str, FloatArray], t: FloatArray,
           y: FloatArray, statuses: tuple[str, ...] = MODELLED) -> tuple[FloatArray, FloatArray, list[str]]:
    """Readings and stamps with the modelled magnetometer effects of `mag_id` (`terms`) removed, and what was
    done. `rec` holds the channels: a Recording or a Problem's aux (resampled at t), or a mapping of channel kind
    value ("battery_current", ...) to its values at t already (the Python API's readings, `magcal_cli.api`)."""
    notes = []
    for e, eff in terms(effects, mag_id, statuses):
        eid = eff.id
        chans = ({k.value: rec[k.value] for k in eff.channels if k.value in rec} if isinstance(rec, Mapping)
                 else _at(e, eff, rec, t))
        missing = [k.value for k in eff.channels if k.value not in chans]
        if missing:
            notes.append(f"{mag_id}: the {e.get('status')} {eid} is not removed (the log lacks its "
                         f"{', '.join(missing)} channel)")
            continue
        t, y = eff.correct(dict(e.get("params") or {}), t, y, chans)
        notes.append(f"{mag_id}: {eid} removed")
    return t, y, notes


def _at(e: dict[str, Any], eff: Effect, rec: Channels, t: FloatArray) -> dict[str, np.ndarray]:
    """The channels of `eff` found in `rec` (the entry's own channel ids first), resampled at t as the fit resampled
    them (`effects.base.resample`: a spline, so what is removed is what was fitted)."""
    chans: dict[str, np.ndarray] = {}
    for kind in eff.channels:
        ok = [s for s in rec.of_kind(kind) if np.isfinite(s.values[:, 0]).sum() >= 2]
        named = [s for s in ok if s.id in (e.get("channels") or [])]
        found = named or ok
        if found and kind is Kind.MOTOR_OUTPUT:          # one stream per motor: (N, motors) in motor order
            chans[kind.value] = np.column_stack([resample(s, t)[:, 0] for s in motor_streams(found)])
        elif found:
            chans[kind.value] = resample(found[0], t)[:, 0]
    return chans
