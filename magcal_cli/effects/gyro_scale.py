"""`gyro_scale`: omega_meas = (I + diag(s)) omega + b_g (mismatch.md E9).

To first order the true rate is omega_meas - b_g - diag(s)(omega_meas - b_g): a per-sample bias diag(w_j) s,
which the preintegration's scale Jacobian (`Preintegrated.d_scale`, the bias Jacobian with each piece weighted
by its rotation vector) carries into the preintegrated rotation: dR <- dR Exp(d_scale s).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from magcal_cli.effects.base import Effect, Inputs, Kinematics, NotTestable, Point, Target, Term
from magcal_cli.params import XYZ, ParamBlock
from magcal_cli.streams import FloatArray, Stream

#: the rate must vary on every axis by at least this (rad/s, std): at a constant rate a scale is a bias
MIN_RATE_STD = 0.05


class GyroScale(Effect):
    """Per-axis gyro scale-factor errors."""

    id = "gyro_scale"
    target = Target.GYRO
    params = (ParamBlock("s", 3, "none", "gyro scale", XYZ),)
    units: ClassVar[dict[str, str]] = {"s": "fraction"}
    limits: ClassVar[dict[str, float]] = {"s": 0.05}
    separating_experiment = ("full turns about each axis in both directions, at different speeds")
    physics_left_out = "The gyro over- or under-reads the rotation rate by a fixed fraction on some axes."

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """Needs varying rotation rates on every axis."""
        sd = np.std(kin.omega, axis=0)
        if float(sd.min()) < MIN_RATE_STD:
            msg = f"the rotation rate about some axis hardly varies (std {sd.min():.3f} rad/s)"
            raise NotTestable(msg)
        return Inputs(kin.t, kin.omega, kin.omega_dot)

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """d_scale s per interval."""
        d_scale = at.pre.d_scale
        return Term(d_scale @ beta, d_scale)


EFFECT = GyroScale()
