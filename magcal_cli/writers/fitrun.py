"""What `magcal fit` does after fitting, shared with `magcal batch`: the firmware file added on its own, the
outputs written together, and the --fail-on verdict. No click: the batch workers run it too."""

from __future__ import annotations

import errno
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from magcal_cli.errors import MagcalError

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult

#: the file system refusing a read or write: the user's environment, not a bug (exit 1, not 123)
USER_ERRNOS = frozenset({errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.ENOTDIR,
                         errno.EISDIR, errno.ENAMETOOLONG, errno.ENOENT})


def firmware_output(log: Path, fmt: str | None, names: list[str]) -> str | None:
    """The firmware output a default `--outputs` adds for `log` (ardupilot for DataFlash, px4 for ULog), or None."""
    from magcal_cli.readers import sniff
    from magcal_cli.writers import FIRMWARE_OUTPUTS

    try:
        auto = FIRMWARE_OUTPUTS.get(fmt or sniff(log))
    except MagcalError:
        return None                     # an unreadable log fails later, with the reader's own message
    return auto if auto not in names else None


def write_fit_outputs(result: RunResult, outdir: Path, names: list[str], auto: str | None,
                      warn: Callable[[str], None], then: Callable[[list[Path]], None] | None = None) -> list[Path]:
    """write_outputs; the firmware file fit adds on its own is skipped with a warning when the calibration
    cannot be written as parameters (asked for with --outputs, it stays an error)."""
    from magcal_cli.firmware import FirmwareError
    from magcal_cli.progress import current
    from magcal_cli.writers import write_outputs

    current()("writing the outputs", 0)      # a stage of its own; a stopped batch task stops here (batch.run)
    try:
        return write_outputs(result, outdir, names, then)
    except FirmwareError as exc:
        if auto is None or auto not in names:
            raise
        warn(f"warning: no {auto} parameter file written: {exc}")
        return write_outputs(result, outdir, [n for n in names if n != auto], then)


def gate_failures(result: RunResult, conditions: tuple[Any, ...]) -> list[str]:
    """The --fail-on conditions a magnetometer meets, as 'MAG: condition (measured x)'; [] when all pass."""
    from magcal_cli.firmware import gates
    from magcal_cli.firmware.metrics import fit_metrics

    if not conditions:
        return []
    return [f"{mag}: {f}" for mag, (metrics, why) in fit_metrics(result).items()
            for f in gates.failures(conditions, metrics, why)]
