"""`motor_interference`: one field vector per motor, driven by that motor's output, y += sum_i c_i s_i(t).

The outputs are scaled as ArduPilot's per-motor compass compensation scales them (Compass_PerMotor.cpp
`scaled_output` @ ef273c61 [S7], the first firmware that has it): u_i = the fraction of the motor's PWM range
(scale_esc_to_unity), 0 when off, times the battery voltage V, to the power COMPASS_PMOT_EXP (default 0.65):
s_i = (u_i V)^0.65. The firmware compensates motors 1-4 only (AP_COMPASS_PMOT_MAX_NUM_MOTORS = 4 in the versions
read), so the effect has four vectors c1..c4 (field per unit of s). When the motors move together (a hover, a
climb), s_i follow the throttle and the effect cannot be told from throttle or current interference: the diagnosis
then finds them ambiguous (canonical correlation); differential thrust (turns, attitude changes) separates them.
"""

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

#: COMPASS_PMOT_EXP's default (AP_GROUPINFO("_EXP", 2, Compass_PerMotor, expo, 0.65) [S7])
EXPO = 0.65
#: the motors the firmware compensates (AP_COMPASS_PMOT_MAX_NUM_MOTORS [S7])
MOTORS = 4
#: a motor whose scaled output never changes by this much (std) cannot be told from the offset
MIN_SPREAD = 0.05
#: below this ratio of the smallest to the largest singular value of the centred outputs, the motors move exactly
#: together: four vectors are one (a rank-deficient block), which throttle or current interference carries
MIN_INDEPENDENT = 1e-3


def motor_streams(aux: tuple[Stream, ...] | list[Stream]) -> list[Stream]:
    """The per-motor output streams, in motor order (ids motor[1], motor[2], ...)."""
    found = [s for s in aux if s.kind is Kind.MOTOR_OUTPUT and len(s) >= 2]
    return sorted(found, key=lambda s: (len(s.id), s.id))


def scaled(u: FloatArray, volts: FloatArray, expo: float = EXPO) -> FloatArray:
    """s = (u V)^expo, 0 where the motor is off (u <= 0): Compass_PerMotor::scaled_output [S7]; u (N, k), V (N,)."""
    x = np.clip(u, 0.0, None) * volts[:, None]
    out: FloatArray = np.where(x > 0, np.abs(x) ** expo, 0.0)
    return out


class Motor(Effect):
    """y += sum_i c_i (u_i V)^0.65 over motors 1-4."""

    id = "motor_interference"
    target = Target.MAG
    additive = True
    zero_at_rest = True
    nests: ClassVar[tuple[str, ...]] = ("throttle_interference", "current_interference")
    params = tuple(ParamBlock(f"c{i}", 3, "field", f"motor {i} interference", XYZ) for i in range(1, MOTORS + 1))
    units: ClassVar[dict[str, str]] = {f"c{i}": "{field}" for i in range(1, MOTORS + 1)} | {"expo": "1"}
    channels = (Kind.MOTOR_OUTPUT, Kind.BATTERY_VOLTAGE)
    limits: ClassVar[dict[str, float]] = {f"c{i}": 1e-4 for i in range(1, MOTORS + 1)}
    separating_experiment = ("yaw turns and roll/pitch steps in a hover (differential thrust), so the motors' "
                             "outputs no longer move together with the throttle and the current")
    physics_left_out = ("Each motor and its leads add a field fixed to the vehicle that grows with that motor's "
                        "output (differential thrust moves them apart).")
    firmware: ClassVar[dict[str, str]] = {"ardupilot": "COMPASS_PMOT_EN=1, COMPASS_PMOT_EXP, COMPASS_PMOT1..4_X/Y/Z "
                                                       "(first compass only)"}

    def applies(self, aux: tuple[Stream, ...]) -> bool:
        """Only a log with the outputs of motors 1-4 is screened for it (the others' documents stay as they were)."""
        return len(motor_streams(aux)) >= MOTORS

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """Motors 1-4's scaled outputs at the epochs; not testable without four motors, a voltage, or outputs
        that change."""
        motors = motor_streams(aux)
        if len(motors) < MOTORS:
            msg = (f"this log has {len(motors)} per-motor output channels (need motors 1-{MOTORS}: ArduPilot RCOU, "
                   "PX4 actuator_outputs)" if motors else "this log has no motor_output channel")
            raise NotTestable(msg)
        volts = pick(aux, Kind.BATTERY_VOLTAGE)
        u = np.column_stack([resample(s, kin.t)[:, 0] for s in motors[:MOTORS]])
        s = scaled(u, resample(volts, kin.t)[:, 0])
        spread = float(np.min(np.std(s, axis=0)))
        if spread < MIN_SPREAD:
            msg = f"the motors' outputs hardly change (smallest std {spread:.3f}): not testable"
            raise NotTestable(msg)
        sv = np.linalg.svd(s - s.mean(axis=0), compute_uv=False)
        if sv[-1] < MIN_INDEPENDENT * sv[0]:
            msg = ("the motors' outputs move together (no differential thrust): one field per motor cannot be told "
                   "apart; throttle or current interference describes it")
            raise NotTestable(msg)
        ids = tuple(m.id for m in motors[:MOTORS]) + (volts.id,)
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"s": s}, ids, {"expo": EXPO})

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """sum_i s_i c_i and d/dc_i = s_i I3."""
        s = inp.channels["s"]
        c = beta.reshape(MOTORS, 3)
        blocks = np.zeros((s.shape[0], 3, MOTORS, 3))
        for j in range(3):                                       # d/dc_i[j] of row j is s_i (a fill, not an einsum)
            blocks[:, j, :, j] = s
        return Term(s @ c, blocks.reshape(s.shape[0], 3, 3 * MOTORS))

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """Subtract sum_i c_i s_i; `channels["motor_output"]` is (N, 4) (motors 1-4), "battery_voltage" (N,)."""
        s = scaled(channels["motor_output"], channels["battery_voltage"], float(params.get("expo", EXPO)))
        c = np.array([params[f"c{i}"] for i in range(1, MOTORS + 1)], dtype=np.float64)
        return t, y - s @ c


EFFECT = Motor()
