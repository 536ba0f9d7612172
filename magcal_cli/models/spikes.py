"""Isolated spikes in magnetometer readings, smoothed before the algebraic start values are computed."""

from __future__ import annotations

import numpy as np

from magcal_cli.streams import FloatArray


def despike(y: FloatArray, width: int = 5, k: float = 6.0, share: float = 0.05) -> tuple[FloatArray, int]:
    """Readings with isolated spikes replaced by a running median (for the initialisation only).

    A reading is a spike when it deviates from the median of its `width` neighbours by more than k robust
    standard deviations (1.4826 MAD) of those deviations and by more than `share` of the typical field
    magnitude: only spikes large enough to distort the algebraic ellipsoid fit. Returns readings and count.
    """
    from scipy import ndimage  # on use: not at `import magcal_cli.pipeline` (issue 27)

    med = ndimage.median_filter(y, size=(width, 1), mode="nearest")
    dev = np.linalg.norm(y - med, axis=1)
    mad = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
    big = share * float(np.median(np.linalg.norm(y - np.median(y, axis=0), axis=1)))
    spike = dev > max(k * mad, big)
    return np.where(spike[:, None], med, y), int(spike.sum())
