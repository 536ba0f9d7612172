"""Cut logs, one policy for every reader: read up to the last complete record and say so; --strict refuses.

A log whose end is cut (a vehicle powered off while logging, a recorder killed) is the normal state of many
flight logs (spec/cli.md). Readers find where their format's last complete record ends; this module turns
that into the note, the `Recording.cut` the CLI warns with, or the --strict error.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from magcal_cli.errors import TruncatedLogError
from magcal_cli.readers import ReadOptions
from magcal_cli.streams import Cut, Recording


def refuse_if_strict(path: Path, options: ReadOptions, cut: Cut | None) -> None:
    """Raise TruncatedLogError for a cut log when --strict asked for complete logs only."""
    if cut is None or options.allow_truncated:
        return
    msg = (f"{path}: the log is cut: {cut.where}. Re-copy the log, or leave out --strict to calibrate from its "
           "complete records")
    raise TruncatedLogError(msg)


def mark_cut(rec: Recording, cut: Cut | None) -> Recording:
    """`rec` with `cut` (its end time filled in) and its note first among the reader's notes."""
    if cut is None:
        return rec
    ends = [float(s.t[-1]) for s in rec.streams if len(s)]
    cut = cut._replace(end_s=max(ends) if ends else None)
    return replace(rec, notes=(cut.message, *rec.notes), cut=cut)


def read_cut(path: Path, options: ReadOptions, cut: Cut | None, rec: Recording) -> Recording:
    """The --strict check and the mark in one call, for readers that find the cut after building `rec`."""
    refuse_if_strict(path, options, cut)
    return mark_cut(rec, cut)


def a_record(name: str) -> str:
    """'a chunk record', 'an IMU record': the article for a record type's name."""
    return f"{'an' if name[:1].upper() in 'AEIOU' else 'a'} {name} record"
