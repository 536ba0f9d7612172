"""The Python API for notebooks and ROS nodes: `fit` a log, `apply` the calibration to readings, `load`/`save`.

`magcal fit` and `magcal apply` run through the same functions (`config` builds fit's Config, `apply` shares
`calibration.apply.calibrated` with the CSV), so a notebook, a node and the command line give the same numbers.
Bad arguments raise `OptionError` (a MagcalError) naming the argument, what it got and what it takes; docs/api.md.
"""

from __future__ import annotations

import datetime as dt
import math
import os
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

import numpy as np
import numpy.typing as npt

from magcal_cli import units
from magcal_cli.calibration import types
from magcal_cli.config import Config
from magcal_cli.effects.motor import MOTORS
from magcal_cli.errors import MagcalError, OptionError, StreamError
from magcal_cli.streams import FloatArray, Sampling

__all__ = ["Calibration", "apply", "apply_stamped", "config", "fit", "load", "save"]

#: the keyword of each effect channel `apply` takes, its unit and its width per reading (streams.Kind values)
CHANNELS = {"battery_current": ("A", 1), "battery_voltage": ("V", 1), "throttle": ("0..1", 1),
            "temperature": ("degC", 1), "motor_output": (f"0..1 of each motor's range, motors 1-{MOTORS}", MOTORS)}
ROBUST_LOSSES = ("l2", "huber", "cauchy")
PathLike = str | os.PathLike[str]


class Calibration(types.Calibration):
    """A calibration document (`magcal.calibration/1`) that loads and saves itself as JSON or YAML."""

    @classmethod
    def of(cls, cal: types.Calibration) -> Calibration:
        """The same document as this class (what `fit` and `load` return)."""
        return cal if isinstance(cal, cls) else cls(**{f.name: getattr(cal, f.name) for f in fields(cal)})

    @classmethod
    def load(cls, path: PathLike) -> Calibration:
        """Read a document from .json or .yaml/.yml (CalibrationFileError when it is not one)."""
        from magcal_cli.calibration.document import load as load_document

        return cls.of(load_document(Path(path)))

    def save(self, path: PathLike) -> Path:
        """Write the document atomically as JSON, or YAML for .yaml/.yml; returns the path."""
        return save(self, path)


def load(path: PathLike) -> Calibration:
    """`Calibration.load`: the document at `path` (.json, .yaml or .yml)."""
    return Calibration.load(path)


def save(cal: types.Calibration, path: PathLike) -> Path:
    """Write `cal` to `path` atomically: JSON for .json, YAML for .yaml/.yml; returns the path."""
    from magcal_cli.atomic import write_text
    from magcal_cli.calibration.document import dumps_json, dumps_yaml

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".json", ".yaml", ".yml"):
        msg = f"save({str(path)!r}): cannot tell the format from {suffix or 'no extension'!r}; name a .json or .yaml file"
        raise OptionError(msg)
    return write_text(path, dumps_json(cal) if suffix == ".json" else dumps_yaml(cal))


# --- fit -----------------------------------------------------------------------------------------------------------

def fit(path: PathLike, *, method: str = "auto", effects: str | Sequence[str] = "auto",
        mag: str | Sequence[str] = "all", imu: str | None = None, start: float | None = None,
        end: float | None = None, location: Sequence[float] | None = None, date: str | dt.date | None = None,
        robust_loss: str = "l2", fmt: str | None = None, strict: bool = False,
        imu_timing: str | Sampling | None = None, mag_timing: str | Sampling | None = None) -> Calibration:
    """Calibrate the magnetometers of the log at `path` as `magcal fit` does (its options, keyword-only)."""
    from magcal_cli.pipeline import calibrate
    from magcal_cli.progress import noop

    cfg = config(method=method, effects=effects, mag=mag, imu=imu, start=start, end=end, location=location,
                 date=date, robust_loss=robust_loss, strict=strict, imu_timing=imu_timing, mag_timing=mag_timing)
    return Calibration.of(calibrate(Path(path), cfg, fmt, noop).calibration)


def config(*, method: str = "auto", effects: str | Sequence[str] = "auto", mag: str | Sequence[str] = "all",
           imu: str | None = None, start: float | None = None, end: float | None = None,
           location: Sequence[float] | None = None, date: str | dt.date | None = None, robust_loss: str = "l2",
           strict: bool = False, imu_timing: str | Sampling | None = None, mag_timing: str | Sampling | None = None,
           export_worse: bool = False) -> Config:
    """The checked Config `fit` (and `magcal fit`) calibrates with; effects 'auto' lets the diagnosis choose."""
    from magcal_cli.methods.table import CHOICES

    if method not in CHOICES:
        msg = f"fit(method={method!r}): unknown method; choose one of {', '.join(CHOICES)}"
        raise OptionError(msg)
    if robust_loss not in ROBUST_LOSSES:
        msg = f"fit(robust_loss={robust_loss!r}): unknown loss; choose one of {', '.join(ROBUST_LOSSES)}"
        raise OptionError(msg)
    ids, diagnose = _effects(method, effects)
    for name, x in (("start", start), ("end", end)):
        if x is not None and not (isinstance(x, int | float) and math.isfinite(x)):
            msg = f"fit({name}={x!r}): expected a finite number of seconds from the log start, or None"
            raise OptionError(msg)
    if start is not None and end is not None and start >= end:
        msg = f"fit(start={start:g}, end={end:g}): start must be before end (seconds from the log start)"
        raise OptionError(msg)
    return Config(method=method, mag=_names(mag, "mag") or "all", imu=imu, start_s=start, end_s=end,
                  allow_truncated=not strict, location=_location(location), date=_date(date),
                  robust_loss=robust_loss, effects=ids, diagnose=diagnose, imu_timing=_sampling(imu_timing, "imu"),
                  mag_timing=_sampling(mag_timing, "mag"), export_worse=export_worse)


def _names(value: str | Sequence[str], what: str) -> str:
    """A comma-separated id list from a string or a sequence of ids ('' for none)."""
    if isinstance(value, str):
        return value
    if not all(isinstance(v, str) for v in value):
        msg = f"fit({what}={value!r}): expected a string such as 'MAG[0],MAG[1]' or a list of ids"
        raise OptionError(msg)
    return ",".join(value)


def _effects(method: str, effects: str | Sequence[str]) -> tuple[tuple[str, ...], bool]:
    """(effect ids, diagnose): 'auto' lets the mismatch diagnosis choose, 'none' or () is the base model."""
    from magcal_cli.effects import parse
    from magcal_cli.methods.choose import not_carried

    text = _names(effects, "effects").strip()
    if text == "auto":
        return (), True
    try:
        ids = parse(text)
    except MagcalError as exc:
        msg = f"fit(effects={effects!r}): {str(exc).removeprefix('--effects: ')}"
        raise OptionError(msg) from None
    refused = not_carried(method, ids) if method != "auto" else ()
    if refused:
        msg = (f"fit(method={method!r}, effects={effects!r}): {method} cannot model {', '.join(refused)}; use "
               "method='map' (models every effect) or effects='none'")
        raise OptionError(msg)
    return ids, False


def _location(value: Sequence[float] | None) -> tuple[float, float, float] | None:
    """(lat, lon, alt) from 2 or 3 numbers in degrees and metres (alt 0 when left out)."""
    if value is None:
        return None
    try:
        numbers = [float(x) for x in value]
    except (TypeError, ValueError):
        numbers = []
    if (len(numbers) not in (2, 3) or not all(map(math.isfinite, numbers)) or not -90 <= numbers[0] <= 90
            or not -180 <= numbers[1] <= 180):
        msg = (f"fit(location={value!r}): expected (lat, lon) or (lat, lon, alt) in degrees and metres, latitude "
               "in [-90, 90] and longitude in [-180, 180], e.g. (52.52, 13.40, 35)")
        raise OptionError(msg)
    return numbers[0], numbers[1], numbers[2] if len(numbers) == 3 else 0.0


def _date(value: str | dt.date | None) -> str | None:
    """The World Magnetic Model's date as YYYY-MM-DD."""
    if value is None or isinstance(value, dt.date):
        return None if value is None else value.isoformat()
    try:
        return dt.date.fromisoformat(value).isoformat()
    except (TypeError, ValueError):
        msg = f"fit(date={value!r}): expected 'YYYY-MM-DD' or a datetime.date, e.g. '2025-06-30'"
        raise OptionError(msg) from None


def _sampling(value: str | Sampling | None, what: str) -> Sampling | None:
    """What each sample stands for (docs/timing.md); None keeps what the log's format says."""
    if value is None or isinstance(value, Sampling):
        return value
    try:
        return Sampling.parse(value)
    except (AttributeError, ValueError):
        msg = (f"fit({what}_timing={value!r}): expected one of {', '.join(s.value for s in Sampling)}, or None for "
               "what the log's format says")
        raise OptionError(msg) from None


# --- apply ---------------------------------------------------------------------------------------------------------

def apply(cal: types.Calibration, field: npt.ArrayLike, t: npt.ArrayLike, *, mag: str | None = None,
          unit: str | None = None, battery_current: npt.ArrayLike | None = None,
          battery_voltage: npt.ArrayLike | None = None, throttle: npt.ArrayLike | None = None,
          temperature: npt.ArrayLike | None = None, motor_output: npt.ArrayLike | None = None,
          skip_missing: bool = False) -> FloatArray:
    """The calibrated field of readings `field` (3,) or (N, 3) at `t` (s), shaped as `field` (docs/api.md)."""
    return apply_stamped(cal, field, t, mag=mag, unit=unit, battery_current=battery_current,
                         battery_voltage=battery_voltage, throttle=throttle, temperature=temperature,
                         motor_output=motor_output, skip_missing=skip_missing)[1]


def apply_stamped(cal: types.Calibration, field: npt.ArrayLike, t: npt.ArrayLike, *, mag: str | None = None,
                  unit: str | None = None, battery_current: npt.ArrayLike | None = None,
                  battery_voltage: npt.ArrayLike | None = None, throttle: npt.ArrayLike | None = None,
                  temperature: npt.ArrayLike | None = None, motor_output: npt.ArrayLike | None = None,
                  skip_missing: bool = False) -> tuple[FloatArray, FloatArray]:
    """`apply` with the stamps each corrected reading belongs to (a time_offset effect re-stamps them)."""
    from magcal_cli.calibration.apply import calibrated
    from magcal_cli.effects.correct import terms

    m = _magnetometer(cal, mag)
    y = np.asarray(field, dtype=np.float64)
    single = y.shape == (3,)
    y2 = y.reshape(1, 3) if single else y
    if y2.ndim != 2 or y2.shape[1] != 3:
        msg = f"apply(field of shape {y.shape}): expected one reading (3,) or readings (N, 3)"
        raise OptionError(msg)
    n = len(y2)
    t1 = _per_reading(t, "t", n, 1)
    if not np.all(np.isfinite(t1)):
        msg = "apply(t=...): the stamps must be finite seconds"
        raise OptionError(msg)
    given = {"battery_current": battery_current, "battery_voltage": battery_voltage, "throttle": throttle,
             "temperature": temperature, "motor_output": motor_output}
    chans = {k: _per_reading(v, k, n, CHANNELS[k][1]) for k, v in given.items() if v is not None}
    if not skip_missing:
        for e, eff in terms(cal.effects, m.id):
            lacking = [k.value for k in eff.channels if k.value not in chans]
            if lacking:
                msg = (f"apply({m.id}): the calibration carries the {e.get('status')} {eff.id}, which needs "
                       f"{' and '.join(f'{k}= ({CHANNELS[k][0]})' for k in lacking)}; pass it, one value per "
                       "reading, or skip_missing=True to leave the effect in (as magcal apply does on a log "
                       "without the channel)")
                raise OptionError(msg)
    scale = 1.0 if unit is None else _unit_factor(unit, m.unit)
    stamps, out, _ = calibrated(cal, m, t1, y2 * scale, chans)
    out = out / scale
    return (stamps[0:1].reshape(()), out[0]) if single else (stamps, out)


def _magnetometer(cal: types.Calibration, mag: str | None) -> types.MagCalibration:
    """The document's magnetometer `mag`; None only when it has one."""
    ids = [m.id for m in cal.magnetometers]
    if mag is None and len(ids) != 1:
        msg = (f"apply(mag=None): the calibration has {len(ids)} magnetometers ({', '.join(ids) or 'none'}); "
               "pass mag= with one of them")
        raise OptionError(msg)
    if mag is not None and mag not in ids:
        msg = f"apply(mag={mag!r}): not in the calibration, which has {', '.join(ids) or 'no magnetometer'}"
        raise OptionError(msg)
    return cal.magnetometer(mag)


def _per_reading(value: npt.ArrayLike, name: str, n: int, width: int) -> FloatArray:
    """`value` as (n,) (width 1) or (n, width): a scalar or one row is held for every reading."""
    a = np.asarray(value, dtype=np.float64)
    shape = (n,) if width == 1 else (n, width)
    try:
        return np.array(np.broadcast_to(a, shape), dtype=np.float64)
    except ValueError:
        want = "a number or (N,)" if width == 1 else f"({width},) or (N, {width})"
        msg = f"apply({name} of shape {a.shape}): expected {want} for {n} reading{'s' * (n != 1)}"
        raise OptionError(msg) from None


def _unit_factor(unit: str, doc_unit: str) -> float:
    """The factor from `unit` to the document's unit."""
    try:
        return units.to_si(unit) * units.from_si(doc_unit)
    except StreamError as exc:
        msg = f"apply(unit={unit!r}): {exc}; or None for the calibration's own unit ({doc_unit})"
        raise OptionError(msg) from None
