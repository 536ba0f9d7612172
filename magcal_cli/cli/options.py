"""Arguments checked the same way in every command: --mag, --format, --location, --start/--end, outputs, a
calibration document where one belongs.

A bad value is click's usage error (exit 2) naming the option, the value and what it accepts.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

if TYPE_CHECKING:
    from magcal_cli.calibration.types import Calibration
    from magcal_cli.streams import Sampling

F = TypeVar("F", bound=Callable[..., Any])

#: latitude and longitude ranges of --location (deg)
LAT_RANGE, LON_RANGE = (-90.0, 90.0), (-180.0, 180.0)
LOCATION_FORM = "LAT,LON[,ALT] in degrees and metres, e.g. 52.52,13.40,35"


def mag_ids(_: click.Context, __: click.Parameter, values: tuple[str, ...]) -> tuple[str, ...]:
    """--mag: repeatable and a comma list, in every command; () means every magnetometer ('all')."""
    ids: list[str] = []
    for value in values:
        parts = [p.strip() for p in value.split(",")]
        if any(not p for p in parts):
            msg = f"{value!r} has an empty id; give stream ids as magcal inspect lists them, e.g. --mag 'MAG[0]'"
            raise click.BadParameter(msg)
        ids += [p for p in parts if p not in ids]
    if "all" in ids and len(ids) > 1:
        msg = f"'all' cannot be combined with ids ({', '.join(i for i in ids if i != 'all')}); give one or the other"
        raise click.BadParameter(msg)
    return () if ids == ["all"] else tuple(ids)


def log_format(_: click.Context, __: click.Parameter, value: str | None) -> str | None:
    """--format: a registered reader's name, or None to sniff the log."""
    from magcal_cli.readers import READERS

    if value is None or value in READERS:
        return value
    msg = f"{value!r} is not a log format; choose from {', '.join(sorted(READERS))}, or leave --format out"
    raise click.BadParameter(msg)


def location(_: click.Context, __: click.Parameter, value: str | None) -> tuple[float, float, float] | None:
    """--location LAT,LON[,ALT] with latitude and longitude in range, or a usage error saying the range."""
    from magcal_cli.errors import MagcalError
    from magcal_cli.wmm import parse_location

    if value is None:
        return None
    try:
        numbers = [float(p) for p in value.split(",")]
    except ValueError:
        numbers = []
    if len(numbers) in (2, 3):
        for name, x, (lo, hi) in (("latitude", numbers[0], LAT_RANGE), ("longitude", numbers[1], LON_RANGE)):
            if not lo <= x <= hi:
                msg = f"{value!r}: {name} {x:g} is out of range [{lo:g}, {hi:g}]; expected {LOCATION_FORM}"
                raise click.BadParameter(msg)
    try:
        return parse_location(value)
    except MagcalError as exc:
        raise click.BadParameter(str(exc).removeprefix("--location ")) from None


def time_window(start_s: float | None, end_s: float | None) -> None:
    """--start and --end: finite, and the start before the end, or a usage error naming both."""
    for name, x in (("--start", start_s), ("--end", end_s)):
        if x is not None and not math.isfinite(x):
            msg = f"{x:g}: expected a finite number of seconds from the log start"
            raise click.BadParameter(msg, param_hint=f"'{name}'")
    if start_s is not None and end_s is not None and start_s >= end_s:
        msg = (f"--start {start_s:g} is not before --end {end_s:g}; give --start S --end E with S < E "
               "(seconds from the log start)")
        raise click.UsageError(msg)


def refuse_existing(paths: Iterable[Path], force: bool, hint: str = "") -> None:
    """Usage error (exit 2) when an output exists already and --force was not given."""
    if force:
        return
    for p in paths:
        if p.exists():
            msg = f"{p}: exists already. Pass --force to overwrite it{hint}"
            raise click.UsageError(msg)


def calibration_document(path: Path, role: str, fix: str) -> Calibration:
    """The calibration document at `path`; a log there is a usage error (exit 2) saying what belongs there."""
    from magcal_cli.calibration.document import load
    from magcal_cli.errors import MagcalError
    from magcal_cli.readers import sniff

    try:
        fmt = sniff(path)
    except MagcalError:
        return load(path)
    msg = f"{path}: a {fmt} log where {role} (a calibration .json or .yaml from magcal fit) belongs. {fix}"
    raise click.UsageError(msg)


def log_extension(out: Path) -> None:
    """simulate OUT: a usage error (exit 2) when no log writer takes OUT's extension."""
    from magcal_cli.synth.logs import LOG_WRITERS

    if out.suffix.lower() not in LOG_WRITERS:
        known = ", ".join(sorted(e or "(none: a ROS 2 bag directory)" for e in LOG_WRITERS))
        msg = f"{out}: cannot write a log with extension {out.suffix!r}; use one of {known}"
        raise click.BadParameter(msg, param_hint="OUT")


#: --imu-timing and --mag-timing: what a sample stands for (docs/timing.md); Sampling's values (timing.CHOICES),
#: spelled out so that the command line starts without importing numpy (tests/test_timing.py checks they agree)
TIMING_CHOICES = ("instant", "preceding", "following")
TIMING_HELP = ("What each {what} sample stands for: instant (the value at its stamp), preceding (the mean over the "
               "interval that ends at its stamp{example}) or following (the mean over the interval that starts at "
               "it) [default: what the log's format defines, docs/timing.md].")


def sampling(_: click.Context, __: click.Parameter, value: str | None) -> Sampling | None:
    """--imu-timing/--mag-timing as a Sampling, None to take the log format's own."""
    from magcal_cli.streams import Sampling

    return None if value is None else Sampling.parse(value)


def timing(func: F) -> F:
    """The --imu-timing and --mag-timing options of every command that fits."""
    for name, what, example in (("--mag-timing", "magnetometer", ""),
                                ("--imu-timing", "gyro and accelerometer", ": PX4 sensor_combined, delta-angle IMUs")):
        func = click.option(name, name.strip("-").replace("-", "_"), type=click.Choice(TIMING_CHOICES),
                            default=None, callback=sampling, help=TIMING_HELP.format(what=what, example=example))(func)
    return func

MAG_HELP = ("Magnetometer stream id(s) to {what}; repeatable and comma-separated (e.g. --mag 'MAG[0],MAG[1]'), "
            "or 'all' [default: all].")
FORMAT_HELP = "Force the log format instead of sniffing it (e.g. mcap)."


def wmm_date(_: click.Context, __: click.Parameter, value: str | None) -> str | None:
    """--date YYYY-MM-DD checked, or a usage error."""
    from magcal_cli.errors import MagcalError
    from magcal_cli.wmm import parse_date

    try:
        return None if value is None else parse_date(value).isoformat()
    except MagcalError as exc:
        raise click.BadParameter(str(exc)) from None


def mag(what: str) -> Callable[[F], F]:
    """--mag ID[,ID...]|all, declared once for every command that selects magnetometers."""
    return click.option("--mag", "mags", multiple=True, callback=mag_ids, metavar="ID[,ID...]|all",
                        help=MAG_HELP.format(what=what))


def fmt(func: F) -> F:
    """--format, declared once for every command that reads a log."""
    return click.option("--format", "fmt", default=None, callback=log_format, help=FORMAT_HELP)(func)


def force(help_text: str = "Overwrite existing outputs.") -> Callable[[F], F]:
    """--force, declared once for every command that writes files."""
    return click.option("--force", is_flag=True, help=help_text)


def as_json(help_text: str) -> Callable[[F], F]:
    """--json, declared once for every command that can print a machine-readable document."""
    return click.option("--json", "as_json", is_flag=True, help=help_text)
