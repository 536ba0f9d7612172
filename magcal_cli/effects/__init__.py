"""Effect plug-ins: physics beyond the base model. Adding one is its module plus one line here.

Ids and parameters: spec/calibration-file.md ("Effects"). Each module defines `EFFECT`, an `base.Effect`.
"""

from __future__ import annotations

from magcal_cli.effects.base import Effect
from magcal_cli.errors import MagcalError
from magcal_cli.registry import resolve

#: id -> "module:EFFECT", imported on use
EFFECTS: dict[str, str] = {
    "current_interference": "magcal_cli.effects.current:EFFECT",
    "throttle_interference": "magcal_cli.effects.throttle:EFFECT",
    "temperature_drift": "magcal_cli.effects.temperature:EFFECT",
    "time_offset": "magcal_cli.effects.time_offset:EFFECT",
    "gyro_scale": "magcal_cli.effects.gyro_scale:EFFECT",
    "accel_scale": "magcal_cli.effects.accel_scale:EFFECT",
    "lever_arm": "magcal_cli.effects.lever_arm:EFFECT",
    "nongravity_acceleration": "magcal_cli.effects.nongravity:EFFECT",
    "transient_disturbance": "magcal_cli.effects.transient:EFFECT",
    "motor_interference": "magcal_cli.effects.motor:EFFECT",
}


class EffectError(MagcalError):
    """An --effects value names an unknown effect."""


def get(effect_id: str) -> Effect:
    """The plug-in with this id."""
    try:
        target = EFFECTS[effect_id]
    except KeyError:
        msg = (f"--effects: unknown effect {effect_id!r}; use none, or a comma list of: "
               f"{', '.join(EFFECTS)}")
        raise EffectError(msg) from None
    effect: Effect = resolve(target, f"the {effect_id} effect")
    return effect


def parse(spec: str) -> tuple[str, ...]:
    """'none' -> (), 'a,b' -> ('a', 'b') (checked, duplicates dropped)."""
    spec = spec.strip()
    if spec in ("", "none"):
        return ()
    ids = tuple(dict.fromkeys(s.strip() for s in spec.split(",") if s.strip()))
    for i in ids:
        get(i)
    return ids
