"""What a command checks in its body, after click has read its options: windows, existing outputs, documents
where a log was given, option combinations, '-' for standard output. A mistake is click's usage error (exit 2); a
log the window leaves empty is a StreamError (exit 1), as for the fit.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import click

from magcal_cli.cli.options import AUTO

if TYPE_CHECKING:
    from magcal_cli.calibration.types import Calibration
    from magcal_cli.streams import Recording


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


def windowed(rec: Recording, start_s: float | None, end_s: float | None) -> Recording:
    """`rec` cut to --start/--end as the fit cuts its streams (`Stream.between`, s from the log start), for the
    commands that use a recording themselves (check, apply); a stream left with under two samples is dropped, and
    no magnetometer left is a StreamError (exit 1), as for the fit."""
    from dataclasses import replace

    from magcal_cli.errors import StreamError
    from magcal_cli.streams import Kind

    if start_s is None and end_s is None:
        return rec
    streams = tuple(c for c in (s.between(start_s, end_s) for s in rec.streams) if len(c) >= 2)
    if not any(s.kind is Kind.MAGNETOMETER for s in streams):
        span = [float(t) for s in rec.of_kind(Kind.MAGNETOMETER) if len(s) for t in (s.t[0], s.t[-1])]
        spans = f" (its magnetometers span {min(span):.1f} to {max(span):.1f} s)" if span else ""
        msg = f"{rec.path.name}: no magnetometer samples between --start and --end{spans}; widen the time window"
        raise StreamError(msg)
    return replace(rec, streams=streams)


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


def log_extension(out: Path, hint: str = "-o") -> None:
    """simulate's log: a usage error (exit 2) when no log writer takes its extension."""
    from magcal_cli.synth.logs import LOG_WRITERS

    if out.suffix.lower() not in LOG_WRITERS:
        known = ", ".join(sorted(e or "(none: a ROS 2 bag directory)" for e in LOG_WRITERS))
        msg = f"{out}: cannot write a log with extension {out.suffix!r}; use one of {known}"
        raise click.BadParameter(msg, param_hint=hint)


def method_effects(method: str, effects: tuple[str, ...]) -> None:
    """--method naming a method that cannot model the --effects asked for: a usage error (exit 2) before the work.
    (With --method auto the choice depends on the log, and the pipeline refuses it, exit 1.)"""
    from magcal_cli.methods.choose import not_carried

    if method == "auto" or effects == AUTO:
        return
    refused = not_carried(method, effects)
    if refused:
        msg = (f"--effects {','.join(refused)} cannot be modelled by --method {method}; the joint MAP method models "
               "every effect (the EKFs current_interference and temperature_drift, ekf-ml also "
               "throttle_interference): use --method map, or --effects none")
        raise click.UsageError(msg)


def mags_in(mags: Iterable[str], have: list[str], where: str) -> None:
    """--mag naming a magnetometer that `where` (a calibration document) does not have: a usage error (exit 2)."""
    missing = [m for m in mags if m not in have]
    if missing:
        msg = (f"{', '.join(missing)}: not in {where}, which has {', '.join(have) or 'no magnetometer'}; give --mag "
               "with some of them")
        raise click.BadParameter(msg, param_hint="'--mag'")


def is_stdout(path: Path | None) -> bool:
    """'-' names standard output wherever a file is written, as Unix tools read it (not a file named '-')."""
    return path is not None and str(path) == "-"


def history(store: Path | None, vehicle: str | None) -> None:
    """--history: a store that opens (created and migrated) before any work; --vehicle needs it (exit 2)."""
    if vehicle is not None and store is None:
        msg = "--vehicle names the vehicle in the history store: give --history DB too"
        raise click.UsageError(msg)
    if store is not None:
        from magcal_cli.history.store import connect

        with connect(store):
            pass
