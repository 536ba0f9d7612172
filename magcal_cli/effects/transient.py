"""`transient_disturbance`: an external field that came and went (a vehicle passing, a tool, a magnet) in some time
windows (mismatch.md E6). The windows are found from the field norm, which no orientation can explain away, and
their readings are excluded from the fit (weight zero): a robust fit, not a model of the disturbance.

The norm residual rho = |D0^-1 (y - o0)| - 1 of an ellipsoid fit is smoothed over SMOOTH_S; epochs whose rho is
more than K_MAD robust standard deviations (and MIN_REL of the field) from its median, in runs of at least
MIN_RUN_S, are flagged; the ellipsoid is refitted without them once and the test repeated.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from magcal_cli.align import columns
from magcal_cli.detect import padded_runs
from magcal_cli.effects.base import Effect, Inputs, Kinematics, NotTestable, Point, Target, Term
from magcal_cli.errors import MagcalError
from magcal_cli.streams import FloatArray, Stream

SMOOTH_S = 0.5
K_MAD = 6.0
#: below this relative norm change (1 % of the field) a window is not worth excluding
MIN_REL = 0.01
MIN_RUN_S = 1.0
#: the first ellipsoid is fitted to the readings whose norm residual is below this percentile
TRIM_PCT = 70.0
#: flagged windows are widened by this much on both sides (a disturbance fades in and out)
PAD_S = 0.5


def _rho(y: FloatArray, keep: np.ndarray) -> FloatArray:
    """Norm residual of an ellipsoid fitted to the kept readings."""
    from magcal_cli.ellipsoid import fit_ellipsoid

    ell = fit_ellipsoid(y[keep])
    return np.asarray(np.linalg.norm((y - ell.o0) @ np.linalg.inv(ell.D0).T, axis=1) - 1.0)


def windows(t: FloatArray, flagged: np.ndarray) -> list[list[float]]:
    """[[t0, t1], ...] of runs of flagged epochs at least MIN_RUN_S long, padded by PAD_S."""
    return padded_runs(t, flagged, PAD_S, MIN_RUN_S)


def detect(t: FloatArray, y: FloatArray) -> list[list[float]]:
    """Disturbed windows of readings y (K, 3) at times t (s)."""
    from scipy.ndimage import median_filter  # on use: not loaded by every fit that never looks for windows

    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    size = max(3, int(round(SMOOTH_S / dt)) | 1)
    keep = np.ones(t.size, bool)
    rho = median_filter(_rho(y, keep), size=size, mode="nearest")
    dev = np.abs(rho - np.median(rho))
    keep = dev <= np.percentile(dev, TRIM_PCT)         # a trimmed start: the windows would bias the ellipsoid
    found: list[list[float]] = []
    for _ in range(2):                                  # then refit without the windows found and test again
        rho = median_filter(_rho(y, keep), size=size, mode="nearest")
        dev = rho - np.median(rho[keep])
        sd = 1.4826 * float(np.median(np.abs(dev[keep])))
        flagged = np.abs(dev) > max(K_MAD * sd, MIN_REL)
        found = windows(t, flagged)
        inside = np.zeros(t.size, bool)
        for lo, hi in found:
            inside |= (t >= lo) & (t <= hi)
        if inside.mean() > 0.5:                        # most of the log "disturbed": nothing is a baseline
            return []
        keep = ~inside
    return found


class Transient(Effect):
    """Readings inside disturbed windows get weight zero."""

    id = "transient_disturbance"
    target = Target.MAG
    params = ()
    units: ClassVar[dict[str, str]] = {"windows_s": "s", "excluded_fraction": "1"}
    physics_left_out = ("An external magnetic field came and went during the recording (a vehicle, a tool, a "
                        "magnet near the sensor); those readings were left out of the fit.")

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """The disturbed windows of this magnetometer, and the weight of each epoch."""
        y = columns(kin.t, mag.t, mag.xyz)
        try:
            found = detect(kin.t, y)
        except MagcalError:
            msg = "the readings do not determine an ellipsoid for the field-norm test"
            raise NotTestable(msg) from None
        weight = np.ones(kin.t.size)
        for lo, hi in found:
            weight[(kin.t >= lo) & (kin.t <= hi)] = 0.0
        return Inputs(kin.t, kin.omega, kin.omega_dot, {"weight": weight}, (mag.id,),
                      {"windows_s": found, "excluded_fraction": float(1.0 - weight.mean())})

    def weights(self, inp: Inputs) -> FloatArray | None:
        """Zero inside the windows."""
        return inp.channels["weight"]

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """Nothing is added to the prediction."""
        m = inp.t.size
        return Term(np.zeros((m, 3)), np.zeros((m, 3, 0)))

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """Readings inside the windows become NaN (they do not measure the Earth's field)."""
        y = np.array(y, dtype=np.float64)
        for lo, hi in params.get("windows_s") or []:
            y[(t >= lo) & (t <= hi)] = np.nan
        return t, y


EFFECT = Transient()
