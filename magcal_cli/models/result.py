"""What every estimator returns, in SI units; the pipeline turns it into a Calibration document."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from magcal_cli.findings import Finding
from magcal_cli.params import Estimate
from magcal_cli.streams import FloatArray


@dataclass(frozen=True, eq=False)
class MagFit:
    """One magnetometer: D (3, 3) and o (3,) in tesla, dip in rad, covariance of (vec D, o, dip) in SI."""

    id: str
    D: FloatArray
    o: FloatArray
    dip: float
    cov: FloatArray
    residual_rms: float
    samples: int
    iterations: int
    converged: bool
    log: tuple[str, ...] = ()
    #: entries the log could not determine, held at a prior (partial calibration): SI values
    held: tuple[HeldEntry, ...] = ()
    #: what fixed the orientation: the log's own motion, or the vehicle's attitude estimate and the WMM
    reference: str = "motion"
    #: the method that calibrated this magnetometer ("" = the result's); each compass gets its own (issue 38)
    method: str = ""


@dataclass(frozen=True)
class Refusal:
    """A magnetometer that no method could calibrate: its id, why (without advice) and what to record instead."""

    id: str
    reason: str
    advice: str


@dataclass(frozen=True)
class HeldEntry:
    """One parameter held at a prior: its entry name in `params.BASE` ('D.02', 'o.z', 'dip',
    'accelerometer_bias.x'), the prior's value and std in SI (total gyro bias; dip in rad) and source."""

    name: str
    prior: float
    prior_std: float
    source: str


@dataclass(frozen=True, eq=False)
class EffectFit:
    """One effect fitted (or found not testable) for one sensor: its parameters in SI by block name, the
    channels it used, the Wald test of "zero" and the status (accepted, rejected, not_testable)."""

    id: str
    sensor: str
    status: str
    estimate: Estimate | None = None
    channels: tuple[str, ...] = ()
    statistic: float = float("nan")
    dof: int = 0
    p_value: float = float("nan")
    reason: str = ""
    constants: dict[str, Any] = field(default_factory=dict)
    #: the diagnosis's evidence (held-out scores, BIC, relevance), the rivals it could not separate, the test
    evidence: dict[str, Any] = field(default_factory=dict)
    confounded_with: tuple[str, ...] = ()
    test_kind: str = "wald"


@dataclass(frozen=True, eq=False)
class ImuFit:
    """IMU biases (m/s^2, rad/s) and their standard deviations; None where not estimated."""

    id: str
    accel_bias: FloatArray | None = None
    gyro_bias: FloatArray | None = None
    accel_bias_std: FloatArray | None = None
    gyro_bias_std: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class MethodResult:
    """An estimator's output: magnetometers, IMU, the noise levels it used, remarks and findings (report)."""

    method: str
    mags: tuple[MagFit, ...]
    imu: ImuFit
    noise: dict[str, list[float]] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    findings: tuple[Finding, ...] = ()
    effects: tuple[EffectFit, ...] = ()
    #: the mismatch diagnosis per magnetometer (diagnose/engine.py), when it ran
    diagnosis: tuple[dict[str, Any], ...] = ()
    #: the magnetometers no method could calibrate, each with its reason
    refused: tuple[Refusal, ...] = ()
