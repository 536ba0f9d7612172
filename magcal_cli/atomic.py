"""Atomic outputs: write to a temporary name in the target's directory, rename on success.

`check_writable` probes an output location before the work starts, so a read-only, full or missing folder is
one error line, not a lost fit.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from magcal_cli.errors import OutputError


def _cannot_write(target: Path, exc: OSError, hint: str) -> OutputError:
    """The one-line error for an output that the file system refuses (read-only, full, permissions)."""
    return OutputError(f"{target}: cannot write here ({exc.strerror or exc}). {hint}")


def check_writable(folder: Path, create: bool = False, hint: str = "Choose another output location") -> None:
    """Refuse (OutputError) when files cannot be written in `folder`; with `create`, the folder may be missing
    as long as its nearest existing ancestor is a writable directory."""
    probe = Path(folder)
    while not probe.exists():
        if not create:
            msg = f"{folder}: no such folder. Create it, or {hint[:1].lower()}{hint[1:]}"
            raise OutputError(msg)
        probe = probe.parent
    if not probe.is_dir():
        what = "is a file, not a folder" if probe == folder else "cannot create the output directory (Not a directory)"
        msg = f"{folder}: {what}. {hint}"
        raise OutputError(msg)
    try:
        fd, name = tempfile.mkstemp(prefix=".magcal-probe-", dir=probe)
    except OSError as exc:
        raise _cannot_write(folder, exc, hint) from None
    try:                                  # a Ctrl-C right after mkstemp must not leave the probe behind
        os.close(fd)
    finally:
        with contextlib.suppress(OSError):
            Path(name).unlink()


@contextlib.contextmanager
def atomic_path(target: Path) -> Iterator[Path]:
    """Yield a temporary path next to `target`; rename it to `target` if the block succeeds, else delete it.

    A KeyboardInterrupt or any error leaves `target` as it was (absent or the old content). The file system
    refusing the write (read-only, full, permissions) is an OutputError naming `target`.
    """
    target = Path(target)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent or Path())
    except OSError as exc:
        raise _cannot_write(target, exc, "Choose another output location") from None
    tmp = Path(name)
    try:                                  # from here on a Ctrl-C (or any error) deletes the temporary file
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o666 & ~umask)         # mkstemp makes 0600; outputs get the usual permissions
        yield tmp
        tmp.replace(target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError) and exc.errno != errno.EPIPE:
            raise _cannot_write(target, exc, "Free some space or choose another output location") from None
        raise


@contextlib.contextmanager
def atomic_dir(target: Path) -> Iterator[Path]:
    """Yield a path named like the folder `target` inside a staging folder next to it (a ROS 2 bag names its
    storage files after its folder); on success it replaces `target` (an old one too), and the staging folder
    and whatever is left in it are removed either way."""
    target = Path(target)
    try:
        parent = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent or Path()))
    except OSError as exc:
        raise _cannot_write(target, exc, "Choose another output location") from None
    try:
        tmp = parent / target.name
        yield tmp
        if target.exists():               # an old output, which the caller was told to replace (--force)
            target.replace(parent / "old")
        tmp.replace(target)
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(parent)


def write_text(target: Path, text: str) -> Path:
    """Write `text` to `target` atomically and return the path."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return target


def write_bytes(target: Path, data: bytes) -> Path:
    """Write `data` to `target` atomically and return the path."""
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
    return target
