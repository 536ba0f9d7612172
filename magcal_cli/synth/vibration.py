"""IMU vibration: while a multirotor's motors run, its IMU is much noisier than at rest (heteroscedastic noise).

The per-sample noise std of the gyro and accelerometer is a function of time: the rest level while the motors
are off, the flight level while they run, with raised-cosine ramps of SPIN_S as they spin up before take-off
and down after touchdown. The levels are those of a flight controller's filtered IMU samples (ArduPilot's
INS_GYRO_FILTER / INS_ACCEL_FILTER low-pass, 20 Hz by default), so they do not scale with the log rate the way
the paper's noise densities do. The noise stays white and Gaussian; the magnetometer's is unchanged.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from magcal_cli.errors import MagcalError
from magcal_cli.streams import FloatArray
from magcal_cli.synth.effects import POWER_EFFECTS
from magcal_cli.synth.physics import window

Intervals = tuple[tuple[float, float], ...]

#: per-sample noise std at noise_scale 1, motors off and running: gyro rad/s, accelerometer m/s^2
VIBRATION_STD = {"gyroscope": (0.003, 0.01), "accelerometer": (0.03, 0.15)}
#: seconds the motors take to spin up (before take-off) and down (after touchdown)
SPIN_S = 1.0


def motor_weight(t: npt.ArrayLike, motors: Intervals) -> FloatArray:
    """0 with the motors off, 1 while they run at flight speed, raised-cosine ramps of SPIN_S outside each
    interval (`motors`: the intervals (s) from take-off to touchdown)."""
    t = np.asarray(t, dtype=np.float64)
    if not motors:
        return np.zeros_like(t)
    return window(t, np.array([(a - SPIN_S, b + SPIN_S) for a, b in motors]), SPIN_S)


def levels(noise_scale: float) -> tuple[dict[str, float], dict[str, float]]:
    """The rest and flight noise std of the gyro and accelerometer at `noise_scale`."""
    rest = {k: v[0] * noise_scale for k, v in VIBRATION_STD.items()}
    flight = {k: v[1] * noise_scale for k, v in VIBRATION_STD.items()}
    return rest, flight


def motors_of(scenario_motors: Intervals, effect_ids: list[str], log_power: bool, end: float,
              scenario: str) -> Intervals:
    """When the motors run: the scenario's phases, else the whole log when a power model runs (a power effect or
    `log_power`), else a MagcalError (nothing vibrates)."""
    if scenario_motors:
        return scenario_motors
    if log_power or any(e in POWER_EFFECTS for e in effect_ids):
        return ((0.0, end),)
    msg = (f"simulate: vibration needs motors, and the {scenario} scenario has none; use the multirotor scenario, "
           f"or a power model ({', '.join(POWER_EFFECTS)} or log_power=True) whose motors run the whole log")
    raise MagcalError(msg)


def imu_std(rest: float, flight: float, weight: FloatArray) -> FloatArray:
    """(N, 1) per-sample std: rest + (flight - rest) x the motors' weight."""
    out: FloatArray = (rest + (flight - rest) * weight)[:, None]
    return out
