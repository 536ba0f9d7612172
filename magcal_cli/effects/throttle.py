"""`throttle_interference`: motor field as a function of throttle, y += c u(t)^p (mismatch.md E1b)."""

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

#: below this spread (std of u) throttle never changes enough to be told from hard iron
MIN_SPREAD = 0.01
#: the exponent exists only under the alternative: a prior N(1, 1) keeps it determined when c ~ 0
P_PRIOR = (1.0, 1.0)
U_FLOOR = 1e-6


class Throttle(Effect):
    """y += c u^p, u in [0, 1]."""

    id = "throttle_interference"
    target = Target.MAG
    additive = True
    zero_at_rest = True
    params = (ParamBlock("c", 3, "field", "throttle interference", XYZ), ParamBlock("p", 1, "none"))
    units: ClassVar[dict[str, str]] = {"c": "{field}", "p": "1"}
    channels = (Kind.THROTTLE,)
    limits: ClassVar[dict[str, float]] = {"c": 1e-4, "p": 5.0}
    separating_experiment = ("throttle steps at several battery charge levels (or a bench run with a payload), so throttle and current are no longer proportional")
    physics_left_out = ("The motors and their currents add a field fixed to the vehicle that grows with "
                        "throttle.")
    firmware: ClassVar[dict[str, str]] = {"ardupilot": "COMPASS_MOTCT=1, COMPASS_MOT_X/Y/Z",
                                          "px4": "CAL_MAG_COMP_TYP=1, CAL_MAGn_X/Y/ZCOMP"}

    compensates = "throttle"

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """Throttle at the epochs, clipped to [0, 1]."""
        s = pick(aux, Kind.THROTTLE)
        u = np.clip(resample(s, kin.t)[:, 0], U_FLOOR, 1.0)
        if float(np.std(u)) < MIN_SPREAD:
            msg = f"the throttle ({s.id}) hardly changes (std {np.std(u):.3f}): not testable"
            raise NotTestable(msg)
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"throttle": u}, (s.id,))

    def start(self) -> FloatArray:
        """c = 0, p = 1."""
        return np.array([0.0, 0.0, 0.0, 1.0])

    def prior(self) -> tuple[FloatArray, FloatArray]:
        """Only p has a prior."""
        return np.array([0.0, 0.0, 0.0, P_PRIOR[0]]), np.array([np.inf, np.inf, np.inf, P_PRIOR[1]])

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """c u^p; d/dc = u^p I3, d/dp = c u^p ln u."""
        u = inp.channels["throttle"]
        up = u ** beta[3]
        jac = np.zeros((u.size, 3, 4))
        jac[:, :, :3] = up[:, None, None] * np.eye(3)
        jac[:, :, 3] = (up * np.log(u))[:, None] * beta[None, :3]
        return Term(up[:, None] * beta[None, :3], jac)

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """Subtract c u^p."""
        u = np.clip(channels["throttle"], 0.0, 1.0) ** float(params.get("p", 1.0))
        return t, y - u[:, None] * np.asarray(params["c"], dtype=np.float64)[None, :]


EFFECT = Throttle()
