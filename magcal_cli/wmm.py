"""The reference field from the World Magnetic Model (NOAA/BGS WMM, via the maintained `pygeomag` port).

Used when the position of a log is known (`fit --location LAT,LON[,ALT] --date YYYY-MM-DD`, or a position
stream in the log): the dip angle starts the joint MAP fit, the total intensity is the document's
`field_strength` (`field_strength_source: "wmm"`).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np

from magcal_cli.errors import MagcalError, MissingDependencyError


@dataclass(frozen=True)
class ReferenceField:
    """WMM at a place and date: dip (rad, down positive), total intensity (T), declination (rad), model."""

    dip: float
    intensity: float
    declination: float
    model: str
    latitude: float
    longitude: float
    altitude_m: float
    date: dt.date

    @property
    def dip_deg(self) -> float:
        """Dip angle in degrees."""
        return float(np.degrees(self.dip))


def parse_location(text: str) -> tuple[float, float, float]:
    """'LAT,LON[,ALT]' (deg, deg, m) -> (lat, lon, alt); a MagcalError showing the expected form otherwise."""
    try:
        parts = [float(p) for p in text.split(",")]
    except ValueError:
        parts = []
    if len(parts) not in (2, 3) or not -90.0 <= parts[0] <= 90.0 or not -180.0 <= parts[1] <= 360.0:
        msg = f"--location {text!r}: expected LAT,LON[,ALT] in degrees and metres, e.g. 52.52,13.40,35"
        raise MagcalError(msg)
    return parts[0], parts[1], parts[2] if len(parts) == 3 else 0.0


def parse_date(text: str) -> dt.date:
    """'YYYY-MM-DD' -> date; raises MagcalError with the expected form."""
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        msg = f"--date {text!r}: expected YYYY-MM-DD, e.g. 2025-06-30"
        raise MagcalError(msg) from None


def decimal_year(date: dt.date) -> float:
    """Year plus the fraction of it elapsed at the start of `date`."""
    start = dt.date(date.year, 1, 1)
    days = (dt.date(date.year + 1, 1, 1) - start).days
    return date.year + (date - start).days / days


def reference_field(lat: float, lon: float, alt_m: float, date: dt.date) -> ReferenceField:
    """The WMM main field at geodetic (lat, lon, alt) on `date` (the model epoch is chosen by the year)."""
    try:
        from pygeomag import GeoMag
    except ImportError:
        msg = "the World Magnetic Model needs the package 'pygeomag'; run: pip install pygeomag"
        raise MissingDependencyError(msg) from None
    year = decimal_year(date)
    base = min(max(int(year // 5 * 5), 2010), 2025)
    geomag = GeoMag(base_year=base)
    lon = lon - 360.0 if lon > 180.0 else lon
    res = geomag.calculate(glat=lat, glon=lon, alt=alt_m / 1000.0, time=year,
                           allow_date_outside_lifespan=True)
    return ReferenceField(float(np.radians(res.i)), float(res.f) * 1e-9, float(np.radians(res.d)),
                          str(geomag.model), lat, lon, alt_m, date)


def reference_for(cfg: object) -> ReferenceField | None:
    """The reference field for a Config with `location` (lat, lon, alt) and `date` set, else None."""
    loc = getattr(cfg, "location", None)
    if loc is None:
        return None
    date = getattr(cfg, "date", None)
    day = parse_date(date) if isinstance(date, str) else (date or dt.datetime.now(dt.timezone.utc).date())
    return reference_field(float(loc[0]), float(loc[1]), float(loc[2]) if len(loc) > 2 else 0.0, day)
