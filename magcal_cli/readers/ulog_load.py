"""Parse a ULog with pyulog behind a guard: every pyulog failure becomes a one-line LogReadError.

pyulog prints warnings on stdout, flips a class-level switch in its constructor, raises TypeError, ValueError
or struct.error on bad input, reads a cut-off file without saying so and, on some corrupt headers, loops
forever (`_read_file_definitions` seeks back past a short read). The guard file below sees every read, so it
can say where the file was cut and stop a parser that stops advancing.
"""

from __future__ import annotations

import contextlib
import errno
import io
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from ..errors import LogReadError

#: reads that may start at or before the furthest position read so far before the parser counts as stuck;
#: a healthy parse re-reads at most a few bytes (resynchronising steps back one byte per message)
STUCK_READS = 1000
#: header reads are 3 bytes (uint16 size, uint8 type; ULog spec "Message Header")
HEADER_SIZE = 3


class _StuckError(Exception):
    """pyulog kept reading the same bytes: the file is corrupt in a way it cannot get past."""


class GuardFile:
    """The log file as pyulog reads it: records where a message was cut off, stops an endless re-read loop."""

    def __init__(self, fh: IO[bytes], size: int) -> None:
        self._fh = fh
        self.size = size
        self.cut_at: int | None = None
        self._furthest = -1
        self._idle = 0

    def read(self, n: int = -1) -> bytes:
        """Read like the wrapped file; a short read of a message (not a clean end of file) marks the cut."""
        pos = self._fh.tell()
        if pos > self._furthest:
            self._furthest, self._idle = pos, 0
        else:
            self._idle += 1
            if self._idle > STUCK_READS:
                raise _StuckError(pos)
        data = self._fh.read(n)
        clean_end = not data and n == HEADER_SIZE          # a header would start at the end: the log is whole
        if n > 0 and len(data) < n and not clean_end and self.cut_at is None:
            self.cut_at = pos
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        """Seek the wrapped file."""
        return self._fh.seek(offset, whence)

    def tell(self) -> int:
        """Position in the wrapped file."""
        return self._fh.tell()

    def tell_safe(self) -> int:
        """The furthest position read so far (valid after the file is closed)."""
        return max(self._furthest, 0)

    def close(self) -> None:
        """Close the wrapped file (pyulog closes it when done)."""
        self._fh.close()


class SeenTopics(list[str]):
    """pyulog's message-name filter that also remembers every topic name the log subscribes to."""

    def __init__(self, wanted: list[str]) -> None:
        super().__init__(wanted)
        self.seen: set[str] = set()

    def __contains__(self, name: object) -> bool:
        if isinstance(name, str):
            self.seen.add(name)
        return super().__contains__(name)


@dataclass(frozen=True)
class Loaded:
    """A parsed ULog, the topics it logs, where it was cut off (if it was) and what pyulog printed."""

    ulog: Any
    topics: tuple[str, ...]
    size: int
    cut_at: int | None
    printed: tuple[str, ...]


def load_ulog(path: Path, wanted: list[str]) -> Loaded:
    """Parse the topics in `wanted` (all topic names are still recorded); LogReadError when pyulog cannot."""
    from pyulog import ULog
    from pyulog.exceptions import ULogException, ULogIncompatibleFlagException

    topics = SeenTopics(wanted)
    out = io.StringIO()
    switch = ULog._disable_str_exceptions                   # pyulog sets this class attribute on every parse
    try:
        raw = path.open("rb")
        size = raw.seek(0, io.SEEK_END)
        raw.seek(0)
    except OSError as exc:
        msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
        raise LogReadError(msg) from None
    guard = GuardFile(raw, size)
    try:
        with raw, contextlib.redirect_stdout(out):
            ulog = ULog(guard, topics, disable_str_exceptions=True)
    except OSError as exc:
        if exc.errno != errno.EINVAL:
            msg = (f"{path}: reading the file failed ({exc.strerror or exc}). Check the storage and copy the "
                   "log again")
            raise LogReadError(msg) from None
        # pyulog seeks back by a message size it could not read: a corrupt size field near the start
        msg = (f"{path}: the ULog is corrupt near byte {guard.tell_safe()} (a message size points outside "
               "the file). Re-copy the log from the vehicle")
        raise LogReadError(msg) from None
    except _StuckError as exc:
        msg = (f"{path}: the ULog is corrupt near byte {exc.args[0]} (the parser cannot find the next "
               "message). Re-copy the log from the vehicle")
        raise LogReadError(msg) from None
    except ULogIncompatibleFlagException:
        msg = (f"{path}: the ULog sets a format flag this pyulog cannot parse (a newer PX4 log format, or a "
               "corrupt header). Update pyulog (pip install --upgrade pyulog) or re-copy the log")
        raise LogReadError(msg) from None
    except ULogException as exc:
        msg = f"{path}: not a readable ULog ({_first_line(exc)}). Re-copy the log from the vehicle"
        raise LogReadError(msg) from None
    except (TypeError, ValueError, KeyError, IndexError, OverflowError, struct.error, UnicodeDecodeError,
            MemoryError) as exc:
        msg = (f"{path}: the ULog is corrupt (pyulog: {type(exc).__name__}: {_first_line(exc)}). "
               "Re-copy the log from the vehicle")
        raise LogReadError(msg) from None
    finally:
        ULog._disable_str_exceptions = switch
    printed = tuple(dict.fromkeys(line.strip() for line in out.getvalue().splitlines() if line.strip()))
    return Loaded(ulog, tuple(sorted(topics.seen)), size, guard.cut_at, printed)


def _first_line(exc: BaseException) -> str:
    """A library exception as a short phrase."""
    text = str(exc).strip().rstrip(".") or type(exc).__name__
    return text.splitlines()[0][:160]
