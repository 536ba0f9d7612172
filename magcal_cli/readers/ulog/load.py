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

from magcal_cli.errors import LogReadError
from magcal_cli.progress import Hook, current, noop

#: message-header reads that may start at or before the furthest header read so far before the parser counts
#: as stuck; a healthy parse never re-reads a header (resynchronising steps forward one byte per header)
STUCK_READS = 1000
#: header reads are 3 bytes (uint16 size, uint8 type; ULog spec "Message Header")
HEADER_SIZE = 3
#: the longest message payload a uint16 size allows
MAX_MESSAGE = 0xFFFF
#: the message types of the ULog spec (B F I M P Q A R D L C S O)
MESSAGE_TYPES = frozenset(b"BFIMPQARDLCSO")
#: bytes between two reports of the fraction read (pyulog parses about 8 MB/s: a few reports a second)
REPORT_BYTES = 1 << 20


class StuckError(Exception):
    """pyulog kept reading the same bytes: the file is corrupt in a way it cannot get past."""


class GuardFile:
    """The log file as pyulog reads it: records where a message was cut off, stops an endless re-read loop, and
    reports the bytes read to `hook` every REPORT_BYTES (one comparison per message header)."""

    def __init__(self, fh: IO[bytes], size: int, hook: Hook | None = None) -> None:
        self._fh = fh
        self.size = size
        self._hook = hook or noop
        self._report_at = 0
        self.cut_at: int | None = None
        self._furthest_start = -1
        self._idle = 0
        self.corrupt_headers = 0
        self._header: tuple[int, int] | None = None

    def read(self, n: int = -1) -> bytes:
        """Read like the wrapped file; a short read of a message (not a clean end of file) marks the cut."""
        pos = self._fh.tell()
        if n == HEADER_SIZE:                 # message headers only: sync searches read ahead, then seek back
            if pos > self._furthest_start:   # resynchronising byte by byte starts each header further on
                self._furthest_start, self._idle = pos, 0
                if pos >= self._report_at:
                    self._report_at = pos + REPORT_BYTES
                    self._hook("reading", pos, self.size)
            else:
                self._idle += 1
                if self._idle > STUCK_READS:
                    raise StuckError(pos)
        data = self._fh.read(n)
        if n == HEADER_SIZE and len(data) == n and self._corrupt_header(pos, data):
            # show pyulog a header of type 0, which it treats as corruption and passes byte by byte until
            # messages line up again, instead of stopping for good at a short read as if the file ended here
            self.corrupt_headers += 1
            data = bytes(HEADER_SIZE)
        payload = self._header is not None and pos == self._header[0] + HEADER_SIZE and n == self._header[1]
        self._header = (pos, int.from_bytes(data[:2], "little")) if n == HEADER_SIZE else None
        clean_end = not data and n == HEADER_SIZE          # a header would start at the end: the log is whole
        if (payload or n == HEADER_SIZE) and len(data) < n and not clean_end and self.cut_at is None:
            self.cut_at = pos - HEADER_SIZE * payload      # sync searches read ahead in blocks: not a cut
        return data

    def _corrupt_header(self, pos: int, header: bytes) -> bool:
        """True for a header of no ULog message type whose message would end past the end of the file, or of a
        message that would end there although the file goes on for longer than any message (a log cut off
        inside its last message ends closer)."""
        size = int.from_bytes(header[:2], "little")
        if pos + HEADER_SIZE + size <= self.size:
            return False
        return header[2] not in MESSAGE_TYPES or self.size - pos > HEADER_SIZE + MAX_MESSAGE

    def seek(self, offset: int, whence: int = 0) -> int:
        """Seek the wrapped file."""
        return self._fh.seek(offset, whence)

    def tell(self) -> int:
        """Position in the wrapped file."""
        return self._fh.tell()

    def tell_safe(self) -> int:
        """The furthest position read so far (valid after the file is closed)."""
        return max(self._furthest_start, 0)

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
    hook = current()
    guard = GuardFile(raw, size, hook)
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
    except StuckError as exc:
        msg = (f"{path}: the ULog is corrupt near byte {exc.args[0]} (the parser cannot find the next "
               "message). Re-copy the log from the vehicle")
        raise LogReadError(msg) from None
    except ULogIncompatibleFlagException:
        msg = (f"{path}: the ULog sets a format flag this pyulog cannot parse (a newer PX4 log format, or a "
               "corrupt header). Update pyulog (pip install --upgrade pyulog) or re-copy the log")
        raise LogReadError(msg) from None
    except ULogException as exc:
        # a header cut short is a damaged copy; a header that does not parse is another format
        fix = ("Re-copy the log from the vehicle" if "too short" in str(exc) else
               "Check that it is a PX4 .ulg log, or pass --format for another log type")
        msg = f"{path}: not a readable ULog ({_first_line(exc)}). {fix}"
        raise LogReadError(msg) from None
    except (TypeError, ValueError, KeyError, IndexError, OverflowError, struct.error, UnicodeDecodeError,
            MemoryError) as exc:
        msg = (f"{path}: the ULog is corrupt (pyulog: {type(exc).__name__}: {_first_line(exc)}). "
               "Re-copy the log from the vehicle")
        raise LogReadError(msg) from None
    finally:
        ULog._disable_str_exceptions = switch
    hook("reading", size, size)
    printed = tuple(dict.fromkeys(line.strip() for line in out.getvalue().splitlines() if line.strip()))
    return Loaded(ulog, tuple(sorted(topics.seen)), size, guard.cut_at, printed)


def _first_line(exc: BaseException) -> str:
    """A library exception as a short phrase."""
    text = str(exc).strip().rstrip(".") or type(exc).__name__
    return text.splitlines()[0][:160]
