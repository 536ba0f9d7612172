"""The estimator's input: the selected IMU and magnetometer streams and the still segments found in them."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from magcal_cli.detect import BlockScale, StillResult
from magcal_cli.models.partial import MagPrior
from magcal_cli.streams import Kind, Stream


@dataclass(frozen=True, eq=False)
class Problem:
    """Streams in SI units on the log's time base, ready for any method; `where` names the log in messages.

    Time convention (timing.for_estimator): gyro sample k is the mean rate over [t_k, t_k+1); accelerometer and
    magnetometer samples are the values at their stamps. `timing` records what the log's samples were taken to
    stand for (the document's source.timing).

    `aux` holds the log's other channels (current, throttle, temperature, position, ...) that effect terms use.
    `priors` holds what a magnetometer's calibration is held at where the log cannot determine it.
    """

    where: str
    imu_id: str
    acc: Stream
    gyr: Stream
    mags: tuple[Stream, ...]
    still: StillResult
    aux: tuple[Stream, ...] = ()
    #: the calibration each magnetometer flew with (by id), the prior of a partial calibration
    priors: Mapping[str, MagPrior] = field(default_factory=dict)
    #: time windows (s) whose motion the IMU did not measure (gyro saturated, impact): the trajectory is broken
    #: there and the samples inside are not used
    unmeasured: tuple[tuple[float, float], ...] = ()
    #: effects every fit of this problem models, whatever else is chosen: known physics the log measures (a
    #: flight's own acceleration from its GPS), not a hypothesis for the diagnosis to test
    base_effects: tuple[str, ...] = ()
    #: {"imu", "magnetometer", "set_by"}: the sampling the log's streams were read with (timing.py)
    timing: Mapping[str, str] = field(default_factory=dict)
    #: each gyro sample's noise std relative to the still level (detect.gyro_noise_scale); None: 1
    gyr_scale: BlockScale | None = None

    def channels(self, kind: Kind) -> tuple[Stream, ...]:
        """The auxiliary streams of one kind, in log order."""
        return tuple(s for s in self.aux if s.kind is kind and len(s) >= 2)

    def of_kind(self, kind: Kind) -> list[Stream]:
        """The auxiliary streams of one kind, as a Recording lists them (effects/correct.remove reads them)."""
        return list(self.channels(kind))
