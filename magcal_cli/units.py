"""The only table of unit factors: native unit name -> factor to SI, and the document's unit names."""

from __future__ import annotations

from magcal_cli.errors import StreamError

#: standard gravity (m/s^2): the magnitude every estimator and the detector take for the vertical
G = 9.80665

#: factor that turns a value in the named unit into SI (tesla, m/s^2, rad/s, s, degC, A, V, 1)
TO_SI: dict[str, float] = {
    "tesla": 1.0,
    "millitesla": 1e-3,
    "microtesla": 1e-6,
    "nanotesla": 1e-9,
    "gauss": 1e-4,
    "milligauss": 1e-7,
    "m/s^2": 1.0,
    "g": G,
    "rad/s": 1.0,
    "deg/s": 3.141592653589793 / 180.0,
    "s": 1.0,
    "ms": 1e-3,
    "us": 1e-6,
    "ns": 1e-9,
    "degC": 1.0,
    "A": 1.0,
    "cA": 1e-2,
    "V": 1.0,
    "1": 1.0,
    "deg": 3.141592653589793 / 180.0,
    "rad": 1.0,
    "m": 1.0,
}

#: spellings users and logs use -> canonical name above
ALIASES: dict[str, str] = {
    "T": "tesla", "mT": "millitesla", "uT": "microtesla", "µT": "microtesla", "μT": "microtesla",
    "nT": "nanotesla", "G": "gauss", "Ga": "gauss", "mG": "milligauss", "mGauss": "milligauss",
    "m/s2": "m/s^2", "m/s/s": "m/s^2", "m/s²": "m/s^2", "rad/sec": "rad/s", "dps": "deg/s",
    "°/s": "deg/s", "deg/sec": "deg/s", "sec": "s", "µs": "us", "μs": "us", "C": "degC", "°C": "degC",
    "celsius": "degC", "amp": "A", "ampere": "A", "volt": "V",
}

#: magnetic units a calibration document may be expressed in
MAG_UNITS = ("tesla", "millitesla", "microtesla", "nanotesla", "gauss", "milligauss")


def canonical(unit: str) -> str:
    """Return the canonical spelling of a unit name, or raise StreamError naming the known ones."""
    name = ALIASES.get(unit.strip(), unit.strip())
    if name not in TO_SI:
        msg = f"unknown unit {unit!r}; known units: {', '.join(sorted(TO_SI))}"
        raise StreamError(msg)
    return name


def to_si(unit: str) -> float:
    """Factor converting a value in `unit` to SI."""
    return TO_SI[canonical(unit)]


def from_si(unit: str) -> float:
    """Factor converting an SI value to `unit`."""
    return 1.0 / TO_SI[canonical(unit)]


#: GPS time: its epoch as a Unix time (1980-01-06), seconds per week, and GPS - UTC since 2017-01-01 (leap seconds)
GPS_EPOCH_UNIX, GPS_WEEK_S, GPS_LEAP_S = 315_964_800.0, 604_800.0, 18.0
