"""The one frozen Config: every threshold and choice, with its default in one place."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling

@dataclass(frozen=True)
class StillConfig:
    """Stationary-segment detection; thresholds scale with the noise level estimated from the log."""

    window_s: float = 0.5            # moving window for the variance and mean tests
    false_alarm: float = 1e-3        # per-window probability that pure noise fails a test (chi-square tail)
    noise_quantile: float = 0.05     # the quietest 5 % of windows define the noise level
    min_duration_s: float = 1.0      # shorter still runs are ignored ...
    min_samples: int = 40            # ... and runs of fewer samples: the drift test needs them at low rates
    edge_trim_s: float = 0.1         # dropped at both ends of a run before averaging
    rate_allowance_dps: float = 0.1  # gyro bias instability allowed between still windows (deg/s)
    gravity_tolerance: float = 0.15  # | |a| - g | / g above this is not at rest (constant linear acceleration)


@dataclass(frozen=True)
class Config:
    """Everything `magcal fit` can be told; nothing else changes the result."""

    method: str = "auto"
    mag: str = "all"
    imu: str | None = None
    start_s: float | None = None
    end_s: float | None = None
    still: StillConfig = StillConfig()
    min_poses: int = 6               # Kok 2012 needs this many distinct still orientations
    min_pose_separation_deg: float = 15.0
    kok_sigma_rounds: int = 3        # ML alternations between theta and the noise covariances
    allow_truncated: bool = False
    location: tuple[float, float, float] | None = None   # lat, lon (deg), alt (m): dip and field from the WMM
    date: str | None = None          # YYYY-MM-DD for the WMM (default: the log's date when known, else today)
    robust_loss: str = "l2"          # joint MAP: l2, huber or cauchy (outlier-tolerant)
    effects: tuple[str, ...] = ()    # effect plug-ins to model (ids of magcal_cli.effects.EFFECTS); () = base model
    diagnose: bool = False           # --effects auto: the mismatch diagnosis chooses the effects (diagnose/)
    imu_timing: Sampling | None = None   # what an IMU sample stands for (None: what the log's format says)
    mag_timing: Sampling | None = None   # the same for the magnetometers (timing.py, docs/timing.md)
    export_worse: bool = False       # write a compass the heading check finds worse than the flown one anyway
