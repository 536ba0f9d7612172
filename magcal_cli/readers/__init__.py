"""Reader registry, format sniffing and `open_recording` (the only entry point for logs)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Protocol

from magcal_cli.errors import LogReadError, UnsupportedFormatError
from magcal_cli.progress import current
from magcal_cli.registry import resolve
from magcal_cli.streams import Recording


@dataclass(frozen=True)
class ReadOptions:
    """What a reader should do beyond the defaults.

    `allow_truncated`: read a cut log up to its last complete record (the default); False is --strict, which
    refuses it. A log more than half unreadable is refused either way unless this is True and data remain.
    """

    allow_truncated: bool = True
    receive_time: bool = False


class Reader(Protocol):
    """A log reader: turns one file (or bag directory) into a Recording in SI units."""

    name: ClassVar[str]

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Read every stream magcal can use."""
        ...


#: format name -> "module:Class" (imported on use, so `magcal --help` stays fast)
READERS: dict[str, str | type[Reader]] = {
    "mcap": "magcal_cli.readers.ros.mcap:McapReader",
    "dataflash": "magcal_cli.readers.dataflash.reader:DataflashReader",
    "rosbag": "magcal_cli.readers.ros.bag:RosbagReader",
    "csv": "magcal_cli.readers.csvfile:CsvReader",
    "ulog": "magcal_cli.readers.ulog.reader:UlogReader",
    "broad": "magcal_cli.readers.broad:BroadReader",
}

#: leading bytes -> format name (mcap read_magic; rosbags; pyulog HEADER_BYTES; DataFlash HEAD1/HEAD2)
MAGIC: dict[bytes, str] = {
    b"\x89MCAP0\r\n": "mcap",
    b"#ROSBAG V2.0\n": "rosbag",
    b"ULog\x01\x12\x35": "ulog",
    b"\xa3\x95": "dataflash",
    b"SQLite format 3\x00": "rosbag",   # the .db3 inside a ROS 2 bag directory
    b"\x89HDF\r\n\x1a\n": "broad",      # HDF5: read in the BROAD dataset layout
    b"MATLAB 5.0 MAT": "broad",          # MATLAB v5: read in the BROAD dataset layout
}

#: extensions tried when the magic bytes say nothing (text formats)
EXTENSIONS: dict[str, str] = {".mcap": "mcap", ".bag": "rosbag", ".ulg": "ulog", ".bin": "dataflash",
                              ".log": "dataflash", ".csv": "csv", ".px4log": "dataflash"}

#: the names `magcal inspect` prints (Recording.format) that are not a reader's name -> the reader that reads them
FORMAT_ALIASES: dict[str, str] = {"px4log": "dataflash", "rosbag2": "rosbag"}
#: readers whose files always start with their magic bytes (a ROS 2 bag: a folder with metadata.yaml)
SIGNED = ("mcap", "rosbag", "ulog", "broad")
#: how a format is called in a message
TITLES: dict[str, str] = {"mcap": "an MCAP file", "rosbag": "a ROS bag", "rosbag2": "a ROS 2 bag",
                          "dataflash": "an ArduPilot DataFlash log", "px4log": "a PX4 sdlog2 log (.px4log)",
                          "ulog": "a PX4 ULog", "csv": "a CSV log", "broad": "a BROAD dataset trial"}


def format_names() -> list[str]:
    """What --format accepts: every reader's name and every other name `magcal inspect` prints, sorted."""
    return sorted({*READERS, *FORMAT_ALIASES})


def _title(name: str) -> str:
    return TITLES.get(name, f"a {name} log")


def signature(path: Path) -> str | None:
    """The format `path` announces itself: a ROS 2 bag directory, or the magic bytes it starts with (None: no
    known magic, e.g. a text format)."""
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "rosbag"
        msg = f"{path}: a directory that is not a ROS 2 bag (no metadata.yaml). Pass a log file or a bag directory"
        raise UnsupportedFormatError(msg)
    try:
        with path.open("rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        msg = f"{path}: cannot read the file ({exc.strerror or exc}). Check the path and its permissions"
        raise LogReadError(msg) from None
    if not head:
        msg = f"{path}: the file is empty. Re-copy the log from the vehicle"
        raise LogReadError(msg)
    return next((name for magic, name in MAGIC.items() if head.startswith(magic)), None)


def sniff(path: Path) -> str:
    """The format of `path`: a ROS 2 bag directory, else magic bytes, else the extension."""
    signed = signature(path)
    if signed is not None:
        return signed
    by_ext = EXTENSIONS.get(path.suffix.lower())
    if by_ext is not None and by_ext not in ("mcap", "rosbag", "ulog"):
        return by_ext
    msg = (f"{path}: unrecognised log format (no known magic bytes at the start). "
           f"Supported: {', '.join(sorted(READERS))}; use --format to force one")
    raise UnsupportedFormatError(msg)


def get_reader(name: str) -> Reader:
    """Instantiate the registered reader `name`, importing its module on demand."""
    target = READERS.get(name)
    if target is None:
        msg = f"format {name!r} has no reader in this version; supported: {', '.join(sorted(READERS))}"
        raise UnsupportedFormatError(msg)
    return resolve(target, f"reading {name} logs")()  # type: ignore[no-any-return]


def open_recording(path: Path, fmt: str | None = None, options: ReadOptions | None = None) -> Recording:
    """Read `path` with the reader for `fmt` (sniffed when None; a name `magcal inspect` prints or a reader's), or
    refuse it when it is not that format; readers report the fraction read as the "reading" stage of
    `progress.current()`, which ends at 1 here."""
    path = Path(path)
    if not path.exists():
        msg = f"{path}: no such file or directory. Check the path"
        raise LogReadError(msg)
    if fmt is None:
        rec = get_reader(sniff(path)).read(path, options or ReadOptions())
    else:
        reader = FORMAT_ALIASES.get(fmt, fmt)
        refuse_other_format(path, fmt, reader)
        rec = get_reader(reader).read(path, options or ReadOptions())
        if fmt != reader and rec.format != fmt:                 # px4log and rosbag2: the reader reads more than that
            msg = (f"{path}: not {_title(fmt)}: it is {_title(rec.format)}. Leave --format out, or give "
                   f"--format {rec.format}")
            raise UnsupportedFormatError(msg)
    current()("reading", 1, 1)
    return rec


def refuse_other_format(path: Path, fmt: str, reader: str) -> None:
    """A forced format (--format) that the file's own signature contradicts, or that needs a signature the file
    lacks: UnsupportedFormatError saying what the file looks like (a reader would find nothing or garbage)."""
    signed = signature(path)
    if signed is not None and signed != reader:
        msg = (f"{path}: not {_title(fmt)}: its first bytes are those of {_title(signed)}. Leave --format out, or "
               f"give --format {signed}")
        raise UnsupportedFormatError(msg)
    if signed is None and reader in SIGNED:
        guess = EXTENSIONS.get(path.suffix.lower())
        looks = (f"by its extension it looks like {_title(guess)}. Leave --format out, or give --format {guess}"
                 if guess is not None and guess not in SIGNED else
                 "it looks like no format magcal reads. Check the file, or name its format with --format")
        msg = f"{path}: not {_title(fmt)}: it does not start with the magic bytes of one; {looks}"
        raise UnsupportedFormatError(msg)
