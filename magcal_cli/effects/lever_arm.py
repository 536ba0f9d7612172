"""`lever_arm`: the accelerometer sits at r from the rotation centre and sees omega_dot x r + omega x (omega x r)
(mismatch.md E4)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from magcal_cli import so3
from magcal_cli.effects.base import Effect, Inputs, Kinematics, NotTestable, Point, Target, Term
from magcal_cli.effects.nongravity import flying
from magcal_cli.params import XYZ, ParamBlock
from magcal_cli.streams import FloatArray, Stream

#: the kinematic regressors must reach this RMS (1/s^2) for a lever arm of a few cm to show
MIN_EXCITATION = 0.2


class LeverArm(Effect):
    """Centripetal and tangential acceleration of an accelerometer away from the rotation centre."""

    id = "lever_arm"
    target = Target.ACCEL
    params = (ParamBlock("r_m", 3, "none", "lever arm", XYZ),)
    units: ClassVar[dict[str, str]] = {"r_m": "m"}
    limits: ClassVar[dict[str, float]] = {"r_m": 0.5}
    separating_experiment = ("fast spins about each axis with the vehicle held away from its centre")
    physics_left_out = ("The accelerometer is away from the centre of rotation, so turning adds centripetal and "
                        "tangential acceleration to gravity.")

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """Needs fast or accelerating rotation, and no flight whose acceleration comes from position fixes."""
        if flying(aux):
            # the acceleration differentiated from fixes passes < 1 Hz; a multirotor's fast accelerations follow its
            # angular acceleration (thrust tilts), so the part it misses looks exactly like omega_dot x r: on
            # simulated flights it was 4 % of a_n, correlated 0.7 with that regressor, a lever arm of 3-4 cm
            msg = ("in flight the vehicle's acceleration comes from its position fixes, which miss the fast part a "
                   "lever arm would be confused with; turn the vehicle quickly in place, away from its centre")
            raise NotTestable(msg)
        k = so3.hat(kin.omega_dot) + so3.hat(kin.omega) @ so3.hat(kin.omega)
        rms = float(np.sqrt(np.mean(k**2)) * 3.0)
        if rms < MIN_EXCITATION:
            msg = f"the rotation is too slow and smooth (RMS {rms:.2f} 1/s^2) for a lever arm to show"
            raise NotTestable(msg)
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"kinematics": k})

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """K r with K = [omega_dot]x + [omega]x^2."""
        k = inp.channels["kinematics"]
        return Term(k @ beta, k)


EFFECT = LeverArm()
