"""`temperature_drift`: the magnetometer's offset moves with temperature, y += k (T - T0) (mismatch.md E2)."""

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

#: a span below this (degC) cannot separate a slope from the offset
MIN_SPAN_C = 2.0


class Temperature(Effect):
    """y += k (T - T0); T0 is the log's mean temperature (o is then the offset at T0), not estimated."""

    id = "temperature_drift"
    target = Target.MAG
    additive = True
    params = (ParamBlock("k", 3, "field", "temperature drift", XYZ),)
    units: ClassVar[dict[str, str]] = {"k": "{field}/degC", "T0": "degC", "T_min": "degC", "T_max": "degC"}
    channels = (Kind.TEMPERATURE,)
    limits: ClassVar[dict[str, float]] = {"k": 1e-6}
    separating_experiment = ("a warm-up or cool-down with the motors off, so the temperature changes while the current does not")
    physics_left_out = "The magnetometer's offset drifts with its temperature."

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """The magnetometer's own temperature where logged (else the IMU's, else the first); T0 its mean, T_min and
        T_max the range the fit saw (a firmware's thermal compensation must not extrapolate beyond it)."""
        s = pick(aux, Kind.TEMPERATURE, (mag.id, "mag"))
        temp = resample(s, kin.t)[:, 0]
        span = float(np.percentile(temp, 98) - np.percentile(temp, 2))
        if span < MIN_SPAN_C:
            msg = (f"the temperature ({s.id}) spans only {span:.1f} degC (need >= {MIN_SPAN_C:g}): a slope "
                   "cannot be told from the offset")
            raise NotTestable(msg)
        t0 = float(np.mean(temp))
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"temperature": temp - t0}, (s.id,),
                      {"T0": t0, "T_min": float(np.min(temp)), "T_max": float(np.max(temp))})

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """k dT and d/dk = dT I3."""
        dt = inp.channels["temperature"]
        return Term(dt[:, None] * beta[None, :], dt[:, None, None] * np.eye(3))

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """Subtract k (T - T0)."""
        dt = channels["temperature"] - float(params["T0"])
        return t, y - dt[:, None] * np.asarray(params["k"], dtype=np.float64)[None, :]


EFFECT = Temperature()
