"""`accel_scale`: f_meas = (I + diag(s)) f + b_a (mismatch.md E10); the term is diag(s) f with f = -R^T g_n."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from magcal_cli import so3
from magcal_cli.effects.base import Effect, Inputs, Kinematics, Point, Target, Term
from magcal_cli.params import XYZ, ParamBlock
from magcal_cli.streams import FloatArray, Stream


class AccelScale(Effect):
    """Per-axis accelerometer scale-factor errors (the scale acts on the gravity part; s a_n is second order)."""

    id = "accel_scale"
    target = Target.ACCEL
    params = (ParamBlock("s", 3, "none", "accelerometer scale", XYZ),)
    units: ClassVar[dict[str, str]] = {"s": "fraction"}
    limits: ClassVar[dict[str, float]] = {"s": 0.05}
    separating_experiment = ("a still pose on each of the six faces")
    physics_left_out = "The accelerometer over- or under-reads by a fixed fraction on some axes."

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """Always evaluated; testability is judged from the attitudes in `term` (the fit's information)."""
        return Inputs(kin.t, kin.omega, kin.omega_dot)

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """-s * g_b; d/ds = diag(-g_b); d/dphi = -diag(s) [g_b]x."""
        m = at.g_b.shape[0]
        d_beta = np.zeros((m, 3, 3))
        idx = np.arange(3)
        d_beta[:, idx, idx] = -at.g_b
        return Term(-at.g_b * beta[None, :], d_beta, -beta[None, :, None] * so3.hat(at.g_b))


EFFECT = AccelScale()

