"""The estimator's input: the selected IMU and magnetometer streams and the still segments found in them."""

from __future__ import annotations

from dataclasses import dataclass

from ..detect import StillResult
from ..streams import Stream


@dataclass(frozen=True, eq=False)
class Problem:
    """Streams in SI units on the log's time base, ready for any method; `where` names the log in messages."""

    where: str
    imu_id: str
    acc: Stream
    gyr: Stream
    mags: tuple[Stream, ...]
    still: StillResult
