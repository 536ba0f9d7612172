"""DataFlash reader: ArduPilot binary `.bin` and text `.log`, and legacy PX4 sdlog2 `.px4log`.

`load` parses the file; `ardupilot` (with the raw field rebuilt by `rawfield`) or `px4log` builds the
Recording. See docs/readers-ardupilot.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from magcal_cli.errors import LogReadError, StreamError
from magcal_cli.progress import active, current, within
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.cut import mark_cut, refuse_if_strict
from magcal_cli.readers.dataflash.ardupilot import build_ardupilot
from magcal_cli.readers.dataflash.format import RawLog
from magcal_cli.readers.dataflash.load import PARSE_SHARE, load
from magcal_cli.streams import Cut, Recording

#: above this share of unreadable bytes a log is an error with --strict, or when what is left is unusable
MOSTLY_CORRUPT = 0.5


def is_px4log(raw: RawLog) -> bool:
    """Legacy PX4 sdlog2 logs carry TIME.StartTime and the field inside IMU (MagX..); ArduPilot never does."""
    imu = raw.formats.get("IMU")
    time = raw.formats.get("TIME")
    return (time is not None and time.has("StartTime")) or (imu is not None and imu.has("MagX"))


class DataflashReader:
    """Reads ArduPilot DataFlash (`.bin`, text `.log`) and PX4 `.px4log` logs into SI streams."""

    name: ClassVar[str] = "dataflash"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Every stream magcal uses; a cut log up to its last complete message (--strict refuses it). The
        fraction read is reported as the "reading" stage of `progress.current()`: bytes parsed, then streams."""
        hook = current()
        raw = load(path)
        mostly_corrupt = raw.skipped_bytes > MOSTLY_CORRUPT * raw.size
        if mostly_corrupt and not options.allow_truncated:
            raise LogReadError(_mostly_corrupt(path, raw, "Re-copy the log, or leave out --strict to use them"))
        cut = Cut(raw.size - raw.truncated_bytes, raw.size, raw.cut_lost) if raw.truncated_bytes else None
        refuse_if_strict(path, options, cut)
        try:
            with active(within(hook, PARSE_SHARE[raw.text], 1.0)):
                if is_px4log(raw):
                    from magcal_cli.readers.dataflash.px4log import build_px4log

                    return mark_cut(build_px4log(path, raw), cut)
                return mark_cut(build_ardupilot(path, raw), cut)
        except StreamError:
            if mostly_corrupt:          # what is missing was lost to the damage: say that, not "never logged"
                why = "They are not enough to calibrate; re-copy the log from the vehicle"
                raise LogReadError(_mostly_corrupt(path, raw, why)) from None
            raise


def _mostly_corrupt(path: Path, raw: RawLog, then: str) -> str:
    """The message for a log more than half unreadable; `then` ends it."""
    kept = sum(v for k, v in raw.counts.items() if k != "FMT")
    return (f"{path}: {raw.skipped_bytes} of {raw.size} bytes are not complete records (the log is mostly "
            f"corrupt, or its FMT records are damaged); {kept} messages could be read. {then}")

