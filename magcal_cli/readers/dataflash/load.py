"""Loading a DataFlash file: the record types magcal decodes, binary or text parsing, parser errors translated."""

from __future__ import annotations

from pathlib import Path

from magcal_cli.errors import LogReadError, MagcalError, UnsupportedFormatError
from magcal_cli.progress import active, current, within
from magcal_cli.readers.dataflash.binary import parse_binary
from magcal_cli.readers.dataflash.format import RawLog
from magcal_cli.readers.dataflash.text import looks_like_text, parse_text

#: the record types of up to three compasses and IMUs (NAME, NAME2, NAME3, or NAME with an instance column)
MAG_NAMES = ("MAG", "MAG2", "MAG3")
IMU_NAMES = ("IMU", "IMU2", "IMU3")
#: the record types magcal uses (the parsers decode only these, plus units)
WANTED = frozenset({*MAG_NAMES, *IMU_NAMES, "PARM", "MSG", "VER", "ATT", "AHR2", "BAT", "BAT2", "CURR",
                    "CTUN", "RCOU", "GPS", "GPS2", "TIME", "IMU1", "BATT", "ATTC"})
#: the share of a read that parsing takes, by text log or not; building the streams takes the rest (measured:
#: 0.26-0.47 on binary logs of 3-55 MB, where rebuilding the raw field and checking the streams is vectorised
#: but touches every sample, 0.93 on a 2.7 MB text log, whose parse splits every line in Python)
PARSE_SHARE = {False: 0.3, True: 0.9}


def load(path: Path) -> RawLog:
    """Parse a binary or text DataFlash file, translating parser failures into one-line LogReadErrors."""
    try:
        with path.open("rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
        raise LogReadError(msg) from None
    hook = current()
    try:
        if b"\xa3\x95" in head[:512]:
            with active(within(hook, 0.0, PARSE_SHARE[False])):
                raw = parse_binary(path, WANTED)
        elif looks_like_text(head):
            with active(within(hook, 0.0, PARSE_SHARE[True])):
                raw = parse_text(path, WANTED)
        else:
            msg = (f"{path}: not a DataFlash log (no A3 95 record header and no FMT text lines at the "
                   "start). Check the file, or pass --format for another log type")
            raise UnsupportedFormatError(msg)
    except MagcalError:
        raise
    except (ValueError, IndexError, KeyError, TypeError, OverflowError) as exc:
        msg = (f"{path}: the DataFlash log is corrupt ({type(exc).__name__}: {exc}). "
               "Re-copy the log from the vehicle")
        raise LogReadError(msg) from None
    if not any(v for k, v in raw.counts.items() if k != "FMT"):
        msg = (f"{path}: the DataFlash log holds no data records (only {raw.counts.get('FMT', 0)} FMT). "
               "Re-copy the log")
        raise LogReadError(msg)
    return raw
