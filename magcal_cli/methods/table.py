"""The calibration methods, in one table: what `--method` accepts, what the report calls them, what runs them.

numpy-free: the command line builds its choices from this table at startup.
"""

from __future__ import annotations

from typing import Any, NamedTuple


class Method(NamedTuple):
    """One calibration method: `--method` id, the report's title, its run and the effects it can carry.

    `run` is "module:function(problem, config) -> MethodResult", imported on use (registry.resolve), or the
    function itself (tests swap in fakes). `carries`: "all" (every effect plug-in), "additive" (the EKFs'
    additive magnetometer terms, models/ekf/effects.py) or "none".
    """

    id: str
    title: str
    run: Any
    carries: str


METHODS: dict[str, Method] = {m.id: m for m in (
    Method("kok2012", "Kok et al. 2012 (ellipsoid fit, alignment with the accelerometer's vertical, maximum "
           "likelihood)", "magcal_cli.models.kok2012:run", "none"),
    Method("map", "Huang et al. 2025 joint MAP (trajectory, accelerometer and gyro biases, D, o, dip; gyro "
           "preintegration)", "magcal_cli.methods.map_run:run", "all"),
    Method("ekf-ml", "Kok & Schoen 2016 (EKF innovation likelihood maximised over the calibration and noise "
           "levels)", "magcal_cli.models.ekf.ml:run", "additive"),
    Method("ekf-aug", "Wu et al. 2018 (one pass of an EKF with orientation and calibration in the state)",
           "magcal_cli.models.ekf.aug:run", "additive"),
    Method("attitude", "the vehicle's attitude estimate and the World Magnetic Model as the reference",
           "magcal_cli.models.attitude_ref:run", "none"),
)}
#: what `--method` accepts: auto (methods/choose.py picks) and every method
CHOICES = ("auto", *METHODS)


def title(method: str) -> str:
    """The report's name for `method` (the id itself for one the table does not know)."""
    m = METHODS.get(method)
    return m.title if m else method
