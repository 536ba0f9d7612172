"""The parsed ULog data sets by topic instance, and the pieces of stream read from them before t0 is known."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli.readers import ReadOptions
from magcal_cli.readers.ulog.load import Loaded
from magcal_cli.streams import FloatArray, Kind, Sampling

IntArray = npt.NDArray[np.int64]

#: a `timestamp_sample` further than this before the publication `timestamp` is not trusted (us)
MAX_SAMPLE_LAG_US = 1_000_000


@dataclass(frozen=True, eq=False)
class Piece:
    """One stream before the log's zero time is known: integer microseconds and SI values."""

    kind: Kind
    id: str
    t_us: IntArray
    values: FloatArray
    source: str
    unit: str
    sampling: Sampling = Sampling.INSTANT
    window_s: float | None = None


@dataclass(frozen=True, eq=False)
class ImuPiece:
    """An IMU's gyro and accelerometer on their own stamps; the accelerometer moves onto the gyro's later."""

    id: str
    gyr: Piece
    acc: Piece


class Topics:
    """The parsed data sets by (topic, instance), with helpers that read fields as numpy arrays."""

    def __init__(self, loaded: Loaded, path: Path, options: ReadOptions) -> None:
        self.sets = {(d.name, int(d.multi_id)): d for d in loaded.ulog.data_list if "timestamp" in d.data}
        self.name = path.name
        self.use_sample = not options.receive_time
        self.notes: list[str] = []
        untimed = sorted({d.name for d in loaded.ulog.data_list if "timestamp" not in d.data})
        if untimed:                             # a format definition damaged: its data cannot be placed in time
            self.notes.append(f"ignored {', '.join(untimed)}: the format has no timestamp field (corrupt definition)")

    def instances(self, topic: str) -> list[int]:
        """The multi-instance indices logged for `topic`, in order."""
        return sorted(i for name, i in self.sets if name == topic)

    def get(self, topic: str, instance: int = 0) -> Any:
        """pyulog's data set of one topic instance, or None."""
        return self.sets.get((topic, instance))

    def stamps(self, ds: Any, label: str) -> IntArray:
        """Sample times (us): `timestamp_sample` (when the sensor sampled) where present and plausible, else
        `timestamp` (when the message was published); `--receive-time` asks for the publication time."""
        ts = np.asarray(ds.data["timestamp"], dtype=np.int64)
        if "timestamp_sample" not in ds.data or not self.use_sample:
            return ts
        tss = np.asarray(ds.data["timestamp_sample"], dtype=np.int64)
        lag = ts - tss
        if np.all((tss > 0) & (lag >= 0) & (lag <= MAX_SAMPLE_LAG_US)):
            return tss
        self.notes.append(f"{label}: timestamp_sample is zero or not within 1 s before timestamp; "
                          "used timestamp")
        return ts

    @staticmethod
    def columns(ds: Any, names: list[str]) -> FloatArray | None:
        """The named fields as an (N, len(names)) float array, or None when one is missing."""
        if not all(n in ds.data for n in names):
            return None
        return np.stack([np.asarray(ds.data[n], dtype=np.float64) for n in names], axis=1)

    def source(self, label: str, fields: str) -> str:
        """Provenance shown by `inspect`: log name, topic instance and fields."""
        return f"{self.name}#{label}: {fields}"


def vector_fields(name: str) -> list[str]:
    """pyulog's names of a float[3] field's elements."""
    return [f"{name}[{i}]" for i in range(3)]


def int_field(ds: Any, name: str, n: int) -> IntArray:
    """An integer field as int64, zeros when the topic version lacks it."""
    return np.asarray(ds.data[name], dtype=np.int64) if name in ds.data else np.zeros(n, dtype=np.int64)
