"""Checks every reader applies to decoded magnetometer samples: unit-length field, held (repeated) readings."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: relative spread of |m| below which the field was normalised upstream; real sensors show >= 0.1 % noise
NORMALISED_SPREAD = 1e-4
#: share of readings that repeat their predecessor bit for bit above which the source holds stale values
HELD_SHARE = 0.5


def field_spread(xyz: npt.ArrayLike) -> tuple[float, float]:
    """Median magnitude and relative spread (std / median) of the field vectors (N, 3)."""
    norms = np.linalg.norm(np.asarray(xyz, dtype=np.float64).reshape(-1, 3), axis=1)
    if norms.size == 0:
        return 0.0, float("inf")
    median = float(np.median(norms))
    return median, float(np.std(norms) / median) if median > 0 else float("inf")


def normalised_field(xyz: npt.ArrayLike) -> bool:
    """True when at least 10 readings all have the same magnitude: the field was scaled to unit length upstream."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return xyz.shape[0] >= 10 and field_spread(xyz)[1] < NORMALISED_SPREAD


def normalised_note(stream_id: str, xyz: FloatArray, unit: str) -> str:
    """The reader note for a field normalised upstream."""
    median, spread = field_spread(xyz)
    return (f"{stream_id}: every field reading has magnitude {median:.6g} {unit} (relative spread {spread:.0e}): "
            "the field was normalised to a unit vector upstream, so hard iron is not recoverable in absolute terms")


def drop_held(t: FloatArray, xyz: FloatArray, where: str) -> tuple[FloatArray, FloatArray, list[str]]:
    """Drop readings that repeat the previous one exactly when most do (a source that holds its last value).

    A held value is a stale reading stamped later than it was taken; keeping it would add up to one update
    period of delay, the time offset interpolation avoids. Below HELD_SHARE repeats are kept (quantisation).
    """
    if len(t) < 3:
        return t, xyz, []
    same = np.concatenate([[False], np.all(xyz[1:] == xyz[:-1], axis=1)])
    if same.mean() < HELD_SHARE:
        return t, xyz, []
    keep = ~same
    note = (f"{where}: {int(same.sum())} of {len(t)} readings repeat the previous one exactly (the source holds "
            f"its last value between updates); kept the {int(keep.sum())} that changed")
    return t[keep], xyz[keep], [note]
