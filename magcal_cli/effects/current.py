"""`current_interference`: current in the power leads adds a body-fixed field, y += c I(t) (mismatch.md E1)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from magcal_cli.effects.base import (
    Effect,
    Inputs,
    Kinematics,
    NotTestable,
    Point,
    Target,
    Term,
    pick,
    resample,
)
from magcal_cli.params import XYZ, ParamBlock
from magcal_cli.streams import FloatArray, Kind, Stream

#: below this spread (A, std) the current never changes enough: its mean is absorbed by the offset o
MIN_SPREAD_A = 0.5


def varying_current(s: Stream, t: FloatArray, min_std: float = MIN_SPREAD_A) -> FloatArray:
    """The current channel `s` (A) at times t; NotTestable when its std there is below `min_std`."""
    i = resample(s, t)[:, 0]
    if float(np.std(i)) < min_std:
        msg = (f"the current ({s.id}) never changes by more than {min_std} A (std {np.std(i):.2f} A): "
               "a constant current is indistinguishable from hard iron")
        raise NotTestable(msg)
    return i


class Current(Effect):
    """y += c I(t); I positive while discharging in every reader (ROS BatteryState is negated on read)."""

    id = "current_interference"
    target = Target.MAG
    additive = True
    zero_at_rest = True
    params = (ParamBlock("c", 3, "field", "current interference", XYZ),)
    units: ClassVar[dict[str, str]] = {"c": "{field}/ampere"}
    channels = (Kind.BATTERY_CURRENT,)
    limits: ClassVar[dict[str, float]] = {"c": 2e-6}
    separating_experiment = ("hover-descend-hover throttle steps at a steady temperature, so current changes quickly while the temperature does not")
    physics_left_out = ("Current in the power leads adds a field fixed to the vehicle, proportional to the "
                        "current.")
    firmware: ClassVar[dict[str, str]] = {"ardupilot": "COMPASS_MOTCT=2, COMPASS_MOT_X/Y/Z",
                                          "px4": "CAL_MAG_COMP_TYP=2, CAL_MAGn_X/Y/ZCOMP"}

    compensates = "current"

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """The current at the epochs; not testable when it hardly changes."""
        s = pick(aux, Kind.BATTERY_CURRENT)
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"current": varying_current(s, kin.t)}, (s.id,))

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """c I and d/dc = I I3."""
        i = inp.channels["current"]
        return Term(i[:, None] * beta[None, :], i[:, None, None] * np.eye(3))

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """Subtract c I."""
        return t, y - channels["battery_current"][:, None] * np.asarray(params["c"], dtype=np.float64)[None, :]


EFFECT = Current()
