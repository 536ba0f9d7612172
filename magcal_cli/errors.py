"""The error tree: everything the CLI reports as one `Error: <where>: <what>. <how to fix>` line."""

from __future__ import annotations


class MagcalError(Exception):
    """Anything the CLI reports as 'Error: ...' with exit code 1."""


class LogReadError(MagcalError):
    """File unreadable, truncated or corrupt."""


class TruncatedLogError(LogReadError):
    """The log ends inside a record (cut at power-off, a killed recorder) and --strict refuses it."""


class UnsupportedFormatError(LogReadError):
    """No reader recognises the file."""


class MissingDependencyError(MagcalError):
    """An optional package needed for this input is not installed."""


class StreamError(MagcalError):
    """Stream absent, empty, wrong shape or wrong unit."""


class SelectionError(StreamError):
    """A stream id given on the command line (--mag, --imu) that the log does not have: a usage mistake (exit 2)."""


class InsufficientDataError(MagcalError):
    """Too few stationary segments or too little orientation coverage to determine the calibration."""


class UnexplainedError(InsufficientDataError):
    """The model leaves the readings unexplained (the calibrated field strength still varies): a disturbance the
    model lacks may dominate, where too little motion would be a plain InsufficientDataError."""


class ConvergenceError(MagcalError):
    """The solver did not converge; carries the iteration log."""

    def __init__(self, message: str, log: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.log = log


class OutputError(MagcalError):
    """An output cannot be written (exists without --force, unwritable directory)."""


class CalibrationFileError(MagcalError):
    """A calibration document is malformed or of an unknown schema."""


class OptionError(MagcalError):
    """A Python API argument (`magcal_cli.api`) out of range or of the wrong shape; the CLI's options are checked
    by click before they get there (exit 2)."""


def reason(exc: Exception, where: str) -> str:
    """A refusal's `<what>` alone, for quoting inside another message: without its `where: ` prefix, its
    `To fix:` advice and its final full stop."""
    return str(exc).removeprefix(f"{where}: ").split(" To fix:")[0].rstrip(".")
